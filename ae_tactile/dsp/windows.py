# SPDX-License-Identifier: Apache-2.0
"""Analysis of windows the device already cut (PACKET frames): `analyze_window` fills the
same per-packet fields as `PacketDetector` does in STREAM mode (onset, noise, saturation,
peak, polarity, SNR), one window at a time, without a stream's state.
"""

from __future__ import annotations

import numpy as np
from scipy import signal

from ..geometry import N_CHANNELS
from .batch import PacketBatch
from .config import DetectorConfig
from .features import window_features
from .filters import design_bandpass_sos
from .onset import aic_pick

#: median of chi^2_1: median(y^2) = 0.4549 sigma^2 for Gaussian y.
_MEDIAN_CHI2_1 = 0.454936


def analyze_window(
    windows,
    sample_rate_hz: float | None = None,
    *,
    config: DetectorConfig | None = None,
    onset_hint=None,
    start_index=None,
) -> PacketBatch:
    """Onset, noise, saturation, peak, polarity and SNR of already-cut windows.

    For PACKET frames (windows cut by the device's trigger), as in STREAM mode. Per window:
    band-pass (state started at the first sample's steady state), noise sigma per channel
    from the median of y^2 (robust to the packet), the first crossing of threshold_sigma
    by the channel-RMS envelope (or ``onset_hint`` where >= 0; or the envelope maximum
    when nothing crosses), the AIC pick in [crossing - aic_pre, crossing + aic_post) and
    the features of ae_tactile/dsp/features.py. Windows with non-finite samples get
    valid=False and are analysed with those samples set to 0 (never NaN out).

    Parameters
    ----------
    windows : array_like, shape (K, 4, M) or (4, M)
        Samples [V], real numbers.
    sample_rate_hz : float, optional
        Sample rate [Hz]; overrides the config's (default 10 MHz without a config).
    config : DetectorConfig, optional
        Filter, threshold, AIC and feature settings.
    onset_hint : array_like of int, shape (K,), optional
        Onset sample index per window (e.g. the device's); negative: none.
    start_index : array_like of int, shape (K,), optional
        Absolute index of each window's first sample (default 0).

    Returns
    -------
    PacketBatch
        One packet per window (packet_id, hit_id -1; no overlap flags).

    Raises
    ------
    ValueError
        Wrong shapes or dtypes, windows too short for the AIC segment.
    """
    config = _window_config(config, sample_rate_hz)
    w = _as_windows(windows)
    k, _, m = w.shape
    sp = config.samples()
    length = sp.aic_pre + sp.aic_post
    if m < max(16, length):
        raise ValueError(f"windows of {m} samples are too short (need >= {max(16, length)})")
    w, valid = _zero_invalid(w, config.invalid_level_v)
    start, hint = _window_indices(k, start_index, onset_hint)
    if k == 0:
        return PacketBatch.empty(config.sample_rate_hz, m)
    onset, crossing, floor_var = _window_onsets(w, config, hint)
    feats = window_features(
        w,
        onset,
        noise_guard=sp.noise_guard,
        peak_window=sp.peak_window,
        polarity_window=sp.polarity_window,
        snr_window=sp.snr_window,
        sat_lo=config.saturation_levels_v[0],
        sat_hi=config.saturation_levels_v[1],
        var_floor=floor_var * 1e-2,
    )
    return PacketBatch(
        sample_rate_hz=float(config.sample_rate_hz),
        start_index=start,
        samples=w,
        onset_index=onset,
        trigger_index=crossing.astype(np.int64),
        overlap=np.zeros(k, bool),
        overlap_prev_id=np.full(k, -1, np.int64),
        overlap_next_id=np.full(k, -1, np.int64),
        clear_after=np.maximum(m - onset, 0).astype(np.int64),
        packet_id=np.full(k, -1, np.int64),
        hit_id=np.full(k, -1, np.int64),
        in_hit=np.zeros(k, bool),
        valid=valid,
        **feats,
    )


