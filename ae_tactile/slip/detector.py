# SPDX-License-Identifier: Apache-2.0
"""Slip / texture detector core: localized emissions in, SLIP_PRECURSOR / SLIP / TEXTURE
events and a latched per-finger contact state out. Pure Python + numpy, no rclpy.

    det = SlipDetector(SlipConfig())
    for ev in localized_events:            # LocalizedEvent, in time order (+- reorder tolerance)
        for out in det.process(ev):        # SlipEvent list (often empty)
            publish(out)
    det.advance(now_ns)                    # time passing without events (timer)
    det.state                              # FingerState (latched)

Model (docs/slip.md). A held contact is silent. Under a growing tangential load Q the
Cattaneo-Mindlin slip annulus c < r < a_H, c = a_H (1 - Q/(mu P))^(1/3), spreads inward
from the contact edge and its micro-slips emit from ever more places around the edge.
The evidence is *where* emissions come from, not their sign:

* an emission far from every contact founds a contact (its founding emission: a touch,
  or the first micro-slip of a contact nobody announced);
* two emissions of a contact on one spot (within the gate of their position
  uncertainties) are a touch and its release, or repeated taps: a pair. Polarity helps
  where it is informative: a release (a rarefaction) pairs with an earlier touch (a
  compression) on its spot, never the other way round (a release comes after its touch);
  a later emission on a paired spot, or a compression on a rarefaction's, is a repeat
  (no evidence); after a touch and its release (in the contact, or in one that ended
  within ``association_radius_m``) compressions are touches, not evidence
  (``touched_compression_weight``), for ``evidence_window_s`` and until the contact's
  next compression however late, and a compression taken for a touch stays one (its
  release may be lost); a rarefaction on the founding touch's spot with nothing
  between them is its release however long the hold (the model floor kept);
  the founding emission paired ends the contact after ``release_confirm_s``;
* an emission of a contact on no other emission's spot is micro-slip evidence:
  SLIP_PRECURSOR (STICK -> INCIPIENT_SLIP) when ``precursor_min_emissions`` of them fall
  within ``evidence_window_s``. Micro-slips come from random places round the annulus;
  touches, releases and taps come from a few fixed spots. Any polarity mix is the same;
* SLIP (-> GROSS_SLIP), whether or not a precursor came first, when the latest
  emissions are more likely gross slip (a rate jump to gross_rate_min_hz ..
  gross_rate_max_hz, from the whole contact disc) than the contact's micro-slips going on
  (its own prior rate, from the slip annulus): a sequential likelihood ratio of at least
  ``gross_llr_threshold`` (``_gross_llr``); or when in the latest ``gross_window_s`` at
  least ``gross_min_events`` emissions came and either one lies inside the stick zone
  (closer than ``gross_inner_fraction`` of the contact radius to the centre fitted to its
  emissions), or their rate is a Poisson tail below ``gross_rate_alpha`` of the rate
  before them; or the contact moves;
* a contact's motion (centre and velocity along the surface) is regressed on its
  emissions over ``track_window_s``; a contact that moves significantly is predicted
  forward for association, so a dragged stylus stays one contact;
* TEXTURE while the contact's latest intervals are periodic (robust dispersion test),
  with spatial period = tracked speed x period (moving contact) or the configured sliding
  speed x period (fixed contact).

Work per event is bounded: ring buffers of ``member_history`` emissions per contact,
at most ``max_contacts`` contacts, small fits run only when their input changed.
"""

from __future__ import annotations

import math
from bisect import bisect_left, bisect_right

import numpy as np

from ae_tactile.records import ContactState, EventType

from .config import SlipConfig
from .types import ContactInfo, FingerState, LocalizedEvent, SlipEvent

# member flags; SLIP_EMISSION: came while the contact slipped or moved; TOUCHED: a
# compression that came during touch-release activity (a touch, for as long as it counts)
FOUNDER, EVID, PAIRED, REPEAT, OVERLAP, SLIP_EMISSION, TOUCHED = 1, 2, 4, 8, 16, 32, 64
TRACKED = EVID | REPEAT
_SLIPPING = (ContactState.INCIPIENT_SLIP, ContactState.GROSS_SLIP)
#: a contact's founder is left out of its activity's rate when the silence after it is
#: this many times the mean of the next (up to 4) intervals: a touch, then micro-slips
#: (4: dense contacts loaded 0.1 s after their touch took SLIP at q < 0.9 in 1.3 % of the
#: trials, sparse unannounced ones SLIP within 50 ms 74.0 %; 10: 3.7 % and 75.0 %;
#: without the rule 55.7 % and 76.0 %; 300 and 1,000 trials, scratch runs)
_FOUNDER_SILENCE_RATIO = 10.0
_NAN3 = np.full(3, np.nan)


def _circle_centre(P):
    """Centre (3,) of the circle best fitting points P (n, 3) on the sphere (algebraic Kasa
    fit u^2 + v^2 = 2 cu u + 2 cv v + k in the tangent plane at their centroid, projected
    back on the sphere); None when the points are nearly collinear or the centre lands
    more than 3 spreads from the centroid."""
    k = len(P)
    m = P.sum(axis=0) / k  # P.mean(axis=0), bit for bit, without its Python wrapper
    rn = float(np.sqrt((P * P).sum(axis=1)).sum() / k)
    n = m / math.sqrt(float(m @ m))
    ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - (ref @ n) * n
    e1 /= math.sqrt(float(e1 @ e1))
    n0, n1, n2 = n.tolist()
    a0, a1, a2 = e1.tolist()
    e2 = np.array([n1 * a2 - n2 * a1, n2 * a0 - n0 * a2, n0 * a1 - n1 * a0])  # n x e1
    D = P - m
    u, v = D @ e1, D @ e2
    suu, svv, suv = float(u @ u), float(v @ v), float(u @ v)
    tr, det = (suu + svv) / k, (suu * svv - suv * suv) / (k * k)
    disc = math.sqrt(max(tr * tr / 4 - det, 0.0))
    lo, hi = tr / 2 - disc, tr / 2 + disc
    if hi <= 0.0 or lo < 0.01 * hi:
        return None
    b = u * u + v * v
    r1, r2 = 2 * float(u @ b), 2 * float(v @ b)
    a11, a12, a22 = 4 * suu, 4 * suv, 4 * svv
    dd = a11 * a22 - a12 * a12
    cu, cv = (a22 * r1 - a12 * r2) / dd, (a11 * r2 - a12 * r1) / dd
    if math.hypot(cu, cv) > 3.0 * math.sqrt(hi):
        return None
    c = m + cu * e1 + cv * e2
    return c * (rn / math.sqrt(float(c @ c)))


def _percentile90(d):
    """np.percentile(d, 90) (linear interpolation, numpy's rounding) of a short list of
    floats, without numpy's per-call overhead."""
    s = sorted(d)
    n = len(s)
    v = (n - 1) * 0.9
    lo = math.floor(v)
    hi = min(lo + 1, n - 1)
    g = v - lo
    a, b = s[lo], s[hi]
    diff = b - a
    return a + diff * g if g < 0.5 else b - diff * (1 - g)


def _multiples(dt, unit):
    """Periods in each interval: 1, unless clearly more (>= 1.7 units: a missed packet;
    timing jitter of 20 % of the period gives 1.7 in 0.3 % of the intervals)."""
    r = dt / unit
    return np.where(r < 1.7, 1.0, np.round(r))


_MISS_PENALTY = 2.0 * math.log(9.0)
#: ambiguous intervals whose period counts `_period_fit_best` tries both ways: at most
#: 2^8 fits, and at most this many times (counts) in all (2^6 fits of a run of 64)
_MAX_AMBIGUOUS = 8
_MAX_FIT_TIMES = 4096


