# SPDX-License-Identifier: Apache-2.0
"""The decision on a searched window: model order, the residual test against noise, the
separation test, each emission's covariance and confidence (`OverlapPacket`), and the
quick path from the raw window to that decision.
"""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.localization import overlap_kernels as _kernels
from ae_tactile.localization.common import Reason
from ae_tactile.localization.overlap.model import (
    OverlapPacket,
    OverlapReason,
    OverlapSource,
    _Model,
)
from ae_tactile.localization.overlap.search import (
    _noise_sat_fs,
    _quick_search_compiled,
    _search,
    _segments_compiled,
)


def _resolve_quick(x, on, plan, geo, pulse, noise_rms_v, saturated, full_scale_v, echo,
                   analysis_s, grid, decide_args) -> list:
    """`resolve_overlaps` with ``exhaustive=False`` by the compiled kernels: per window one
    call to prepare it (`overlap_kernels.prepare_window`, the equations of
    `common.prepare` and `common.adc_noise`), one to cut its segment and one for the whole
    quick search; then the same decisions (`_answers`)."""
    K, _, m = x.shape
    noise, sat, fsv = _noise_sat_fs(noise_rms_v, saturated, full_scale_v, K)
    out: list = [None] * K
    ok, preps = [], []
    for k in range(K):
        pr = _kernels.prepare_window(
            x[k], int(on[k]), float(noise[k]), int(sat[k]), fsv, plan.pre, plan.seg_len,
            plan.flat_run,
        )
        flags, scale, s2 = int(pr[2]), pr[4], pr[5]
        if not (math.isfinite(s2) and s2 > 0):
            flags |= 1 << Reason.WINDOW
        if flags:
            noise_v = math.sqrt(float(np.nan_to_num(s2))) * scale
            out[k] = OverlapPacket(False, _first_reason(flags), noise_rms_v=noise_v)
        else:
            ok.append(k)
            preps.append(pr)
    if not ok:
        return out
    fs = plan.fs
    ys, masks, start, L = _segments_compiled(preps, m, plan, geo, analysis_s)
    sigma2 = np.array([pr[5] for pr in preps])
    if noise_rms_v is None:
        n_noise = np.maximum(4 * (np.array([pr[3] for pr in preps]) - plan.pre), 4)
        n_noise = n_noise.astype(float)
    else:
        n_noise = np.full(len(ok), np.inf)
    N = masks.sum(axis=1)
    search_limit = _search_limit(n_noise, N)
    model = _Model(geo, fs, start, L, pulse, echo)
    max_sources, add_threshold = decide_args[0], decide_args[1]
    deferred = np.zeros(len(ok), bool)
    fits = _quick_search_compiled(
        model, ys, masks, max_sources, grid, sigma2, add_threshold, search_limit, deferred
    )
    res = _answers(
        fits, deferred, N, sigma2, n_noise, *decide_args,
        np.array([pr[4] for pr in preps]), geo, model.tab.h_samples, fs,
        (ys * ys * masks).sum(axis=1), _misfit(pulse),
    )
    for k, r in zip(ok, res):
        out[k] = r
    return out


def _first_reason(flags: int) -> int:
    for r in Reason:
        if r != Reason.OK and flags & (1 << int(r)):
            return int(r)
    return int(OverlapReason.UNRESOLVED)


def _search_limit(n_noise, n_fit):
    """Residual per sample and sigma^2 above which another emission is searched: 1 + 2
    sqrt(2 / n_noise + 2 / n_fit) (two standard deviations of both variance estimates)."""
    return 1.0 + 2.0 * np.sqrt(2.0 / n_noise + 2.0 / n_fit)


def _chi2_limit(n_noise, dof, max_chi2_ratio):
    if max_chi2_ratio is not None:
        return np.full(np.shape(dof), max_chi2_ratio)
    return 1.0 + 5.0 * np.sqrt(2.0 / n_noise + 2.0 / dof)


