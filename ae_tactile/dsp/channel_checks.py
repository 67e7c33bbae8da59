# SPDX-License-Identifier: Apache-2.0
"""Per-packet checks on the raw samples that need no model of the device: four identical
channels, and clipping (flat tops at a rail).

Identical channels. Four sensors and four amplifiers always add their own, independent
noise: after any common waveform, the difference of two channels carries at least the
noise of both (2 sigma^2 per sample). Four channels that differ by much less than that
are one signal copied onto four inputs (a wiring or firmware fault, a replayed or
synthetic packet, common-mode interference with no channel noise), never four sensors'
view of one emission, which places it at the pole. The noise is the packet's own: the
variance of the first half of the samples before the onset (mean removed; the half
furthest from the onset, where a packet's own leading edge, a filter's precursor or an
arrival before the detector's onset, has least energy), else the caller's noise sigma,
floored by the ADC's quantization (LSB^2 / 12, the LSB the smallest step between two
consecutive samples, where every sample is a multiple of it): identical when the mean over
the six channel pairs of sum_n (x_c - x_d)^2, each channel less its mean (an ADC's offset is
no signal), is below IDENTICAL_MAX_SHARE of 2 sigma^2 M (M samples). Without any noise seen
(noise-free, unquantized samples, no pretrigger, or only float rounding: below FLOAT_NOISE
of the packet's extent), nothing tells a copied signal from a noise-free touch at the pole:
not identical.

Clipping. An ADC (or an amplifier before it) that saturates holds its rail: a run of
equal samples at the channel's extreme value. A channel is clipped when its dominant
extreme (the larger excursion from its mean) is held for at least
``max(CLIP_MIN_RUN, CLIP_MIN_RUN_S fs)`` consecutive samples and lies at least
CLIP_MIN_LSB quantization steps from the mean (a smooth peak a few LSB high can hold
one value for a while without clipping). The rail itself need not be known: +/- full
scale, an amplifier's lower rail, or an offset ADC's all look the same.
"""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.jit import NUMBA_AVAILABLE, njit

#: channel differences below this share of what independent noise gives: identical [1]
#: (an estimate of the noise from >= 8 pretrigger samples errs by a factor of 2 at most
#: at 5 sigma of its chi^2; real channels give 1 or more)
IDENTICAL_MAX_SHARE = 0.1
#: samples within this share of a step of a multiple of the smallest step between two
#: consecutive samples: the packet is quantized (ADC codes x LSB) [1]
QUANTIZED_TOL = 0.01
#: codes an ADC has at most (24 bits): a smaller smallest step is float resolution
MAX_ADC_LEVELS = 2.0**24
#: noise sigma below this share of the packet's largest |sample| is float rounding [1]
#: (a 24-bit ADC's LSB is 6e-8 of its full scale)
FLOAT_NOISE = 1e-9
#: pretrigger samples (onset - 2) from which the noise is measured on the packet (on
#: their first half)
IDENTICAL_MIN_PRETRIGGER = 8
#: a flat top holds its rail for at least this many samples, and this long [s] (a smooth peak
#: quantized below one LSB of noise holds one value for a sample or two)
CLIP_MIN_RUN = 4
CLIP_MIN_RUN_S = 0.3e-6
#: a clipped extreme lies at least this many quantization steps from the channel's mean
CLIP_MIN_LSB = 16.0


@njit(cache=True, nogil=True)
def _smallest_step(x, c0, c1, first_only):  # pragma: no cover - compiled
    """The smallest nonzero step between consecutive samples of channels c0..c1-1 (inf:
    none); ``first_only``: the first nonzero step found (an upper bound of the smallest)."""
    step = np.inf
    m = x.shape[1]
    for c in range(c0, c1):
        prev = float(x[c, 0])
        for i in range(1, m):
            v = float(x[c, i])
            d = abs(v - prev)
            if d > 0.0:
                if first_only:
                    return d
                if d < step:
                    step = d
            prev = v
    return step


