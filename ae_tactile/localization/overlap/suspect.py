# SPDX-License-Identifier: Apache-2.0
"""`suspect_overlap`: the cheap test of the windows `localize` accepted as single emissions.
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft

from ae_tactile.geometry import FingertipGeometry
from ae_tactile.localization import overlap_kernels as _kernels
from ae_tactile.localization.common import adc_noise, make_plan, validate_windows
from ae_tactile.localization.overlap.decide import _chi2_limit
from ae_tactile.localization.overlap.model import (
    _compiled_medium,
    _kernel_args,
    _lstsq_amplitudes,
    _Model,
    _model_values,
)
from ae_tactile.localization.overlap.pulse import PulseModel, _given
from ae_tactile.localization.overlap.search import _noise_sat_fs, _segments, _segments_compiled
from ae_tactile.localization.segments import prepare


def suspect_overlap(
    windows, sample_rate_hz, onset_index, single_source_result, *, geometry=None, pulse=None,
    noise_rms_v=None, band_hz=(100e3, 1e6), analysis_s=None, echo=True, max_chi2_ratio=None,
    engine="auto",
):
    """Packets that `localize` accepted as single-source but hold more than one emission.

    The one-emission fit (known pulse, first echo, started at the accepted point) of each
    accepted packet leaves a residual; a chi^2 per degree of freedom above the limit of
    `resolve_overlaps` marks the packet: hand those to `resolve_overlaps`. Rejected packets
    give False (they are not single-source answers to withdraw). Cost: a 1-D matched-filter
    search of the emission time and a linearised amplitude fit per accepted packet.

    Parameters
    ----------
    windows : array_like, (K, 4, M)
        The packets' windows [V].
    sample_rate_hz : float
        Sample rate [Hz].
    onset_index : array_like of int, (K,)
        Packet onset (earliest arrival) per window [samples].
    single_source_result : LocalizationResult
        `localize`'s answer for the same K windows (``accepted``, ``point_m``).
    geometry : FingertipGeometry, optional
        Sensor geometry and medium (default `FingertipGeometry()`).
    pulse : PulseModel, optional
        The front end's pulse (default `PulseModel.for_sample_rate(sample_rate_hz)`).
    noise_rms_v : float or array_like (K,), optional
        Known noise sigma [V]; default measured before the onset.
    band_hz : (float, float)
        Analysis band [Hz].
    analysis_s : float, optional
        Length of the fit window after the onset [s]; default up to just before the
        second wall echo.
    echo : bool
        Model the first wall echo.
    max_chi2_ratio : float, optional
        Largest accepted residual / (sigma^2 dof) (default 1 + 5 sqrt(2/n_noise + 2/dof),
        as in `resolve_overlaps`).
    engine : {"auto", "numpy"}
        "auto": one compiled call per packet (`overlap_kernels.suspect_rss`) where numba
        is present and the medium lossless; "numpy": always numpy.

    Returns
    -------
    numpy.ndarray of bool, (K,)
        True: the packet is suspected to hold overlapping emissions.
    """
    geo = FingertipGeometry() if geometry is None else geometry
    pulse = PulseModel.for_sample_rate(sample_rate_hz) if pulse is None else pulse
    x, on = validate_windows(windows, onset_index)
    x, noise_rms_v = pulse.correct_channels(x, sample_rate_hz, noise_rms_v, on)
    K = x.shape[0]
    acc = np.asarray(single_source_result.accepted, bool)
    pts = np.asarray(single_source_result.point_m, float)
    if acc.shape != (K,) or pts.shape != (K, 3):
        raise ValueError(f"single_source_result must hold {K} packets, got {acc.shape[0]}")
    if engine not in ("auto", "numpy"):
        raise ValueError(f"engine must be 'auto' or 'numpy', got {engine!r}")
    plan = make_plan(sample_rate_hz, geo, x.shape[2], band_hz)
    out = np.zeros(K, bool)
    ids = np.nonzero(acc)[0]
    if ids.size == 0:
        return out
    if engine == "auto" and _compiled_medium(pulse):
        with np.errstate(all="ignore"):
            out[ids] = _suspects_compiled(
                x[ids], on[ids], pts[ids, :2], plan, geo, pulse, noise_rms_v, K, ids,
                analysis_s, echo, max_chi2_ratio,
            )
        return out
    out[ids] = _suspects_numpy(
        x[ids], on[ids], pts[ids, :2], plan, geo, pulse, noise_rms_v, K, ids, analysis_s, echo,
        max_chi2_ratio,
    )
    return out


def _suspects_numpy(x, on, s_xy, plan, geo, pulse, noise_rms_v, K, ids, analysis_s, echo,
                    max_chi2_ratio):
    """`suspect_overlap` of accepted windows x (n, 4, M) at their points s_xy (n, 2) by numpy;
    (n,) bool."""
    with np.errstate(all="ignore"):
        prep = prepare(
            x,
            on,
            plan,
            noise_rms_v=None
            if noise_rms_v is None
            else np.broadcast_to(np.asarray(noise_rms_v, float), (K,))[ids],
            spectra=False,
        )
        seg, start, length, inside = _segments(prep, plan, geo, plan.fs, analysis_s)
        sigma2 = adc_noise(prep.sigma2, prep.quant2, _given(prep))
        model = _Model(geo, plan.fs, start, length, pulse, echo, inside)
        # emission time: matched filter along the accepted point's travel times
        th0 = _time_search(model, seg, s_xy)
        y = seg.reshape(len(ids), -1)
        # Linearised in the emission time: LS on [h, h'] of the direct wave and the echo at
        # (ml point, matched-filter time +- half a sample); the ml point is good to ~20 um,
        # whose residual is negligible against the noise.
        phi, parts = model.evaluate(th0[:, None, :])
        dh, gain = parts[1], parts[2]
        dcol = (gain[..., None] * dh).reshape(phi.shape)
        if model.mask is not None:
            dcol = dcol * model.mask[:, None, :]
        cols = np.concatenate([phi, dcol], axis=1)
        a2 = _lstsq_amplitudes(cols, y)
        res = y - _model_values(cols, a2)
        rss = np.einsum("kn,kn->k", res, res)
        dof = np.maximum(model.mask.sum(axis=1) - 5, 1)
        n_noise = np.maximum(4 * start, 4).astype(float)
        if noise_rms_v is not None:
            n_noise[:] = np.inf
        limit = _chi2_limit(n_noise, dof, max_chi2_ratio)
        ratio = rss / (sigma2 * dof)
        return ~(ratio <= limit)


def _suspects_compiled(x, on, s_xy, plan, geo, pulse, noise_rms_v, K, ids, analysis_s, echo,
                       max_chi2_ratio):
    """`suspect_overlap` of accepted windows x (n, 4, M) at their points s_xy (n, 2) by the
    compiled kernels (`overlap_kernels.prepare_window`, `segment`, `suspect_rss`)."""
    m = x.shape[2]
    noise = None if noise_rms_v is None else np.broadcast_to(
        np.asarray(noise_rms_v, float), (K,)
    )[ids]
    noise, _, _ = _noise_sat_fs(noise, None, None, len(x))
    preps = [
        _kernels.prepare_window(
            x[i], int(on[i]), float(noise[i]), -1, np.nan, plan.pre, plan.seg_len,
            plan.flat_run,
        )
        for i in range(len(x))
    ]
    ys, masks, start, L = _segments_compiled(preps, m, plan, geo, analysis_s)
    model = _Model(geo, plan.fs, start, L, pulse, echo)
    args = _kernel_args(model)
    rss = np.array(
        [
            _kernels.suspect_rss(
                ys[i], masks[i], float(start[i]), float(s_xy[i, 0]), float(s_xy[i, 1]),
                *args, model.tab.half_z, model.tab.half_res,
            )
            for i in range(len(x))
        ]
    )
    sigma2 = np.array([pr[5] for pr in preps])
    dof = np.maximum(masks.sum(axis=1) - 5, 1)
    n_noise = np.maximum(4 * start, 4).astype(float)
    if noise_rms_v is not None:
        n_noise[:] = np.inf
    limit = _chi2_limit(n_noise, dof, max_chi2_ratio)
    return ~(rss / (sigma2 * dof) <= limit)


def _time_search(model: _Model, seg, s_xy):
    """(s_x, s_y, T) (K, 3): the emission time maximising the channel-summed matched filter
    along the travel times of the given points (K, 2)."""
    K, _, L = seg.shape
    fs = model.fs
    h = model.tab.h_samples
    nfft = sfft.next_fast_len(2 * L, real=True)
    corr = sfft.irfft(
        sfft.rfft(seg, n=nfft, axis=2) * np.conj(sfft.rfft(h, n=nfft)), n=nfft, axis=2
    )[..., :L]
    d = model.geo._xy_distances(s_xy[:, 0], s_xy[:, 1])
    tt = d / model.c
    rel = np.rint((tt - tt.min(axis=1, keepdims=True)) * fs).astype(np.int64)
    idx = np.clip(rel[:, :, None] + np.arange(L), 0, L - 1)
    c = (np.take_along_axis(corr, idx, axis=2) * (model.R / d)[..., None]).sum(axis=1)
    m = np.argmax(c * c, axis=1)
    T = (model.start + m) / fs - tt.min(axis=1)
    return np.concatenate([s_xy, T[:, None]], axis=1)
