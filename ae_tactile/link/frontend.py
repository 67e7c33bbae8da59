# SPDX-License-Identifier: Apache-2.0
"""Per-packet front end of the link: counts -> volts, pre-trigger noise and onset.

`window_noise_and_onset` is the numpy reference; `packet_volts_noise_onset` the compiled
form the link runs on every PACKET (one pass over the window, numpy where numba is
missing); the two agree up to the order of a sum (test_link_frontend).
"""

from __future__ import annotations

import math

import numpy as np

from ae_tactile.jit import NUMBA_AVAILABLE, njit


def window_noise_and_onset(volts: np.ndarray, pre_trigger: int) -> tuple[float, int]:
    """Noise RMS (V, DC removed) of the pre-trigger samples, and the onset index.

    The device triggered at sample ``pre_trigger``; the onset is the first sample at or
    after ``pre_trigger // 2`` whose largest |x - DC| over the 4 channels exceeds 4 noise
    sigma (``pre_trigger`` if none does or the pre-trigger part is too short):

        DC_c = mean(x_c[:P]),  sigma^2 = mean_c,n (x_c[n] - DC_c)^2 over n < P,
        onset = min { n >= P // 2 : max_c |x_c[n] - DC_c| > 4 sigma }.

    The numpy reference; `packet_volts_noise_onset` is the compiled form of the link.

    Parameters
    ----------
    volts : numpy.ndarray, shape (4, N)
        The window [V].
    pre_trigger : int
        Samples before the device's trigger (P above), clipped to [0, N - 1].

    Returns
    -------
    noise_rms_v : float
        Noise RMS of the pre-trigger samples, DC removed [V]; 0 when P < 4.
    onset : int
        Onset index in the window.
    """
    x = np.asarray(volts, dtype=np.float64)
    n = x.shape[1]
    pre_trigger = int(min(max(pre_trigger, 0), n - 1))
    if pre_trigger < 4:
        return 0.0, pre_trigger
    dc = x[:, :pre_trigger].mean(axis=1, keepdims=True)
    pre = x[:, :pre_trigger] - dc
    noise = float(np.sqrt(np.mean(pre * pre)))
    env = np.abs(x - dc).max(axis=0)
    start = pre_trigger // 2
    above = np.flatnonzero(env[start:] > 4.0 * noise)
    onset = int(start + above[0]) if above.size and noise > 0 else pre_trigger
    return noise, onset


@njit(cache=True, nogil=True)
def _volts_noise_onset_kernel(counts, v_per_count, pre_trigger, volts):  # pragma: no cover
    """Compiled `window_noise_and_onset` of counts * v_per_count (float32), in one pass
    over the window; writes the volts into ``volts``; returns (noise, onset)."""
    nch, n = counts.shape
    for c in range(nch):
        for i in range(n):
            volts[c, i] = np.float32(counts[c, i]) * v_per_count
    p = min(max(pre_trigger, 0), n - 1)
    if p < 4:
        return 0.0, p
    dc = np.empty(nch)
    ss = 0.0
    for c in range(nch):
        s = 0.0
        for i in range(p):
            s += np.float64(volts[c, i])
        dc[c] = s / p
        for i in range(p):
            d = np.float64(volts[c, i]) - dc[c]
            ss += d * d
    noise = math.sqrt(ss / (nch * p))
    if not noise > 0.0:
        return noise, p
    thr = 4.0 * noise
    for i in range(p // 2, n):
        for c in range(nch):
            if abs(np.float64(volts[c, i]) - dc[c]) > thr:
                return noise, i
    return noise, p


def packet_volts_noise_onset(
    counts: np.ndarray, v_per_count: float, pre_trigger: int
) -> tuple[np.ndarray, float, int]:
    """One PACKET's counts -> volts, noise RMS and onset index.

    volts = counts * float32(v_per_count); noise and onset as `window_noise_and_onset`.
    One compiled pass where numba is available (it runs on every packet, in the reader
    thread), the numpy reference otherwise; the two agree up to the order of a sum.

    Parameters
    ----------
    counts : numpy.ndarray, shape (4, N)
        ADC counts (int16 for the compiled pass).
    v_per_count : float
        Volts per ADC count [V].
    pre_trigger : int
        Samples before the device's trigger.

    Returns
    -------
    volts : numpy.ndarray, shape (4, N), float32
        The samples [V].
    noise_rms_v : float
        Noise RMS of the pre-trigger samples, DC removed [V].
    onset : int
        Onset index (see `window_noise_and_onset`).
    """
    vpc = np.float32(v_per_count)
    if NUMBA_AVAILABLE and counts.ndim == 2 and counts.dtype == np.int16:
        volts = np.empty(counts.shape, dtype=np.float32)
        noise, onset = _volts_noise_onset_kernel(counts, vpc, int(pre_trigger), volts)
        return volts, float(noise), int(onset)
    volts = (counts * vpc).astype(np.float32)
    noise, onset = window_noise_and_onset(volts, pre_trigger)
    return volts, noise, onset


def warm_up() -> None:
    """Compile (or load from numba's cache) the link's kernel for the arrays it meets:
    read-only counts (decoded from the wire) and writable ones."""
    counts = np.zeros((4, 16), dtype=np.int16)
    packet_volts_noise_onset(counts, 1e-3, 8)
    counts.flags.writeable = False
    packet_volts_noise_onset(counts, 1e-3, 8)