@njit(cache=True, nogil=True)
def _sum_min_max(x, c):  # pragma: no cover - compiled
    """(sum, min, max) of channel c (the sum is not finite where a sample is not)."""
    total = 0.0
    lo = np.inf
    hi = -np.inf
    for i in range(x.shape[1]):
        v = float(x[c, i])
        total += v
        lo = min(lo, v)
        hi = max(hi, v)
    return total, lo, hi


@njit(cache=True, nogil=True)
def _identical_kernel(x, npre, nv_given, share):  # pragma: no cover - compiled
    """Identical-channel test of one packet ``x`` (4, M): see the module docstring."""
    m = x.shape[1]
    mean = np.zeros(4)
    lo = np.inf
    hi = -np.inf
    for c in range(4):
        total, c_lo, c_hi = _sum_min_max(x, c)
        if not math.isfinite(total):
            return False
        mean[c] = total / m
        lo = min(lo, c_lo)
        hi = max(hi, c_hi)
    dd = 0.0
    for i in range(m):
        a0 = float(x[0, i]) - mean[0]
        a1 = float(x[1, i]) - mean[1]
        a2 = float(x[2, i]) - mean[2]
        a3 = float(x[3, i]) - mean[3]
        dd += ((a0 - a1) ** 2 + (a0 - a2) ** 2 + (a0 - a3) ** 2 + (a1 - a2) ** 2
               + (a1 - a3) ** 2 + (a2 - a3) ** 2)
    dd /= 6.0
    if not hi > lo:
        return False
    nv = 0.0
    if npre >= IDENTICAL_MIN_PRETRIGGER:
        nh = npre // 2  # the first half: a packet's own leading edge is no noise
        for c in range(4):  # two passes: an offset must not leave its rounding as noise
            mu = 0.0
            for i in range(nh):
                mu += float(x[c, i])
            mu /= nh
            s2 = 0.0
            for i in range(nh):
                v = float(x[c, i]) - mu
                s2 += v * v
            nv += s2 / (nh - 1)
        nv /= 4.0
    elif nv_given > 0.0:
        nv = nv_given
    # noise below FLOAT_NOISE of the packet's extent is float rounding (an offset added to
    # noise-free samples), not a sensor's: no noise seen
    floor = FLOAT_NOISE * max(abs(hi), abs(lo))
    floor2 = floor * floor
    if nv > floor2 and dd <= share * 2.0 * nv * m:
        return True
    # the quantization floor q = step^2 / 12 is at most the first step's: most packets
    # differ by more than that allows, without a scan for the smallest step
    step = _smallest_step(x, 0, 4, True)
    if not (math.isfinite(step) and dd <= share * 2.0 * (step * step / 12.0) * m):
        return False
    step = _smallest_step(x, 0, 4, False)
    q = step * step / 12.0 if math.isfinite(step) else 0.0
    if not (q > nv and q > floor2 and dd <= share * 2.0 * q * m):
        return False
    # the ADC's step is a noise floor only where every sample is a multiple of it (codes x
    # LSB) and the packet spans at most an ADC's 2^24 of them
    if (hi - lo) > MAX_ADC_LEVELS * step:
        return False
    for c in range(4):
        x0 = float(x[c, 0])
        for i in range(m):
            r = (float(x[c, i]) - x0) / step  # (an offset is no step)
            if abs(r - np.floor(r + 0.5)) > QUANTIZED_TOL:
                return False
    return True


