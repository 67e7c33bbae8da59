# SPDX-License-Identifier: Apache-2.0
"""Maximum-likelihood fit of the exact spherical geometry (method ``"ml"``).

For an unknown deterministic waveform in white noise with equal channel gains, the
likelihood of a contact point s on the sphere is maximised by the steered response power

    P(s) = sum_{f in band} | sum_k Y_k(f) exp(+j w eps_k(s)) |^2,
    eps_k(s) = t_k(s) - c_k,   t_k(s) = |s - e_k| / c   (exact, no far-field step),

Y_k the spectra of the aligned segments (each cut at its own integer-sample arrival,
offset c_k). The two unknowns are the in-plane coordinates (s_x, s_y) of the point on
the upper hemisphere; P does not depend on the emission time.

Start: the band-limited cross-correlation of the 6 channel pairs (integer lag + parabola,
LS for tau_x, tau_y, twist), inverted exactly with `point_from_delays`. Then damped
Newton steps on P with the analytic gradient and Hessian through d t_k / d s and
d^2 t_k / d s^2 (`FingertipGeometry.arrival_time_derivatives`), a vectorised line search
(step 1, 1/2, 1/4, 1/8 or none), and a projection onto the horizon circle
rho <= R. If the fit drifts by more than 3/4 sample from the integer cut, the segments
are re-cut once and the Newton steps repeated.

Band: fixed (``plan.band``), or with a data-driven plan (``plan.auto_fallback_hz > 0``)
each packet keeps the candidate bins up to its own edge (`common.band_edge_hz`): the
others are zeroed in the spectra, which removes them from P, its derivatives, the misfit
and the covariance. The compiled kernel (fast.py) does the same per packet.
"""

from __future__ import annotations

import numpy as np

from ae_tactile.localization.common import PAIRS, Plan, adc_noise, band_edge_hz
from ae_tactile.localization.covariance import arrival_fisher, sphere_covariance
from ae_tactile.localization.pairs import aligned_spectra, delays_from_pairs, pair_delays
from ae_tactile.localization.segments import Prepared, subset

_ALPHAS = np.array([1.0, 0.5, 0.25, 0.125, 0.0])


def _project(sx, sy, r):
    rho = np.hypot(sx, sy)
    lim = r * (1.0 - 1e-9)
    over = rho > lim
    f = np.where(over, lim / np.where(rho > 0, rho, 1.0), 1.0)
    return sx * f, sy * f, over


def srp(Yb, w, eps):
    """P (K, ...) for residual shifts eps (K, ..., 4)."""
    z = Yb.reshape(Yb.shape[:1] + (1,) * (eps.ndim - 2) + Yb.shape[1:]) * np.exp(
        1j * w * eps[..., None]
    )
    b = z.sum(axis=-2)
    return (b.real**2 + b.imag**2).sum(axis=-1)


