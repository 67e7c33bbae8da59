# SPDX-License-Identifier: Apache-2.0
"""Micro-slip evidence of the slip detector: an emission joining a contact is classified
(slip emission of a slipping contact, a touch / release pair, a repeat on an earlier
spot, or micro-slip evidence on no other emission's spot) and the evidence in the window
decides SLIP_PRECURSOR; the gross-slip and texture tests follow."""

from __future__ import annotations

import numpy as np

from ae_tactile.records import ContactState

from .contact import (
    EVID,
    FOUNDER,
    OVERLAP,
    PAIRED,
    REPEAT,
    SLIP_EMISSION,
    SLIPPING,
    TOUCHED,
)


class MicroSlipEvidence:
    """An emission's membership of its contact and the SLIP_PRECURSOR decision.

    Methods of `SlipDetector` (`ae_tactile.slip.detector`), which holds the state they
    use: ``config``, ``counts``, ``contacts`` and the windows in ns set by ``_apply``.
    """

    def _member(self, c, ev, p, var, t, overlap, out):
        cfg = self.config
        k = c.valid()
        T, F = c.t[:k], c.flags[:k]
        slipping = c.state in SLIPPING or c.moving  # a moving contact has no fixed spots
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
