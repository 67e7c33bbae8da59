# SPDX-License-Identifier: Apache-2.0
"""The GCC-PHAT estimator (method ``"gcc_phat"``), and the pair-delay post-processing it
shares with the paper's baseline (``"xcorr_farfield"``, in `xcorr_farfield`).

GCC-PHAT: cross-spectra G_ij = X_i X_j^* of the 6 channel pairs on the common (coarse)
segment, PHAT weight 1/|G_ij| inside the signal band only (zero outside: whitening the
noise-only bins would amplify noise), integer peak within the physically possible lags,
parabolic interpolation, then Newton steps on the band-limited correlation
r(d) = sum_f W Re(G e^{j w d}) (exact sub-sample interpolation of a band-limited
function). LS over the 6 pairs gives (tau_x, tau_y, twist) and an RMS pair residual
(consistency, s); the point follows from the exact inversion.
"""

from __future__ import annotations

import numpy as np

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


