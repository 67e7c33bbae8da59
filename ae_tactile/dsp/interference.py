"""Common-mode electrical interference on packets (a motor driver's switching edges,
ground bounce, ESD spikes): reject it before the localizer, keep real touches.

Electrical interference reaches the four channels at once with one waveform (zero
delays, equal amplitudes), so the localizer puts it at the apex. A touch at or near the
apex also arrives with near-zero delays and nearly equal waveforms, so common mode alone
cannot tell them apart. What does: an acoustic packet has passed the fingertip and the
front end, its spectrum lies inside the front end's band (high-pass f_hp .. low-pass
f_lp); interference coupled after the filters (the ADC lines, the board's ground) keeps
its own spectrum: switching edges and spikes carry energy below f_hp (a step: a DC
offset over the window) and above f_lp (an edge or spike sharper than the anti-alias
filter allows). Per packet (all vectorized over K packets, M samples after the onset):

  s_n      = mean over the 4 channels (the common mode), x_cn the channels
  common   = |s|^2 / mean_c |x_c|^2 (noise power removed): 1 for identical channels
  low      = (mean_n s_n)^2 W / sum s_n^2: share of the window's energy at DC (< 1/W)
  high     = sum (s_{n+1} - s_n)^2 / (2 sum s_n^2 (1 - cos(2 pi f_lp / fs))):
             1 for a tone at f_lp, > 1 only with energy above the front end's band
  score    = common * max(low / low_max, high / high_max)

Interference when common >= ``common_min`` and score >= 1. Interference shaped by the
front end itself (coupled into the amplifier's input) has an acoustic packet's spectrum
and is not separable from an apex touch by one packet: docs/slip.md gives the measured
rates for both couplings.
"""
from __future__ import annotations

import math

import numpy as np

COMMON_MIN = 0.9
LOW_MAX = 0.25
HIGH_MAX = 1.5


def common_mode_interference(windows, sample_rate_hz: float, onset_index, *, geometry=None,
                             noise_rms_v=None, lowpass_hz: float = 1e6, highpass_hz: float = 100e3,
                             window_s: float = 20e-6, common_min: float = COMMON_MIN,
                             low_max: float = LOW_MAX, high_max: float = HIGH_MAX):
    """(mask (K,) bool: interference, score (K,) float) for packets ``windows`` (K, 4, M)
    volts at ``sample_rate_hz`` with onsets ``onset_index`` (K,) (window-relative samples).

    ``noise_rms_v``: per-channel noise sigma (scalar or (K,)), removed from the energies
    (None: not removed). ``lowpass_hz`` / ``highpass_hz``: the front end's band edges
    (SimConfig.lowpass_hz / highpass_hz); ``window_s``: analysis length after the onset;
    ``geometry`` is accepted for the pipeline's uniform call signature (unused).
    Non-finite windows give mask False and score NaN (the localizer rejects them)."""
    x = np.asarray(windows, dtype=float)
    if x.ndim != 3 or x.shape[1] != 4:
        raise ValueError(f"windows must be (K, 4, M), got shape {x.shape}")
    k, _, m = x.shape
    fs = float(sample_rate_hz)
    if not (math.isfinite(fs) and fs > 0):
        raise ValueError(f"sample_rate_hz must be positive, got {sample_rate_hz!r}")
    on = np.asarray(onset_index, dtype=np.int64).reshape(-1)
    if on.size == 1 and k != 1:
        on = np.full(k, int(on[0]))
    if on.shape != (k,):
        raise ValueError(f"onset_index must have one entry per packet ({k}), got {on.shape}")
    if k == 0:
        return np.zeros(0, bool), np.zeros(0)
    w = max(4, min(m, int(round(window_s * fs))))
    start = np.clip(on - 1, 0, max(0, m - w))
    idx = start[:, None] + np.arange(w)[None, :]
    seg = np.take_along_axis(x, np.broadcast_to(idx[:, None, :], (k, 4, w)), axis=2)
    s = seg.mean(axis=1)                                          # (K, W)
    nv = 0.0 if noise_rms_v is None else np.asarray(noise_rms_v, float).reshape(-1) ** 2
    e_ch = (seg * seg).sum(axis=2).mean(axis=1) - w * nv          # signal energy per channel
    e_s = (s * s).sum(axis=1) - w * nv / 4.0
    tiny = 1e-30
    common = np.clip(e_s / np.maximum(e_ch, tiny), 0.0, 1.0)
    mean = s.mean(axis=1)
    low = np.clip((mean * mean * w - nv / 4.0) / np.maximum(e_s, tiny), 0.0, None)
    d = np.diff(s, axis=1)
    band = 2.0 * (1.0 - math.cos(2.0 * math.pi * min(lowpass_hz, 0.5 * fs) / fs))
    e_d = (d * d).sum(axis=1) - (w - 1) * 2.0 * nv / 4.0
    high = np.clip(e_d / np.maximum(e_s * band, tiny), 0.0, None)
    score = common * np.maximum(low / low_max, high / high_max)
    score = np.where(e_s > 0, score, 0.0)
    finite = np.isfinite(x).all(axis=(1, 2))
    score = np.where(finite, score, np.nan)
    mask = finite & (common >= common_min) & (score >= 1.0)
    return mask, score
