# SPDX-License-Identifier: Apache-2.0
"""Per-window features (vectorized over windows): noise, saturation, peak, polarity, SNR.

Given windows w (K, 4, M) of original samples and an onset index per window:

    pre-onset part   t < onset - guard  (guard = noise_guard samples: the AIC pick can be
                     a sample or two late, and the packet must not leak into the noise)
    noise            mean_k and var_k over the pre-onset part (mean removed);
                     noise_rms = sqrt(mean_k var_k). With fewer than MIN_NOISE_SAMPLES
                     pre-onset samples the whole window's MAD is used instead
                     (1.4826 median |x - median|), which a packet inflates somewhat.
    d = w - mean     the window with each channel's pre-onset mean (DC) removed
    peak             max |d| over the channels and [onset, onset + peak_window)
    polarity         sign of the channel sum s = sum_k d_k at its largest |s| within
                     [onset, onset + polarity_window); 0 when that |s| is below
                     3 sqrt(sum_k var_k) (not distinguishable from noise)
    snr_db           10 log10(P / sigma^2), P = mean of d^2 over channels and
                     [onset, onset + snr_window) minus sigma^2 = mean_k var_k (floored
                     at 1e-3 sigma^2, i.e. -30 dB), the package's SNR definition
                     evaluated on the noisy window
    saturated        any sample <= low rail or >= high rail (per channel and any)
"""
from __future__ import annotations

import numpy as np

MIN_NOISE_SAMPLES = 8
#: 1 / (Phi^-1(3/4))^2: converts a squared MAD into a Gaussian variance.
MAD_TO_VAR = 1.4826 ** 2


def _masked_last_sum(a: np.ndarray, mask: np.ndarray) -> np.ndarray:
    return np.where(mask, a, 0.0).sum(axis=-1)


def _chan_sum(a: np.ndarray) -> np.ndarray:
    """Sum over axis 1 in channel order (bit-reproducible whatever the number of windows)."""
    out = a[:, 0]
    for ch in range(1, a.shape[1]):
        out = out + a[:, ch]
    return out


def window_features(w: np.ndarray, onset: np.ndarray, *, noise_guard: int, peak_window: int,
                    polarity_window: int, snr_window: int, sat_lo: float, sat_hi: float,
                    var_floor: float) -> dict:
    """Features of windows w (K, C, M) with onsets (K,); see the module docstring."""
    k, c, m = w.shape
    t = np.arange(m)
    onset = np.asarray(onset, dtype=np.int64)
    pre_end = np.clip(onset - noise_guard, 0, m)
    pre_mask = (t[None, :] < pre_end[:, None])[:, None, :]          # (K, 1, M)
    npre = pre_end.astype(np.float64)
    cnt = np.maximum(npre, 1.0)[:, None]
    mean = _masked_last_sum(w, pre_mask) / cnt                        # (K, C)
    d = w - mean[..., None]
    var = _masked_last_sum(d * d, pre_mask) / cnt
    few = pre_end < MIN_NOISE_SAMPLES
    if np.any(few):
        wf = w[few]
        med = np.median(wf, axis=-1)
        mad = np.median(np.abs(wf - med[..., None]), axis=-1)
        mean[few] = med
        var[few] = MAD_TO_VAR * mad * mad
        d = w - mean[..., None]
    var = np.maximum(var, var_floor)
    nvar = _chan_sum(var) / c                                         # (K,)

    after = t[None, :] >= onset[:, None]
    peak_mask = (after & (t[None, :] < onset[:, None] + peak_window))[:, None, :]
    peak = np.where(peak_mask, np.abs(d), 0.0).max(axis=(1, 2))

    s = _chan_sum(d)
    pol_mask = after & (t[None, :] < onset[:, None] + polarity_window)
    sa = np.where(pol_mask, np.abs(s), -1.0)
    j = np.argmax(sa, axis=-1)
    sj = s[np.arange(k), j]
    pol = np.where(np.abs(sj) > 3.0 * np.sqrt(_chan_sum(var)), np.sign(sj), 0.0)
    pol = np.where(pol_mask.any(axis=-1), pol, 0.0).astype(np.int8)

    snr_mask = (after & (t[None, :] < onset[:, None] + snr_window))[:, None, :]
    nsnr = c * np.maximum(snr_mask[:, 0].sum(axis=-1), 1).astype(np.float64)
    power = _chan_sum(np.where(snr_mask, d * d, 0.0).sum(axis=-1)) / nsnr

    sat_ch = np.any((w <= sat_lo) | (w >= sat_hi), axis=-1)
    return _features(nvar, var, sat_ch, peak, pol, power)


def _features(nvar, var, sat_ch, peak, pol, power) -> dict:
    """The per-window feature dict both variants return; SNR = (P - sigma^2) / sigma^2 in
    dB, the signal power floored at 1e-3 sigma^2."""
    p_sig = np.maximum(power - nvar, 1e-3 * nvar)
    return {
        "noise_rms_v": np.sqrt(nvar),
        "noise_rms_channel_v": np.sqrt(var),
        "saturated": sat_ch.any(axis=-1),
        "saturated_channels": sat_ch,
        "peak_amplitude_v": peak,
        "polarity": pol,
        "snr_db": 10.0 * np.log10(p_sig / nvar),
    }


def window_features_fixed(w: np.ndarray, onset: int, *, noise_guard: int, peak_window: int,
                          polarity_window: int, snr_window: int, sat_lo: float, sat_hi: float,
                          var_floor: float) -> dict:
    """`window_features` for windows that all have the same onset (stream windows):
    the same definitions with slices instead of masks (cheaper). Requires
    onset - noise_guard >= MIN_NOISE_SAMPLES."""
    k, c, m = w.shape
    pre_end = onset - noise_guard
    if pre_end < MIN_NOISE_SAMPLES:
        return window_features(w, np.full(k, onset, np.int64), noise_guard=noise_guard,
                               peak_window=peak_window, polarity_window=polarity_window,
                               snr_window=snr_window, sat_lo=sat_lo, sat_hi=sat_hi,
                               var_floor=var_floor)
    pre = w[:, :, :pre_end]
    mean = pre.sum(axis=-1) / pre_end
    dp = pre - mean[..., None]
    var = np.maximum((dp * dp).sum(axis=-1) / pre_end, var_floor)     # (K, C)
    nvar = _chan_sum(var) / c
    d = w[:, :, onset:] - mean[..., None]                              # after the onset
    peak = np.abs(d[:, :, :peak_window]).max(axis=(1, 2))
    s = _chan_sum(d[:, :, :polarity_window])
    j = np.argmax(np.abs(s), axis=-1)
    sj = s[np.arange(k), j]
    pol = np.where(np.abs(sj) > 3.0 * np.sqrt(_chan_sum(var)), np.sign(sj), 0.0).astype(np.int8)
    ds = d[:, :, :snr_window]
    power = _chan_sum((ds * ds).sum(axis=-1)) / (c * ds.shape[-1])
    sat_ch = (w.max(axis=-1) >= sat_hi) | (w.min(axis=-1) <= sat_lo)
    return _features(nvar, var, sat_ch, peak, pol, power)