def identical_channels(windows, onset_index=None, noise_rms_v=None, *,
                       max_share: float = IDENTICAL_MAX_SHARE) -> np.ndarray:
    """Which packets carry one waveform on all four channels, equal beyond what the
    channels' independent noise allows (the physics: the module docstring).

    Parameters
    ----------
    windows : array_like, (K, 4, M) or (4, M)
        Packet windows [V].
    onset_index : int or array_like of int (K,), optional
        Onset sample of each packet; the noise is measured on the samples before
        onset - 2 when there are >= IDENTICAL_MIN_PRETRIGGER. None: no pretrigger.
    noise_rms_v : float or array_like (K,), optional
        Per-channel noise sigma [V] used when the pretrigger is too short (NaN, 0 or None:
        unknown).
    max_share : float
        Channel differences below this share of the independent noise's 2 sigma^2 per
        sample are identical [1].

    Returns
    -------
    numpy.ndarray
        (K,) bool (a scalar-shaped (1,) for one (4, M) window): True where the four
        channels are one signal. Non-finite or all-zero windows and onsets outside the
        window are False (other checks reject them).
    """
    x = np.asarray(windows)
    if x.ndim == 2:
        x = x[None]
    if x.ndim != 3 or x.shape[1] != 4:
        raise ValueError(f"windows must be (K, 4, M) or (4, M), got shape {x.shape}")
    k, _, m = x.shape
    on = (np.zeros(k, np.int64) if onset_index is None
          else np.broadcast_to(np.asarray(onset_index, np.int64).reshape(-1), (k,)))
    nr = (np.zeros(k) if noise_rms_v is None
          else np.broadcast_to(np.asarray(noise_rms_v, float).reshape(-1), (k,)))
    if not np.issubdtype(x.dtype, np.floating):
        x = x.astype(np.float64)
    out = np.zeros(k, bool)
    for i in range(k):
        out[i] = packet_identical(x[i], int(on[i]), float(nr[i]), max_share=max_share)
    return out


def packet_identical(samples_v, onset_index=None, noise_rms_v=None, *,
                     max_share: float = IDENTICAL_MAX_SHARE) -> bool:
    """`identical_channels` of one packet (4, M) (compiled where numba is: a few us).

    Parameters
    ----------
    samples_v : numpy.ndarray
        The window (4, M) [V].
    onset_index : int, optional
        Its onset sample (None: no pretrigger).
    noise_rms_v : float, optional
        Per-channel noise sigma [V] when the pretrigger is too short.
    max_share : float
        As in `identical_channels`.

    Returns
    -------
    bool
        True where the four channels are one signal.
    """
    x = samples_v
    if not (isinstance(x, np.ndarray) and x.dtype in (np.float32, np.float64)):
        x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] != 4 or x.shape[1] < 2:
        raise ValueError(f"samples_v must be (4, M) with M >= 2, got shape {x.shape}")
    npre = 0
    if onset_index is not None:
        if not 0 <= int(onset_index) < x.shape[1]:
            return False  # no onset in the window: nothing to judge (the localizer's WINDOW)
        npre = max(int(onset_index) - 2, 0)
    nv = 0.0
    if noise_rms_v is not None:
        nr = float(noise_rms_v)
        nv = nr * nr if math.isfinite(nr) and nr > 0 else 0.0
    if not NUMBA_AVAILABLE:
        x = np.ascontiguousarray(x, dtype=np.float64)
    return bool(_identical_kernel(x, npre, nv, float(max_share)))


@njit(cache=True, nogil=True)
def _clip_kernel(x, min_run, min_lsb):  # pragma: no cover - compiled
    """Flat-top test of one packet ``x`` (4, M): see the module docstring."""
    m = x.shape[1]
    for c in range(4):
        total, vmin, vmax = _sum_min_max(x, c)
        if not math.isfinite(total):
            return False
        if not vmax > vmin:
            continue
        mean = total / m
        v = vmax if vmax - mean >= mean - vmin else vmin
        run = 0
        longest = 0
        for i in range(m):
            run = run + 1 if float(x[c, i]) == v else 0
            longest = max(longest, run)
        # held long enough, and far enough from the mean in quantization steps (the
        # smallest step is looked for only then: few packets hold a value that long)
        if longest >= min_run and abs(v - mean) >= min_lsb * _smallest_step(x, c, c + 1, False):
            return True
    return False


