# SPDX-License-Identifier: Apache-2.0
"""Contact tracking of the slip detector: which contact an emission belongs to (nearest
predicted centre or latest emission, or the contact of the touch a release pairs with), new
contacts, the fitted centre and radius, the motion track, and contacts ending."""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.records import ContactState, EventType

from .contact import (
    EVID,
    FOUNDER,
    OVERLAP,
    PAIRED,
    SLIP_EMISSION,
    SLIPPING,
    TOUCH_POINT,
    TRACKED,
    Contact,
)
from .fits import circle_centre, drift_fit, percentile90
from .model import amp_ln


class ContactTracking:
    """Association of emissions with contacts, contact creation, geometry and motion.

    Methods of `SlipDetector` (`ae_tactile.slip.detector`), which holds the state they
    use: ``config``, ``counts``, ``contacts`` and the windows in ns set by ``_apply``.
    """

    def _associate(self, px, py, pz, t, pol=1, var=0.0):
        """The contact whose (predicted) centre, or whose latest emission of the last
        track_window_s, is nearest within association_radius_m (the latest emission carries
        a contact that moves before its track is established); failing that, for a
        rarefaction (polarity ``pol`` < 0, per-axis variance ``var`` m^2), the contact of an
        unpaired touch on its spot. With the fingertip model (`model`), its gates instead:
        `_model_distance`, then a rarefaction's object (`_object_of_release`)."""
        if self._model:
            return self._associate_model(px, py, pz, t, pol, var)
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

    def _associate_model(self, px, py, pz, t, pol, var):
        """`_associate` of the fingertip model: the nearest contact within its gate
        (`_model_distance`); failing that, for a rarefaction, the contact of the touch on
        its spot, or the object it releases."""
        best, best_d2 = None, math.inf
        for c in self.contacts:
            d2, gate = self._model_distance(c, px, py, pz, t, pol)
            if d2 <= gate and d2 <= best_d2:
                best, best_d2 = c, d2
        if best is None and pol < 0:
            best = self._touch_of_release(px, py, pz, var, t)
        if best is None and pol < 0:
            best = self._object_of_release(px, py, pz, t, var)
        return best

    def _model_distance(self, c, px, py, pz, t, pol):
        """(squared distance, squared gate) [m^2] of an emission of polarity ``pol`` at
        (px, py, pz), time ``t``, to contact ``c`` as the fingertip model reads it."""
        q = c.centre_xyz if not c.moving or c.track_c is None else c.centre_at(t)
        dx, dy, dz = px - q[0], py - q[1], pz - q[2]
        d2 = dx * dx + dy * dy + dz * dz
        lp = c.last_p
        held = c.state not in SLIPPING and not c.moving
        if not held:
            # a sliding contact reaches association_radius_m round its centre or its
            # latest emission (it moves before its track is established)
            gate = self._assoc2
            if lp is not None and t - c.last_ns <= self._w_track:
                dx, dy, dz = px - lp[0], py - lp[1], pz - lp[2]
                d2 = min(d2, dx * dx + dy * dy + dz * dz)
        elif (
            pol > 0
            and c.arriving
            and not c.saw_rarefaction
            and t - c.founder_ns <= self._w_arrive
        ):
            # a point of an arriving object: within association_radius_m of its points
            gate = self._assoc2
            d2 = min(d2, self._touch_point_d2(c, px, py, pz))
        else:
            # a held or arriving contact's patch: its disc round its touch points (an
            # arriving one's: round any of its emissions)
            gate = self._patch2 if c.founder[2] > 0 else self._assoc2
            if d2 > gate:
                d2 = min(d2, self._touch_point_d2(c, px, py, pz, c.arriving))
        return d2, gate

    def _object_of_release(self, px, py, pz, t, var):
        """The held, silent contact (or one releasing now) nearest a rarefaction within
        association_radius_m: a broad object leaves where it pleases, so its release may
        land off its patch (an untouched spot releases nothing). None if none, or if the
        rarefaction lands on the spot (the same-spot gate, per-axis variance ``var``
        [m^2]) where another object was touched and released within evidence_window_s:
        a spot tapped again, its touch lost, releases there (`_tapped_spot`)."""
        if self._tapped_spot(np.array((px, py, pz)), t, var):
            return None
        best, best_d2 = None, self._assoc2
        for c in self.contacts:
            if c.moving or c.state != ContactState.STICK:
                continue
            releasing = (
                c.pending_release_ns is not None and t - c.pending_release_ns <= self._w_release
            )
            if not releasing and (c.arriving or not self._silent(c, t)):
                continue
            q = c.centre_xyz
            d2 = (px - q[0]) ** 2 + (py - q[1]) ** 2 + (pz - q[2]) ** 2
            d2 = min(d2, self._touch_point_d2(c, px, py, pz))
            if d2 <= best_d2:
                best, best_d2 = c, d2
        return best

    def _touch_point_d2(self, c, px, py, pz, any_member=False):
        """Squared distance [m^2] from (px, py, pz) to the nearest touch point (founder or
        arrival touch; ``any_member``: any emission) of contact ``c`` in its buffer."""
        k = c.valid()
        m = (c.flags[:k] & TOUCH_POINT) != 0
        if any_member:
            m = (c.flags[:k] & PAIRED) == 0
        if not m.any():
            return math.inf
        D = c.p[:k][m] - np.array((px, py, pz))
        return float(np.einsum("ij,ij->i", D, D).min())

    def _touch_of_release(self, px, py, pz, var, t):
        """The contact (sticking, not moving) holding a touch this release pairs with
        (`_held_touch`, or its founder's record, `_founder_release`), however far its
        centre: a release belongs to its touch's contact, whatever the touches after it
        made of the contact (touches wandering over seconds of holds carry it farther than
        association_radius_m). The nearest such touch's contact; None if none."""
        p = np.array((px, py, pz))
        best, best_d2 = None, math.inf
        for c in self.contacts:
            if c.state in SLIPPING or c.moving:
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
            idle = [c for c in self.contacts if c.state not in SLIPPING] or self.contacts
            drop = min(idle, key=lambda c: (c.confirmed, c.last_ns))
            self.contacts.remove(drop)
            if drop.confirmed:
                self._contact_event(EventType.DETOUCH, drop, t, drop.centre_at(t))
            self.counts["contacts_dropped"] += 1
        c = Contact(self._next_id, t, self.config.member_history, confirmed=ev.polarity >= 0)
        self._next_id += 1
        c.add(t, p, var, ev.polarity, ev.packet_id, FOUNDER | (OVERLAP if overlap else 0))
        c.founder = (p.copy(), var, int(ev.polarity))
        c.founder_ns, c.founder_n = t, 0
        if ev.polarity > 0 and self._model:
            self._note_amplitude(c, amp_ln(ev), True)
        c.centre = p.copy()
        c.arriving = self._model  # (the per-emission rules know no arrival)
        lifted = self._near_lifted(p, t) if self._model else None
        if lifted is not None:
            self._resume(c, lifted, t)
        self.contacts.append(c)
        self.counts["contacts_created"] += 1
        if c.confirmed:
            self._contact_event(EventType.TOUCH, c, t, p)
        return c

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
        centre = circle_centre(P) if n >= self.config.fit_min_events else None
        if centre is not None:
            c.centre, c.fitted = centre, True
        d = np.sqrt(np.einsum("ij,ij->i", P - c.centre, P - c.centre))
        c.radius = percentile90(d.tolist())
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
        fit = drift_fit(c.t[:k][m], c.p[:k][m])
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

    def _end_contact(self, c):
        """Remove contact ``c`` (its DETOUCH queued when it was reported begun); its
        touch-release activity outlives it for evidence_window_s (`_ended_activity_near`)."""
        if c in self.contacts:
            self.contacts.remove(c)
        if c.confirmed:
            t = c.pending_release_ns if c.pending_release_ns is not None else self.now_ns
            t = c.last_ns if t is None else t
            self._contact_event(EventType.DETOUCH, c, t, c.centre_at(t))
        if self._model and c.pending_in_slip:
            # lifted after a slide or released off its touches: an emission on its disc
            # soon after is the same object re-stuck or loaded (`_near_lifted`)
            lst = self._lifted
            q = self._lift_quiet_ns(c) if c.slid else 0
            lst.append((c.last_ns, np.array(c.centre_at(c.last_ns), dtype=float), q))
            if len(lst) > self.config.max_contacts:
                del lst[0]
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

    def _tapped_spot(self, p, t, var):
        """Does ``p`` lie on the spot (the same-spot gate, model floor included, per-axis
        variance ``var`` [m^2] for both) of a touch and its release of a contact that
        ended within evidence_window_s before ``t``?"""
        gate = self._g2 * (2.0 * var + self._f2)
        for t_act, q in self._ended_activity:
            d = q - p
            if t - t_act <= self._w_ev and float(d @ d) <= gate:
                return True
        return False

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
