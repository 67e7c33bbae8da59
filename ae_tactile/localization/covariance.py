# SPDX-License-Identifier: Apache-2.0
"""Delay and position uncertainty from the Fisher information of the fitted model.

Model of an aligned packet: y_k(t) = g_k s(t - eps_k) + n_k(t), white Gaussian noise of
variance sigma^2 per sample, unknown waveform s, channel gains g_k (from the 1/l
spreading: up to +-20 % near grazing). Per channel the delay information in the band is

    E_k = g_k^2 sum_n s'(t_n)^2 = g_k^2 (2/N) sum_{f in band} w^2 |S(f)|^2     (N = DFT length)

and eliminating the unknown waveform (Schur complement, equal to treating the common
delay T0 as a nuisance) gives the 4x4 Fisher matrix of the arrival times

    F_eps = (diag(E) - E E^T / sum(E)) / sigma^2        (rank 3: a common shift is free).

|S|^2 is estimated from the aligned mean |B/4|^2 minus its noise bias L sigma^2 / 4, the
gains from the per-channel band energies. Position covariances then follow by linear
propagation: the exact-sphere fit uses F_s = J^T F_eps J (J = d t / d(s_x, s_y)); the
delay estimators give C_tau = A F_eps^+ A^T (A the tau_x, tau_y contrasts), mapped by
`FingertipGeometry.point_covariance`.

A weighted pair estimator (GCC with weight W(f)) has, to first order, independent
per-channel errors of variance  v1 = (N sigma^2 / 2) sum W^2 w^2 |S|^2 / D^2  plus a
noise-by-noise term per pair  v2 = (N sigma^2 L sigma^2 / 2) sum W^2 w^2 / D^2,
D = sum W w^2 |S|^2; the pair LS then gives C = P (v1 Inc Inc^T + v2 I) P^T.
"""

from __future__ import annotations

import numpy as np

from ae_tactile.localization.common import CONTRASTS, PAIR_INCIDENCE, PAIR_PINV

#: Weight of the noise-by-noise term of `arrival_fisher` (calibrated, see there).
NOISE_BY_NOISE = 0.5


def signal_spectrum(Zb, sigma2, count, n_bins=None):
    """Noise-debiased |S(f)|^2 (K, nb) of the common waveform and the channel gains^2 (K, 4).
    ``n_bins`` (K,): bins in use per packet (the others are zero), default all."""
    L = count.mean(axis=1)
    B = Zb.mean(axis=1)
    s2 = np.maximum(np.abs(B) ** 2 - L[:, None] * sigma2[:, None] / 4.0, 0.0)
    nb = Zb.shape[2] if n_bins is None else np.asarray(n_bins)[:, None]
    e = (np.abs(Zb) ** 2).sum(axis=2) - nb * L[:, None] * sigma2[:, None]
    e = np.maximum(e, 1e-12 * np.abs(e).max(axis=1, keepdims=True) + 1e-300)
    g2 = e / np.maximum(e.mean(axis=1, keepdims=True), 1e-300)
    g2 = np.clip(g2, 0.1, 10.0)
    return s2, g2


def arrival_fisher(Zb, w, sigma2, count, n_fft, n_bins=None, noise_by_noise=False):
    """F_eps (K, 4, 4) of the four arrival times (s^-2), see the module docstring.

    ``noise_by_noise``: divide by 1 + kappa, kappa = c L sigma^2 sum_f w^2 / sum_f w^2 |S|^2
    over the bins in use (a prefix of ``n_bins`` per packet), c = NOISE_BY_NOISE: the
    noise-by-noise share of the delay variance, which matters at low per-bin SNR (kappa ~4 %
    at 10 dB for the simulator's pulse, < 1 % from 20 dB). c = 1 is the two-channel
    correlator's first-order term; 1/2 calibrates the four-channel fit on simulated and
    analytic pulses (bench/bench_localization.py)."""
    s2, g2 = signal_spectrum(Zb, sigma2, count, n_bins)
    e_mean = (2.0 / n_fft) * (w * w * s2).sum(axis=1)  # (K,)
    if noise_by_noise:
        cw2 = np.cumsum(w * w)
        nb = np.full(len(s2), len(w)) if n_bins is None else np.asarray(n_bins, int)
        sw2 = cw2[np.clip(nb, 1, len(w)) - 1]
        kappa = (
            NOISE_BY_NOISE
            * count.mean(axis=1)
            * sigma2
            * sw2
            / np.maximum((w * w * s2).sum(axis=1), 1e-300)
        )
        e_mean = e_mean / (1.0 + kappa)
    e = g2 * e_mean[:, None]  # (K, 4)
    f = np.zeros(e.shape + (4,))
    idx = np.arange(4)
    f[:, idx, idx] = e
    f -= e[:, :, None] * e[:, None, :] / np.maximum(e.sum(axis=1), 1e-300)[:, None, None]
    return f / sigma2[:, None, None]