def _window_config(config: DetectorConfig | None, sample_rate_hz) -> DetectorConfig:
    """The config (default: `DetectorConfig` at 10 MHz) with ``sample_rate_hz`` [Hz] set."""
    if config is None:
        config = DetectorConfig(sample_rate_hz=10e6 if sample_rate_hz is None else sample_rate_hz)
    elif sample_rate_hz is not None and float(sample_rate_hz) != float(config.sample_rate_hz):
        config = config.replace(sample_rate_hz=sample_rate_hz)
    return config


def _zero_invalid(w: np.ndarray, lim: float):
    """float64 copy of w (K, 4, M) with NaN, inf and |x| > lim [V] set to 0; (copy, valid
    (K,) False where a window held such a sample)."""
    w = np.array(w, dtype=np.float64, copy=True)
    bad = ~(np.abs(w) <= lim)
    valid = ~bad.any(axis=(1, 2))
    w[bad] = 0.0
    return w, valid


def _as_windows(windows) -> np.ndarray:
    """``windows`` as an array (K, 4, M) of real numbers (a (4, M) window gets K = 1)."""
    try:
        w = np.asarray(windows)
    except Exception as exc:  # noqa: BLE001
        raise ValueError(f"windows must be an array of shape (K, 4, M): {exc}") from None
    if w.dtype == bool or w.dtype.kind not in "fiu":
        raise ValueError(f"windows must be real numbers, got dtype {w.dtype}")
    if w.ndim == 2:
        w = w[None]
    if w.ndim != 3 or w.shape[1] != N_CHANNELS:
        raise ValueError(f"windows must have shape (K, 4, M) or (4, M), got {np.shape(windows)}")
    return w


def _window_indices(k: int, start_index, onset_hint):
    """Checked (start indices (K,) int64, onset hints (K,) int64 or None)."""
    if start_index is None:
        start = np.zeros(k, np.int64)
    else:
        start = np.asarray(start_index, dtype=np.int64).reshape(-1)
        if start.shape != (k,):
            raise ValueError(f"start_index must have shape ({k},), got {np.shape(start_index)}")
    hint = None
    if onset_hint is not None:
        hint = np.asarray(onset_hint).reshape(-1)
        if hint.shape != (k,) or hint.dtype.kind not in "iu":
            raise ValueError(
                f"onset_hint must be {k} integers (negative: none), got {onset_hint!r}"
            )
        hint = hint.astype(np.int64)
    return start, hint


def _window_onsets(w: np.ndarray, config: DetectorConfig, hint):
    """Band-pass, noise, envelope crossing and AIC onset of windows w (K, 4, M) [V].

    Returns (onset index (K,), crossing index (K,), noise variance floor [V^2])."""
    k, _, m = w.shape
    sp = config.samples()
    length = sp.aic_pre + sp.aic_post
    sos = design_bandpass_sos(
        config.sample_rate_hz, config.highpass_hz, config.lowpass_hz, config.filter_order
    )
    zi = signal.sosfilt_zi(sos)[:, None, None, :] * w[None, :, :, 0, None]
    y, _ = signal.sosfilt(sos, w, axis=-1, zi=zi)
    floor_var = (0.1 * config.lsb_v) ** 2
    var = np.maximum(np.median(y * y, axis=-1) / _MEDIAN_CHI2_1, floor_var)  # (K, 4)
    e2 = y[:, 0] ** 2 * (0.25 / var[:, 0, None])
    for ch in range(1, N_CHANNELS):
        e2 = e2 + y[:, ch] ** 2 * (0.25 / var[:, ch, None])
    above = e2 >= float(config.threshold_sigma) ** 2
    crossing = np.where(above.any(axis=-1), np.argmax(above, axis=-1), np.argmax(e2, axis=-1))
    if hint is not None:
        crossing = np.where((hint >= 0) & (hint < m), hint, crossing)
    seg_start = np.clip(crossing - sp.aic_pre, 0, m - length)
    idx = seg_start[:, None] + np.arange(length)[None, :]
    seg = np.take_along_axis(w, np.broadcast_to(idx[:, None, :], (k, N_CHANNELS, length)), axis=-1)
    pick, _ = aic_pick(seg, 1.0 / var, margin=2)
    onset = (seg_start + pick).astype(np.int64)
    return onset, crossing, floor_var


__all__ = ["analyze_window"]