def _decide(
    model,
    seg,
    sigma2,
    n_noise,
    max_sources,
    add_threshold,
    max_chi2_ratio,
    max_sigma_m,
    min_snr_db,
    scale,
    geo,
    grid,
    min_separation_s,
    exhaustive=True,
):
    K = seg.shape[0]
    deferred = None if exhaustive else np.zeros(K, bool)
    N = (
        model.mask.sum(axis=1)
        if model.mask is not None
        else np.full(K, seg.shape[1] * seg.shape[2])
    )
    search_limit = _search_limit(n_noise, N)
    fits = _search(
        model, seg, max_sources, grid, sigma2, add_threshold, search_limit, deferred
    )
    return _answers(
        fits, deferred, N, sigma2, n_noise, max_sources, add_threshold, max_chi2_ratio,
        max_sigma_m, min_snr_db, min_separation_s, scale, geo, model.tab.h_samples, model.fs,
        (seg * seg).reshape(K, -1).sum(axis=1), _misfit(model.pulse),
    )


def _answers(
    fits, deferred, N, sigma2, n_noise, max_sources, add_threshold, max_chi2_ratio,
    max_sigma_m, min_snr_db, min_separation_s, scale, geo, h_samples, fs, energy,
    misfit_share=0.0,
):
    """The `OverlapPacket` of each window from its fits (one per number of emissions):
    model order, residual test, separation, covariances, per-emission SNR and confidence.
    N (K,): samples in each window's fit; energy (K,): the window's energy on them;
    misfit_share: the pulse's own misfit on single touches (`PulseModel.misfit_share`)."""
    K = len(sigma2)
    J, refused = _model_order(fits, sigma2, max_sources, add_threshold, energy, misfit_share)
    out = []
    snr_len = int(round(30e-6 * fs))
    e_pulse = float((h_samples[:snr_len] ** 2).sum())  # the direct wave's energy in 30 us
    for i in range(K):
        if deferred is not None and deferred[i]:
            out.append(
                OverlapPacket(
                    False,
                    int(OverlapReason.DEFERRED),
                    noise_rms_v=float(np.sqrt(sigma2[i]) * scale[i]),
                )
            )
            continue
        f = fits[J[i] - 1]
        j = int(J[i])
        theta, amp, rss, gram = f.theta[i, :j], f.amp[i, : 2 * j], f.rss[i], f.gram[i]
        dof = max(N[i] - 5 * j, 1)
        ratio = rss / (sigma2[i] * dof)
        noise_v = float(np.sqrt(sigma2[i]) * scale[i])
        # the noise's chi^2 quantile plus the pulse's own misfit: the residual a right fit
        # of a learnt pulse leaves (the allowance `_model_order` grants a spurious emission)
        limit = float(_chi2_limit(n_noise[i], dof, max_chi2_ratio)) + _misfit_ratio(
            misfit_share, energy[i], sigma2[i], dof)
        times = theta[:, 2].tolist()
        too_close = j > 1 and min(b - a for a, b in zip(times, times[1:])) < min_separation_s
        if not math.isfinite(ratio) or ratio > limit or too_close:
            out.append(
                OverlapPacket(
                    False,
                    int(OverlapReason.UNRESOLVED),
                    n_fitted=j,
                    chi2_ratio=float(ratio),
                    noise_rms_v=noise_v,
                    n_refused=int(refused[i]),
                )
            )
            continue
        sources, dropped = _sources(theta, amp, gram, sigma2[i], float(scale[i]), ratio, limit,
                                    geo, max_sigma_m, min_snr_db, e_pulse, snr_len)
        out.append(
            OverlapPacket(
                bool(sources),
                0 if sources else int(OverlapReason.UNCERTAIN),  # UNCERTAIN: all dropped
                sources,
                n_fitted=j,
                n_dropped=dropped,
                chi2_ratio=float(ratio),
                noise_rms_v=noise_v,
                n_refused=int(refused[i]),
            )
        )
    return out


def _misfit(pulse) -> float:
    """[1] `PulseModel.misfit_share` of a pulse (0 for None, the nominal one)."""
    return 0.0 if pulse is None else float(getattr(pulse, "misfit_share", 0.0))


