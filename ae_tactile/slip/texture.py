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
        """TEXTURE while the contact's latest texture_min_intervals intervals are periodic
        (`_periodic_window`) for texture_confirm_events tests in a row; the period by least
        squares on the intervals' period counts (`period_fit_best`), the spatial period
        from the tracked speed (moving contact) or the sliding speed (fixed contact). With the
        fingertip model only a sliding (GROSS_SLIP) or moving contact has a texture; the
        rules make a texture gross slip: GROSS_SLIP and its SLIP come first."""
        cfg = self.config
        n = cfg.texture_min_intervals + 1
        k = c.valid()
        if k < n or (self._model and not (c.state == ContactState.GROSS_SLIP or c.moving)):
            # a texture is read off a sliding contact: a held one's regular micro-slips
            # under a steady load are no texture
            return
        window = self._periodic_window(c, n, k)
        if window is None:
            c.texture_on, c.texture_run = False, 0
            return
        sel, ts, dt, m, llr = window
        period, se_period, kk = period_fit_best(ts, dt, (m,))
        c.texture_run += 1
        if c.texture_run < cfg.texture_confirm_events or not period > 0:
            return
        t = ev.time_ns
        lam = math.nan
        if c.moving:
            spatial = self._moving_period(c, k, period, se_period)
            if spatial is None:
                return  # periodic, but the spatial period is not known well yet
            lam, period = spatial
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

    def _periodic_window(self, c, n, k):
        """The latest ``n`` emissions of the contact if they pass the periodicity tests:
        mostly evidence (unless the contact moves: a run of pairs and repeats is tapping,
        not texture), the cheap screen (`_near_multiples`), no interval longer than
        texture_max_multiple periods, and the interval model's log-likelihood ratio against
        Poisson (`_interval_llr`) at least texture_min_llr. Returns (their slots as a mask
        of the ``k`` valid ones, times [ns] sorted, intervals [ns], median interval [ns],
        log-likelihood ratio), or None."""
        cfg = self.config
        # every emission of the contact counts (a texture under a fixed contact also lands
        # on spots hit before). The latest n slots of the ring (events come nearly in time
        # order), sorted.
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
            return None
        tl.sort()
        dtl = [b - a for a, b in zip(tl, tl[1:])]
        m = sorted(dtl)[len(dtl) // 2]
        if not m > 0 or not _near_multiples(dtl, m):
            return None
        slots = [(c.n - n + i) % H for i in range(n)] if c.n >= n else list(range(n))
        order = np.asarray(slots)
        sel = np.zeros(k, bool)
        sel[order] = True
        ts = np.asarray(tl, dtype=np.int64)
        dt = np.asarray(dtl, dtype=float)
        m = float(m)
        kk = multiples(dt, m)
        if kk.max() > cfg.texture_max_multiple:
            return None
        period = float(dt.sum() / kk.sum())
        llr = self._interval_llr(dt / period)
        if llr < cfg.texture_min_llr:
            return None
        return sel, ts, dt, m, llr

    def _interval_llr(self, x):
        """Log-likelihood ratio of intervals ``x`` (in periods): a jittered periodic train
        with missed packets (k = 1, 2, 3 periods, sd texture_interval_sd sqrt(k), prior
        0.9 on k = 1) against a Poisson process of the same mean rate."""
        return float(
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

    def _moving_period(self, c, k, period, se_period):
        """(spatial period [m], period [s]) of a moving contact's texture: the speed along
        its great circle over every remembered emission of the run (not only
        track_window_s: its standard error falls as n^-3/2) times the period refitted over
        the same emissions (a longer run: a smaller error); None until their relative
        standard error is below texture_period_rel_se."""
        cfg = self.config
        run = (c.flags[:k] & (FOUNDER | PAIRED)) == 0
        fit = self._motion_fit(c, run)
        if fit is None:
            return None
        tr = np.sort(c.t[:k][run])
        dtr = np.diff(tr).astype(float)
        h = dtr.size // 2  # the run's median interval (the upper one of an even count)
        pr, ser, kr = period_fit_best(tr, dtr, (period * 1e9, float(np.partition(dtr, h)[h])))
        if kr is not None and kr.max() <= cfg.texture_max_multiple:
            period, se_period = pr, ser
        rel = math.hypot(fit[1] / fit[0], se_period / period) if fit[0] > 0 else math.inf
        if rel > cfg.texture_period_rel_se:
            return None
        return fit[0] * period, period

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


def _near_multiples(dtl, m):
    """Cheap screen of intervals ``dtl`` [ns] with median ``m`` [ns]: at least 60 % of them
    within 40 % of the median or 30 % of its double or triple, where a texture's intervals
    mostly lie and a Poisson process's mostly do not."""
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
    return near * 10 >= 6 * len(dtl)
