"""Onset refinement: multichannel Akaike-information-criterion (AIC) picker.

Maeda's AIC picker splits a segment x[0:L] at every m and scores

    AIC(m) = m log V1(m) + (L - m) log V2(m),
    V1(m)  = sum_k w_k var(x_k[0:m]),   V2(m) = sum_k w_k var(x_k[m:L])

(variances with their own mean removed, so DC offsets do not matter; w_k = 1 / noise
variance of channel k, so every channel counts by its SNR). The onset is the m with the
smallest AIC: the first sample of the high-variance part. Pooling the variances over
the channels (rather than adding per-channel AICs) makes the pick follow the *earliest*
channel: as soon as one channel's packet enters the first part, V1 grows by that
channel's signal power, which at useful SNR dwarfs the noise.

Accuracy: about half a sample at useful SNR (see docs/detection.md); use it to place
windows and gates, not as a delay estimate.
"""
from __future__ import annotations

import numpy as np


def aic_pick(segments: np.ndarray, weights: np.ndarray | None = None, margin: int = 2
             ) -> tuple[np.ndarray, np.ndarray]:
    """Onset index m in [margin, L - margin] for each segment, and its AIC curve.

    segments: (K, C, L) float; weights: (K, C) non-negative (None: all ones).
    Returns (onset (K,) int64, aic (K, L - 1) float64 for m = 1 .. L - 1, +inf outside
    the allowed range). Constant segments give a finite curve (variances are floored);
    the pick is then the first allowed m.
    """
    x = np.asarray(segments, dtype=np.float64)
    if x.ndim != 3:
        raise ValueError(f"segments must have shape (K, C, L), got {x.shape}")
    k, c, length = x.shape
    if length < 2 * margin + 1 or margin < 1:
        raise ValueError(f"segments of {length} samples are too short for margin {margin}")
    if weights is None:
        w = np.ones((k, c))
    else:
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (k, c):
            raise ValueError(f"weights must have shape {(k, c)}, got {w.shape}")
    if k == 0:
        return np.zeros(0, np.int64), np.zeros((0, length - 1))
    # pooled variances of sqrt(w_k) x_k: V = sum_k w_k var(x_k); x - x[0] limits
    # cancellation in the running sums when the segment has a DC offset
    x = (x - x[..., :1]) * np.sqrt(np.maximum(w, 0.0))[..., None]
    s1 = np.cumsum(x, axis=-1)                          # (K, C, L) per channel
    s2 = np.cumsum(_channel_sum(x * x), axis=-1)        # (K, L) pooled
    m = _M_CACHE.get(length)
    if m is None:
        m = np.arange(1, length, dtype=np.float64)
        _M_CACHE[length] = m
    n2 = length - m
    a1 = s1[..., :-1] / m
    a2 = (s1[..., -1:] - s1[..., :-1]) / n2
    v1 = s2[:, :-1] / m - _channel_sum(a1 * a1)
    v2 = (s2[:, -1:] - s2[:, :-1]) / n2 - _channel_sum(a2 * a2)
    total = s2[:, -1] / length - _channel_sum((s1[..., -1] / length) ** 2)
    floor = (1e-12 * np.maximum(total, 0.0) + 1e-300)[:, None]
    aic = m * np.log(np.maximum(v1, 0.0) + floor) + n2 * np.log(np.maximum(v2, 0.0) + floor)
    aic[:, :margin - 1] = np.inf
    aic[:, length - margin:] = np.inf
    onset = np.argmin(aic, axis=-1).astype(np.int64) + 1
    return onset, aic


_M_CACHE: dict[int, np.ndarray] = {}


def _channel_sum(v: np.ndarray) -> np.ndarray:
    """sum over axis 1 accumulated in channel order (bit-reproducible for any K)."""
    out = v[:, 0]
    for ch in range(1, v.shape[1]):
        out = out + v[:, ch]
    return out
