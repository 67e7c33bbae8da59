# SPDX-License-Identifier: Apache-2.0
"""Texture test of the slip detector: TEXTURE while a contact's latest emission intervals
are periodic, with the spatial period from the tracked speed (moving contact) or the
configured sliding speed (fixed contact)."""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.records import ContactState, EventType

from .contact import EVID, FOUNDER, PAIRED
from .fits import multiples, period_fit_best
from .types import SlipEvent


class TextureTest:
    """The periodicity test of a contact's emissions and its TEXTURE events.

    Methods of `SlipDetector` (`ae_tactile.slip.detector`), which holds the state they
    use: ``config``, ``counts``, ``contacts`` and the windows in ns set by ``_apply``.
    """

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
        kk = multiples(dt, m)
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
        period, se_period, kk = period_fit_best(ts, dt, (m,))
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
            pr, ser, kr = period_fit_best(tr, dtr, (period * 1e9, float(np.partition(dtr, h)[h])))
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
