# SPDX-License-Identifier: Apache-2.0
"""The analysis segments of a batch of windows: raw gather, baseline removal, flat-top
(saturation) runs, and `prepare`, which turns (K, 4, M) windows and their onsets into the
demeaned, band-limited segments, spectra, noise and SNR every estimator starts from
(`Prepared`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft
from numpy.lib.stride_tricks import sliding_window_view

from ae_tactile.localization.common import Plan, Reason, _positive, per_packet
from ae_tactile.localization.noise_model import pre_onset_autocov, whitening_gains


def raw_gather(x, start, length):
    """Raw samples x[k, c, start[k, c] : start[k, c] + length] (K, 4, length) and the count
    of samples inside the window (K, 4); positions outside the window hold the nearest
    edge sample (`demean` masks them)."""
    k, _, m = x.shape
    lo, hi = int(start.min(initial=0)), int(start.max(initial=0))
    full = np.full(start.shape, length)
    if lo == hi and 0 <= lo and lo + length <= m:
        return x[:, :, lo : lo + length], full
    if 0 <= lo and hi + length <= m:
        v = sliding_window_view(x, length, axis=2)
        return v[np.arange(k)[:, None], np.arange(4)[None, :], start], full
    idx = start[..., None] + np.arange(length)
    inside = (idx >= 0) & (idx < m)
    seg = np.take_along_axis(x, np.clip(idx, 0, m - 1), axis=2)
    return seg, inside.sum(axis=2)


def demean(raw, start, count, m, baseline=None):
    """Segments minus a per-channel baseline (K, 4) (default: their own mean); samples
    outside the window set to 0.

    The estimators subtract the pre-onset mean: it removes any DC offset exactly without
    subtracting the packet's own mean, which would add a rectangle that does not move
    with the delays (a bias at low sample rates)."""
    length = raw.shape[2]
    inside_all = bool(np.all(count == length))
    if baseline is None:
        if inside_all:
            return raw - raw.mean(axis=2, keepdims=True)
        idx = start[..., None] + np.arange(length)
        inside = (idx >= 0) & (idx < m)
        baseline = (raw * inside).sum(axis=2) / np.maximum(count, 1)
    seg = raw - baseline[..., None]
    if not inside_all:
        idx = start[..., None] + np.arange(length)
        seg *= (idx >= 0) & (idx < m)
    return seg


def gather(x, start, length, baseline=None):
    """Baseline-removed segments (K, 4, length) starting at start (K, 4), zero outside the
    window, and the count of samples inside it (K, 4)."""
    raw, count = raw_gather(x, start, length)
    return demean(raw, start, count, x.shape[2], baseline), count


@dataclass
class Prepared:
    """Sanitised input and what every estimator shares."""

    x: np.ndarray  # (K, 4, M) float64 (x - first sample) / scale; non-finite zeroed, gains divided
    onset: np.ndarray  # (K,) int64 (clipped into the window)
    flags: np.ndarray  # (K,) int64 reason bits so far
    sigma2: np.ndarray  # (K,) noise variance (V^2), NaN where unknown yet
    pre_mean: np.ndarray  # (K, 4) channel baselines (pre-onset mean or segment mean)
    seg_start: np.ndarray  # (K,) first sample of the coarse segment
    X: np.ndarray  # (K, 4, n_fft//2+1) coarse spectra (full rfft)
    seg_count: np.ndarray  # (K, 4) samples of the coarse segment inside the window
    p_signal: np.ndarray  # (K,) mean power over the SNR window (V^2), noise included
    quant2: np.ndarray  # (K,) q^2 / 12 of the apparent ADC quantum q, 0 if none
    scale: np.ndarray  # (K,) volts per unit of x (sigma2, p_signal, quant2 are in units^2)
    noise_given: np.ndarray = None  # (K,) bool: sigma2 from the caller's noise_rms_v
    noise_acov: np.ndarray = None  # (K, P + 1) pre-onset autocovariance (units^2), NaN: none


def subset(prep: Prepared, ids) -> Prepared:
    """The packets ``ids`` of a prepared batch."""
    return Prepared(
        **{
            f: (None if getattr(prep, f) is None else getattr(prep, f)[ids])
            for f in prep.__dataclass_fields__
        }
    )


def flat_top(seg_raw, run):
    """(K,) True where, in some channel, the dominant extreme (the larger deviation from the
    channel's mean) repeats ``run`` times in a row: the signature of a clipped ADC when
    neither the full scale nor an upstream flag is known. Per channel, so that channel DC
    offsets do not matter; only the dominant side, because the slow after-lobe of the
    high-passed pulse has a quantized flat bottom."""
    k = seg_raw.shape[0]
    if seg_raw.shape[2] < run:
        return np.zeros(k, bool)
    vmax = seg_raw.max(axis=2)
    vmin = seg_raw.min(axis=2)
    mean = seg_raw.mean(axis=2)
    v = np.where(vmax - mean >= mean - vmin, vmax, vmin)
    eq = seg_raw == v[:, :, None]
    r = eq[..., : eq.shape[2] - run + 1].copy()
    for i in range(1, run):
        r &= eq[..., i : eq.shape[2] - run + 1 + i]
    return (r.any(axis=2) & (vmax > vmin)).any(axis=1)


def _quantum2(raw):
    """(K,) q^2 / 12 of the ADC quantum q: the smallest non-zero step between successive raw
    samples (exact for quantized data, negligible otherwise). Below ~1 LSB of noise the
    pre-onset samples under-read the noise while the signal dithers the quantizer: the
    estimators use sigma^2 + q^2 / 12."""
    dif = np.abs(np.diff(raw, axis=2))
    dif[dif == 0] = np.inf
    dif = dif.min(axis=(1, 2))
    return np.where(np.isfinite(dif), dif * dif / 12.0, 0.0)


def _zero_nonfinite(x, flags) -> None:
    """Non-finite samples set to 0 in place; their packets flagged NONFINITE."""
    total = x.sum(axis=(1, 2))
    suspect = ~np.isfinite(total)
    if suspect.any():
        ids = np.nonzero(suspect)[0]
        sub = x[ids]
        fin = np.isfinite(sub)
        bad_sub = ~fin.all(axis=(1, 2))
        sub[~fin] = 0.0
        x[ids] = sub
        flags[ids[bad_sub]] |= 1 << Reason.NONFINITE


def _pre_onset_noise(x, n_pre):
    """(noise variance (K,) pooled over the 4 channels, NaN with fewer than 4 samples;
    pre-onset mean (K, 4)) of the samples [0, n_pre), relative to each channel's first
    sample (no cancellation under DC offsets)."""
    k = x.shape[0]
    p_max = int(n_pre.max(initial=0))
    x0 = x[:, :, :1]
    if p_max > 0:
        xp = x[:, :, :p_max] - x0
        if int(n_pre.min()) < p_max:
            xp *= (np.arange(p_max)[None, :] < n_pre[:, None])[:, None, :]
        n = np.maximum(n_pre, 1)[:, None]
        mu = xp.sum(axis=2) / n
        s2 = np.einsum("kcm,kcm->kc", xp, xp)
        var = np.maximum(s2 - n * mu * mu, 0.0) / np.maximum(n - 1, 1)
        sigma2 = var.mean(axis=1)
        pre_mean = x0[:, :, 0] + mu
    else:
        sigma2 = np.zeros(k)
        pre_mean = x0[:, :, 0].copy()
    return np.where(n_pre >= 4, sigma2, np.nan), pre_mean


def _given_noise(noise_rms_v, k, channel_gains, scale, sigma2):
    """(sigma^2 with the known noise [V] where given (scaled like the samples), given
    (K,) bool)."""
    nr = per_packet("noise_rms_v", noise_rms_v, k)
    ok = np.isfinite(nr) & (nr > 0)
    if channel_gains is not None:
        nr = nr / np.sqrt(np.mean(np.asarray(channel_gains, float) ** 2))
    nr = nr / scale
    return np.where(ok, nr * nr, sigma2), ok


def _snr_window_power(x, on, plan: Plan, pre_mean):
    """Mean power (K,) over the SNR window after the onset (what the window holds of it)."""
    k, _, m = x.shape
    w_len = min(plan.snr_len, m)
    s0 = np.minimum(on, m - w_len)
    lo, hi = int(s0.min()), int(s0.max())
    if lo == hi:
        sw = x[:, :, lo : lo + w_len]
    else:
        sw = sliding_window_view(x, w_len, axis=2)[
            np.arange(k)[:, None], np.arange(4)[None, :], np.repeat(s0[:, None], 4, axis=1)
        ]
    sw = sw - pre_mean[..., None]
    return np.einsum("kcm,kcm->k", sw, sw) / (4.0 * w_len)


def _upstream_saturation(x, start4, plan: Plan, full_scale_v, saturated):
    """(K,) bool: a coarse-segment sample at the clip level ``full_scale_v`` [V], or the
    upstream flag ``saturated``."""
    k = x.shape[0]
    sat = np.zeros(k, bool)
    if full_scale_v is not None:
        fsv = _positive("full_scale_v", full_scale_v)
        sat |= (np.abs(raw_gather(x, start4, plan.seg_len)[0]) >= fsv * (1.0 - 1e-3)).any(
            axis=(1, 2)
        )
    if saturated is not None:
        sat |= per_packet("saturated", saturated, k, dtype=bool)
    return sat


def _normalise(x, flags):
    """Per-packet scale (K,), applied in place: the estimators work on
    (x - x[:, :, :1]) / scale, scale the largest deviation from the first samples, so that
    every statistic is gain- and DC-invariant to rounding and nothing overflows; volts are
    restored on output. Packets with |x| ~ 1e308 (as unusable as inf) are zeroed and
    flagged NONFINITE."""
    x -= x[:, :, :1].copy()
    dev = np.abs(x).max(axis=(1, 2))
    huge = ~np.isfinite(dev)
    if huge.any():
        x[huge] = 0.0
        flags[huge] |= 1 << Reason.NONFINITE
    scale = np.where(np.isfinite(dev) & (dev > 0), dev, 1.0)
    x /= scale[:, None, None]
    return scale


def _whitened_spectra(seg, x, n_pre, pre_mean, plan: Plan):
    """(coarse spectra (K, 4, n_fft//2+1) with the band bins whitened by the noise's colour
    of the pre-onset samples (`noise_model`: for the band edge and the start), that colour's
    lag-windowed autocovariance (K, P + 1))."""
    X = sfft.rfft(seg, n=plan.n_fft, axis=2)
    acov = pre_onset_autocov(x, n_pre, pre_mean, plan.seg_len)
    X[..., plan.band] *= whitening_gains(acov, plan.w, plan.fs)[:, None, :]
    return X, acov


def prepare(
    x,
    onset,
    plan: Plan,
    *,
    noise_rms_v=None,
    saturated=None,
    full_scale_v=None,
    channel_gains=None,
    spectra: bool = True,
) -> Prepared:
    """Sanitise, flag and transform a batch (see the module docstring). ``spectra=False``
    leaves out what only the single-emission estimators use (``X``, ``p_signal``: None)."""
    k, _, m = x.shape
    flags = np.zeros(k, np.int64)
    _zero_nonfinite(x, flags)
    outside = (onset < 0) | (onset >= m)
    on = np.clip(onset, 0, m - 1)
    # Too little of the packet inside the window: fewer than a quarter of the
    # echo-free samples after the onset.
    short = (m - on) < max(4, (plan.seg_len - plan.pre) // 4)
    flags[outside | short] |= 1 << Reason.WINDOW
    seg_start = on - plan.pre
    start4 = np.repeat(seg_start[:, None], 4, axis=1)
    sat = _upstream_saturation(x, start4, plan, full_scale_v, saturated)
    if channel_gains is not None:
        g = np.asarray(channel_gains, dtype=float)
        if g.shape != (4,) or not np.all(np.isfinite(g)) or np.any(g <= 0):
            raise ValueError(
                f"channel_gains must be 4 positive finite numbers, got {channel_gains!r}"
            )
        x /= g[None, :, None]
    scale = _normalise(x, flags)

    # Noise from the pre-onset samples [0, onset - pre), pooled over the 4 channels
    # (relative to each channel's first sample: no cancellation under DC offsets).
    n_pre = np.clip(seg_start, 0, m)
    sigma2, pre_mean = _pre_onset_noise(x, n_pre)
    given = np.zeros(k, bool)
    if noise_rms_v is not None:
        sigma2, given = _given_noise(noise_rms_v, k, channel_gains, scale, sigma2)

    # Coarse segment (common start), raw for saturation checks, baseline-removed for spectra.
    raw, count = raw_gather(x, start4, plan.seg_len)
    const = (raw.max(axis=2) == raw.min(axis=2)).any(axis=1)
    flags[const] |= 1 << Reason.NO_SIGNAL
    if saturated is None and full_scale_v is None:
        # Only without upstream knowledge: a weak, slow pulse quantized to a few LSB also
        # shows a flat top, so the heuristic must not overrule a driver's saturation flags.
        sat |= flat_top(raw, plan.flat_run)
    flags[sat] |= 1 << Reason.SATURATED
    no_pre = n_pre < 4
    if no_pre.any():
        pre_mean = np.where(no_pre[:, None], raw.mean(axis=2), pre_mean)
    if not spectra:
        return Prepared(
            x=x, onset=on, flags=flags, sigma2=sigma2, pre_mean=pre_mean, seg_start=seg_start,
            X=None, seg_count=count, p_signal=None, quant2=_quantum2(raw), scale=scale,
            noise_given=given,
        )
    seg = demean(raw, start4, count, m, pre_mean)

    p_total = _snr_window_power(x, on, plan, pre_mean)

    X, acov = _whitened_spectra(seg, x, n_pre, pre_mean, plan)
    return Prepared(
        x=x,
        onset=on,
        flags=flags,
        sigma2=sigma2,
        pre_mean=pre_mean,
        seg_start=seg_start,
        X=X,
        seg_count=count,
        p_signal=p_total,
        quant2=_quantum2(raw),
        scale=scale,
        noise_given=given,
        noise_acov=acov,
    )
