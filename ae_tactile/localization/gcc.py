# SPDX-License-Identifier: Apache-2.0
"""Pairwise correlation estimators: GCC-PHAT (method ``"gcc_phat"``) and the paper's
one-shot far-field inversion from plain cross-correlation peaks (``"xcorr_farfield"``).

GCC-PHAT: cross-spectra G_ij = X_i X_j^* of the 6 channel pairs on the common (coarse)
segment, PHAT weight 1/|G_ij| inside the signal band only (zero outside: whitening the
noise-only bins would amplify noise), integer peak within the physically possible lags,
parabolic interpolation, then Newton steps on the band-limited correlation
r(d) = sum_f W Re(G e^{j w d}) (exact sub-sample interpolation of a band-limited
function). LS over the 6 pairs gives (tau_x, tau_y, twist) and an RMS pair residual
(consistency, s); the point follows from the exact inversion.

xcorr_farfield (baseline, what the paper did for Fig. 7(d) and 8(e)): plain full-band
cross-correlation of the sums p11 + p1-1 against p-11 + p-1-1 (lag = -2 tau_x) and of
p11 + p-11 against p1-1 + p-1-1 (lag = -2 tau_y), parabolic peak, and the far-field
inversion of Eq. 2-3, (s_x, s_y) = (c R / a)(tau_x, tau_y).
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft

from ae_tactile.localization.common import Plan
from ae_tactile.localization.covariance import (
    arrival_fisher,
    delay_covariance_from_fisher,
    signal_spectrum,
    weighted_pair_delay_covariance,
)
from ae_tactile.localization.pairs import (
    aligned_spectra,
    delays_from_pairs,
    pair_delays,
    relative_arrivals,
)
from ae_tactile.localization.segments import Prepared


def _finish(prep, plan, theta, point, clamped, cov_kind, pair_res, raw, edge):
    fs = plan.fs
    t = relative_arrivals(theta)
    al = aligned_spectra(prep, plan, t)
    eps = t - al.ref[:, None] - al.shift / fs
    zb = al.Yb * np.exp(1j * plan.w_al * eps[..., None])
    z = al.Y * np.exp(1j * plan.w_full_al * eps[..., None])

    def covariance(sigma2):
        if cov_kind == "phat":
            s2, _ = signal_spectrum(zb, sigma2, al.count)
            L = al.count.mean(axis=1)
            weight = 1.0 / np.maximum(s2 + L[:, None] * sigma2[:, None], 1e-300)
            c = weighted_pair_delay_covariance(
                zb, plan.w_al, sigma2, al.count, plan.n_fft_al, weight
            )
        else:
            F = arrival_fisher(zb, plan.w_al, sigma2, al.count, plan.n_fft_al)
            c = delay_covariance_from_fisher(F)
        return c, np.ones(len(sigma2), bool)

    return dict(
        theta=theta,
        point=point,
        clamped=clamped,
        zb=zb,
        z=z,
        count=al.count,
        raw_delays=raw,
        covariance=covariance,
        pair_residual_s=pair_res,
        at_edge=edge,
    )


def estimate_gcc_phat(prep: Prepared, plan: Plan, *, refine: int = 3):
    d, _, edge = pair_delays(prep.X, plan, phat=True, refine=refine)
    theta, pair_res = delays_from_pairs(d)
    point, clamped = plan.geometry.point_from_delays(theta[:, 0], theta[:, 1], exact=True)
    return _finish(prep, plan, theta, point, clamped, "phat", pair_res, theta[:, :2], edge)


def _sum_pair_lag(U, V, plan, max_lag):
    """Lag (samples) of the plain full-band cross-correlation peak of U against V (K,), and
    whether it sits at the edge of the allowed lags (K,)."""
    n = plan.n_fft
    G = U * np.conj(V)
    G[:, 0] = 0.0
    r = sfft.irfft(G, n=n, axis=1)
    lags = np.arange(n)
    lags = np.where(lags > n // 2, lags - n, lags)
    rm = np.where(np.abs(lags)[None, :] <= max_lag, r, -np.inf)
    i0 = np.argmax(rm, axis=1)
    rows = np.arange(r.shape[0])
    y0, ym, yp = r[rows, i0], r[rows, (i0 - 1) % n], r[rows, (i0 + 1) % n]
    den = ym - 2 * y0 + yp
    frac = np.where(den < 0, 0.5 * (ym - yp) / np.where(den < 0, den, -1.0), 0.0)
    return lags[i0] + np.clip(frac, -0.5, 0.5), np.abs(lags[i0]) >= max_lag


def estimate_xcorr_farfield(prep: Prepared, plan: Plan):
    X = prep.X
    fs = plan.fs
    max_lag = int(plan.max_lag[0])  # elements 2a apart
    lx, ex = _sum_pair_lag(X[:, 0] + X[:, 1], X[:, 2] + X[:, 3], plan, max_lag)
    ly, ey = _sum_pair_lag(X[:, 0] + X[:, 2], X[:, 1] + X[:, 3], plan, max_lag)
    tx = -lx / (2.0 * fs)
    ty = -ly / (2.0 * fs)
    theta = np.stack([tx, ty, np.zeros_like(tx)], axis=1)
    point, clamped = plan.geometry.point_from_delays(tx, ty, exact=False)
    return _finish(
        prep, plan, theta, point, clamped, "plain", np.zeros_like(tx), theta[:, :2], ex | ey
    )
