# SPDX-License-Identifier: Apache-2.0
"""The interference screen's model of an acoustic packet, from the front end: templates
(the front end's step response, or the pulses of a stated or calibrated `PulseModel`,
at sub-sample offsets and lags) and the spectrum limits a stated front end's pulses need.
`ae_tactile.dsp.interference` judges packets with them."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from scipy import signal

from ae_tactile.dsp.acoustic_model import spectrum_stats
from ae_tactile.geometry import resolve_front_end_lowpass

#: [1] the spectrum tests' limits over a stated front end's largest statistics (its pulses
#: span the corners' tolerance and the emission decays): room for the noise's scatter of
#: the statistics (apex touches at 20 dB kept on every zoo device with a stated front end)
PULSE_MARGIN = 1.2


def acoustic_templates(
    sample_rate_hz: float,
    n_samples: int,
    highpass_hz: float = 100e3,
    highpass_order: int = 2,
    lowpass_hz: float | None = None,
    lowpass_order: int = 4,
    n_offsets: int = 4,
    pulse=None,
) -> np.ndarray:
    """Unit-norm templates (n_offsets, n_samples) of an acoustic packet: the front end's
    response to a pressure step (a touch's Eq. 9 pulse is a step in the band, emission.py),
    the step at sub-sample offsets j / n_offsets before the first sample... + 1 sample.
    ``pulse`` (a `PulseModel`: a front end stated or calibrated for the device, its
    emission's decay included) in place of the Butterworth front end given by the other
    arguments: its pulse at those instants.

    The analysis length changes from packet to packet (it stops at the window's end), so
    the responses are computed once for a length rounded up to a power of two (>= 256)
    and cut: a new length costs a slice, not a new simulation (~15 ms)."""
    n_cap = max(256, 1 << (int(n_samples) - 1).bit_length())
    if pulse is not None:
        y = _pulse_responses(float(sample_rate_hz), n_cap, pulse, n_offsets)
    else:
        y = _step_responses(float(sample_rate_hz), n_cap, highpass_hz, highpass_order,
                            lowpass_hz, lowpass_order, n_offsets)
    y = y[:, : int(n_samples)]
    return y / np.maximum(np.linalg.norm(y, axis=1, keepdims=True), 1e-300)


def _pulses(front_end) -> tuple | None:
    """The `PulseModel`s of ``front_end`` (one, or a tuple of them: a family, e.g. the
    stated front end over the emission decays); None for the Butterworth tuple."""
    if not isinstance(front_end, tuple):
        return (front_end,)
    if front_end and hasattr(front_end[0], "waveform"):
        return front_end
    return None


def _front_end_templates(sample_rate_hz, n_samples, front_end) -> np.ndarray:
    """`acoustic_templates` of ``front_end``: `PulseModel`s (`_pulses`: the templates of
    each, stacked), or the Butterworth tuple (high-pass Hz, order, low-pass Hz or None,
    order)."""
    pulses = _pulses(front_end)
    if pulses is not None:
        return _distinct(np.concatenate([acoustic_templates(sample_rate_hz, n_samples, pulse=p)
                                         for p in pulses]))
    hp, hp_order, lp, lp_order = front_end
    return acoustic_templates(sample_rate_hz, n_samples, float(hp), int(hp_order),
                              None if lp is None else float(lp), int(lp_order))


#: [1] a family's template this close to one kept (squared correlation) adds nothing: it
#: would explain at most 0.2 % more of a packet than the kept one, against the shape
#: test's 6 %
DISTINCT_MAX = 0.998


def _distinct(t: np.ndarray) -> np.ndarray:
    """The rows of unit-norm templates ``t`` (J, L) that differ from the ones kept before
    them (squared correlation below DISTINCT_MAX): a family's near copies cost time only."""
    keep = [0]
    for j in range(1, t.shape[0]):
        c = t[keep] @ t[j]
        if float(np.max(c * c)) < DISTINCT_MAX:
            keep.append(j)
    return t[keep]


@lru_cache(maxsize=32)
def _lag_templates(sample_rate_hz, n_samples, n_lags, front_end) -> np.ndarray:
    """The shape test's templates for a span of ``n_samples``, (n_lags * J, n_samples): for
    each lag l < n_lags the unit-norm templates of ``front_end`` (`_front_end_templates`)
    of length n_samples - l behind l zeros (computed once per span; one product
    correlates a packet with all of them)."""
    rows = []
    for lag in range(n_lags):
        t = _front_end_templates(sample_rate_hz, n_samples - lag, front_end)
        rows.append(np.pad(t, ((0, 0), (lag, 0))))
    out = np.concatenate(rows)
    out.setflags(write=False)
    return out


def _front_end_lowpass(sample_rate_hz, lowpass_hz, lowpass_order):
    """("auto" resolved as `ae_tactile.sim.SimConfig` does) low-pass of the front end."""
    hz, order = resolve_front_end_lowpass(sample_rate_hz, lowpass_hz, lowpass_order)
    return (None if hz is None else float(hz)), int(order)


@lru_cache(maxsize=16)
def _step_responses(
    sample_rate_hz, n_samples, highpass_hz, highpass_order, lowpass_hz, lowpass_order, n_offsets
) -> np.ndarray:
    """Front-end step responses (n_offsets, n_samples), not normalized (see above)."""
    z, p, k = signal.butter(
        highpass_order, 2 * math.pi * highpass_hz, "highpass", analog=True, output="zpk"
    )
    if lowpass_hz is not None:
        z2, p2, k2 = signal.butter(
            lowpass_order, 2 * math.pi * lowpass_hz, "lowpass", analog=True, output="zpk"
        )
        z, p, k = np.concatenate([z, z2]), np.concatenate([p, p2]), k * k2
    sys_ = signal.lti(z, p, k)
    fine = np.arange((n_samples + 2) * 8 * n_offsets) / (8 * n_offsets * sample_rate_hz)
    _, yf = signal.step(sys_, T=fine)
    out = np.zeros((n_offsets, n_samples))
    for j in range(n_offsets):
        t = (np.arange(n_samples) + 1.0 - j / n_offsets) / sample_rate_hz
        out[j] = np.interp(t, fine, yf)
    out.setflags(write=False)
    return out


@lru_cache(maxsize=16)
def _pulse_responses(sample_rate_hz, n_samples, pulse, n_offsets) -> np.ndarray:
    """``pulse``'s waveform (n_offsets, n_samples) at the instants of `_step_responses`."""
    j = np.arange(n_offsets)[:, None] / n_offsets
    out = pulse.waveform((np.arange(n_samples)[None, :] + 1.0 - j) / sample_rate_hz)
    out.setflags(write=False)
    return out


@lru_cache(maxsize=16)
def _pulse_limits(sample_rate_hz, n_samples, front_end, f_top_hz) -> tuple[float, float]:
    """The spectrum tests' limits [1] an acoustic packet of the ``front_end``'s pulses
    needs over an analysis length of ``n_samples``: PULSE_MARGIN x their largest low and
    high statistics (over the sub-sample offsets), as the device's own touches set them
    once learnt."""
    t = _front_end_templates(sample_rate_hz, n_samples, front_end)
    low, high = spectrum_stats(t, 0.0, f_top_hz, sample_rate_hz)
    return PULSE_MARGIN * float(low.max()), PULSE_MARGIN * float(high.max())
