# SPDX-License-Identifier: Apache-2.0
"""Micro-slip evidence of the slip detector: an emission joining a contact is classified
(slip emission of a slipping contact, a touch / release pair, a repeat on an earlier
spot, or micro-slip evidence on no other emission's spot) and the evidence in the window
decides SLIP_PRECURSOR; the gross-slip and texture tests follow."""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.records import ContactState, EventType, Reading

from .contact import (
    ARRIVAL,
    EVID,
    FOUNDER,
    OVERLAP,
    PAIRED,
    REPEAT,
    SLIP_EMISSION,
    SLIPPING,
    TOUCH_POINT,
    TOUCHED,
)
from .model import LIFT_INTERVALS, LOST_RELEASE_LLR, RING_SIGMAS, RING_SPREAD_FIT, amp_ln


class MicroSlipEvidence:
    """An emission's membership of its contact and the SLIP_PRECURSOR decision.

    Methods of `SlipDetector` (`ae_tactile.slip.detector`), which holds the state they
    use: ``config``, ``counts``, ``contacts`` and the windows in ns set by ``_apply``.
    """

    def _member(self, c, ev, p, var, t, overlap, out):
        """Add ``ev`` (point ``p`` [m], per-axis variance ``var`` [m^2], time ``t`` [ns],
        ``overlap``: it may share a trigger window) to contact ``c``: classify it, update
        the contact and its tests, and append the events they decide to ``out``."""
        slipping = c.state in SLIPPING or c.moving  # a moving contact has no fixed spots
        x = amp_ln(ev) if self._model else None
        if self._model and ev.polarity > 0 and (
            self._released_held(c, p, var, t) or self._louder_than_micro_slip(c, x, t)
        ):
            # a compression after a loaded (held) contact's release on its touch, off its
            # disc or its activity stopped round the release, or after any release of a
            # held contact and as loud as a touch: the next object's touch
            c.pending_in_slip = False  # released: no re-stuck object to resume
            self._end_contact(c)
            n = self._found(ev, p, var, t, overlap)
            self.last_reading = (Reading.TOUCH if n.confirmed else Reading.UNKNOWN, n.id)
            return
        flags = OVERLAP if overlap else 0
        kind = None if slipping or not self._model else self._arrival_flags(c, ev, t)
        if slipping:
            flags |= self._slip_emission(c, ev, p, var, t)
        elif kind is not None:
            flags |= kind
        else:
            kind = self._held_emission(c, ev, p, var, t)
            if kind is None:
                # the founder was released: this is a new touch nearby
                self._end_contact(c)
                n = self._found(ev, p, var, t, overlap)
                self.last_reading = (Reading.TOUCH if n.confirmed else Reading.UNKNOWN, n.id)
                return
            flags |= kind
            if self._model and kind & EVID and self._provisional_release(c, ev, t):
                flags |= REPEAT
        c.add(t, p, var, ev.polarity, ev.packet_id, flags)
        if ev.polarity > 0 and flags & (ARRIVAL | FOUNDER):
            self._note_amplitude(c, x, True)
        elif flags & EVID and not flags & REPEAT and c.state != ContactState.GROSS_SLIP:
            # a micro-slip of a held contact (a provisional release left out)
            self._note_amplitude(c, x, False)
        if not c.confirmed:
            c.confirmed = True
            self._contact_event(EventType.TOUCH, c, c.founder_ns, c.founder[0])
        self._geometry(c)
        c.events_since_track += 1
        if c.events_since_track >= 8 or (c.moving and c.events_since_track >= 4):
            self._track(c, t)
        if c.arriving and not slipping:
            if flags & EVID:
                self._slide_decision(c, ev, t, out)
        elif flags & EVID and c.state != ContactState.GROSS_SLIP and not flags & REPEAT:
            self._precursor_decision(c, ev, p, t, out)
        if c.arriving and not slipping:
            pass
        elif c.state != ContactState.GROSS_SLIP and flags & (EVID | REPEAT):
            why = self._gross_test(c, t)
            if why:
                c.state, c.since_ns = ContactState.GROSS_SLIP, t
                out.append(self._slip_event(c, ev, why, onset=True))
        elif c.state == ContactState.GROSS_SLIP and self._due(c, 4, t):
            out.append(self._slip_event(c, ev, 0.0, onset=False))
        self._texture(c, ev, out)
        if ev.polarity > 0:
            c.touch_release_open = False
        self.last_reading = (self._reading(c, ev, flags), c.id)

    @staticmethod
    def _reading(c, ev, flags):
        """What an emission of contact ``c`` with member ``flags`` was read as: a slip
        emission (TEXTURE in a periodic run), a release (or a release-like emission of a
        slipping contact), a touch or re-touch on an earlier spot, a micro-slip."""
        if flags & SLIP_EMISSION:
            if c.pending_release_ns == ev.time_ns:
                return Reading.RELEASE
            return Reading.TEXTURE if c.texture_on else Reading.SLIP
        if flags & PAIRED:
            return Reading.RELEASE
        if flags & ARRIVAL:
            return Reading.TOUCH
        if flags & REPEAT:
            return Reading.TOUCH if ev.polarity > 0 else Reading.RELEASE
        if flags & EVID:
            return Reading.MICRO_SLIP
        return Reading.UNKNOWN

    def _slip_emission(self, c, ev, p, var, t):
        """The flags of an emission of a slipping (or moving) contact: every one is a slip
        emission; one on the founding touch's spot with the opposite polarity may be its
        release: the contact ends unless another emission follows within quiet_s."""
        fp, fvar, fpol = c.founder
        fd = fp - p
        if ev.polarity * fpol < 0 and float(fd @ fd) <= self._g2 * (fvar + var + self._f2):
            c.pending_release_ns, c.pending_in_slip = t, True  # confirmed by quiet_s
            c.pending_release_spot = (p.copy(), var)
            self.counts["releases"] += 1
            if self._model:
                k = c.valid()
                tl = sorted(c.t[:k].tolist())[-5:]  # [ns] the latest emissions before it
                c.release_gap_ns = t - tl[-1]
                c.release_iv_ns = (tl[-1] - tl[0]) / (len(tl) - 1) if len(tl) > 1 else 0.0
        elif c.pending_release_ns is not None:
            c.pending_release_ns, c.provisional = None, False
            self.counts["releases_cancelled"] += 1
        return EVID | SLIP_EMISSION

    def _louder_than_micro_slip(self, c, x, t):
        """Is a compression of ln-amplitude ``x`` at ``t`` [ns] on contact ``c`` (held or
        loaded, not sliding) more likely a new object's touch than the contact's next
        micro-slip (`model.touch_llr`)? With its release pending: when the ratio is
        above 1. On a silent held contact (STICK, no micro-slip in the window, no release
        seen): a touch here means its release was lost, so the ratio must beat the prior
        odds against a lost emission (`model.LOST_RELEASE_LLR`)."""
        if c.state == ContactState.GROSS_SLIP or c.moving or x is None:
            return False
        if c.pending_release_ns is not None:
            return self._touch_llr(c, x) > 0.0
        return (
            c.state == ContactState.STICK
            and not c.arriving
            and self._silent(c, t)
            and self._touch_llr(c, x) > LOST_RELEASE_LLR
        )

    @staticmethod
    def _released_held(c, p, var, t):
        """Is contact ``c`` a held, loaded contact (INCIPIENT_SLIP, not moving) whose
        touch's release (a rarefaction on its compression founder's spot) is pending,
        and is a compression at ``p`` [m] (per-axis variance ``var`` [m^2]) at ``t`` [ns]
        none of its micro-slips nor its gross slip: off its disc (beyond its radius, a
        `model.RING_SPREAD_FIT` margin and RING_SIGMAS localization sigmas), or its
        activity stopped round the release (the silences before the release and after it
        up to ``t`` together longer than `model.LIFT_INTERVALS` of its latest intervals,
        as a slide's lift; a gross slip's emissions go on at its rate)?"""
        if not (
            c.state == ContactState.INCIPIENT_SLIP
            and not c.moving
            and c.pending_release_ns is not None
            and c.pending_release_spot is not None
            and c.founder[2] > 0
        ):
            return False
        d = p - c.centre
        r = c.radius * (1.0 + RING_SPREAD_FIT) + RING_SIGMAS * math.sqrt(2.0 * var)
        if c.radius > 0 and float(d @ d) > r * r:
            return True
        return c.release_gap_ns + (t - c.pending_release_ns) > LIFT_INTERVALS * c.release_iv_ns

    def _held_emission(self, c, ev, p, var, t):
        """The flags of an emission of a sticking contact: the founding touch's release
        (PAIRED), a pair with an earlier emission on its spot (PAIRED), a repeat on an
        earlier spot (REPEAT, FOUNDER for a re-touch), or micro-slip evidence (EVID); None:
        the contact's founder was released and this is a new touch nearby."""
        k = c.valid()
        T, F = c.t[:k], c.flags[:k]
        D = c.p[:k] - p
        d2 = np.einsum("ij,ij->i", D, D)
        vsum = c.var[:k] + var
        # a touch makes a spot (a release pairs with it, a re-touch repeats it); so does
        # any compression for an emission within 3 sigma of it, without the model floor (a
        # tap's touch and release; micro-slips seldom land that close): an emission near
        # an earlier micro-slip is another micro-slip
        spot = d2 <= self._g2 * (vsum + self._f2)
        if self._model:
            touch = (F & TOUCH_POINT) != 0
            # a held touch's spot is occupied: a compression there is a re-touch only on
            # its exact spot (its release lost; micro-slips keep off the centre)
            tight = d2 <= 9.0 * vsum
            tp = touch & (((F & PAIRED) != 0) | tight) if ev.polarity > 0 else touch
            spot &= tp
            spot |= (d2 <= 9.0 * vsum) & ~touch & (c.pol[:k] > 0)
        if spot.any():
            near, cand = self._pair_candidates(c, ev, k, T, F, d2, vsum, spot, t)
        else:
            near = cand = spot
        if not cand.any() and self._founder_release(c, ev.polarity, p, var, t):
            # the founding touch's release, its slot no longer in the ring buffer: it
            # ends the contact after release_confirm_s, as any release does
            c.founder_paired = True
            c.pending_release_ns, c.pending_in_slip = t, False
            c.pending_release_spot = (p.copy(), var)
            self.counts["pairs"] += 1
            self.counts["releases"] += 1
            return PAIRED
        # on the spot of an earlier emission: a release / tap pair, or a repeat
        if cand.any():
            return self._pair(c, ev, p, var, t, F, d2, cand)
        if near.any():
            return self._repeat(c, ev, p, var, t)
        return self._isolated(c, t, T, F)

    def _pair_candidates(self, c, ev, k, T, F, d2, vsum, spot, t):
        """(the emissions of the window on the new one's spot, those it may pair with) of
        the ``k`` buffered ones (times ``T`` [ns], flags ``F``, squared distances ``d2``
        [m^2], summed per-axis variances ``vsum`` [m^2], on its spot: ``spot``)."""
        recent = T >= t - self._w_ev
        near = spot & recent
        # a pair: an emission of unknown polarity with any unpaired one of the window on
        # its spot; a release (a rarefaction) with an unpaired touch (a compression) on its
        # spot, never the other way round
        cand = spot & ((F & PAIRED) == 0)
        if ev.polarity > 0:
            cand[:] = False
        elif ev.polarity < 0:
            held = self._held_touch(F, d2, vsum, recent)
            if c.n - c.founder_n == 1:
                # nothing since the founding touch (a held touch is silent): on its spot,
                # model floor included, is its release however long the hold
                held = held | ((F & FOUNDER) != 0)
            cand &= (c.pol[:k] > 0) & held
            if c.arriving and c.n - c.founder_n > 1:
                # a release of one of an arriving object's points lands on its spot to the
                # localization error: its other emissions (a slide's) seldom do. A
                # rarefaction right after the object's one touch, nothing between them (a
                # tap), keeps the gate with the model floor (the localization bias is that
                # of one spot), as a held touch's release does
                cand &= d2 <= 9.0 * vsum
        else:
            cand &= recent
        return near, cand

    def _pair(self, c, ev, p, var, t, F, d2, cand):
        """Pair the new emission with the nearest candidate (``cand``): the candidate leaves
        the evidence; the founder's pair is its release (the contact ends after
        release_confirm_s); a touch and its release open touch-release activity."""
        j = int(np.flatnonzero(cand)[np.argmin(d2[cand])])
        if (int(F[j]) & (EVID | OVERLAP)) == EVID:
            c.n_fit_members -= 1
        F[j] = (F[j] | PAIRED) & (0xFF ^ EVID)
        c.flist[j] = int(F[j])
        self.counts["pairs"] += 1
        founder = bool(F[j] & FOUNDER)
        if (
            self._model
            and ev.polarity < 0 < int(c.pol[j])
            and F[j] & TOUCH_POINT
            and c.pending_release_ns is None
        ):
            # the release of a point of the object: a point contact leaves where it
            # touched (on its spot to 3 localization sigmas), and the object is released
            # when none of its touch points is left held, or all but one (a release lost)
            # when the others left together, within RELEASE_WINDOW_S (one object's
            # release; spread out, they were objects of their own); a release elsewhere
            # on the disc of a silent contact, paired with a point of its arrival, is a
            # broad object's edge peeling off, the whole object's release (a micro-slip
            # that follows cancels it; under load, no micro-slip silence: a micro-slip)
            k = c.valid()
            F_ = c.flags[:k]
            tp = ((F_ & TOUCH_POINT) != 0) & (c.pol[:k] > 0)
            n_tp = int(tp.sum())
            left = int((tp & ((F_ & PAIRED) == 0)).sum())
            on_spot = float(d2[j]) <= 9.0 * (float(c.var[j]) + var)
            broad = (
                not on_spot
                and int(c.t[j]) - c.founder_ns <= self._w_arrive
                and self._silent(c, t)
            )
            burst = 1 + int((((F_ & PAIRED) != 0) & (c.pol[:k] < 0)
                             & (c.t[:k] >= t - self._w_release)).sum())
            if broad or left == 0 or (left == 1 and n_tp >= 3 and burst >= n_tp - 1):
                founder = True
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
            # a touch and its release on one spot (3 sigma, no model floor: a micro-slip
            # landing near an earlier one rarely comes that close); the founder's too when
            # nothing came between them (a held touch is silent)
            c.touch_release_ns = t
            c.touch_release_open = True
        return PAIRED

    def _repeat(self, c, ev, p, var, t):
        """The flags of a repeat on an earlier emission's spot: REPEAT, plus FOUNDER when a
        touch on the founder's (or its release's) spot comes before the release was
        confirmed: the re-touch takes over as the founder and the contact goes on; its
        release pairs with it here and ends the contact (not a lone rarefaction after it
        ended)."""
        flags = REPEAT
        if self._model and ev.polarity > 0:
            flags |= ARRIVAL  # a touch again on a released spot: its release ends the contact
        if ev.polarity > 0 and c.pending_release_ns is not None:
            fp, fvar, _ = c.founder
            rp, rvar = c.pending_release_spot or (fp, fvar)
            fd, rd = fp - p, rp - p
            if min(
                float(fd @ fd) - self._g2 * (fvar + var + self._f2),
                float(rd @ rd) - self._g2 * (rvar + var + self._f2),
            ) <= 0.0:
                c.pending_release_ns, c.provisional = None, False
                c.founder = (p.copy(), var, 1)
                c.founder_ns, c.founder_n = t, c.n
                c.founder_paired = False
                flags |= FOUNDER
                self.counts["releases_cancelled"] += 1
        self.counts["repeats"] += 1
        return flags

    def _isolated(self, c, t, T, F):
        """EVID for an emission on no other emission's spot (micro-slip evidence; it cancels
        a pending release), or None when the contact's founder was released and no
        evidence came in the window (a new touch nearby)."""
        if c.pending_release_ns is not None:
            ev_m = (F & EVID) != 0
            if not (T[ev_m] >= t - self._w_ev).any():
                return None
            c.pending_release_ns, c.provisional = None, False
            self.counts["releases_cancelled"] += 1
        self.counts["evidence"] += 1
        return EVID

    def _precursor_decision(self, c, ev, p, t, out):
        """Micro-slip evidence in the window (compressions weighed down during touch-release
        activity): SLIP_PRECURSOR (STICK -> INCIPIENT_SLIP) once it reaches
        precursor_min_emissions, then again every report_interval_s."""
        cfg = self.config
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
                # a touch when it came, a touch for as long as it counts (its release may
                # be lost): the weight an emission had on arrival stays
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