def _safe_inv2(m):
    """Inverse of (K, 2, 2) symmetric matrices; singular ones get a huge isotropic inverse."""
    a, b, d = m[:, 0, 0], m[:, 0, 1], m[:, 1, 1]
    det = a * d - b * b
    ok = np.isfinite(det) & (det > 1e-30 * np.maximum(a * d, 1e-300)) & (a > 0) & (d > 0)
    det = np.where(ok, det, 1.0)
    inv = np.stack([np.stack([d, -b], -1), np.stack([-b, a], -1)], -2) / det[:, None, None]
    return np.where(ok[:, None, None], inv, np.nan), ok


def delay_noise_covariance(timing_sd_s):
    """(2, 2) [s^2]: what independent per-channel arrival errors of ``timing_sd_s`` [s] add
    to the covariance of (tau_x, tau_y), each a quarter of a signed sum of the four
    arrivals (`FingertipGeometry.delays_from_arrival_times`)."""
    return np.eye(2) * (float(timing_sd_s) ** 2 / 4.0)


def with_delay_noise(geometry, point_m, covariance_m2, delay_noise):
    """(3, 3) [m^2]: a point's covariance ``covariance_m2`` from a fit whose delay noise
    is the model's, made to carry a device's delay noise (scale, per-channel timing sd
    [s]; None: unchanged): scale C + the image of `delay_noise_covariance` at the point
    (the map from delays to a point is linear)."""
    c = np.asarray(covariance_m2, dtype=float)
    if delay_noise is None:
        return c
    scale, sd = delay_noise
    extra = geometry.point_covariance(np.asarray(point_m, dtype=float),
                                      delay_noise_covariance(sd))
    return scale * c + extra


def delay_covariance_from_fisher(F_eps):
    """C_tau (K, 2, 2) for (tau_x, tau_y) from F_eps (pseudo-inverse on the rank-3 space)."""
    # F_eps 1 = 0; F + (1 1^T)/4 is invertible and its inverse acts as F^+ on contrasts.
    ones = np.full((4, 4), 0.25)
    inv = np.linalg.inv(
        F_eps + ones[None] * np.maximum(np.trace(F_eps, axis1=1, axis2=2), 1e-300)[:, None, None]
    )
    A = CONTRASTS[:2]
    return A @ inv @ A.T


def sphere_covariance(F_eps, dt):
    """C_xy (K, 2, 2) of the exact-sphere fit: (J^T F_eps J)^-1, J = dt/ds (K, 4, 2)."""
    fs = np.einsum("kai,kab,kbj->kij", dt, F_eps, dt)
    return _safe_inv2(fs)


def weighted_pair_delay_covariance(Zb, w, sigma2, count, n_fft, weight):
    """C_tau (K, 2, 2) of a pair-correlation estimator with band weights ``weight`` (K, nb)."""
    s2, _ = signal_spectrum(Zb, sigma2, count)
    L = count.mean(axis=1)
    w2 = w * w
    D = (weight * w2 * s2).sum(axis=1)
    D = np.maximum(D, 1e-300)
    nu = n_fft * sigma2
    v1 = 0.5 * nu * (weight**2 * w2 * s2).sum(axis=1) / D**2
    v2 = 0.5 * nu * L * sigma2 * (weight**2 * w2).sum(axis=1) / D**2
    inc = PAIR_INCIDENCE @ PAIR_INCIDENCE.T
    c_delta = v1[:, None, None] * inc[None] + v2[:, None, None] * np.eye(6)[None]
    c_theta = PAIR_PINV[None] @ c_delta @ PAIR_PINV.T[None]
    return c_theta[:, :2, :2]
