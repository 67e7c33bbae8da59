# SPDX-License-Identifier: Apache-2.0
"""The slip detector's output records: SLIP_PRECURSOR and SLIP events of a contact, its
slip emission rate, the covariance of its centre, its direction of travel, and the
report interval between repeated events."""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.records import EventType

from .contact import EVID, NAN3, OVERLAP, PAIRED, REPEAT
from .fits import drift_fit
from .types import SlipEvent


class SlipOutputs:
    """The events a contact reports and the quantities they carry.

    Methods of `SlipDetector` (`ae_tactile.slip.detector`), which holds the state they
    use: ``config``, ``counts``, ``contacts`` and the windows in ns set by ``_apply``.
    """

    def _rate(self, c, t):
        """The contact's slip emission rate at ``t`` [ns] (1/s), cached per members over
        the span of time [t0, t1) [ns] in which its count stays the same (an output value
        only: read at every timer tick, recounted when an emission joins or leaves the
        window)."""
        key = c.rate_key
        if key is not None and key[0] == c.n and key[1] <= t < key[2]:
            return c.rate_val
        c.rate_val, t1 = self._rate_now(c, t)
        c.rate_key = (c.n, t, t1)
        return c.rate_val

    def _rate_now(self, c, t):
        """(Unpaired emissions of the contact in the latest rate_window_s / its length
        (1/s), the time [ns] the oldest of them leaves the window)."""
        k = c.valid()
        m = ((c.flags[:k] & PAIRED) == 0) & (c.t[:k] > t - self._w_rate)
        n = int(m.sum())
        t1 = int(c.t[:k][m].min()) + self._w_rate if n else t + self._w_rate
        return n / (self._w_rate * 1e-9), t1

    def _due(self, c, kind, t):
        """Is an event of ``kind`` (3 SLIP_PRECURSOR, 4 SLIP, 5 TEXTURE) of the contact due
        at ``t`` [ns]: none reported yet, or the last one report_interval_s ago?"""
        last = c.last_report.get(kind)
        return last is None or t - last >= self._report

    def _precursor(self, c, ev, n_ev, ids, onset):
        """The SLIP_PRECURSOR of contact ``c`` decided by emission ``ev`` at its point, on
        ``n_ev`` micro-slips of evidence (packets ``ids``); confidence grows with the
        evidence and the localization confidence."""
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
            NAN3.copy(),
            float(conf) * (0.5 + 0.5 * ev.confidence),
            ids,
            onset,
            float(n_ev),
        )

    def _slip_event(self, c, ev, why, onset):
        """The SLIP of contact ``c`` decided by emission ``ev`` at the contact's centre, for
        reason ``why`` (`GrossSlipTest._gross_test`; 5: a texture; 0: a repeated report);
        an onset lists the packets of the gross-slip window."""
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

    def _contact_event(self, kind, c, t, position):
        """Queue the TOUCH (``kind``) of contact ``c`` beginning, or its DETOUCH, at time
        ``t`` [ns] and ``position`` (3,) [m] (nothing when contact events are off)."""
        if not self.contact_events:
            return
        v = max(float(c.var[0]), 1e-12) if c.n else 1e-12
        pids = (int(c.pid[(c.n - 1) % c.H]),) if c.n else ()
        self._pending.append(
            SlipEvent(
                kind,
                int(t),
                np.array(position, dtype=float),
                np.eye(3) * v,
                c.id,
                0.0,
                confidence=1.0,
                packet_ids=pids,
                onset=True,
            )
        )

    def _centre_cov(self, c):
        """(3, 3) covariance of the contact's centre [m^2]: the scatter of its unpaired
        emissions / n, or (fewer than 3, or moving) the latest emission's variance."""
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
                return NAN3.copy()
            cfg = self.config
            k = c.valid()
            m = ((c.flags[:k] & (OVERLAP | EVID)) == EVID) & (c.t[:k] > t - self._w_track)
            n = int(m.sum())
            if n < cfg.track_min_events:
                return NAN3.copy()
            fit = drift_fit(c.t[:k][m], c.p[:k][m])
            if fit is None:
                return NAN3.copy()
            v, _, _, s2, stt = fit
            se = math.sqrt(s2 / stt)
            sp = math.sqrt(float(v @ v))
            if sp < cfg.min_speed_m_s or sp < cfg.direction_significance * se:
                return NAN3.copy()
            return v / sp
        s = math.sqrt(float(c.vel @ c.vel))
        if not s > 0:
            return NAN3.copy()
        u = c.vel / s
        at = t if t is not None else tt
        if at is None or c.track_c is None:
            return u
        # the track's velocity belongs to its mean time; along the great circle the
        # direction turns by omega dt (omega = v / |p|) toward -p: the direction at ``at``
        rn = math.sqrt(float(c.track_c @ c.track_c))
        a = s / rn * (at * 1e-9 - c.track_t)
        return u * math.cos(a) - (c.track_c / rn) * math.sin(a)
