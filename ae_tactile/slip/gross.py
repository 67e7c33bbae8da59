# SPDX-License-Identifier: Apache-2.0
"""Gross-slip test of the slip detector: SLIP (-> GROSS_SLIP) when the contact moves, when
the sequential likelihood ratio of gross slip against micro-slip continuation reaches
``gross_llr_threshold``, when an emission of the latest window lies inside the stick
zone, or when the latest emissions' rate is a tail of the contact's own micro-slip rate
(learnt from its emissions before them: a negative binomial predictive)."""

from __future__ import annotations

import math
from bisect import bisect_left, bisect_right

import numpy as np

from .contact import EVID, PAIRED, REPEAT

#: a contact's founder is left out of its activity's rate when the silence after it is
#: this many times the mean of the next (up to 4) intervals: a touch that announced the
#: contact, then its micro-slips, whose onset is no jump from that silence
FOUNDER_SILENCE_RATIO = 10.0


class GrossSlipTest:
    """The gross-slip decision of a contact.

    Methods of `SlipDetector` (`ae_tactile.slip.detector`), which holds the state they
    use: ``config``, ``counts``, ``contacts`` and the windows in ns set by ``_apply``.
    """

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
        onset = self._activity_onset(c, tu)
        if (
            cfg.gross_llr_threshold > 0
            and self._gross_llr(c, t, T, use, tu, onset) >= cfg.gross_llr_threshold
        ):
            return 6
        n_w = len(tu) - bisect_right(tu, t - self._w_gross)  # T > t - gross_window
        if n_w < cfg.gross_min_events:
            return 0
        if c.fitted and c.radius > 0 and self._in_stick_zone(c, t, k, T, use):
            return 1
        return 2 if self._rate_jump(tu, t, onset) else 0

    def _activity_onset(self, c, tu):
        """The onset [ns] of the contact's current activity, from which its rate is learnt:
        its first emission, or the first after a silence of gross_prior_s or more (a grasp
        held silent for seconds, then loaded: its micro-slips' onset is no jump from that
        silence); ``tu``: the times used [ns], sorted."""
        onset = c.created_ns
        if len(tu) > 2 and tu[0] == c.founder_ns:
            # a founder followed by a silence much longer than the intervals after it is a
            # touch that announced the contact, not its first micro-slip: the activity
            # starts after it (a grasp loaded 0.1 s after its touch)
            nxt = tu[2:6]
            if tu[1] - tu[0] > FOUNDER_SILENCE_RATIO * (nxt[-1] - tu[1]) / len(nxt):
                onset = tu[1]
        if len(tu) > 1:
            gaps = np.flatnonzero(np.diff(np.asarray(tu)) >= self._w_prior)
            if gaps.size:
                onset = max(onset, tu[int(gaps[-1]) + 1])
        return onset

    def _in_stick_zone(self, c, t, k, T, use):
        """Does an emission of the latest gross_window_s lie inside the stick zone
        (gross_inner_fraction of the radius) of the ring as fitted now or as fitted before
        this window? (The window's own emissions, gross slip's among them, pull the fit; a
        drifting contact's older ring lags behind it.)"""
        inner = self.config.gross_inner_fraction
        Pw = c.p[:k][use & (T > t - self._w_gross)]
        D = Pw - c.centre
        if float(np.einsum("ij,ij->i", D, D).min()) < (inner * c.radius) ** 2:
            return True
        t_old = t - self._w_gross
        for tr, cr, rr in reversed(c.rings):
            if tr <= t_old:
                if tr != c.rings[-1][0]:
                    D = Pw - cr
                    if float(np.einsum("ij,ij->i", D, D).min()) < (inner * rr) ** 2:
                        return True
                break
        return False

    def _rate_jump(self, tu, t, onset):
        """Rate jump (scan statistic): the latest j emissions (times ``tu`` [ns], sorted)
        span tau; j - 1 of them in tau under the contact's own micro-slip rate is a tail
        P(N >= j - 1) below gross_rate_alpha / (number of spans tested): a jump. That rate
        is known only from the n_p emissions of the part of gross_history_s before them
        that the contact has lived since ``onset`` (h of it): lambda ~ Gamma(n_p + 1, h)
        (flat prior), times gross_rate_growth (a Cattaneo-Mindlin load's rate grows as
        (1 - q)^(-1/3)), the same micro-slip hypothesis as `_gross_llr`; N is then
        negative binomial (r = n_p + 1, p = b / (b + tau), b = h / gross_rate_growth):
        a plug-in Poisson rate would read the clusters of a Poisson stream whose rate is
        learnt from ~10 emissions as jumps."""
        cfg = self.config
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
            b = covered / cfg.gross_rate_growth  # [ns]
            r, p = n_p + 1.0, b / (b + (t - t0))
            # P(N >= j - 1) for N ~ NegativeBinomial(r, p): P(0) = p^r, then the ratio
            term, cdf = math.exp(r * math.log(p)), 0.0
            for i in range(j - 1):
                cdf += term
                term *= (r + i) / (i + 1) * (1.0 - p)
            if 1.0 - cdf < alpha:
                return True
        return False

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
        rings = c.rings if c.fitted else ()
        # the prior starts at the onset of the contact's activity, or at the oldest
        # emission the ring buffer still holds once it has wrapped
        born = onset if c.n <= c.H else max(onset, int(T.min()))
        plan = self._llr_plan(ts, J, born, rings)
        ring = _ring_rho2(c, k, T, idx, rings, plan)
        kap, eps = cfg.gross_stick_fraction, cfg.gross_position_outlier
        kap2 = kap * kap
        pos = (kap, kap2, eps, -math.log(eps), 0.5 / (1.0 - kap2) if kap < 1 else 0.0)
        best = -math.inf
        for j, t0, cov, ri in plan:
            llr = self._timing_llr(tu, t, j, t0, cov)
            if ri is not None:
                llr = _position_llr(llr, j, J, t0, ring, ri, pos)
            if llr > best:
                best = llr
        return best

    def _llr_plan(self, ts, J, born, rings):
        """The spans `_gross_llr` tests [(j, t_0 [ns], prior time covered [ns], index of the
        latest ring fitted before t_0, without the tested emissions; None: no ring, no
        position term)] over the latest ``J`` used times ``ts`` [ns]."""
        plan = []
        for j in range(self.config.gross_min_events, J + 1):
            t0 = ts[J - j]
            cov = min(self._w_prior, t0 - born)
            if cov <= 0:
                break
            ri = None
            for i in range(len(rings) - 1, -1, -1):
                if rings[i][0] < t0:
                    ri = i if rings[i][2] > 0 else None
                    break
            plan.append((j, t0, cov, ri))
        return plan

    def _timing_llr(self, tu, t, j, t0, cov):
        """ln L_t of `_gross_llr` for the span of the latest ``j`` used emissions from
        ``t0`` to ``t`` [ns], the prior rate learnt over the ``cov`` ns before ``t0``."""
        cfg = self.config
        lo, hi = cfg.gross_rate_min_hz, cfg.gross_rate_max_hz
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
        return llr


def _ring_rho2(c, k, T, idx, rings, plan):
    """Every planned ring's rho^2 at once (rho = distance to the ring's centre / its
    radius): (ring index -> row, the micro-slips' times in time order [ns], rho^2 of the
    tested emissions ``idx`` (time order), the innermost micro-slip's rho^2 before each
    time (running minimum over the micro-slips in time order): the annulus the contact's
    micro-slips drew); empty when no span has a ring."""
    rows, ev_t, r2_used, ev_min = {}, None, None, None
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
    return rows, ev_t, r2_used, ev_min


def _position_llr(llr, j, J, t0, ring, ri, pos):
    """``llr`` plus the position term of `_gross_llr` for the span of the latest ``j`` of
    ``J`` tested emissions from ``t0`` [ns], against ring ``ri`` (``ring``: `_ring_rho2`;
    ``pos``: kappa, kappa^2, eps, ln(1/eps), 1 / (2 (1 - kappa^2)))."""
    rows, ev_t, r2_used, ev_min = ring
    kap, kap2, eps, s_in, d_all = pos
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
    return llr