def _period_fit_best(ts_ns, dt, units):
    """Period T (s), its standard error and the period count of each interval, the counts
    chosen by the whole fit: a wrong count shifts every later time by a period, a jitter
    of sd s T only one time by s T. For each trial ``unit`` (ns: the median interval, a
    period found before), every interval counts `_multiples` units, except the ambiguous
    ones (1.25 .. 2.75 units, > 0.25 from a whole number: a jittered double interval or a
    long single one; the ``_MAX_AMBIGUOUS`` farthest from a whole number, fewer in a long
    run: at most ``_MAX_FIT_TIMES`` times in all), whose counts are tried both ways in one
    batch. Score n ln(RSS) (Gaussian jitter, its variance fitted) + 2 ln 9 per missed
    packet (one interval in ten spans two periods a priori); the least wins over every
    unit. (A unit that is itself wrong, e.g. a period that took four long singles for
    doubles, cannot reach the right counts alone: hence several units.)
    Least squares t_j = t_0 + K_j T on the cumulative counts K_j (c: less the mean):
    T = Kc.tc / Kc.Kc, RSS = tc.tc - (Kc.tc)^2 / Kc.Kc."""
    tc = (ts_ns - ts_ns[0]) * 1e-9
    tc -= tc.mean()
    stt = float(tc @ tc)
    n = ts_ns.size
    n_amb = max(0, min(_MAX_AMBIGUOUS, (_MAX_FIT_TIMES // n).bit_length() - 1))
    K = np.zeros((1, n))
    best = None
    tried = []
    for unit in units:
        if not unit > 0:
            continue
        r = dt / unit
        rr = np.rint(r)
        dev = np.abs(r - rr)
        kk = np.where(r < 1.7, 1.0, rr)
        amb = np.flatnonzero((dev > 0.25) & (r > 1.25) & (r < 2.75))
        if amb.size > n_amb:
            amb = amb[np.argsort(-dev[amb])[:n_amb]]
        key = (kk.tobytes(), amb.tobytes())
        if key in tried:  # the same counts to try as a unit before
            continue
        tried.append(key)
        if amb.size:
            bits = (np.arange(1 << amb.size)[:, None] >> np.arange(amb.size)) & 1
            k2 = np.repeat(kk[None, :], bits.shape[0], axis=0)
            k2[:, amb] = np.floor(r[amb]) + bits
        else:
            k2 = kk[None, :]
        if K.shape[0] != k2.shape[0]:
            K = np.zeros((k2.shape[0], n))
        np.cumsum(k2, axis=1, out=K[:, 1:])
        Kc = K - K.mean(axis=1, keepdims=True)
        skk = np.einsum("ij,ij->i", Kc, Kc)
        skt = Kc @ tc
        rss = np.maximum(stt - skt * skt / skk, 1e-30)
        score = n * np.log(rss) + _MISS_PENALTY * (k2.sum(axis=1) - k2.shape[1])
        j = int(np.argmin(score))
        if best is None or score[j] < best[0]:
            best = (float(score[j]), Kc[j].copy(), k2[j])
    if best is None:
        return math.nan, math.inf, None
    _, Kc, kk = best
    # the chosen fit's error from its residuals: tc.tc - (Kc.tc)^2 / Kc.Kc cancels when
    # the jitter is tiny (a near-perfect train), the residuals do not
    skk = float(Kc @ Kc)
    T = float(Kc @ tc) / skk
    res = tc - Kc * T
    se = math.sqrt(float(res @ res) / max(1.0, n - 2.0) / skk)
    return T, se, kk


def _drift_fit(t_ns, P):
    """Drift of emission points along the surface, least squares p(t) = p_m + v (t - t_m)
    with v projected onto the tangent plane at p_m (one 4 x 4 moment matrix of (t, p)):
    (v (3,) m/s, p_m (3,) m, t_m s, s2 m^2, stt s^2), s2 = |p - p_m - v (t - t_m)|^2 summed
    / (2 (n - 2)) (residual variance per tangent axis), stt = sum (t - t_m)^2; None when
    the times have no spread."""
    n = len(P)
    Z = np.empty((n, 4))
    t_ref = int(t_ns[0])  # times from the first, in integer ns: exact for any clock origin
    Z[:, 0] = (t_ns - t_ref) * 1e-9
    Z[:, 1:] = P
    zm = Z.sum(axis=0) / n
    Zc = Z - zm
    M = (Zc.T @ Zc).tolist()
    stt = M[0][0]
    if not stt > 0:
        return None
    g = M[0][1:]  # sum (t - t_m)(p - p_m)
    tm, px, py, pz = zm.tolist()
    tm += t_ref * 1e-9
    pn = math.sqrt(px * px + py * py + pz * pz)
    nx, ny, nz = px / pn, py / pn, pz / pn
    vx, vy, vz = g[0] / stt, g[1] / stt, g[2] / stt
    d = vx * nx + vy * ny + vz * nz
    vx, vy, vz = vx - d * nx, vy - d * ny, vz - d * nz
    # sum |Pc - tc v|^2 = tr(Pc' Pc) - 2 v . g + stt |v|^2
    rss = M[1][1] + M[2][2] + M[3][3] - 2.0 * (vx * g[0] + vy * g[1] + vz * g[2])
    rss += stt * (vx * vx + vy * vy + vz * vz)
    s2 = max(rss, 0.0) / max(1, 2 * (n - 2))
    return np.array([vx, vy, vz]), zm[1:], tm, s2, stt


class _Contact:
    """One tracked contact: ring buffers of its emissions and its state."""

    def __init__(self, cid, t_ns, history, confirmed):
        H = history
        self.id = cid
        self.H = H
        self.t = np.zeros(H, np.int64)
        self.p = np.zeros((H, 3))
        self.var = np.zeros(H)  # per-axis position variance (m^2)
        self.pol = np.zeros(H, np.int8)
        self.pid = np.zeros(H, np.int64)
        self.flags = np.zeros(H, np.uint8)
        self.tlist = [0] * H  # self.t as Python ints (cheap per-element reads)
        self.flist = [0] * H  # self.flags as Python ints
        self.n_fit_members = 0  # valid members with EVID set and OVERLAP clear
        # the box holding every compression the contact ever had (m, grown only) and their
        # largest per-axis variance: a cheap test for a far release's touch
        self.touch_box = [math.inf, math.inf, math.inf, -math.inf, -math.inf, -math.inf]
        self.touch_var = 0.0
        self.n = 0
        self.state = ContactState.STICK
        self.since_ns = t_ns
        self.created_ns = t_ns
        self.last_ns = t_ns
        self.confirmed = confirmed
        self.pending_release_ns = None
        self.pending_in_slip = False  # a release-like emission while slipping
        self.pending_release_spot = None  # (point, variance) of the founder's release
        self.touch_release_ns = None  # latest touch-release pair
        self.touch_release_open = False  # no compression came since it (the next is a touch)
        self.founder = None  # (point, variance, polarity) of the founder
        self.founder_ns = t_ns  # its time
        self.founder_n = 0  # its index among the contact's emissions (c.n when added)
        self.founder_paired = False  # an emission paired with the founder (its release)
        self.last_p = None  # latest emission's point
        self.precursor_count = 0
        self.last_report = {}
        self.texture_on = False
        self.texture_run = 0
        self._centre = None
        self.centre_xyz = None  # self.centre as a tuple of floats (association)
        self.fitted = False  # centre from a circle fit to micro-slips
        self.radius = 0.0
        self.n_evid_fit = -1  # evidence count at the last circle fit
        self.rings = []  # (time ns, centre, radius) of the latest circle fits
        self.moving = False
        self.vel = np.zeros(3)
        self.track_t = 0.0  # reference time (s) of the motion fit
        self.track_c = None  # centre at track_t
        self.track_se = math.inf  # standard error of the speed (m/s)
        self.events_since_track = 0
        self.rate_key = None
        self.rate_val = 0.0

    @property
    def centre(self):
        """Centre (3,) of a fixed contact (m); ``centre_xyz`` holds the same as floats."""
        return self._centre

    @centre.setter
    def centre(self, value):
        self._centre = value
        self.centre_xyz = (
            None if value is None else (float(value[0]), float(value[1]), float(value[2]))
        )

    # -------------------------------------------------------------- buffers
    def add(self, t, p, var, pol, pid, flags):
        i = self.n % self.H
        if self.n >= self.H and (int(self.flags[i]) & (EVID | OVERLAP)) == EVID:
            self.n_fit_members -= 1  # the overwritten slot leaves the fit set
        if (flags & (EVID | OVERLAP)) == EVID:
            self.n_fit_members += 1
        self.tlist[i] = int(t)
        self.flist[i] = flags
        self.t[i] = t
        self.p[i] = p
        self.var[i] = var
        self.pol[i] = pol
        self.pid[i] = pid
        self.flags[i] = flags
        self.n += 1
        if pol > 0:
            b = self.touch_box
            x, y, z = float(p[0]), float(p[1]), float(p[2])
            if x < b[0]:
                b[0] = x
            if x > b[3]:
                b[3] = x
            if y < b[1]:
                b[1] = y
            if y > b[4]:
                b[4] = y
            if z < b[2]:
                b[2] = z
            if z > b[5]:
                b[5] = z
            if var > self.touch_var:
                self.touch_var = float(var)
        if t >= self.last_ns:
            self.last_ns = t
            self.last_p = (float(p[0]), float(p[1]), float(p[2]))
        return i

    def valid(self):
        """Number of valid slots (the first ``k`` slots)."""
        return self.n if self.n < self.H else self.H

    def centre_at(self, t_ns):
        if self.moving and self.track_c is not None:
            return self.track_c + self.vel * (t_ns * 1e-9 - self.track_t)
        return self.centre


class SlipDetector:
    """Stateful slip / texture detector for one finger (see the module docstring)."""

    def __init__(self, config: SlipConfig | None = None):
        if config is None:
            config = SlipConfig()
        if not isinstance(config, SlipConfig):
            raise TypeError(f"config must be a SlipConfig, got {type(config).__name__}")
        self._apply(config)
        self._speed = config.sliding_speed_m_s
        self.contacts: list[_Contact] = []
        self._next_id = 1
        self.now_ns = None
        self.counts = {
            "events": 0,
            "rejected_low_confidence": 0,
            "rejected_out_of_order": 0,
            "rejected_non_finite": 0,
            "rejected_bad_type": 0,
            "releases": 0,
            "releases_cancelled": 0,
            "orphans_dropped": 0,
            "pairs": 0,
            "repeats": 0,
            "evidence": 0,
            "contacts_created": 0,
            "contacts_dropped": 0,
        }
        self._finger = FingerState(ContactState.NO_CONTACT, 0, _NAN3.copy(), 0.0, 0, -1, 0, 0)
        self._fs_state, self._fs_since, self._fs_pending = ContactState.NO_CONTACT, 0, None
        self._last_end_ns = 0
        self._last_t = None
        #: (touch-release time ns, spot (3,)) of contacts that ended, at most max_contacts
        self._ended_activity = []

    def _apply(self, c: SlipConfig):
        def ns(s):
            return int(round(s * 1e9))

        self.config = c
        self._w_ev, self._w_rate, self._w_track = (
            ns(c.evidence_window_s),
            ns(c.rate_window_s),
            ns(c.track_window_s),
        )
        self._confirm, self._quiet, self._report = (
            ns(c.release_confirm_s),
            ns(c.quiet_s),
            ns(c.report_interval_s),
        )
        self._reorder, self._guard = ns(c.reorder_tolerance_s), ns(c.overlap_guard_s)
        self._w_gross, self._w_hist = ns(c.gross_window_s), ns(c.gross_history_s)
        self._w_prior = ns(c.gross_prior_s)
        self._assoc2 = c.association_radius_m**2
        # interval model of a texture: k periods (k = 1, 2, 3: missed packets), sd s sqrt(k)
        km = np.arange(1, c.texture_max_multiple + 1, dtype=float)[:, None]
        prior = np.where(km == 1, 0.9, 0.1 / max(1, c.texture_max_multiple - 1))
        self._tex_k, self._tex_s = km, c.texture_interval_sd * np.sqrt(km)
        self._tex_w = np.log(prior) - 0.5 * math.log(2 * math.pi)
        self._g2 = c.release_gate_sigma**2
        self._f2 = c.release_floor_m**2

    # ------------------------------------------------------------------ public API
    @property
    def state(self) -> FingerState:
        """Latched finger state (as of the last ``process`` / ``advance``)."""
        return self._finger_state()

    def update_config(self, **changes) -> SlipConfig:
        """Change run-time-safe parameters (``SlipConfig.runtime_fields()``) at once; the
        whole new configuration is validated first (ValueError, nothing changed)."""
        bad = sorted(set(changes) - set(SlipConfig.runtime_fields()))
        if bad:
            raise ValueError(
                f"SlipConfig fields {bad} cannot change at run time "
                f"(runtime fields: {', '.join(SlipConfig.runtime_fields())})"
            )
        new = self.config.replace(**changes)
        self._finger_state()  # the state as of now, under the old rate window
        self._apply(new)
        if "sliding_speed_m_s" in changes:
            self._speed = new.sliding_speed_m_s
        return new

    def set_sliding_speed(self, speed_m_s: float | None) -> None:
        """Sliding speed for TEXTURE spatial periods of fixed contacts (m/s, > 0), or None."""
        if speed_m_s is not None:
            v = float(speed_m_s)
            if not math.isfinite(v) or v <= 0:
                raise ValueError(
                    f"sliding speed must be a positive number of m/s, got {speed_m_s!r}"
                )
            speed_m_s = v
        self._speed = speed_m_s

    def contact_infos(self) -> list[ContactInfo]:
        """Snapshots of every tracked contact (unconfirmed candidates included)."""
        now = self.now_ns if self.now_ns is not None else 0
        out = []
        for c in self.contacts:
            out.append(
                ContactInfo(
                    c.id,
                    c.state,
                    c.since_ns,
                    c.centre_at(now).copy(),
                    c.radius,
                    True,
                    c.confirmed,
                    c.pending_release_ns is not None,
                    self._rate(c, now),
                    c.precursor_count,
                    c.valid(),
                    c.last_ns,
                    c.vel.copy() if c.moving else np.zeros(3),
                    c.moving,
                )
            )
        return out

    def reset(self) -> None:
        """Forget every contact (e.g. after a gap in the data)."""
        self.contacts.clear()
        self._ended_activity.clear()
        self.now_ns = None
        self._last_t = None
        self._finger = FingerState(ContactState.NO_CONTACT, 0, _NAN3.copy(), 0.0, 0, -1, 0, 0)
        self._fs_state, self._fs_since, self._fs_pending = ContactState.NO_CONTACT, 0, None

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
            return self._finger_state()
        self._expire(now)
        self._update_finger(now)
        return self._finger_state()

    def _expire(self, now):
        self.now_ns = now
        for c in list(self.contacts):
            wait = self._quiet if c.pending_in_slip else self._confirm
            if c.pending_release_ns is not None and now - c.pending_release_ns >= wait:
                self._end_contact(c)
                continue
            if not c.confirmed and now - c.last_ns >= self._w_ev:
                self.contacts.remove(c)
                continue
            if c.state in _SLIPPING and now - c.last_ns >= self._quiet:
                c.state = ContactState.STICK
                c.since_ns = c.last_ns + self._quiet
                c.texture_on = False
                c.texture_run = 0
                c.moving = False

    def process(self, ev: LocalizedEvent) -> list[SlipEvent]:
        """Feed one localized emission; returns the events it produced. Never raises on
        bad event data: it is rejected and counted in ``counts``."""
        if not isinstance(ev, LocalizedEvent):
            self.counts["rejected_bad_type"] += 1
            return []
        p = ev.point_m
        px, py, pz = p.tolist()
        cov = ev.covariance_m2
        cl = cov.ravel().tolist()
        tr = cl[0] + cl[4] + cl[8]
        if not (
            math.isfinite(px + py + pz)
            and math.isfinite(tr)
            and all(map(math.isfinite, cl))
            and px * px + py * py + pz * pz > 0.0
        ):
            self.counts["rejected_non_finite"] += 1
            return []
        t = ev.time_ns
        if self.now_ns is not None and t < self.now_ns - self._reorder:
            self.counts["rejected_out_of_order"] += 1
            return []
        if ev.confidence < self.config.min_confidence:
            self.counts["rejected_low_confidence"] += 1
            return []
        self.counts["events"] += 1
        if self.now_ns is None or t > self.now_ns:
            self._expire(t)
        out: list[SlipEvent] = []
        var = 0.5 * max(tr, 0.0)
        c = self._associate(px, py, pz, t, ev.polarity, var)
        overlap = self._last_t is not None and abs(t - self._last_t) < self._guard
        self._last_t = t if self._last_t is None else max(t, self._last_t)
        if c is not None and not c.confirmed and ev.polarity > 0:
            # a touch next to a lone rarefaction (a release whose touch was missed): the
            # touch founds the contact, the orphan is forgotten
            self.contacts.remove(c)
            self.counts["orphans_dropped"] += 1
            c = None
        if c is None:
            self._found(ev, p, var, t, overlap)
            self._update_finger(self.now_ns)
            return out
        self._member(c, ev, p, var, t, overlap, out)
        self._update_finger(self.now_ns)
        return out

    # ------------------------------------------------------------------ tracking
    def _associate(self, px, py, pz, t, pol=1, var=0.0):
        """The contact whose (predicted) centre, or whose latest emission of the last
        track_window_s, is nearest within association_radius_m (the latest emission carries
        a contact that moves before its track is established); failing that, for a
        rarefaction (polarity ``pol`` < 0, per-axis variance ``var`` m^2), the contact of an
        unpaired touch on its spot."""
        best, best_d2 = None, self._assoc2
        for c in self.contacts:
            q = c.centre_xyz if not c.moving or c.track_c is None else c.centre_at(t)
            dx, dy, dz = px - q[0], py - q[1], pz - q[2]
            d2 = dx * dx + dy * dy + dz * dz
            lp = c.last_p
            if lp is not None and t - c.last_ns <= self._w_track:
                dx, dy, dz = px - lp[0], py - lp[1], pz - lp[2]
                d2 = min(d2, dx * dx + dy * dy + dz * dz)
            if d2 <= best_d2:
                best, best_d2 = c, d2
        if best is None and pol < 0:
            best = self._touch_of_release(px, py, pz, var, t)
        return best

    def _touch_of_release(self, px, py, pz, var, t):
        """The contact (sticking, not moving) holding a touch this release pairs with
        (`_held_touch`, or its founder's record, `_founder_release`), however far its
        centre: a release belongs to its touch's contact, whatever the touches after it
        made of the contact (touches wandering over seconds of holds carry it farther than
        association_radius_m). The nearest such touch's contact; None if none."""
        p = np.array((px, py, pz))
        best, best_d2 = None, math.inf
        for c in self.contacts:
            if c.state in _SLIPPING or c.moving:
                continue
            b = c.touch_box
            r = math.sqrt(self._g2 * (c.touch_var + var + self._f2))  # the widest gate
            if not (
                b[0] - r <= px <= b[3] + r
                and b[1] - r <= py <= b[4] + r
                and b[2] - r <= pz <= b[5] + r
            ):
                continue  # no compression of this contact within reach
            d = math.inf
            k = c.valid()
            F = c.flags[:k]
            m = (c.pol[:k] > 0) & ((F & PAIRED) == 0)
            if m.any():
                D = c.p[:k] - p
                d2 = np.einsum("ij,ij->i", D, D)
                vsum = c.var[:k] + var
                m &= d2 <= self._g2 * (vsum + self._f2)
                if m.any():
                    m &= self._held_touch(F, d2, vsum, c.t[:k] >= t - self._w_ev)
                    if m.any():
                        d = float(d2[m].min())
            if d == math.inf and self._founder_release(c, -1, p, var, t):
                fd = c.founder[0] - p
                d = float(fd @ fd)
            if d < best_d2:
                best, best_d2 = c, d
        return best

    def _found(self, ev, p, var, t, overlap):
        """A new contact founded by ``ev``. A lone rarefaction (a release, or a micro-slip
        of a contact nobody announced) stays unconfirmed until a second emission joins."""
        if len(self.contacts) >= self.config.max_contacts:
            idle = [c for c in self.contacts if c.state not in _SLIPPING] or self.contacts
            drop = min(idle, key=lambda c: (c.confirmed, c.last_ns))
            self.contacts.remove(drop)
            self.counts["contacts_dropped"] += 1
        c = _Contact(self._next_id, t, self.config.member_history, confirmed=ev.polarity >= 0)
        self._next_id += 1
        c.add(t, p, var, ev.polarity, ev.packet_id, FOUNDER | (OVERLAP if overlap else 0))
        c.founder = (p.copy(), var, int(ev.polarity))
        c.founder_ns, c.founder_n = t, 0
        c.centre = p.copy()
        self.contacts.append(c)
        self.counts["contacts_created"] += 1
        return c

    def _member(self, c, ev, p, var, t, overlap, out):
        cfg = self.config
        k = c.valid()
        T, F = c.t[:k], c.flags[:k]
        slipping = c.state in _SLIPPING or c.moving  # a moving contact has no fixed spots
        flags = OVERLAP if overlap else 0
        if slipping:
            # every emission of a slipping contact is a slip emission; one on the founding
            # touch's spot with the opposite polarity may be its release: the contact ends
            # unless another emission follows within release_confirm_s
            flags |= EVID | SLIP_EMISSION
            fp, fvar, fpol = c.founder
            fd = fp - p
            if ev.polarity * fpol < 0 and float(fd @ fd) <= self._g2 * (fvar + var + self._f2):
                c.pending_release_ns, c.pending_in_slip = t, True  # confirmed by quiet_s
                c.pending_release_spot = (p.copy(), var)
                self.counts["releases"] += 1
            elif c.pending_release_ns is not None:
                c.pending_release_ns = None
                self.counts["releases_cancelled"] += 1
        else:
            D = c.p[:k] - p
            d2 = np.einsum("ij,ij->i", D, D)
            vsum = c.var[:k] + var
            spot = d2 <= self._g2 * (vsum + self._f2)
            if spot.any():
                recent = T >= t - self._w_ev
                near = spot & recent
                # a pair: an emission of unknown polarity with any unpaired one of the
                # window on its spot; a release (a rarefaction) with an unpaired touch (a
                # compression) on its spot, never the other way round
                cand = spot & ((F & PAIRED) == 0)
                if ev.polarity > 0:
                    cand[:] = False
                elif ev.polarity < 0:
                    held = self._held_touch(F, d2, vsum, recent)
                    if c.n - c.founder_n == 1:
                        # nothing since the founding touch (a held touch is silent): on
                        # its spot, model floor included, is its release however long
                        # the hold
                        held = held | ((F & FOUNDER) != 0)
                    cand &= (c.pol[:k] > 0) & held
                else:
                    cand &= recent
            else:
                near = cand = spot
            if not cand.any() and self._founder_release(c, ev.polarity, p, var, t):
                # the founding touch's release, its slot no longer in the ring buffer: it
                # ends the contact after release_confirm_s, as any release does
                flags |= PAIRED
                c.founder_paired = True
                c.pending_release_ns, c.pending_in_slip = t, False
                c.pending_release_spot = (p.copy(), var)
                self.counts["pairs"] += 1
                self.counts["releases"] += 1
            elif cand.any() or near.any():
                # on the spot of an earlier emission: a release / tap pair, or a repeat
                if cand.any():
                    j = int(np.flatnonzero(cand)[np.argmin(d2[cand])])
                    if (int(F[j]) & (EVID | OVERLAP)) == EVID:
                        c.n_fit_members -= 1
                    F[j] = (F[j] | PAIRED) & (0xFF ^ EVID)
                    c.flist[j] = int(F[j])
                    flags |= PAIRED
                    self.counts["pairs"] += 1
                    founder = bool(F[j] & FOUNDER)
                    if founder:
                        c.founder_paired = True
                        c.pending_release_ns, c.pending_in_slip = t, False
                        c.pending_release_spot = (p.copy(), var)
                        self.counts["releases"] += 1
                    if (
                        (not founder or c.n - c.founder_n == 1)
                        and ev.polarity < 0 < int(c.pol[j])
                        and float(d2[j]) <= 9.0 * (float(c.var[j]) + var)
                    ):
                        # a touch and its release on one spot (3 sigma, no model floor: a
                        # micro-slip landing near an earlier one rarely comes that close);
                        # the founder's too when nothing came between them (a held touch
                        # is silent)
                        c.touch_release_ns = t
                        c.touch_release_open = True
                else:
                    if ev.polarity > 0 and c.pending_release_ns is not None:
                        fp, fvar, _ = c.founder
                        rp, rvar = c.pending_release_spot or (fp, fvar)
                        fd, rd = fp - p, rp - p
                        if min(
                            float(fd @ fd) - self._g2 * (fvar + var + self._f2),
                            float(rd @ rd) - self._g2 * (rvar + var + self._f2),
                        ) <= 0.0:
                            # the founder's (or its release's) spot touched again before
                            # the release was confirmed: the re-touch takes over as the
                            # founder and the contact goes on; its release pairs with it
                            # here and ends the contact (not a lone rarefaction after it
                            # ended)
                            c.pending_release_ns = None
                            c.founder = (p.copy(), var, 1)
                            c.founder_ns, c.founder_n = t, c.n
                            c.founder_paired = False
                            flags |= FOUNDER
                            self.counts["releases_cancelled"] += 1
                    flags |= REPEAT
                    self.counts["repeats"] += 1
            else:
                if c.pending_release_ns is not None:
                    ev_m = (F & EVID) != 0
                    if not (T[ev_m] >= t - self._w_ev).any():
                        # the founder was released: this is a new touch nearby
                        self._end_contact(c)
                        self._found(ev, p, var, t, overlap)
                        return
                    c.pending_release_ns = None
                    self.counts["releases_cancelled"] += 1
                flags |= EVID
                self.counts["evidence"] += 1
        c.add(t, p, var, ev.polarity, ev.packet_id, flags)
        c.confirmed = True
        self._geometry(c)
        c.events_since_track += 1
        if c.events_since_track >= 8 or (c.moving and c.events_since_track >= 4):
            self._track(c, t)
        if flags & EVID and c.state != ContactState.GROSS_SLIP:
            # micro-slip evidence in the window (needed only for a precursor decision)
            k = c.valid()
            T, F = c.t[:k], c.flags[:k]
            ev_mask = ((F & EVID) != 0) & (T > t - self._w_ev)
            n_ev = float(ev_mask.sum())
            w = cfg.compression_evidence_weight
            w_touch = min(w, cfg.touched_compression_weight)
            if (
                c.touch_release_open
                or (c.touch_release_ns is not None and t - c.touch_release_ns <= self._w_ev)
                or self._ended_activity_near(t, p, c.founder[0])
            ):
                w = w_touch
                if ev.polarity > 0:
                    # a touch when it came, a touch for as long as it counts (its release
                    # may be lost): the weight an emission had on arrival stays
                    i = (c.n - 1) % c.H
                    F[i] |= TOUCHED
                    c.flist[i] = int(F[i])
            if w < 1.0:
                n_ev -= (1.0 - w) * float((ev_mask & (c.pol[:k] > 0)).sum())
            if w > w_touch:
                n_ev -= (w - w_touch) * float((ev_mask & ((F & TOUCHED) != 0)).sum())
            if c.state == ContactState.STICK and n_ev >= cfg.precursor_min_emissions:
                c.state, c.since_ns = ContactState.INCIPIENT_SLIP, t
                idx = np.flatnonzero(ev_mask)
                idx = idx[np.argsort(T[idx], kind="stable")]
                ids = tuple(int(x) for x in c.pid[idx] if x != ev.packet_id) + (ev.packet_id,)
                out.append(self._precursor(c, ev, n_ev, ids, onset=True))
            elif c.state == ContactState.INCIPIENT_SLIP and self._due(c, 3, t):
                out.append(self._precursor(c, ev, n_ev, (ev.packet_id,), onset=False))
        if c.state != ContactState.GROSS_SLIP and flags & (EVID | REPEAT):
            why = self._gross_test(c, t)
            if why:
                c.state, c.since_ns = ContactState.GROSS_SLIP, t
                out.append(self._slip_event(c, ev, why, onset=True))
        elif c.state == ContactState.GROSS_SLIP and self._due(c, 4, t):
            out.append(self._slip_event(c, ev, 0.0, onset=False))
        self._texture(c, ev, out)
        if ev.polarity > 0:
            c.touch_release_open = False

    def _held_touch(self, F, d2, vsum, recent):
        """Which buffered emissions (flags ``F``, squared distances ``d2`` m^2, summed
        per-axis variances ``vsum``) a release may pair with by time and place: those of
        the evidence window (the same-spot gate, model floor included), and older ones
        however old, since a grasp is held as long as it is held, if they came while the
        contact stuck (a slipping contact's emissions are slip, not touches) and within
        ``release_gate_sigma`` sigma of the difference without the model floor (a
        touch's release lands on its spot to the localization error; a micro-slip near
        an old one rarely does)."""
        return recent | (((F & SLIP_EMISSION) == 0) & (d2 <= self._g2 * vsum))

    def _founder_release(self, c, pol, p, var, t):
        """Is an emission of polarity ``pol`` at ``p`` (per-axis variance ``var``, time
        ``t``) the release of the contact's founding touch after the ring buffer
        overwrote the founder's slot? The founder unpaired, the polarities fitting (a
        rarefaction after a compression; unknown polarity only within the evidence
        window) and on its spot as `_held_touch` has it."""
        if (
            c.founder_paired
            or c.pending_release_ns is not None
            or c.n - c.founder_n < c.H  # still in the buffer: the pairing sees it
        ):
            return False
        fp, fvar, fpol = c.founder
        recent = t - c.founder_ns <= self._w_ev
        if pol > 0 or (pol < 0 and fpol <= 0) or (pol == 0 and not recent):
            return False
        fd = fp - p
        d2 = float(fd @ fd)
        return d2 <= self._g2 * (fvar + var + (self._f2 if recent else 0.0))

    def _geometry(self, c):
        """Centre (circle fit to the evidence emissions, refitted when their number changed:
        every one up to 16, then every 4th) and radius (90th percentile of their distances)."""
        n = c.n_fit_members
        if n < 3 or n == c.n_evid_fit or (n > 16 and abs(n - c.n_evid_fit) < 4):
            return
        k = c.valid()
        F = c.flags[:k]
        m = ((F & EVID) != 0) & ((F & OVERLAP) == 0)
        c.n_evid_fit = n
        P = c.p[:k][m]
        centre = _circle_centre(P) if n >= self.config.fit_min_events else None
        if centre is not None:
            c.centre, c.fitted = centre, True
        d = np.sqrt(np.einsum("ij,ij->i", P - c.centre, P - c.centre))
        c.radius = _percentile90(d.tolist())
        if c.fitted:
            c.rings.append((c.last_ns, c.centre, c.radius))
            if len(c.rings) > 8:
                del c.rings[0]

    def _track(self, c, t):
        """Motion regression p(t) = c0 + v (t - t_mean) over the track window."""
        c.events_since_track = 0
        cfg = self.config
        k = c.valid()
        F = c.flags[:k]
        # the latest emissions within track_window_s, or the latest 12 within 4 x that
        # (a slow stylus emits a few per window)
        m = (
            ((F & (OVERLAP | PAIRED)) == 0)
            & ((F & TRACKED) != 0)
            & (c.t[:k] > t - 4 * self._w_track)
        )
        recent = m & (c.t[:k] > t - self._w_track)
        if int(recent.sum()) >= 12:
            m = recent
        elif int(m.sum()) > 12:
            idx = np.flatnonzero(m)
            keep = idx[np.argsort(c.t[:k][idx])[-12:]]
            m = np.zeros(k, bool)
            m[keep] = True
        n = int(m.sum())
        if n < max(cfg.track_min_events, 3):
            c.moving = False
            return
        fit = _drift_fit(c.t[:k][m], c.p[:k][m])
        if fit is None:
            return
        v, pm, tm, s2, stt = fit
        se = math.sqrt(s2 / stt)
        speed = math.sqrt(float(v @ v))
        tk = c.t[:k][m]
        c.track_se = se
        was = c.moving
        # a moving contact: fast enough, significant, its emissions close to the track (a
        # few fixed spots hit in turn are no motion), and it left its spot: the track spans
        # more than the same-spot gate (a spot hit again and again, e.g. apex phantoms of
        # electrical interference, drifts within it)
        span = speed * float(tk.max() - tk.min()) * 1e-9
        c.moving = (
            speed >= cfg.min_speed_m_s
            and speed >= cfg.track_significance * se
            and s2 <= cfg.track_max_residual_m**2
            and span * span > self._g2 * (2.0 * float(c.var[:k][m].sum()) / n + self._f2)
        )
        if c.moving:
            c.vel, c.track_t, c.track_c = v, tm, pm
        elif was:
            c.centre = c.centre_at(t) if c.track_c is not None else c.centre

    @staticmethod
    def _motion_fit(c, m):
        """(speed, its standard error) (m/s) of the members ``m`` along a great circle: the
        plane through the centre of the sphere that best holds them (the eigenvectors of
        their 3 x 3 moment matrix), the angle phi of each in that plane regressed on time,
        speed = |p| dphi/dt. (A straight-line fit in 3-D would read the curvature of a
        stroke over the sphere as a lower speed: -5 % over 14 mm on R = 10 mm.) A stroke
        that turns is not a great circle: biased."""
        k = c.valid()
        n = int(m.sum())
        if n < 6:
            return None
        ts = c.t[:k][m] * 1e-9
        P = c.p[:k][m]
        try:  # the plane: P'P's eigenvectors (ascending), as P's right singular vectors
            _, ev3 = np.linalg.eigh(P.T @ P)
        except np.linalg.LinAlgError:
            return None
        u, w, normal = ev3[:, 2], ev3[:, 1], ev3[:, 0]
        pu = P @ u
        if pu.sum() < 0:  # singular vectors have no sign: face the points
            pu = -pu
        phi = np.arctan2(P @ w, pu)
        tc = ts - ts.mean()
        stt = float(tc @ tc)
        if stt <= 0:
            return None
        om = float(tc @ (phi - phi.mean())) / stt
        res = phi - phi.mean() - om * tc
        rn = float(np.sqrt(np.einsum("ij,ij->i", P, P)).mean())
        # the scatter round the track is isotropic in the tangent plane (the contact patch,
        # localization): the variance along it (n - 2 dof) pooled with the distances from
        # the great circle's plane (n - 2 more), so that the first report, made once the
        # standard error falls below a bound, is not made on a chance low estimate of it
        off = P @ normal
        s2 = (rn * rn * float(res @ res) + float(off @ off)) / max(1, 2 * n - 4)
        return rn * abs(om), math.sqrt(s2 / stt)

    def _end_contact(self, c):
        if c in self.contacts:
            self.contacts.remove(c)
        if c.pending_release_ns is not None:
            self._last_end_ns = c.pending_release_ns
        if c.touch_release_ns is not None:
            # its touch-release activity outlives it (`_ended_activity_near`)
            spot = c.pending_release_spot[0] if c.pending_release_spot is not None else c.last_p
            act = self._ended_activity
            act[:] = [a for a in act if c.touch_release_ns - a[0] <= self._w_ev]
            act.append((c.touch_release_ns, np.array(spot, dtype=float)))
            if len(act) > self.config.max_contacts:
                del act[0]  # bounded work per event: the oldest forgotten first

    def _ended_activity_near(self, t, *points):
        """Did a contact that ended see a touch and its release within evidence_window_s
        before ``t``, its end within association_radius_m of one of ``points``? (Prunes
        the list.)"""
        act = self._ended_activity
        if not act:
            return False
        act[:] = [a for a in act if t - a[0] <= self._w_ev]
        for _, q in act:
            for p in points:
                d = q - p
                if float(d @ d) <= self._assoc2:
                    return True
        return False

    # ------------------------------------------------------------------ decisions
    def _rate(self, c, t):
        if c.rate_key == (t, c.n):
            return c.rate_val
        c.rate_key = (t, c.n)
        c.rate_val = self._rate_now(c, t)
        return c.rate_val

    def _rate_now(self, c, t):
        k = c.valid()
        F = c.flags[:k]
        return float((((F & PAIRED) == 0) & (c.t[:k] > t - self._w_rate)).sum()) / (
            self._w_rate * 1e-9
        )

    def _gross_test(self, c, t):
        """0 or the reason for GROSS_SLIP (1 inner emission, 2 rate jump, 4 moving, 6 the
        sequential likelihood ratio; 5, TEXTURE, is set by ``_texture``)."""
        cfg = self.config
        k = c.valid()
        if c.moving:
            return 4
        T, F = c.t[:k], c.flags[:k]
        use = (F & (PAIRED | REPEAT)) == 0
        tu = sorted(T[use].tolist())  # the times used, sorted: counts in ranges by bisection
        # the contact's rate is learnt from its current activity: from its first emission,
        # or the first after a silence of gross_prior_s or more (a grasp held silent for
        # seconds, then loaded: its micro-slips' onset is no jump from that silence)
        onset = c.created_ns
        if len(tu) > 2 and tu[0] == c.founder_ns:
            # a founder followed by a silence much longer than the intervals after it is a
            # touch that announced the contact, not its first micro-slip: the activity
            # starts after it (a grasp loaded 0.1 s after its touch)
            nxt = tu[2:6]
            if tu[1] - tu[0] > _FOUNDER_SILENCE_RATIO * (nxt[-1] - tu[1]) / len(nxt):
                onset = tu[1]
        if len(tu) > 1:
            gaps = np.flatnonzero(np.diff(np.asarray(tu)) >= self._w_prior)
            if gaps.size:
                onset = max(onset, tu[int(gaps[-1]) + 1])
        if (
            cfg.gross_llr_threshold > 0
            and self._gross_llr(c, t, T, use, tu, onset) >= cfg.gross_llr_threshold
        ):
            return 6
        n_w = len(tu) - bisect_right(tu, t - self._w_gross)  # T > t - gross_window
        if n_w < cfg.gross_min_events:
            return 0
        if c.fitted and c.radius > 0:
            inner = cfg.gross_inner_fraction
            # the stick zone of the ring as fitted now and as fitted before this window
            # (the window's own emissions, gross slip's among them, pull the fit; a
            # drifting contact's older ring lags behind it): inside either
            Pw = c.p[:k][use & (T > t - self._w_gross)]
            D = Pw - c.centre
            if float(np.einsum("ij,ij->i", D, D).min()) < (inner * c.radius) ** 2:
                return 1
            t_old = t - self._w_gross
            for tr, cr, rr in reversed(c.rings):
                if tr <= t_old:
                    if tr != c.rings[-1][0]:
                        D = Pw - cr
                        if float(np.einsum("ij,ij->i", D, D).min()) < (inner * rr) ** 2:
                            return 1
                    break
        # rate jump (scan statistic): the latest j emissions span tau; under the contact's
        # prior rate lambda (over the part of gross_history_s before them that it has
        # lived) j - 1 of them in tau is a Poisson tail P(N >= j - 1 | lambda tau); SLIP
        # when that is below gross_rate_alpha / (number of spans tested)
        ts = tu[-cfg.gross_scan_events :]
        n = len(ts)
        alpha = cfg.gross_rate_alpha / (n - cfg.gross_min_events + 1)
        w_hist, w_min, created = self._w_hist, 2 * self._w_gross, onset
        for j in range(cfg.gross_min_events, n + 1):
            t0 = ts[n - j]
            # local prior: the 4 spans before this one (2 .. gross_history_s long), so a
            # rate that grows smoothly (Cattaneo-Mindlin) is no jump
            covered = min(w_hist, max(4 * (t - t0), w_min), t0 - created)
            if covered < w_min:
                continue
            n_p = bisect_left(tu, t0) - bisect_left(tu, t0 - covered)  # t0 - covered <= T < t0
            mu = max(n_p, 1) / covered * (t - t0)
            # P(N >= j - 1) for N ~ Poisson(mu)
            term, cdf = math.exp(-mu), 0.0
            for i in range(j - 1):
                cdf += term
                term *= mu / (i + 1)
            if 1.0 - cdf < alpha:
                return 2
        return 0

    def _gross_llr(self, c, t, T, use, tu, onset):
        """Largest log likelihood ratio ln L over the latest j = gross_min_events ..
        gross_scan_events used emissions (times t_0 < ... < t_(j-1) = t, m = j - 1 arrivals
        in tau = t - t_0), gross slip (H1) against micro-slip continuation (H0):

        timing: H1 Poisson at lambda_1 = clip(m / tau, gross_rate_min_hz,
        gross_rate_max_hz); H0 Poisson at g lambda, g = gross_rate_growth, lambda ~
        Gamma(n_p + 1, h) (flat prior, n_p of the contact's emissions in the h =
        min(gross_prior_s, t_0 - born) before t_0; born: ``onset``, the first emission of
        its current activity, or the oldest one the ring buffer holds), marginalised
        (a = n_p + 1, b = h / g):
          ln L_t = m ln lambda_1 - lambda_1 tau
                   - [a ln b + lnG(a + m) - lnG(a) - (a + m) ln(b + tau)],
        0 unless m / tau > a / b (a jump), floored at 0;
        positions, rho = |p - centre| / radius of the ring fitted before t_0 (no ring:
        nothing): H1 uniform over the disc, p1 = 2 rho; H0 the slip annulus, p0 = 2 rho
        [eps + (1 - eps) (1[rho > kappa] / (2 (1 - kappa^2)) + 1[rho > k_o] /
        (2 (1 - k_o^2)))], kappa = gross_stick_fraction, eps = gross_position_outlier, k_o
        = max(kappa, the innermost micro-slip before t_0): half the annulus the contact
        drew, half the widest one allowed (its stick zone may have shrunk);
          ln L = ln L_t + sum_i ln(p1 / p0)(rho_i)."""
        cfg = self.config
        k = len(T)
        J = min(cfg.gross_scan_events, len(tu))
        if J < 2:
            return -math.inf
        ts = tu[-J:]
        idx = np.flatnonzero(use)
        idx = idx[np.argsort(T[idx], kind="stable")][-J:]
        lo, hi = cfg.gross_rate_min_hz, cfg.gross_rate_max_hz
        w_prior, created = self._w_prior, onset
        kap, eps = cfg.gross_stick_fraction, cfg.gross_position_outlier
        s_in = -math.log(eps)
        rings = c.rings if c.fitted else ()
        # the prior starts at the onset of the contact's activity, or at the oldest
        # emission the ring buffer still holds once it has wrapped
        born = created if c.n <= c.H else max(created, int(T.min()))
        kap2 = kap * kap
        d_all = 0.5 / (1.0 - kap2) if kap < 1 else 0.0
        # the spans tested, and for each the latest ring fitted before it (without the
        # tested emissions; None: no ring, no position term)
        plan = []
        for j in range(cfg.gross_min_events, J + 1):
            t0 = ts[J - j]
            cov = min(w_prior, t0 - born)
            if cov <= 0:
                break
            ri = None
            for i in range(len(rings) - 1, -1, -1):
                if rings[i][0] < t0:
                    ri = i if rings[i][2] > 0 else None
                    break
            plan.append((j, t0, cov, ri))
        # every ring's rho^2 at once: of the tested emissions (time order), and the
        # innermost micro-slip before each time (running minimum over the micro-slips in
        # time order): the annulus the contact's micro-slips drew
        rows = {}
        used = sorted({ri for *_, ri in plan if ri is not None})
        if used:
            C = np.array([rings[i][1] for i in used])
            rr = np.array([rings[i][2] for i in used])
            D = c.p[:k][None, :, :] - C[:, None, :]
            rho2 = np.einsum("rij,rij->ri", D, D) / (rr * rr)[:, None]
            ev_i = np.flatnonzero((c.flags[:k] & EVID) != 0)
            ev_i = ev_i[np.argsort(T[ev_i], kind="stable")]
            ev_t = T[ev_i].tolist()
            r2_used = rho2[:, idx].tolist()
            ev_min = np.minimum.accumulate(rho2[:, ev_i], axis=1).tolist()
            rows = {ri: n for n, ri in enumerate(used)}
        best = -math.inf
        for j, t0, cov, ri in plan:
            n_p = bisect_left(tu, t0) - bisect_left(tu, t0 - cov)
            a, b = n_p + 1.0, cov * 1e-9 / cfg.gross_rate_growth
            m, tau = j - 1, (t - t0) * 1e-9
            llr = 0.0
            if m > tau * a / b:  # faster than the prior rate
                lam1 = min(hi, max(lo, m / tau if tau > 0 else hi))
                llr = max(
                    0.0,
                    m * math.log(lam1)
                    - lam1 * tau
                    - a * math.log(b)
                    - math.lgamma(a + m)
                    + math.lgamma(a)
                    + (a + m) * math.log(b + tau),
                )
            if ri is not None:
                row = rows[ri]
                n_before = bisect_left(ev_t, t0)
                k_obs = max(kap, math.sqrt(ev_min[row][n_before - 1])) if n_before else kap
                k_obs2 = k_obs * k_obs
                r2 = r2_used[row][J - j :]
                n_in = sum(1 for v in r2 if v < kap2)
                n_obs = sum(1 for v in r2 if v >= k_obs2)
                d_obs = 0.5 / (1.0 - k_obs2) if k_obs < 1 else 0.0
                llr += n_in * s_in
                llr -= (j - n_in - n_obs) * math.log(eps + (1.0 - eps) * d_all)
                llr -= n_obs * math.log(eps + (1.0 - eps) * (d_all + d_obs))
            if llr > best:
                best = llr
        return best

    def _due(self, c, kind, t):
        last = c.last_report.get(kind)
        return last is None or t - last >= self._report

    def _precursor(self, c, ev, n_ev, ids, onset):
        c.precursor_count += 1
        c.last_report[3] = ev.time_ns
        conf = 1.0 - 2.0 ** (-n_ev / self.config.precursor_min_emissions)
        return SlipEvent(
            EventType.SLIP_PRECURSOR,
            ev.time_ns,
            ev.point_m.copy(),
            ev.covariance_m2.copy(),
            c.id,
            self._rate(c, ev.time_ns),
            math.nan,
            _NAN3.copy(),
            float(conf) * (0.5 + 0.5 * ev.confidence),
            ids,
            onset,
            float(n_ev),
        )

    def _slip_event(self, c, ev, why, onset):
        t = ev.time_ns
        c.last_report[4] = t
        ids = (ev.packet_id,)
        if onset:
            k = c.valid()
            w = ((c.flags[:k] & (PAIRED | REPEAT)) == 0) & (c.t[:k] > t - self._w_gross)
            ids = tuple(int(x) for x in c.pid[:k][w] if x != ev.packet_id) + ids
        conf = 0.9 if why in (1, 4) or c.texture_on else 0.75
        return SlipEvent(
            EventType.SLIP,
            t,
            c.centre_at(t).copy(),
            self._centre_cov(c),
            c.id,
            self._rate(c, t),
            math.nan,
            self._direction(c, t),
            conf,
            ids,
            onset,
            float(why),
        )

    def _texture(self, c, ev, out):
        """Periodicity of the contact's latest intervals: robust dispersion MAD/median of the
        intervals (counting multiples of the period for missed packets) below
        ``texture_max_dispersion``; period by least squares on the cumulative counts."""
        cfg = self.config
        n = cfg.texture_min_intervals + 1
        k = c.valid()
        if k < n:
            return
        # every emission of the contact counts (a texture under a fixed contact also lands
        # on spots hit before), but a run of pairs and repeats is tapping, not texture.
        # The latest n slots of the ring (events come nearly in time order), sorted.
        H = c.H
        if c.n >= n:
            s0 = (c.n - n) % H
            if s0 + n <= H:
                tl, fl = c.tlist[s0 : s0 + n], c.flist[s0 : s0 + n]
            else:
                tl = c.tlist[s0:] + c.tlist[: s0 + n - H]
                fl = c.flist[s0:] + c.flist[: s0 + n - H]
        else:
            tl, fl = c.tlist[:n], c.flist[:n]
        if not c.moving and sum(1 for f in fl if f & EVID) * 2 < n:
            c.texture_on, c.texture_run = False, 0
            return
        tl.sort()
        dtl = [b - a for a, b in zip(tl, tl[1:])]
        m = sorted(dtl)[len(dtl) // 2]
        if not m > 0:
            c.texture_on, c.texture_run = False, 0
            return
        # cheap screen: a texture's intervals mostly lie within 40 % of the median or 30 %
        # of its double or triple (20 % jitter: ~85 %), a Poisson process's do not (~44 %)
        lo1, hi1, lo2, hi2, lo3, hi3 = 0.6 * m, 1.4 * m, 1.7 * m, 2.3 * m, 2.7 * m, 3.3 * m
        far_max = len(dtl) - (6 * len(dtl) + 9) // 10  # more far intervals fail the screen
        near = far = 0
        for d in dtl:
            if lo1 <= d <= hi1 or lo2 <= d <= hi2 or lo3 <= d <= hi3:
                near += 1
            else:
                far += 1
                if far > far_max:
                    break
        if near * 10 < 6 * len(dtl):
            c.texture_on, c.texture_run = False, 0
            return
        slots = [(c.n - n + i) % H for i in range(n)] if c.n >= n else list(range(n))
        order = np.asarray(slots)
        sel = np.zeros(k, bool)
        sel[order] = True
        ts = np.asarray(tl, dtype=np.int64)
        dt = np.asarray(dtl, dtype=float)
        m = float(m)
        kk = _multiples(dt, m)
        if kk.max() > cfg.texture_max_multiple:
            c.texture_on, c.texture_run = False, 0
            return
        period = float(dt.sum() / kk.sum())
        x = dt / period
        llr = float(
            (
                np.logaddexp.reduce(
                    self._tex_w
                    - np.log(self._tex_s)
                    - 0.5 * ((x - self._tex_k) / self._tex_s) ** 2,
                    axis=0,
                )
                + np.log(x.mean())
                + x / x.mean()
            ).sum()
        )
        if llr < cfg.texture_min_llr:
            c.texture_on, c.texture_run = False, 0
            return
        period, se_period, kk = _period_fit_best(ts, dt, (m,))
        c.texture_run += 1
        if c.texture_run < cfg.texture_confirm_events or not period > 0:
            return
        t = ev.time_ns
        lam = math.nan
        if c.moving:
            # the speed over every remembered emission of the run (not only track_window_s):
            # its standard error falls as n^-3/2
            run = (c.flags[:k] & (FOUNDER | PAIRED)) == 0
            fit = self._motion_fit(c, run)
            if fit is None:
                return
            # the period over the same emissions (a longer run: a smaller error)
            tr = np.sort(c.t[:k][run])
            dtr = np.diff(tr).astype(float)
            h = dtr.size // 2  # the run's median interval (the upper one of an even count)
            pr, ser, kr = _period_fit_best(tr, dtr, (period * 1e9, float(np.partition(dtr, h)[h])))
            if kr is not None and kr.max() <= cfg.texture_max_multiple:
                period, se_period = pr, ser
            rel = math.hypot(fit[1] / fit[0], se_period / period) if fit[0] > 0 else math.inf
            if rel > cfg.texture_period_rel_se:
                return  # periodic, but the spatial period is not known well yet
            lam = fit[0] * period
        elif self._speed is not None:
            lam = self._speed * period
        onset = not c.texture_on
        c.texture_on = True
        if c.state != ContactState.GROSS_SLIP:
            c.state, c.since_ns = ContactState.GROSS_SLIP, t
            out.append(self._slip_event(c, ev, 5.0, onset=True))
        if onset or self._due(c, 5, t):
            c.last_report[5] = t
            ids = tuple(int(x) for x in c.pid[:k][sel] if x != ev.packet_id)[-n + 1 :] + (
                ev.packet_id,
            )
            frac = float((kk == 1).mean())
            out.append(
                SlipEvent(
                    EventType.TEXTURE,
                    t,
                    c.centre_at(t).copy(),
                    self._centre_cov(c),
                    c.id,
                    1.0 / period,
                    lam,
                    self._direction(c, tt=t),
                    frac,
                    ids,
                    onset,
                    llr,
                )
            )

    def _centre_cov(self, c):
        k = c.valid()
        m = (c.flags[:k] & PAIRED) == 0
        P = c.p[:k][m]
        if len(P) < 3 or c.moving:
            v = max(float(c.var[(c.n - 1) % c.H]), 1e-12)
            return np.eye(3) * v
        D = P - P.sum(axis=0) / len(P)
        return (D.T @ D) / (len(P) * (len(P) - 1))

    def _direction(self, c, t=None, tt=None):
        """Unit tangent direction of travel at time ``t`` or ``tt`` (ns): the tracked motion
        of a moving contact (carried along its great circle to that time), else, given
        ``t``, a fresh regression of the slip emissions over track_window_s when its drift
        exceeds ``direction_significance`` standard errors (and min_speed_m_s); else NaN."""
        if not c.moving:
            if t is None:
                return _NAN3.copy()
            cfg = self.config
            k = c.valid()
            m = ((c.flags[:k] & (OVERLAP | EVID)) == EVID) & (c.t[:k] > t - self._w_track)
            n = int(m.sum())
            if n < cfg.track_min_events:
                return _NAN3.copy()
            fit = _drift_fit(c.t[:k][m], c.p[:k][m])
            if fit is None:
                return _NAN3.copy()
            v, _, _, s2, stt = fit
            se = math.sqrt(s2 / stt)
            sp = math.sqrt(float(v @ v))
            if sp < cfg.min_speed_m_s or sp < cfg.direction_significance * se:
                return _NAN3.copy()
            return v / sp
        s = math.sqrt(float(c.vel @ c.vel))
        if not s > 0:
            return _NAN3.copy()
        u = c.vel / s
        at = t if t is not None else tt
        if at is None or c.track_c is None:
            return u
        # the track's velocity belongs to its mean time; along the great circle the
        # direction turns by omega dt (omega = v / |p|) toward -p: the direction at ``at``
        rn = math.sqrt(float(c.track_c @ c.track_c))
        a = s / rn * (at * 1e-9 - c.track_t)
        return u * math.cos(a) - (c.track_c / rn) * math.sin(a)

    def _update_finger(self, t):
        """The finger's state and its start time now; the FingerState record itself is built
        when read (``state``): nothing it depends on changes before the next update."""
        if t is None:
            return
        top, top_key, n_conf = None, None, 0
        for c in self.contacts:
            if c.confirmed:
                n_conf += 1
                key = (int(c.state), c.last_ns)
                if top is None or key > top_key:  # the first of equals, as max() picks
                    top, top_key = c, key
        if top is None:
            if self._fs_state != ContactState.NO_CONTACT:
                self._fs_since = self._last_end_ns
            self._fs_state = ContactState.NO_CONTACT
        else:
            if top.state != self._fs_state:
                self._fs_since = top.since_ns
            self._fs_state = top.state
        self._fs_pending = (top, n_conf, t)
        self._finger = None

    def _finger_state(self) -> FingerState:
        """The FingerState record of the last update (built once)."""
        if self._finger is None:
            top, n_conf, t = self._fs_pending
            if top is None:
                self._finger = FingerState(
                    ContactState.NO_CONTACT, self._fs_since, _NAN3.copy(), 0.0, 0, -1, 0, t
                )
            else:
                self._finger = FingerState(
                    top.state,
                    int(self._fs_since),
                    top.centre_at(t).copy(),
                    self._rate(top, t),
                    top.precursor_count,
                    top.id,
                    n_conf,
                    t,
                )
        return self._finger
