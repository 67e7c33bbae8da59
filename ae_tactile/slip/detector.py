"""Slip / texture detector core: localized emissions in, SLIP_PRECURSOR / SLIP / TEXTURE
events and a latched per-finger contact state out. Pure Python + numpy, no rclpy.

    det = SlipDetector(SlipConfig())
    for ev in localized_events:            # LocalizedEvent, in time order
        for out in det.process(ev):        # SlipEvent list (often empty)
            publish(out)
    det.advance(now_ns)                    # time passing without events (timer)
    det.state                              # FingerState (latched)

Model (docs/slip.md). A held contact is silent; micro-slip under a growing tangential
load emits from the Cattaneo-Mindlin annulus c < r < a_H at the contact edge, with random
polarity, and the localizer types each emission TOUCH (+1) or DETOUCH (-1) by polarity
only. The tracker therefore keeps, per contact, its emissions and its *open touches*
(compressions not yet released):

* a rarefaction (-1) inside the release gate of an open touch (Mahalanobis distance under
  C_touch + C_release + floor^2 I) is that touch's release: it ends the contact after
  ``release_confirm_s`` unless slip emissions of the contact cancel it;
* a rarefaction that matches no open touch is an *orphan*: no touch can explain it, so it
  is micro-slip evidence (weight 1) for the contact it falls in (within
  ``association_radius_m`` of the centre), or starts an unconfirmed candidate contact;
* a compression near an existing contact is ambiguous (a new touch, or a micro-slip): an
  open sub-touch with evidence weight ``touch_evidence_weight``, withdrawn if its release
  arrives; a compression far from every contact is a new contact (TOUCH);
* SLIP_PRECURSOR when the evidence of a contact within ``evidence_window_s`` reaches
  ``precursor_threshold`` (STICK -> INCIPIENT_SLIP); while slipping every emission of the
  contact is a slip emission;
* SLIP (-> GROSS_SLIP) when the stick zone is gone: at least ``gross_min_inner`` of the
  latest ``gross_window_events`` slip emissions lie within ``gross_inner_fraction`` of the
  contact radius from its centre (Cattaneo-Mindlin: no micro-slip inside the stick radius
  c = a_H (1 - q)^(1/3)), at a rate >= ``gross_min_rate_hz``; or a periodic texture run;
* TEXTURE while the contact's latest emissions are periodic (`periodicity`), with
  spatial period v T when the sliding speed v is known.

Work per event is bounded by ``member_history`` x ``max_contacts`` (bounded deques).
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from .config import SlipConfig
from .periodicity import periodicity
from .types import ContactInfo, ContactState, FingerState, LocalizedEvent, SlipEvent, SlipEventType

MAIN, SUB, SLIP, PAIRED = 0, 1, 2, 3          # member roles
_ROLE_NAMES = {MAIN: "touch", SUB: "sub_touch", SLIP: "slip", PAIRED: "paired"}
_SLIPPING = (ContactState.INCIPIENT_SLIP, ContactState.GROSS_SLIP)
_NAN3 = np.full(3, np.nan)


def _p90(d):
    """90th percentile (linear interpolation, as numpy's default) without the overhead."""
    n = d.size
    pos = 0.9 * (n - 1)
    i = int(pos)
    part = np.partition(d, (i, min(i + 1, n - 1)))
    return float(part[i] + (pos - i) * (part[min(i + 1, n - 1)] - part[i]))


def _circle_centre(P):
    """Centre (3,) of the circle best fitting points P (n, 3) on the sphere, by the
    algebraic (Kasa) fit u^2 + v^2 = 2 cu u + 2 cv v + k in the tangent plane at their
    centroid, projected back onto the sphere; None when the points are nearly collinear
    or the centre lands implausibly far (more than 3 spreads) from the centroid."""
    m = P.mean(axis=0)
    rn = float(np.linalg.norm(P, axis=1).mean())
    n = m / np.linalg.norm(m)
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - (ref @ n) * n
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    D = P - m
    u, v = D @ e1, D @ e2
    suu, svv, suv = float(u @ u), float(v @ v), float(u @ v)
    k = len(u)
    tr, det = (suu + svv) / k, (suu * svv - suv * suv) / (k * k)
    disc = math.sqrt(max(tr * tr / 4 - det, 0.0))
    lo, hi = tr / 2 - disc, tr / 2 + disc            # eigenvalues of the 2x2 covariance
    if hi <= 0.0 or lo < 0.01 * hi:
        return None
    spread = math.sqrt(hi)
    # normal equations of [2u 2v 1] [cu cv k]^T = u^2 + v^2 (u, v centred: block diagonal)
    b = u * u + v * v
    rhs = np.array([2 * float(u @ b), 2 * float(v @ b)])
    sol = np.linalg.solve(np.array([[4 * suu, 4 * suv], [4 * suv, 4 * svv]]), rhs)
    if math.hypot(sol[0], sol[1]) > 3.0 * spread:
        return None
    c = m + sol[0] * e1 + sol[1] * e2
    return c * (rn / np.linalg.norm(c))


class _Member:
    __slots__ = ("t", "p", "cov", "pol", "role", "w", "pid", "open", "clean")

    def __init__(self, ev: LocalizedEvent, role: int, w: float, is_open: bool):
        self.t = ev.time_ns
        self.p = ev.point_m
        self.cov = ev.covariance_m2
        self.pol = ev.polarity
        self.role = role
        self.w = w
        self.pid = ev.packet_id
        self.open = is_open
        self.clean = True            # not within the overlap guard of another emission


class _Contact:
    def __init__(self, cid: int, t_ns: int, announced: bool, history: int):
        self.id = cid
        self.members: deque[_Member] = deque(maxlen=history)
        self.state = ContactState.STICK
        self.since_ns = t_ns
        self.announced = announced
        self.confirmed = announced
        self.created_ns = t_ns
        self.last_ns = t_ns
        self.last_slip_ns = None
        self.pending_release = None          # (time_ns, member) of a matched release
        self.precursor_count = 0
        self.last_report = {}
        self.texture_on = False
        self.texture_run = 0                 # consecutive periodic tests
        self.centre = None
        self.radius = 0.0

    # -------------------------------------------------------------- geometry
    def update_geometry(self, fit_min: int = 8):
        """Centre and radius of the contact. With >= ``fit_min`` slip emissions: a circle
        fitted to them in the tangent plane (algebraic least squares, `_circle_centre`):
        micro-slips lie on the Cattaneo-Mindlin annulus around the centre, and a circle fit
        does not care how unevenly they cover it (the centroid does). Before that: the
        open touch that announced the contact, else the centroid. Radius: 90th percentile
        of the slip emissions' distances from the centre."""
        use = [m for m in self.members if m.role in (MAIN, SLIP) or (m.role == SUB and m.open)]
        clean = [m for m in use if m.clean] or use or list(self.members)
        slip = [m.p for m in clean if m.role != MAIN]
        main = [m for m in self.members if m.role == MAIN and m.open]
        centre = None
        if len(slip) >= fit_min:
            centre = _circle_centre(np.asarray(slip))
        if centre is None:
            centre = main[-1].p if main else np.mean([m.p for m in clean], axis=0)
        self.centre = centre
        if len(slip) >= 2:
            d = np.linalg.norm(np.asarray(slip) - centre, axis=1)
            self.radius = _p90(d)
        else:
            self.radius = 0.0

    def slip_members(self, n=None, since_ns=None, clean=False):
        """Latest slip emissions (orphans, open sub-touches, slipping-state emissions)."""
        out = []
        for m in reversed(self.members):
            if since_ns is not None and m.t <= since_ns:
                break
            if clean and not m.clean:
                continue
            if m.role == SLIP or (m.role == SUB and m.open):
                out.append(m)
                if n is not None and len(out) >= n:
                    break
        out.reverse()
        return out

    def evidence(self, now_ns, window_ns):
        return sum(m.w for m in self.slip_members(since_ns=now_ns - window_ns))

    def orphans(self, now_ns, window_ns):
        """Unmatched rarefactions in the window."""
        return sum(1 for m in self.slip_members(since_ns=now_ns - window_ns) if m.role == SLIP and m.pol < 0)

    def rate_hz(self, now_ns, window_ns):
        return len(self.slip_members(since_ns=now_ns - window_ns)) / (window_ns * 1e-9)

    def open_touches(self):
        return [m for m in self.members if m.open and m.role in (MAIN, SUB)]


class SlipDetector:
    """Stateful slip / texture detector for one finger (see the module docstring)."""

    def __init__(self, config: SlipConfig | None = None):
        if config is None:
            config = SlipConfig()
        if not isinstance(config, SlipConfig):
            raise TypeError(f"config must be a SlipConfig, got {type(config).__name__}")
        self.config = config
        c = config
        self._ns = lambda s: int(round(s * 1e9))
        self._w_ev = self._ns(c.evidence_window_s)
        self._w_rate = self._ns(c.rate_window_s)
        self._w_dir = self._ns(c.direction_window_s)
        self._confirm = self._ns(c.release_confirm_s)
        self._quiet = self._ns(c.quiet_s)
        self._report = self._ns(c.report_interval_s)
        self._reorder = self._ns(c.reorder_tolerance_s)
        self._guard = self._ns(c.overlap_guard_s)
        self._last_member = None
        self._speed = c.sliding_speed_m_s
        self.contacts: list[_Contact] = []
        self._next_id = 1
        self.now_ns = None
        self.counts = {"events": 0, "ignored_low_confidence": 0, "rejected_out_of_order": 0,
                       "releases": 0, "releases_cancelled": 0, "orphans": 0, "sub_touches": 0,
                       "contacts_created": 0, "contacts_dropped": 0}
        self._finger = FingerState(ContactState.NO_CONTACT, 0, _NAN3.copy(), 0.0, 0, -1, 0, 0)
        self._last_end_ns = 0

    # ------------------------------------------------------------------ public API
    @property
    def state(self) -> FingerState:
        """Latched finger state (as of the last ``process`` / ``advance``)."""
        return self._finger

    def set_sliding_speed(self, speed_m_s: float | None) -> None:
        """Sliding speed for TEXTURE spatial periods (m/s, > 0), or None (unknown)."""
        if speed_m_s is not None:
            v = float(speed_m_s)
            if not math.isfinite(v) or v <= 0:
                raise ValueError(f"sliding speed must be a positive number of m/s, got {speed_m_s!r}")
            speed_m_s = v
        self._speed = speed_m_s

    def contact_infos(self) -> list[ContactInfo]:
        """Snapshots of every tracked contact (unconfirmed candidates included)."""
        now = self.now_ns if self.now_ns is not None else 0
        out = []
        for c in self.contacts:
            out.append(ContactInfo(c.id, c.state, c.since_ns, c.centre.copy(), c.radius, c.announced,
                                   c.confirmed, c.pending_release is not None,
                                   c.rate_hz(now, self._w_rate), c.precursor_count, len(c.members), c.last_ns))
        return out

    def reset(self) -> None:
        """Forget every contact (e.g. after a gap in the data)."""
        self.contacts.clear()
        self.now_ns = None
        self._finger = FingerState(ContactState.NO_CONTACT, 0, _NAN3.copy(), 0.0, 0, -1, 0, 0)

    def process_batch(self, events) -> list[SlipEvent]:
        """``process`` for each event in order; the outputs concatenated."""
        out = []
        for ev in events:
            out.extend(self.process(ev))
        return out

    def advance(self, now_ns: int) -> FingerState:
        """Let time pass to ``now_ns`` without events: release confirmations, candidate
        expiry, quiet slip states falling back to STICK. Returns the finger state."""
        if isinstance(now_ns, bool) or not hasattr(now_ns, "__index__"):
            raise TypeError(f"now_ns must be an integer (ns), got {now_ns!r}")
        now = int(now_ns.__index__())
        if self.now_ns is not None and now < self.now_ns:
            return self._finger
        self.now_ns = now
        for c in list(self.contacts):
            if c.pending_release is not None and now - c.pending_release[0] >= self._confirm:
                self._end_contact(c)
                continue
            if not c.confirmed and now - c.last_ns >= self._w_ev:
                self.contacts.remove(c)
                continue
            if c.state in _SLIPPING and c.last_slip_ns is not None and now - c.last_slip_ns >= self._quiet:
                c.state = ContactState.STICK
                c.since_ns = c.last_slip_ns + self._quiet
                c.texture_on = False
                c.texture_run = 0
        self._update_finger(now)
        return self._finger

    def process(self, ev: LocalizedEvent) -> list[SlipEvent]:
        """Feed one localized emission (time order); returns the events it produced."""
        if not isinstance(ev, LocalizedEvent):
            raise TypeError(f"process() takes a LocalizedEvent, got {type(ev).__name__}")
        if self.now_ns is not None and ev.time_ns < self.now_ns - self._reorder:
            self.counts["rejected_out_of_order"] += 1
            return []
        if ev.confidence < self.config.min_confidence:
            self.counts["ignored_low_confidence"] += 1
            return []
        self.counts["events"] += 1
        self.advance(max(ev.time_ns, self.now_ns if self.now_ns is not None else ev.time_ns))
        out: list[SlipEvent] = []
        t = ev.time_ns
        if ev.polarity < 0:
            touch, owner = self._match_release(ev)
            if touch is not None:
                self._release(ev, touch, owner, out)
            else:
                self.counts["orphans"] += 1
                c = self._associate(ev)
                if c is None:
                    c = self._new_contact(t, announced=False)
                    c.members.append(_Member(ev, SLIP, 1.0, False))
                    c.update_geometry()
                else:
                    self._add_slip(c, ev, weight=1.0, cancels=True, out=out)
        else:
            same = self._match_release(ev)[0] if ev.polarity > 0 else None
            c = self._associate(ev)
            if c is None:
                c = self._new_contact(t, announced=True)
                c.members.append(_Member(ev, MAIN, 0.0, True))
                c.update_geometry()
            elif not c.confirmed:
                # a touch next to an unconfirmed candidate (a lone orphan): a contact now,
                # announced by this touch; the orphan stays as evidence
                c.announced = c.confirmed = True
                c.members.append(_Member(ev, MAIN, 0.0, True))
                c.last_ns = t
                c.update_geometry()
            else:
                # a compression on top of an open touch (the same spot touched again, or
                # two touches side by side) is no micro-slip evidence
                w = 0.0 if same is not None else self.config.touch_evidence_weight
                self._add_slip(c, ev, weight=w, cancels=False, out=out)
        self._mark_overlaps(ev, out)
        self._update_finger(t)
        return out

    # ------------------------------------------------------------------ internals
    def _mark_overlaps(self, ev, out):
        """Flag this emission's member and the previous one when they may share a window;
        run the texture test on the contact that took the emission."""
        new = None
        for c in self.contacts:
            if c.members and c.members[-1].pid == ev.packet_id and c.members[-1].t == ev.time_ns:
                new = c.members[-1]
                self._texture(c, ev, c.rate_hz(ev.time_ns, self._w_rate), out)
                break
        prev = self._last_member
        if prev is not None and new is not None and abs(ev.time_ns - prev.t) < self._guard:
            prev.clean = False
            new.clean = False
        if new is not None:
            self._last_member = new

    def _new_contact(self, t_ns, announced):
        if len(self.contacts) >= self.config.max_contacts:
            idle = [c for c in self.contacts if c.state not in _SLIPPING] or self.contacts
            drop = min(idle, key=lambda c: (c.confirmed, c.last_ns))
            self.contacts.remove(drop)
            self.counts["contacts_dropped"] += 1
        c = _Contact(self._next_id, t_ns, announced, self.config.member_history)
        self._next_id += 1
        self.contacts.append(c)
        self.counts["contacts_created"] += 1
        return c

    def _associate(self, ev):
        best, best_d = None, self.config.association_radius_m
        for c in self.contacts:
            d = float(np.linalg.norm(ev.point_m - c.centre))
            if d <= best_d:
                best, best_d = c, d
        return best

    def _match_release(self, ev):
        """Open touch (member, contact) whose release gate holds ``ev``, or (None, None)."""
        g2 = self.config.release_gate_sigma ** 2
        f2 = self.config.release_floor_m ** 2
        best, owner, best_m2 = None, None, g2
        for c in self.contacts:
            for m in c.members:
                if not m.open or m.role not in (MAIN, SUB):
                    continue
                d = ev.point_m - m.p
                if float(d @ d) > g2 * (3.0 * f2 + np.trace(m.cov) + np.trace(ev.covariance_m2)):
                    continue     # |d|^2 / tr(S) bounds the Mahalanobis distance from below
                S = m.cov + ev.covariance_m2 + f2 * np.eye(3)
                try:
                    m2 = float(d @ np.linalg.solve(S, d))
                except np.linalg.LinAlgError:
                    continue
                if m2 <= best_m2:
                    best, owner, best_m2 = m, c, m2
        return best, owner

    def _release(self, ev, touch, c, out):
        t = ev.time_ns
        touch.open = False
        self.counts["releases"] += 1
        if touch.role == SUB:
            touch.role = PAIRED
            touch.w = 0.0
            c.members.append(_Member(ev, PAIRED, 0.0, False))
            c.last_ns = t
            c.update_geometry()
            return
        subs = [m for m in c.members if m.role == SUB and m.open]
        if subs and c.state not in _SLIPPING:
            # another touch of the same contact region is still held: it carries on
            subs[0].role = MAIN
            subs[0].w = 0.0
            c.members.append(_Member(ev, PAIRED, 0.0, False))
            c.last_ns = t
            c.update_geometry()
            return
        c.pending_release = (t, touch)
        if c.state in _SLIPPING:
            # a centre emission of a slipping contact looks like a release: count it as a
            # slip emission too; the confirmation window decides
            self._add_slip(c, ev, weight=1.0, cancels=False, out=out)

    def _end_contact(self, c):
        t_rel = c.pending_release[0]
        self.contacts.remove(c)
        self._last_end_ns = t_rel
        subs = [m for m in c.members if m.role == SUB and m.open]
        if subs:       # touches still held in the region become a contact of their own
            n = _Contact(self._next_id, t_rel, True, self.config.member_history)
            self._next_id += 1
            self.counts["contacts_created"] += 1
            for i, m in enumerate(subs):
                if i == 0:
                    m.role, m.w = MAIN, 0.0
                n.members.append(m)
            n.last_ns = subs[-1].t
            n.update_geometry()
            self.contacts.append(n)

    def _add_slip(self, c, ev, *, weight, cancels, out):
        cfg = self.config
        t = ev.time_ns
        slipping = c.state in _SLIPPING
        if c.pending_release is not None:
            recent = c.evidence(t, self._w_ev) > 0
            if slipping or cancels or recent:
                c.pending_release[1].open = True        # the touch is still there
                c.pending_release = None
                self.counts["releases_cancelled"] += 1
        if slipping or ev.polarity < 0:
            m = _Member(ev, SLIP, 1.0 if slipping else weight, False)
        else:
            m = _Member(ev, SUB, weight, True)
            self.counts["sub_touches"] += 1
        c.members.append(m)
        c.last_ns = t
        c.update_geometry()
        if c.state in _SLIPPING or m.w > 0:
            c.last_slip_ns = t
        evidence = c.evidence(t, self._w_ev)
        rate = c.rate_hz(t, self._w_rate)
        if (c.state == ContactState.STICK and evidence >= cfg.precursor_threshold
                and c.orphans(t, self._w_ev) >= cfg.precursor_min_orphans):
            c.state, c.since_ns, c.confirmed = ContactState.INCIPIENT_SLIP, t, True
            c.last_slip_ns = t
            ids = tuple(x.pid for x in c.slip_members(since_ns=t - self._w_ev) if x.w > 0)
            for x in c.members:         # the unreleased compressions were micro-slips
                if x.role == SUB and x.open:
                    x.role, x.open, x.w = SLIP, False, max(x.w, weight)
            out.append(self._precursor(c, ev, rate, evidence, ids, onset=True))
        elif c.state == ContactState.INCIPIENT_SLIP and self._due(c, SlipEventType.SLIP_PRECURSOR, t):
            out.append(self._precursor(c, ev, rate, evidence, (ev.packet_id,), onset=False))
        if c.state == ContactState.INCIPIENT_SLIP:
            n_in, sm = self._inner(c, cfg.gross_window_events)
            if (n_in >= cfg.gross_min_inner and rate >= cfg.gross_min_rate_hz
                    and len(c.slip_members(n=cfg.gross_min_events, clean=True)) >= cfg.gross_min_events):
                self._to_gross(c, ev, rate, float(n_in), tuple(x.pid for x in sm), out)
        elif c.state == ContactState.GROSS_SLIP:
            n_in, sm = self._inner(c, cfg.gross_exit_events)
            if n_in == 0 and len(sm) >= cfg.gross_exit_events and not c.texture_on:
                c.state, c.since_ns = ContactState.INCIPIENT_SLIP, t
            elif self._due(c, SlipEventType.SLIP, t):
                out.append(self._slip_event(c, ev, rate, float(n_in), (ev.packet_id,), onset=False))

    def _inner(self, c, n):
        sm = c.slip_members(n=n, clean=True)
        if not sm or c.radius <= 0:
            return 0, sm
        P = np.asarray([m.p for m in sm])
        d = np.linalg.norm(P - c.centre, axis=1)
        return int(np.sum(d < self.config.gross_inner_fraction * c.radius)), sm

    def _due(self, c, kind, t):
        last = c.last_report.get(kind)
        return last is None or t - last >= self._report

    def _precursor(self, c, ev, rate, evidence, ids, onset):
        c.precursor_count += 1
        c.last_report[SlipEventType.SLIP_PRECURSOR] = ev.time_ns
        conf = 1.0 - 2.0 ** (-evidence / self.config.precursor_threshold)
        return SlipEvent(SlipEventType.SLIP_PRECURSOR, ev.time_ns, ev.point_m.copy(), ev.covariance_m2.copy(),
                         c.id, rate, math.nan, _NAN3.copy(), float(conf) * (0.5 + 0.5 * ev.confidence), ids,
                         onset, float(evidence))

    def _to_gross(self, c, ev, rate, n_in, ids, out):
        c.state, c.since_ns = ContactState.GROSS_SLIP, ev.time_ns
        out.append(self._slip_event(c, ev, rate, n_in, ids, onset=True))

    def _slip_event(self, c, ev, rate, n_in, ids, onset):
        c.last_report[SlipEventType.SLIP] = ev.time_ns
        conf = 1.0 - 2.0 ** (-max(n_in, 1.0) / self.config.gross_min_inner)
        if c.texture_on:
            conf = max(conf, 0.75)
        return SlipEvent(SlipEventType.SLIP, ev.time_ns, c.centre.copy(), self._centre_cov(c), c.id, rate,
                         math.nan, self._direction(c, ev.time_ns), float(conf), ids, onset, n_in)

    def _texture(self, c, ev, rate, out):
        """Periodicity of all the contact's latest emissions (touch/release pairs included:
        in a small patch a texture's rarefactions fall in the release gate of its
        compressions). A strictly alternating +,-,+,- run is tapping, not texture."""
        cfg = self.config
        n = cfg.texture_min_intervals + 1
        if len(c.members) < n:
            return
        sm = list(c.members)[-n:]
        pol = np.array([m.pol for m in sm])
        if np.all(pol[1:] * pol[:-1] == -1):
            c.texture_on = False
            c.texture_run = 0
            return
        res = periodicity([m.t for m in sm], tolerance=cfg.texture_tolerance,
                          min_fraction=cfg.texture_min_fraction, max_multiple=cfg.texture_max_multiple)
        if not res.periodic:
            c.texture_on = False
            c.texture_run = 0
            return
        c.texture_run += 1
        if c.texture_run < cfg.texture_confirm_events:
            return
        t = ev.time_ns
        onset = not c.texture_on
        c.texture_on = True
        if c.state != ContactState.GROSS_SLIP:
            if c.state == ContactState.STICK:
                c.confirmed = True
            self._to_gross(c, ev, rate, 0.0, tuple(m.pid for m in sm), out)
        if onset or self._due(c, SlipEventType.TEXTURE, t):
            c.last_report[SlipEventType.TEXTURE] = t
            lam = res.period_s * self._speed if self._speed is not None else math.nan
            out.append(SlipEvent(SlipEventType.TEXTURE, t, c.centre.copy(), self._centre_cov(c), c.id,
                                 res.rate_hz, lam, self._direction(c, t), float(res.regular_fraction),
                                 tuple(m.pid for m in sm), onset, float(res.regular_fraction)))

    def _centre_cov(self, c):
        P = np.asarray([m.p for m in c.members if m.role != PAIRED])
        if len(P) < 2:
            return c.members[-1].cov.copy()
        return np.cov(P.T) / len(P)

    def _direction(self, c, t):
        """Unit tangent direction of the drift of the contact's emissions, or NaN."""
        cfg = self.config
        sm = c.slip_members(since_ns=t - self._w_dir)
        if len(sm) < cfg.direction_min_events:
            return _NAN3.copy()
        ts = np.array([m.t for m in sm], dtype=float) * 1e-9
        P = np.asarray([m.p for m in sm])
        tc = ts - ts.mean()
        stt = float(tc @ tc)
        if stt <= 0:
            return _NAN3.copy()
        v = (tc @ (P - P.mean(axis=0))) / stt
        n = c.centre / np.linalg.norm(c.centre)
        v = v - (v @ n) * n
        res = (P - P.mean(axis=0)) - np.outer(tc, v)
        s2 = float((res * res).sum()) / max(1, 2 * (len(sm) - 2))
        se = math.sqrt(s2 / stt)
        speed = float(np.linalg.norm(v))
        if speed < cfg.direction_min_speed_m_s or speed < cfg.direction_significance * se or speed == 0:
            return _NAN3.copy()
        return v / speed

    def _update_finger(self, t):
        confirmed = [c for c in self.contacts if c.confirmed]
        prev = self._finger
        if not confirmed:
            state, since = ContactState.NO_CONTACT, (prev.since_ns if prev.state == ContactState.NO_CONTACT
                                                     else self._last_end_ns)
            self._finger = FingerState(state, since, _NAN3.copy(), 0.0, 0, -1, 0, t)
            return
        top = max(confirmed, key=lambda c: (int(c.state), c.last_ns))
        since = top.since_ns if top.state != prev.state else prev.since_ns
        if top.state != prev.state:
            since = top.since_ns
        self._finger = FingerState(top.state, int(since), top.centre.copy(), top.rate_hz(t, self._w_rate),
                                   top.precursor_count, top.id, len(confirmed), t)
