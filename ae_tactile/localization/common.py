# SPDX-License-Identifier: Apache-2.0
"""Shared definitions of the delay estimators: channel contrasts and pairs, `Reason`,
validation, the analysis plan (`Plan`), ADC noise and the data-driven band edge; the
segments and spectra below are cut and computed in `segments`.

Every estimator works on the *well-ordered* part of each packet, the direct wave before
the first wall echo: per channel, from ``pre_onset_s`` before its arrival to
``geometry.echo_free_duration_s - echo_guard_s`` after it (derived from R, a and c, see
`FingertipGeometry.echo_free_duration_s`). The *coarse* segment is common to the four
channels and starts ``pre_onset_s`` before the packet onset (earliest arrival); the
*aligned* segments start at each channel's own (integer-sample) arrival, so that the
four windows hold the same part of the waveform.

Each segment has its channel's pre-onset mean (its segment mean when there are fewer
than 4 pre-onset samples) removed before any transform, which makes every estimate
invariant to a DC offset (and, because every statistic is a ratio, to a common gain).

Spectra are unnormalised DFTs of zero-padded segments: Y(f) = sum_n y[n] e^{-j w n/fs}.
White noise of variance sigma^2 over L samples gives E|N(f)|^2 = L sigma^2 per bin.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum
from functools import lru_cache

import numpy as np
import scipy.fft as sfft

from ae_tactile.geometry import CHANNEL_XI_ETA, FingertipGeometry

XI = CHANNEL_XI_ETA[:, 0].astype(float)
ETA = CHANNEL_XI_ETA[:, 1].astype(float)
#: Rows of t_k = T0 + ROW_k . (tau_x, tau_y, twist):
#: t_k = T0 - xi tau_x - eta tau_y + xi eta twist.
CHANNEL_ROWS = np.stack([-XI, -ETA, XI * ETA], axis=1)
#: Contrasts giving (tau_x, tau_y, twist) from arrival times (geometry.delays_from_arrival_times).
CONTRASTS = np.stack([-XI, -ETA, XI * ETA], axis=0) / 4.0
#: The 6 channel pairs (i, j) used by the pairwise estimators.
PAIRS = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)])
#: Pair design matrix: t_i - t_j = PAIR_DESIGN @ (tau_x, tau_y, twist).
PAIR_DESIGN = CHANNEL_ROWS[PAIRS[:, 0]] - CHANNEL_ROWS[PAIRS[:, 1]]
PAIR_PINV = np.linalg.pinv(PAIR_DESIGN)  # (3, 6)
#: Pair incidence (6, 4): +1 at i, -1 at j.
PAIR_INCIDENCE = np.zeros((6, 4))
PAIR_INCIDENCE[np.arange(6), PAIRS[:, 0]] = 1.0
PAIR_INCIDENCE[np.arange(6), PAIRS[:, 1]] = -1.0

#: Length of the SNR window after the onset (docs/conventions.md).
SNR_WINDOW_S = 30e-6


class Reason(IntEnum):
    """Why a packet was rejected (``LocalizationResult.reason``; 0 = accepted).

    When several apply, ``reason`` holds the first in this order and ``reason_flags``
    has bit ``1 << code`` set for each of them.
    """

    OK = 0
    NONFINITE = 1  # NaN or inf samples in the window
    NO_SIGNAL = 2  # a channel is constant over the analysis segment (all-zero, constant, dead)
    WINDOW = 3  # onset outside the window, or too little of the packet inside it
    SATURATED = 4  # clipped samples (flag from upstream, full scale, or a flat top)
    LOW_SNR = 5  # estimated SNR (conventions.md) below min_snr_db
    OVERLAP = 6  # the four channels are not shifted copies of one waveform
    OUT_OF_RANGE = 7  # delays beyond the sphere's horizon by more than the noise allows


REASON_DESCRIPTIONS = {
    Reason.OK: "accepted",
    Reason.NONFINITE: "NaN or inf samples in the window",
    Reason.NO_SIGNAL: "a channel is constant over the analysis segment "
    "(zero/constant window or dead channel)",
    Reason.WINDOW: "onset outside the window or too little of the packet inside it",
    Reason.SATURATED: "clipped (saturated) samples in the analysis segment",
    Reason.LOW_SNR: "estimated SNR below min_snr_db",
    Reason.OVERLAP: "the four channels are not shifted copies of one waveform "
    "(overlapping packets)",
    Reason.OUT_OF_RANGE: "delays imply a point beyond the horizon by more than the noise allows",
}


def primary_reason(flags: np.ndarray) -> np.ndarray:
    """First reason (in `Reason` order) whose bit is set in ``flags``; 0 when none."""
    flags = np.asarray(flags, dtype=np.int64)
    out = np.zeros(flags.shape, dtype=np.uint8)
    for r in reversed(list(Reason)[1:]):
        out = np.where(flags & (1 << int(r)), np.uint8(r), out)
    return out


def _positive(name, value):
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return v


# --------------------------------------------------------------------------- plan
@dataclass(frozen=True)
class Plan:
    """Sizes and frequency grids for one (fs, geometry, window length, band).

    pre        samples kept before each arrival
    seg_len    L, samples per (coarse or aligned) segment
    n_fft      coarse DFT length (>= L + largest pair lag: no circular wrap of lags)
    n_fft_al   aligned DFT length (L + a few samples of zero padding)
    band, band_al   boolean masks over the rfft bins of n_fft / n_fft_al
    w, w_al    angular frequencies of those band bins (rad/s)
    max_lag    (6,) largest |t_i - t_j| of each pair, in samples (+ 2 of margin)
    snr_len    samples of the SNR window (30 us)
    """

    fs: float
    geometry: FingertipGeometry
    n_samples: int
    band_hz: tuple
    pre: int
    seg_len: int
    n_fft: int
    n_fft_al: int
    band: np.ndarray
    band_al: np.ndarray
    w: np.ndarray
    w_al: np.ndarray
    w_full_al: np.ndarray
    max_lag: np.ndarray
    snr_len: int
    flat_run: int
    #: Data-driven upper band edge (`band_edge_hz`): 0 for a fixed band, else the edge (Hz)
    #: used when the noise is unknown; ``band`` then holds the candidate bins.
    auto_fallback_hz: float = 0.0


#: [s] a segment starts this long before its arrival (its noise is measured before it)
PRE_ONSET_S = 1e-6

#: Per-bin SNR (channel-summed power over its noise expectation, 3-bin mean) above which a
#: bin counts as signal for the data-driven band edge.
BAND_EDGE_POWER_RATIO = 2.0
#: Aliasing guard of the data-driven band: the spectrum at the candidate top (>= 0.4 fs)
#: within this many dB of its peak means folded content (`band_edge_hz`).
ALIAS_GUARD_DB = -25.0


@lru_cache(maxsize=64)
def _make_plan(
    fs, geometry, n_samples, lo, hi, pre_onset_s, echo_guard_s, auto_fallback_hz=0.0
) -> Plan:
    pre = max(2, int(math.ceil(pre_onset_s * fs)))
    n_ef = int(math.floor((geometry.echo_free_duration_s - echo_guard_s) * fs))
    n_ef = max(n_ef, 4)
    seg_len = pre + n_ef
    e = geometry.element_positions_m
    dist = np.linalg.norm(e[PAIRS[:, 0]] - e[PAIRS[:, 1]], axis=1)
    max_lag = np.ceil(dist / geometry.sound_speed_m_s * fs).astype(int) + 2
    n_fft = sfft.next_fast_len(seg_len + int(max_lag.max()) + 1, real=True)
    n_fft_al = sfft.next_fast_len(seg_len + 4, real=True)
    f = np.fft.rfftfreq(n_fft, 1.0 / fs)
    f_al = np.fft.rfftfreq(n_fft_al, 1.0 / fs)
    band = (f >= lo) & (f <= hi) & (f > 0)
    band_al = (f_al >= lo) & (f_al <= hi) & (f_al > 0)
    if band_al.sum() < 2 or band.sum() < 2:
        # Too few bins in the band at this window length: widen to the nearest bins.
        band = (f > 0) & (f >= min(lo, f[1])) & (f <= max(hi, f[min(3, len(f) - 1)]))
        band_al = (
            (f_al > 0)
            & (f_al >= min(lo, f_al[1]))
            & (f_al <= max(hi, f_al[min(3, len(f_al) - 1)]))
        )
    flat_run = max(4, int(math.ceil(0.3e-6 * fs)))
    return Plan(
        fs=fs,
        geometry=geometry,
        n_samples=n_samples,
        band_hz=(lo, hi),
        pre=pre,
        seg_len=seg_len,
        n_fft=n_fft,
        n_fft_al=n_fft_al,
        band=band,
        band_al=band_al,
        w=2 * np.pi * f[band],
        w_al=2 * np.pi * f_al[band_al],
        w_full_al=2 * np.pi * f_al,
        max_lag=max_lag,
        snr_len=int(round(SNR_WINDOW_S * fs)),
        flat_run=flat_run,
        auto_fallback_hz=float(auto_fallback_hz),
    )


def make_plan(
    sample_rate_hz,
    geometry,
    n_samples,
    band_hz,
    pre_onset_s=PRE_ONSET_S,
    echo_guard_s=0.3e-6,
    auto_fallback_hz=None,
) -> Plan:
    """Validated, cached `Plan`. ValueError on bad parameters.

    ``auto_fallback_hz``: choose each packet's upper band edge from its spectrum
    (`band_edge_hz`) within ``band_hz``; this edge applies when the noise is unknown."""
    fs = _positive("sample_rate_hz", sample_rate_hz)
    if not isinstance(geometry, FingertipGeometry):
        raise TypeError(f"geometry must be a FingertipGeometry, got {type(geometry).__name__}")
    try:
        lo, hi = (float(b) for b in band_hz)
    except (TypeError, ValueError):
        raise ValueError(f"band_hz must be a pair (lo, hi) in Hz, got {band_hz!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo < 0 or hi <= lo:
        raise ValueError(f"band_hz must satisfy 0 <= lo < hi, got {band_hz!r}")
    if lo >= fs / 2:
        raise ValueError(f"band_hz lower edge {lo} Hz is at or above Nyquist ({fs / 2} Hz)")
    hi = min(hi, fs / 2)
    pre_s = float(pre_onset_s)
    guard = float(echo_guard_s)
    if not (math.isfinite(pre_s) and pre_s >= 0):
        raise ValueError(f"pre_onset_s must be >= 0, got {pre_onset_s!r}")
    if not (math.isfinite(guard) and 0 <= guard < geometry.echo_free_duration_s):
        raise ValueError(
            f"echo_guard_s must lie in [0, {geometry.echo_free_duration_s}), got {echo_guard_s!r}"
        )
    auto = 0.0 if auto_fallback_hz is None else _positive("auto_fallback_hz", auto_fallback_hz)
    return _make_plan(fs, geometry, int(n_samples), lo, hi, pre_s, guard, auto)


def _quantized_noise_table(s_max=1.0, n=801):
    """(V, sigma^2) in units of q^2: the variance V of round(n / q) q for n ~ N(0, sigma^2)
    (a mid-tread quantizer, the baseline on a level), sigma = 0 ... s_max q:

        V(sigma) = q^2 sum_k k^2 [Phi((k + 1/2) q / sigma) - Phi((k - 1/2) q / sigma)].

    V is increasing; V -> sigma^2 + q^2/12 (Sheppard) from sigma ~ q/2 (within 1e-8 q^2 at
    s_max = 1)."""
    s = np.linspace(0.0, s_max, n)
    k = np.arange(-12, 13, dtype=float)[:, None]
    erf = np.vectorize(math.erf)
    with np.errstate(divide="ignore"):
        z = np.where(s > 0, 1.0 / (np.sqrt(2.0) * np.maximum(s, 1e-300)), np.inf)
    cdf = 0.5 * (1.0 + erf(np.clip((k + 0.5) * z, -40, 40)))
    cdf_lo = 0.5 * (1.0 + erf(np.clip((k - 0.5) * z, -40, 40)))
    v = (k * k * (cdf - cdf_lo)).sum(axis=0)
    keep = np.concatenate([[True], v[1:] > np.maximum.accumulate(v)[:-1] + 1e-15])
    return v[keep], (s * s)[keep]  # strictly increasing: V = 0 <-> sigma = 0


#: V (q^2) -> sigma^2 (q^2) of `_quantized_noise_table`, for `adc_noise`.
QUANT_V_Q2, QUANT_SIGMA2_Q2 = _quantized_noise_table()


def adc_noise(var, quant2, given):
    """Noise variance on the signal samples: sigma^2 + q^2/12, sigma the analog noise, q the
    apparent ADC quantum (``quant2`` = q^2/12; the rounding error of a signal that moves
    across levels is uniform, variance q^2/12). A given (analog) sigma^2 gets + q^2/12. A
    variance V measured on quiet, quantized pre-onset samples is inverted through the exact
    relation V(sigma) of a mid-tread quantizer with the baseline on a level
    (`_quantized_noise_table`): V + 0 when sigma >~ q/2 (Sheppard: V = sigma^2 + q^2/12),
    while below that the quiet samples sit on one level more often than the noise alone
    would say (at sigma = 0.27 q, 40 dB for the simulator's 12-bit ADC, V = 0.064 q^2
    against sigma^2 = 0.073 q^2; at 0.15 q, V = 0.001 q^2 against 0.023 q^2)."""
    quant2 = np.asarray(quant2, dtype=float)
    q2 = 12.0 * quant2
    ok = q2 > 0
    v = np.asarray(var, dtype=float) / np.where(ok, q2, 1.0)
    s2 = np.where(v <= QUANT_V_Q2[-1], np.interp(v, QUANT_V_Q2, QUANT_SIGMA2_Q2), v - 1.0 / 12.0)
    measured = np.where(ok, (s2 + 1.0 / 12.0) * q2, var)
    return np.where(given, var + quant2, measured)


def band_edge_hz(Xb, sigma2, count, plan: Plan):
    """Data-driven upper band edge (K,) in Hz from the coarse spectra's band bins Xb (K, 4, nb).

    Per bin the channel-summed power P(f) = sum_k |X_k(f)|^2 against its noise expectation
    4 L sigma^2 (L samples inside the window); the edge is the highest band bin whose 3-bin
    mean of P exceeds BAND_EDGE_POWER_RATIO times that (per-bin SNR ~ 1: beyond it a bin
    adds more noise-by-noise variance than timing information), at least the 4th band bin.
    Aliasing guard: when the candidate band reaches 0.4 fs and, at its top bin, the signal
    is still above the noise and within ALIAS_GUARD_DB of the spectrum's peak (it has not
    rolled off towards Nyquist: no steep anti-alias filter), the content above fs/2 folds
    into the band and does not shift like the rest between channels: the edge drops to
    fs/4.
    Unknown noise (NaN): ``plan.auto_fallback_hz``."""
    f = plan.w / (2 * np.pi)
    p = (Xb.real**2 + Xb.imag**2).sum(axis=1)  # (K, nb)
    nb = p.shape[1]
    sm = p.copy()
    sm[:, 1:] += p[:, :-1]
    sm[:, :-1] += p[:, 1:]
    div = np.full(nb, 3.0)
    div[0] -= 1.0
    div[-1] -= 1.0
    sm /= np.maximum(div, 1.0)
    n0 = 4.0 * count.mean(axis=1) * sigma2
    above = sm > BAND_EDGE_POWER_RATIO * n0[:, None]
    last = np.where(above.any(axis=1), nb - 1 - np.argmax(above[:, ::-1], axis=1), 0)
    last = np.maximum(last, min(3, nb - 1))
    edge = f[last]
    if f[-1] >= 0.4 * plan.fs:
        flat = sm[:, -1] > 10 ** (ALIAS_GUARD_DB / 10) * sm.max(axis=1)
        edge = np.where((last == nb - 1) & flat, np.minimum(edge, 0.25 * plan.fs), edge)
    return np.where(np.isfinite(sigma2), edge, plan.auto_fallback_hz)


# --------------------------------------------------------------------------- input
def validate_windows(windows, onset_index, copy=True):
    """(K, 4, M) float64 copy of the windows and (K,) int64 onsets; ValueError on bad shapes.
    ``copy=False``: float32 / float64 windows are passed through (C-contiguous, no copy
    when they already are; the compiled kernel copies each packet itself)."""
    x = np.asarray(windows)
    if x.dtype == object or not (
        np.issubdtype(x.dtype, np.floating) or np.issubdtype(x.dtype, np.integer)
    ):
        raise TypeError(f"windows must be a real numeric array, got dtype {x.dtype}")
    if x.ndim == 2 and x.shape[0] == 4:
        x = x[None]
    if x.ndim != 3 or x.shape[1] != 4:
        raise ValueError(f"windows must have shape (K, 4, M), got {np.shape(windows)}")
    if x.shape[2] < 4:
        raise ValueError(f"windows need at least 4 samples per channel, got {x.shape[2]}")
    if copy or x.dtype not in (np.float32, np.float64):
        x = np.array(x, dtype=np.float64, copy=True)
    else:
        x = np.ascontiguousarray(x)
    on = np.asarray(onset_index)
    if on.ndim == 0:
        on = np.full(x.shape[0], on)
    if on.shape != (x.shape[0],):
        raise ValueError(f"onset_index must have shape ({x.shape[0]},), got {on.shape}")
    if on.dtype == bool or not (
        np.issubdtype(on.dtype, np.integer) or np.issubdtype(on.dtype, np.floating)
    ):
        raise TypeError(f"onset_index must be integer sample indices, got dtype {on.dtype}")
    if np.issubdtype(on.dtype, np.floating):
        if not np.all(np.isfinite(on)) or np.any(on != np.round(on)):
            raise ValueError("onset_index must hold integer sample indices")
    return x, on.astype(np.int64)


def per_packet(name, value, k, *, dtype=float):
    """Scalar or (K,) parameter -> (K,) array."""
    v = np.asarray(value, dtype=dtype)
    if v.ndim == 0:
        v = np.full(k, v, dtype=dtype)
    if v.shape != (k,):
        raise ValueError(f"{name} must be a scalar or have shape ({k},), got {v.shape}")
    return v
