# SPDX-License-Identifier: Apache-2.0
"""Cramer-Rao lower bounds on the contact position: one emission for a given pulse, noise
and geometry (`position_crlb`, `simulated_crlb`) and the joint bound of two or three
overlapping emissions under the overlap model (`joint_crlb`).

Model (white Gaussian noise of variance sigma^2 per sample, per channel):

    x_k[n] = A c_k(t_n - (t_k(s) - t_k(s0)) - T0) + noise,

c_k the noise-free signal of channel k for the true point s0 (e.g. the simulator's
``clean_v``), s = (s_x, s_y) on the sphere, T0 the unknown emission time, A an unknown
amplitude. The Fisher matrix over theta = (s_x, s_y, T0, A) is

    F = (1/sigma^2) sum_{k, n} d mu/d theta  d mu/d theta^T,
    d mu/d s_i = -c_k'(t_n) d t_k / d s_i,   d mu / d T0 = -c_k'(t_n),   d mu / d A = c_k(t_n),

and the in-plane bound is CRB_xy = (F^-1)[:2, :2]; we report sqrt(tr CRB_xy) (RMS
in-plane error of an unbiased estimator). This is the *known pulse shape* bound (the
amplitude ratios between channels, from 1/l spreading, are not used as position
information). For an *unknown* waveform the waveform nuisance removes the common shift
only (Schur complement): F_t = (diag(E) - E E^T / sum E) / sigma^2 with
E_k = sum_n c_k'(t_n)^2, F_s = J^T F_t J; both are returned (they agree to a few
percent: the unknown-waveform bound is the slightly higher one).

The samples used are those an echo-free analysis can use: per channel, everything
before its arrival + ``geometry.echo_free_duration_s - echo_guard_s`` (``window='echo_free'``,
as the estimators do), or the whole window (``window='full'``; meaningful only when the
simulation has no wall echoes).

c_k' is needed at the sample instants: `simulated_crlb` gets it exactly from the
simulator (which evaluates the continuous-time response at any sub-sample offset) by a
central difference over +-1e-3 sample of the trigger offset.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import linalg

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization.overlap.model import _lstsq_amplitudes, _Model, _model_values
from ae_tactile.localization.overlap.pulse import PulseModel
from ae_tactile.sim import SimConfig, noise_rms_for_snr, render_triggered, signal_power_v2

__all__ = ["position_crlb", "simulated_crlb", "joint_crlb", "noise_covariance",
           "coloured_position_crlb"]


def position_crlb(
    clean_v,
    dclean_dt_v,
    sample_rate_hz,
    noise_var_v2,
    points_m,
    arrival_times_s,
    geometry: FingertipGeometry,
    *,
    window="echo_free",
    echo_guard_s=0.3e-6,
):
    """Bounds for K packets. Arrays: clean_v, dclean_dt_v (K, 4, M) (V, V/s), noise_var_v2
    (K,) or scalar, points_m (K, 3), arrival_times_s (K, 4) (relative to the first sample).

    Returns dict: crb_xy_m2 (K, 2, 2) known-shape bound, rms_m (K,) = sqrt(tr),
    crb_xy_unknown_m2 and rms_unknown_m (K,) for an unknown waveform.
    """
    c = np.asarray(clean_v, float)
    dc = np.asarray(dclean_dt_v, float)
    k, _, m = c.shape
    fs = float(sample_rate_hz)
    var = np.broadcast_to(np.asarray(noise_var_v2, float), (k,))
    pts = np.asarray(points_m, float)
    arr = np.asarray(arrival_times_s, float)
    t = np.arange(m) / fs
    if window == "echo_free":
        mask = t[None, None, :] < (arr + geometry.echo_free_duration_s - echo_guard_s)[..., None]
    elif window == "full":
        mask = np.ones((k, 4, m), bool)
    else:
        raise ValueError("window must be 'echo_free' or 'full'")
    _, dt, _ = geometry.arrival_time_derivatives(pts[:, 0], pts[:, 1])  # (K, 4, 2)
    dcm = dc * mask
    cm = c * mask
    # Per-channel sums.
    e_dd = np.einsum("kcn,kcn->kc", dcm, dcm)  # sum c'^2
    e_dc = np.einsum("kcn,kcn->kc", dcm, cm)  # sum c' c
    e_cc = np.einsum("kcn,kcn->kc", cm, cm)
    f = np.zeros((k, 4, 4))
    # d mu/d s_i = -c' dt_i, d mu/d T0 = -c', d mu/d A = c
    f[:, :2, :2] = np.einsum("kc,kci,kcj->kij", e_dd, dt, dt)
    f[:, :2, 2] = np.einsum("kc,kci->ki", e_dd, dt)
    f[:, :2, 3] = -np.einsum("kc,kci->ki", e_dc, dt)
    f[:, 2, 2] = e_dd.sum(axis=1)
    f[:, 2, 3] = -e_dc.sum(axis=1)
    f[:, 3, 3] = e_cc.sum(axis=1)
    f = np.triu(f) + np.swapaxes(np.triu(f, 1), 1, 2)
    f /= var[:, None, None]
    crb = np.linalg.inv(f)[:, :2, :2]
    # Unknown waveform.
    e = e_dd
    ft = np.zeros((k, 4, 4))
    idx = np.arange(4)
    ft[:, idx, idx] = e
    ft -= e[:, :, None] * e[:, None, :] / e.sum(axis=1)[:, None, None]
    ft /= var[:, None, None]
    fsph = np.einsum("kai,kab,kbj->kij", dt, ft, dt)
    crb_u = np.linalg.inv(fsph)
    return dict(
        crb_xy_m2=crb,
        rms_m=np.sqrt(np.trace(crb, axis1=1, axis2=2)),
        crb_xy_unknown_m2=crb_u,
        rms_unknown_m=np.sqrt(np.trace(crb_u, axis1=1, axis2=2)),
    )


def noise_covariance(config, noise_var_v2, m_len, include_quantization=True):
    """True per-channel noise covariance (M, M) [V^2] of a simulated device: white ADC
    noise (share 1 - ``amplifier_noise_share`` of ``noise_var_v2``), amplifier noise through
    the chain (the rest, its exact sampled autocorrelation `AmplifierNoise.autocorrelation`)
    and LSB^2/12 of rounding when the config quantizes.

    Parameters
    ----------
    config : SimConfig
    noise_var_v2 : float
        sigma_n^2 of the SNR definition [V^2].
    m_len : int
        Samples.
    include_quantization : bool

    Returns
    -------
    ndarray (M, M)
    """
    share = float(config.amplifier_noise_share)
    q = config.lsb_v**2 / 12.0 if (include_quantization and config.quantization) else 0.0
    cov = (noise_var_v2 * (1.0 - share) + q) * np.eye(m_len)
    if share > 0:
        r = config.frontend.amplifier_noise.autocorrelation(m_len)
        cov = cov + noise_var_v2 * share * linalg.toeplitz(r)
    return cov


def coloured_position_crlb(clean_v, dclean_dt_v, sample_rate_hz, noise_cov_v2, points_m,
                           arrival_times_s, geometry: FingertipGeometry, *,
                           echo_guard_s=0.3e-6):
    """Known-shape bound of `position_crlb` (x, y, emission time, amplitude) in Gaussian
    noise of any covariance: per channel F += J^T Sigma^-1 J over the echo-free samples
    (Sigma restricted to them), channels independent.

    Parameters
    ----------
    clean_v, dclean_dt_v : ndarray (K, 4, M)
        Noise-free windows [V] and their time derivative [V/s].
    sample_rate_hz : float
    noise_cov_v2 : ndarray (K, M, M) or (M, M)
        Per-channel noise covariance of each packet [V^2] (`noise_covariance`).
    points_m : ndarray (K, 3)
    arrival_times_s : ndarray (K, 4)
        Relative to the first sample [s].
    geometry : FingertipGeometry
    echo_guard_s : float

    Returns
    -------
    dict
        crb_xy_m2 (K, 2, 2), rms_m (K,) = sqrt(tr).
    """
    c = np.asarray(clean_v, float)
    dc = np.asarray(dclean_dt_v, float)
    k, _, m = c.shape
    cov = np.asarray(noise_cov_v2, float)
    if cov.ndim == 2:
        cov = np.broadcast_to(cov, (k, m, m))
    pts = np.asarray(points_m, float)
    t = np.arange(m) / float(sample_rate_hz)
    cut = np.asarray(arrival_times_s, float) + geometry.echo_free_duration_s - echo_guard_s
    _, dt, _ = geometry.arrival_time_derivatives(pts[:, 0], pts[:, 1])
    crb = np.empty((k, 2, 2))
    for i in range(k):
        f = np.zeros((4, 4))
        for ch in range(4):
            n = int(np.sum(t < cut[i, ch]))
            chol = linalg.cholesky(cov[i, :n, :n], lower=True)
            jac = np.column_stack([-dc[i, ch, :n] * dt[i, ch, 0], -dc[i, ch, :n] * dt[i, ch, 1],
                                   -dc[i, ch, :n], c[i, ch, :n]])
            w = linalg.solve_triangular(chol, jac, lower=True)
            f += w.T @ w
        crb[i] = np.linalg.inv(f)[:2, :2]
    return dict(crb_xy_m2=crb, rms_m=np.sqrt(np.trace(crb, axis1=1, axis2=2)))


def simulated_crlb(
    points_m,
    config=None,
    *,
    snr_db,
    subsample_offset=0.5,
    include_quantization=True,
    window="echo_free",
    echo_guard_s=0.3e-6,
    **render_kwargs,
):
    """CRLB for the simulator's pulse at ``points_m`` (N, 3) and ``snr_db`` (conventions.md).

    The noise variance is sigma_n^2 of the SNR definition, plus LSB^2/12 when the config
    quantizes and ``include_quantization`` (the ADC's rounding noise, which the data
    carry too). ``subsample_offset`` in [1e-3, 1 - 1e-3] (scalar or (N,)). Returns the
    dict of `position_crlb` plus ``noise_var_v2`` and ``sigma_n_v``.
    """
    cfg = SimConfig() if config is None else config
    h = 1e-3
    u = np.clip(np.asarray(subsample_offset, float), h, 1 - h)
    kw = dict(render_kwargs)
    base = render_triggered(points_m, cfg, subsample_offset=u, **kw)
    plus = render_triggered(points_m, cfg, subsample_offset=u + h, **kw)
    minus = render_triggered(points_m, cfg, subsample_offset=u - h, **kw)
    fs = base.sample_rate_hz
    # A later trigger offset delays the signal: c(t - d) -> d/dd = -c'.
    dcdt = -(plus.clean_v - minus.clean_v) / (2.0 * h / fs)
    p_sig = signal_power_v2(base.clean_v, base.onset_index, fs)
    sigma_n = noise_rms_for_snr(p_sig, snr_db)
    var = sigma_n**2
    if include_quantization and cfg.quantization:
        var = var + cfg.lsb_v**2 / 12.0
    if cfg.amplifier_noise_share > 0 and window == "echo_free":
        # coloured noise: the bound with the true covariance (white + amplifier noise)
        m_len = base.clean_v.shape[2]
        covs = np.stack([noise_covariance(cfg, s2, m_len, include_quantization)
                         for s2 in np.broadcast_to(sigma_n**2, (len(base),))])
        out = coloured_position_crlb(base.clean_v, dcdt, fs, covs, base.points_m,
                                     base.arrival_times_s, cfg.geometry,
                                     echo_guard_s=echo_guard_s)
        out["noise_var_v2"] = np.broadcast_to(var, (len(base),)).copy()
        out["sigma_n_v"] = np.broadcast_to(sigma_n, (len(base),)).copy()
        return out
    out = position_crlb(
        base.clean_v,
        dcdt,
        fs,
        var,
        base.points_m,
        base.arrival_times_s,
        cfg.geometry,
        window=window,
        echo_guard_s=echo_guard_s,
    )
    out["noise_var_v2"] = np.broadcast_to(var, (len(base),)).copy()
    out["sigma_n_v"] = np.broadcast_to(sigma_n, (len(base),)).copy()
    return out


def joint_crlb(
    clean_v,
    sample_rate_hz,
    onset_index,
    points_m,
    emission_time_s,
    noise_var_v2,
    *,
    geometry=None,
    pulse=None,
    analysis_s=None,
    pre_onset_s=1e-6,
):
    """Cramer-Rao bound of the J-emission model over the samples `resolve_overlaps` analyses.

    Model: the module's (known pulse shape h; unknowns per emission s_x, s_y, emission time,
    direct and echo amplitudes: 5J), white noise of variance ``noise_var_v2`` (K,) V^2.
    clean_v (K, 4, M): the noise-free windows (the true amplitudes are their LS fit at the
    true points and times, which also measures how well the model describes them),
    points_m (K, J, 3), emission_time_s (K, J) (window time).

    Returns dict: crb_xy_m2 (K, J, 2, 2), rms_m (K, J) = sqrt(tr) (joint bound),
    single_rms_m (K, J) (the bound of each emission were it alone, same samples),
    amplitudes (K, 2J) (V), model_mismatch (K,) = ||clean - model|| / ||clean|| at the truth.
    """
    geo = FingertipGeometry() if geometry is None else geometry
    pulse = PulseModel.for_sample_rate(sample_rate_hz) if pulse is None else pulse
    fs = float(sample_rate_hz)
    c = np.asarray(clean_v, float)
    pts = np.asarray(points_m, float)
    K, J, _ = pts.shape
    m = c.shape[2]
    pre = max(2, int(math.ceil(pre_onset_s * fs)))
    if analysis_s is None:
        a = geo.element_offset_m
        analysis_s = (4.0 * geo.radius_m - 2.0 * math.sqrt(2.0) * a) / geo.sound_speed_m_s - 0.3e-6
    start = np.clip(np.asarray(onset_index, np.int64) - pre, 0, m - 1)
    length = int(min(m - int(start.max()), pre + math.floor(analysis_s * fs)))
    idx = np.clip(start[:, None] + np.arange(length), 0, m - 1)
    y = np.take_along_axis(c, idx[:, None, :].repeat(4, axis=1), axis=2).reshape(K, -1)
    model = _Model(geo, fs, start, length, pulse, True)
    theta = np.concatenate([pts[..., :2], np.asarray(emission_time_s, float)[..., None]], axis=2)
    phi, parts = model.evaluate(theta)
    amp = _lstsq_amplitudes(phi, y, ridge=1e-12)
    mismatch = np.linalg.norm(y - _model_values(phi, amp), axis=1) / np.linalg.norm(y, axis=1)
    jac = np.concatenate([model.jacobian(parts, amp), phi], axis=1)
    var = np.broadcast_to(np.asarray(noise_var_v2, float), (K,))
    fis = jac @ jac.transpose(0, 2, 1) / var[:, None, None]
    cov = np.linalg.pinv(fis, hermitian=True)
    crb = np.stack([cov[:, 3 * q : 3 * q + 2, 3 * q : 3 * q + 2] for q in range(J)], axis=1)
    single = np.zeros((K, J))
    for q in range(J):
        cols = [3 * q, 3 * q + 1, 3 * q + 2, 3 * J + 2 * q, 3 * J + 2 * q + 1]
        c1 = np.linalg.pinv(fis[:, cols][:, :, cols], hermitian=True)
        single[:, q] = np.sqrt(np.trace(c1[:, :2, :2], axis1=1, axis2=2))
    return dict(
        crb_xy_m2=crb,
        rms_m=np.sqrt(np.trace(crb, axis1=2, axis2=3)),
        single_rms_m=single,
        amplitudes=amp,
        model_mismatch=mismatch,
    )