#: [1] how many times the pulse's misfit on single touches (`PulseModel.misfit_share`) of
#: the window's energy a further emission must explain. A j-emission fit leaves the misfit
#: of each of its emissions, their cross terms and the joint fit's own error, which a
#: spurious emission can absorb: up to ~16x a single touch's share on two overlapping
#: emissions of the lossy bodies. The allowance stays far under the weakest emission the
#: resolver is asked for (1:4, ~6 % of a pair's energy): >= 5x on every device whose
#: share is <= 2.2e-4; a weaker one is refused and counted, never a spurious point
MISFIT_ALLOWANCE = 50.0


def _model_order(fits, sigma2, max_sources, add_threshold, energy=None, misfit_share=0.0):
    """Emissions per window (K,) and the additions refused (K,): emission j+1 is added
    while the residual energy drops by more than ``add_threshold`` sigma^2, unless (refused,
    counted in ``n_refused``) the drop is within the learnt pulse's own misfit,
    MISFIT_ALLOWANCE x ``misfit_share`` x the window's energy (``energy`` (K,)); with no
    learnt misfit (the default pulse, whose misfit on the device is unknown), unless one
    emission of the larger fit carries more energy than the whole window: emissions
    cancelling each other, a fit absorbing the pulse's misfit. (Two real emissions of
    opposite polarity cancel too where their waves overlap: on a long-ringing front end
    such pairs lie at rho = -0.3 .. -0.6, their weaker one explaining ~20 % of the
    window, far above the learnt misfit: only the misfit decides there.)"""
    J = np.ones(len(sigma2), np.int64)
    refused = np.zeros(len(sigma2), np.int64)
    going = np.ones(len(sigma2), bool)
    for j in range(2, max_sources + 1):
        gain = (fits[j - 2].rss - fits[j - 1].rss) / sigma2
        step = going & (gain > add_threshold)
        if energy is not None:
            if misfit_share > 0:
                over = step & (gain * sigma2 <= MISFIT_ALLOWANCE * misfit_share * energy)
            else:
                over = step & (_source_energy(fits[j - 1], j).max(axis=1) > energy)
            refused += over
            step &= ~over
        J[step] = j
        going &= step
    return J, refused


def _misfit_ratio(misfit_share, energy, sigma2, dof) -> float:
    """[1] The pulse's misfit allowance, MISFIT_ALLOWANCE x ``misfit_share`` x the
    window's ``energy``, as a chi^2 ratio over ``dof`` samples of noise variance
    ``sigma2`` (0 for the nominal pulse)."""
    if misfit_share <= 0.0 or energy is None:
        return 0.0
    return MISFIT_ALLOWANCE * misfit_share * float(energy) / (float(sigma2) * dof)


def _source_energy(fit, j):
    """(K, j) energy of each emission's modelled waves alone (direct and echo: a^T G a
    over its block of the amplitude Gram matrix)."""
    a = fit.amp[:, : 2 * j].reshape(-1, j, 2)
    g = fit.gram[:, 3 * j :, 3 * j :]
    out = np.zeros(a.shape[:2])
    for q in range(j):
        b = g[:, 2 * q : 2 * q + 2, 2 * q : 2 * q + 2]
        out[:, q] = np.einsum("ki,kij,kj->k", a[:, q], b, a[:, q])
    return out