def newton(Yb, w, geometry, s, c0, iterations, max_step_m, tol_m):
    """Damped Newton ascent of P over (s_x, s_y), vectorised; a packet stops moving once its
    step falls below ``tol_m`` (so results do not depend on the rest of the batch)."""
    r = geometry.radius_m
    sx, sy = s[:, 0].copy(), s[:, 1].copy()
    w2 = w * w
    clamped = np.zeros(sx.shape, bool)
    act = np.arange(len(sx))
    for _ in range(iterations):
        if act.size == 0:
            break
        yb, c = Yb[act], c0[act]
        ax, ay = sx[act], sy[act]
        t, dt, d2t = geometry.arrival_time_derivatives(ax, ay)
        z = yb * np.exp(1j * w * (t - c)[..., None])
        b = z.sum(axis=1)
        cb = np.conj(b)[:, None, :] * z  # (K, 4, nb)
        g_e = -2.0 * (w * cb.imag).sum(axis=2)  # dP/d eps_k
        h_e = 2.0 * np.einsum("kaf,kbf,f->kab", z, np.conj(z), w2).real
        idx = np.arange(4)
        h_e[:, idx, idx] -= 2.0 * (w2 * cb.real).sum(axis=2)
        g = np.einsum("kai,ka->ki", dt, g_e)
        h = np.einsum("kai,kab,kbj->kij", dt, h_e, dt) + np.einsum("ka,kaij->kij", g_e, d2t)
        a, bb, d = h[:, 0, 0], h[:, 0, 1], h[:, 1, 1]
        mid = 0.5 * (a + d)
        rad = np.sqrt(0.25 * (a - d) ** 2 + bb * bb)
        lmax, lmin = mid + rad, mid - rad
        scale = np.abs(a) + np.abs(d) + 1e-300
        # Levenberg shift where the Hessian is not negative definite.
        mu = np.where(lmax > -1e-6 * scale, lmax + 0.1 * np.abs(lmin) + 1e-3 * scale, 0.0)
        a, d = a - mu, d - mu
        det = a * d - bb * bb
        det = np.where(np.abs(det) > 0, det, 1e-300)
        stx = -(d * g[:, 0] - bb * g[:, 1]) / det
        sty = -(a * g[:, 1] - bb * g[:, 0]) / det
        norm = np.hypot(stx, sty)
        f = np.where(norm > max_step_m, max_step_m / np.where(norm > 0, norm, 1.0), 1.0)
        stx = np.where(np.isfinite(stx), stx * f, 0.0)
        sty = np.where(np.isfinite(sty), sty * f, 0.0)
        taken = np.where(np.isfinite(norm), norm * f, 0.0)
        # Full step; a line search (1/2, 1/4, 1/8 or no step) only where P fell.
        nx, ny, over = _project(ax + stx, ay + sty, r)
        p_new = srp(yb, w, _times(geometry, nx, ny) - c)
        p_old = (b.real**2 + b.imag**2).sum(axis=1)
        worse = ~(p_new >= p_old)
        if worse.any():
            ids = np.nonzero(worse)[0]
            al = _ALPHAS[1:]
            cx = ax[ids, None] + al * stx[ids, None]
            cy = ay[ids, None] + al * sty[ids, None]
            cx, cy, ov = _project(cx, cy, r)
            pc = srp(yb[ids], w, _times(geometry, cx, cy) - c[ids, None, :])
            best = np.argmax(pc, axis=1)
            rows = np.arange(len(ids))
            nx[ids], ny[ids], over[ids] = cx[rows, best], cy[rows, best], ov[rows, best]
            taken[ids] = taken[ids] * al[best]
        sx[act], sy[act], clamped[act] = nx, ny, over
        act = act[taken >= tol_m]
    return np.stack([sx, sy], axis=1), clamped


def _times(geometry, sx, sy):
    return geometry._xy_distances(sx, sy) / geometry.sound_speed_m_s


def _data_band(prep: Prepared, plan: Plan, X):
    """Data-driven band: each packet keeps the candidate bins up to its own edge. Returns
    (X with the pair start's bins cut at min(edge, fallback edge) (the start needs the
    integer lag only), the (K, 1, bins) mask of the aligned bins up to each edge)."""
    given = np.zeros(len(prep.sigma2), bool) if prep.noise_given is None else prep.noise_given
    s2 = adc_noise(prep.sigma2, prep.quant2, given)
    f_edge = band_edge_hz(X[..., plan.band], s2, prep.seg_count, plan)
    X = X.copy()
    f_start = np.minimum(f_edge, plan.auto_fallback_hz)
    X[..., plan.band] *= (plan.w / (2 * np.pi) <= f_start[:, None])[:, None, :]
    mask_al = (plan.w_al / (2 * np.pi) <= f_edge[:, None])[:, None, :]
    return X, mask_al


def _recut(prep, plan, ids, s, clamped, al, c0, mask_al, iterations, max_step, cdel):
    """Re-cut the packets ``ids`` on their fitted points and fit them again; ``s``,
    ``clamped``, ``al`` and ``c0`` are updated in place."""
    geo = plan.geometry
    fs = plan.fs
    sub = subset(prep, ids)
    t = _times(geo, s[ids, 0], s[ids, 1])
    al2 = aligned_spectra(sub, plan, t + cdel)
    if mask_al is not None:
        al2.Yb = al2.Yb * mask_al[ids]
    c2 = al2.ref[:, None] + al2.shift / fs - cdel
    s2, cl2 = newton(al2.Yb, plan.w_al, geo, s[ids], c2, iterations, max_step, 1e-4 * max_step)
    s[ids], clamped[ids] = s2, cl2
    al.Y[ids], al.Yb[ids], al.shift[ids], al.ref[ids], al.count[ids] = (
        al2.Y,
        al2.Yb,
        al2.shift,
        al2.ref,
        al2.count,
    )
    al.seg[ids] = al2.seg
    c0[ids] = c2