def packet_clipped(samples_v, sample_rate_hz: float) -> bool:
    """Whether a packet (4, M) is clipped: a flat top at a rail on any channel (the rule:
    the module docstring), whatever the device's saturation flag says.

    Parameters
    ----------
    samples_v : numpy.ndarray
        The window (4, M) [V].
    sample_rate_hz : float
        Its sample rate [Hz] (the shortest flat top is CLIP_MIN_RUN_S long).

    Returns
    -------
    bool
        True when a channel holds its dominant extreme for the flat-top run.
    """
    x = samples_v
    if not (isinstance(x, np.ndarray) and x.dtype in (np.float32, np.float64)):
        x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] != 4:
        raise ValueError(f"samples_v must be (4, M), got shape {x.shape}")
    fs = float(sample_rate_hz)
    run = max(CLIP_MIN_RUN, int(math.ceil(CLIP_MIN_RUN_S * fs))) if math.isfinite(fs) else 0
    if run < 1 or x.shape[1] < run:
        return False
    if not NUMBA_AVAILABLE:
        x = np.ascontiguousarray(x, dtype=np.float64)
    return bool(_clip_kernel(x, run, CLIP_MIN_LSB))


@njit(cache=True, nogil=True)
def _checks_kernel(x, npre, nv, share, run, min_lsb):  # pragma: no cover - compiled
    """`_identical_kernel`, then (run >= 1: the device did not flag saturation)
    `_clip_kernel` of one packet: 1 identical, 2 clipped, 0 neither."""
    if _identical_kernel(x, npre, nv, share):
        return 1
    if run >= 1 and x.shape[1] >= run and _clip_kernel(x, run, min_lsb):
        return 2
    return 0


#: `packet_checks`' answers
CHECK_PASSED, CHECK_IDENTICAL, CHECK_CLIPPED = 0, 1, 2


def packet_checks(samples_v, onset_index, noise_rms_v, sample_rate_hz, flagged: bool) -> int:
    """`packet_identical` and, unless the device flagged saturation, `packet_clipped` of
    one packet in one compiled call (the pipeline's per-packet check: one pass of the
    dispatcher instead of two).

    Parameters
    ----------
    samples_v : numpy.ndarray
        The window (4, M), M >= 2 [V].
    onset_index : int
        Its onset sample.
    noise_rms_v : float or None
        Per-channel noise sigma [V] when the pretrigger is too short.
    sample_rate_hz : float
        Its sample rate [Hz].
    flagged : bool
        The device's saturation flag (True: no clipping test).

    Returns
    -------
    int
        CHECK_IDENTICAL, CHECK_CLIPPED or CHECK_PASSED: what `packet_identical` then
        `packet_clipped` answer.
    """
    if not NUMBA_AVAILABLE:
        if packet_identical(samples_v, onset_index, noise_rms_v):
            return CHECK_IDENTICAL
        if not flagged and packet_clipped(samples_v, sample_rate_hz):
            return CHECK_CLIPPED
        return CHECK_PASSED
    x = samples_v
    if not (isinstance(x, np.ndarray) and x.dtype in (np.float32, np.float64)):
        x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] != 4 or x.shape[1] < 2:
        raise ValueError(f"samples_v must be (4, M) with M >= 2, got shape {x.shape}")
    on = int(onset_index)
    if not 0 <= on < x.shape[1]:  # no onset in the window: not identical (packet_identical)
        return CHECK_CLIPPED if not flagged and packet_clipped(x, sample_rate_hz) else CHECK_PASSED
    nv = 0.0
    if noise_rms_v is not None:
        nr = float(noise_rms_v)
        nv = nr * nr if math.isfinite(nr) and nr > 0 else 0.0
    run = 0
    fs = float(sample_rate_hz)
    if not flagged and math.isfinite(fs):
        run = max(CLIP_MIN_RUN, int(math.ceil(CLIP_MIN_RUN_S * fs)))
    return int(_checks_kernel(x, max(on - 2, 0), nv, IDENTICAL_MAX_SHARE, run, CLIP_MIN_LSB))