def _sources(theta, amp, gram, sigma2, scale, ratio, limit, geo, max_sigma_m, min_snr_db,
             e_pulse, snr_len):
    """(the `OverlapSource` of each fitted emission of one window, earliest first; how many
    were dropped for a 1-sigma above ``max_sigma_m`` or an SNR below ``min_snr_db``)."""
    R = geo.radius_m
    s2 = sigma2 * max(ratio, 1.0)
    fis = gram / s2
    try:
        cov = np.linalg.pinv(fis, rcond=1e-13, hermitian=True)
    except np.linalg.LinAlgError:
        cov = np.full(fis.shape, np.nan)
    d_all = geo._xy_distances(theta[:, 0], theta[:, 1])  # (j, 4)
    gain2 = ((R / d_all) ** 2).sum(axis=1)
    sources = []
    dropped = 0
    for q in range(len(theta)):
        c_xy = cov[3 * q : 3 * q + 2, 3 * q : 3 * q + 2]
        sx, sy, T = (float(v) for v in theta[q])
        vxx, vxy, vyx, vyy = c_xy.ravel().tolist()
        finite = all(math.isfinite(v) for v in (vxx, vxy, vyx, vyy))
        sig = math.sqrt(max(vxx + vyy, 0.0)) if finite else math.inf
        a_dir = float(amp[2 * q])
        # SNR of this emission alone: power of its direct wave over the 30 us window
        p_sig = a_dir**2 * float(gain2[q]) * e_pulse / (4.0 * snr_len)
        snr = 10.0 * math.log10(max(p_sig, 1e-300) / sigma2)
        if not (sig <= max_sigma_m) or snr < min_snr_db:
            dropped += 1
            continue
        sz = math.sqrt(max(R**2 - sx * sx - sy * sy, 0.0))
        c3 = surface_covariance(sx, sy, c_xy, R)
        c_snr = math.sqrt(min(max((snr - min_snr_db) / 20.0, 0.0), 1.0))
        c_pos = 1.0 / (1.0 + (sig / 0.5e-3) ** 2)
        c_fit = min(max(1.0 - max(ratio - 1.0, 0.0) / max(limit - 1.0, 1e-9), 0.0), 1.0)
        conf = min(max(c_snr * c_pos * c_fit, 0.0), 1.0)
        sources.append(
            OverlapSource(
                point_m=np.array([sx, sy, sz]),
                covariance_m2=c3,
                sigma_m=sig,
                confidence=conf,
                polarity=(a_dir > 0) - (a_dir < 0),
                amplitude_v=a_dir * scale,
                emission_time_s=T,
                arrival_times_s=T + d_all[q] / geo.sound_speed_m_s,
                snr_db=float(snr),
            )
        )
    return sources, dropped


def surface_covariance(sx, sy, c_xy, R) -> np.ndarray:
    """(3, 3) covariance [m^2] of the surface point (s_x, s_y, sqrt(R^2 - s_x^2 - s_y^2))
    [m] from that of (s_x, s_y) (``c_xy`` (2, 2)), by linear propagation."""
    sz = max(math.sqrt(max(R * R - sx * sx - sy * sy, 0.0)), 1e-6 * R)
    g = np.array([[1.0, 0.0], [0.0, 1.0], [-sx / sz, -sy / sz]])
    return g @ c_xy @ g.T


#: [1] quantile of the single touches' misfit shares kept as `PulseModel.misfit_share`
MISFIT_QUANTILE = 0.9


def _misfit_share(ratio, y, sigma2, inside) -> float:
    """[1] The pulse's misfit on single touches: per packet the residual energy beyond the
    noise's ((chi^2 ratio - 1) sigma^2 dof) over the packet's energy on the fitted
    samples, its MISFIT_QUANTILE quantile (0 without packets)."""
    if len(ratio) == 0:
        return 0.0
    dof = np.maximum(4 * inside.sum(axis=1) - 5, 1)
    energy = np.maximum((y * y).sum(axis=1), 1e-300)
    share = np.maximum(ratio - 1.0, 0.0) * dof * sigma2 / energy
    share = share[np.isfinite(share)]
    return float(np.quantile(share, MISFIT_QUANTILE)) if share.size else 0.0


def _trusted(ratio, limit, n, min_packets, min_inlier_share) -> bool:
    """Enough of the ``n`` candidates pass the residual test (chi^2 ``ratio`` <= ``limit``)
    for the pulse to be trusted: >= ``min_packets`` and >= ``min_inlier_share`` of them."""
    n_in = int(np.sum(ratio <= limit))
    return n_in >= min_packets and n_in >= min_inlier_share * n