def _delays_arg(channel_delays_s):
    """(4,) float64 [s] of the channels' own delays (zeros for None); ValueError."""
    if channel_delays_s is None:
        return np.zeros(4)
    d = np.asarray(channel_delays_s, dtype=float)
    if d.shape != (4,) or not np.isfinite(d).all():
        raise ValueError(f"channel_delays_s must be 4 finite delays [s], got {channel_delays_s!r}")
    return d


def estimate(prep: Prepared, plan: Plan, *, iterations: int = 4, channel_delays_s=None):
    """Exact-sphere ML fit. Returns the estimator core dict (see estimators.py).

    ``channel_delays_s`` (4,) [s]: each channel's own delay (front-end group delay), taken
    out of its arrival: the model is t_k(s) + d_k (None: zeros). The core's ``eps_samples``
    and ``zb`` are then the residual shifts less d_k, so the misfit and covariance see
    the corrected channels."""
    cdel = _delays_arg(channel_delays_s)
    if (
        isinstance(iterations, bool)
        or not isinstance(iterations, (int, np.integer))
        or iterations < 1
    ):
        raise ValueError(f"iterations must be a positive integer, got {iterations!r}")
    geo = plan.geometry
    fs = plan.fs
    X = prep.X
    mask_al = None
    if plan.auto_fallback_hz > 0:
        X, mask_al = _data_band(prep, plan, X)
    d, _, edge = pair_delays(X, plan)
    d = d - (cdel[PAIRS[:, 0]] - cdel[PAIRS[:, 1]])  # pair lag ~ t_i - t_j: own delays out
    theta0, pair_res = delays_from_pairs(d)
    pts0, _ = geo.point_from_delays(theta0[:, 0], theta0[:, 1], exact=True)
    s = np.nan_to_num(pts0[:, :2])
    # One Newton step is worth about one sample of delay at most.
    max_step = geo.radius_m * geo.sound_speed_m_s / (geo.element_offset_m * fs)
    t = _times(geo, s[:, 0], s[:, 1])
    al = aligned_spectra(prep, plan, t + cdel)
    if mask_al is not None:
        al.Yb = al.Yb * mask_al
    c0 = al.ref[:, None] + al.shift / fs - cdel  # eps_k = t_k(s) + d_k - cut_k
    s, clamped = newton(al.Yb, plan.w_al, geo, s, c0, iterations, max_step, 1e-4 * max_step)
    # Re-cut (once) the packets whose fit drifted more than 3/4 sample from the integer cut.
    eps = _times(geo, s[:, 0], s[:, 1]) - c0
    drift = np.abs(eps - eps.mean(axis=1, keepdims=True)).max(axis=1) * fs >= 0.75
    if drift.any():
        _recut(prep, plan, np.nonzero(drift)[0], s, clamped, al, c0, mask_al, iterations,
               max_step, cdel)
    t, dt, _ = geo.arrival_time_derivatives(s[:, 0], s[:, 1])
    eps = t - c0
    zb = al.Yb * np.exp(1j * plan.w_al * eps[..., None])
    z = al.Y * np.exp(1j * plan.w_full_al * eps[..., None])
    sz = np.sqrt(np.maximum(geo.radius_m**2 - s[:, 0] ** 2 - s[:, 1] ** 2, 0.0))
    point = np.stack([s[:, 0], s[:, 1], sz], axis=1)
    delays = geo.delays_from_arrival_times(t)

    n_bins = np.full(len(s), zb.shape[2]) if mask_al is None else mask_al[:, 0, :].sum(axis=1)

    def covariance(sigma2):
        F = arrival_fisher(
            zb, plan.w_al, sigma2, al.count, plan.n_fft_al, n_bins, noise_by_noise=True
        )
        c_xy, ok = sphere_covariance(F, dt)
        jac = geo.delay_jacobian(s[:, 0], s[:, 1])
        c_tau = jac @ c_xy @ np.swapaxes(jac, 1, 2)
        return c_tau, ok

    return dict(
        theta=delays,
        point=point,
        clamped=clamped,
        zb=zb,
        z=z,
        count=al.count,
        raw_delays=theta0[:, :2],
        covariance=covariance,
        pair_residual_s=pair_res,
        at_edge=edge,
        aligned_seg=al.seg,
        eps_samples=eps * fs,
        n_bins=n_bins,
    )
