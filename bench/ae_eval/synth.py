# SPDX-License-Identifier: Apache-2.0
"""Analytic test streams with known packets (independent of ae_tactile.sim).

A packet is the paper's collision pulse after the 100 kHz high-pass (Eq. 10-11 with
omega_0 >> alpha): the step response of a 2nd-order Butterworth high-pass,

    h(t) = e^{-a t} (cos(a t) - sin(a t)),  t >= 0,   a = 2 pi f_hp / sqrt(2),

a jump of 1 at the arrival, zero crossing after pi / (4 a) (1.77 us at 100 kHz), a
negative lobe of -0.21 and a decay time 1/a = 2.25 us. Channel k hears it at
t0 + delay_k; samples are the exact values of h at the sample instants, so the first
non-zero sample of channel k is ceil((t0 + delay_k) fs) and the packet's true onset is
the smallest of those. Optionally a wall echo (same pulse, ``echo_ratio`` times the
amplitude, ``echo_delay_s`` later) and a Gaussian tone burst shape for band-limited
tests. White Gaussian noise of ``noise_rms_v`` per channel (full band) and a DC offset
are added; ``full_scale_v`` clips like an ADC rail.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SynthEvent:
    """One emission: arrival time (s) at the array centre, amplitude (V), per-channel
    extra delays (s, 4), polarity via the sign of the amplitude."""

    time_s: float
    amplitude_v: float
    delays_s: tuple = (0.0, 0.0, 0.0, 0.0)

    def onset_index(self, sample_rate_hz: float) -> int:
        """First sample index i with i / fs - t_k >= 0 for some channel k (the first
        non-zero sample, evaluated exactly as `synth_stream` does)."""
        fs = float(sample_rate_hz)
        best = None
        for d in self.delays_s:
            t0 = self.time_s + d
            i = int(math.ceil(t0 * fs))
            while i / fs - t0 < 0:
                i += 1
            while (i - 1) / fs - t0 >= 0:
                i -= 1
            best = i if best is None else min(best, i)
        return best


def hp_step(t_s: np.ndarray, highpass_hz: float = 100e3) -> np.ndarray:
    """Step response of a 2nd-order Butterworth high-pass (0 for t < 0)."""
    a = 2.0 * math.pi * highpass_hz / math.sqrt(2.0)
    t = np.asarray(t_s, dtype=np.float64)
    tp = np.where(t >= 0, t, 0.0)
    return np.where(t >= 0, np.exp(-a * tp) * (np.cos(a * tp) - np.sin(a * tp)), 0.0)


def tone_burst(t_s: np.ndarray, freq_hz: float = 500e3, width_s: float = 1.5e-6) -> np.ndarray:
    """Gaussian-windowed sine centred 3 widths after t = 0 (its 'onset')."""
    t = np.asarray(t_s, dtype=np.float64) - 3.0 * width_s
    return np.exp(-0.5 * (t / width_s) ** 2) * np.sin(2.0 * math.pi * freq_hz * t)


def random_delays(rng: np.random.Generator, max_delay_s: float = 1.0e-6) -> tuple:
    """Per-channel delays of a random source direction (far field, paper Eq. 1-3):
    t_k = -(xi_k tau_x + eta_k tau_y) with (tau_x, tau_y) = max_delay sin(theta) (cos phi,
    sin phi), theta uniform in solid angle over the upper hemisphere; shifted so the
    earliest channel has delay 0. max_delay = a / c (1 us for the paper's tip)."""
    cos_t = rng.uniform(0.0, 1.0)
    sin_t = math.sqrt(1.0 - cos_t * cos_t)
    phi = rng.uniform(0.0, 2.0 * math.pi)
    tx, ty = max_delay_s * sin_t * math.cos(phi), max_delay_s * sin_t * math.sin(phi)
    xi = np.array([1, 1, -1, -1])
    eta = np.array([1, -1, 1, -1])
    d = -(xi * tx + eta * ty)
    return tuple(float(v) for v in d - d.min())


def synth_stream(n_samples: int, sample_rate_hz: float, events, *, noise_rms_v: float = 0.0,
                 dc_v=0.0, seed: int = 0, shape: str = "hp_step", highpass_hz: float = 100e3,
                 echo_ratio: float = 0.0, echo_delay_s: float = 13.5e-6,
                 full_scale_v: float | None = None, dtype=np.float64,
                 support_s: float = 60e-6) -> np.ndarray:
    """(4, n) stream with the given `SynthEvent`s; see the module docstring."""
    fs = float(sample_rate_hz)
    x = np.zeros((4, int(n_samples)))
    support = int(support_s * fs) + 2
    for ev in events:
        for k in range(4):
            t_arr = ev.time_s + ev.delays_s[k]
            paths = [(t_arr, ev.amplitude_v)]
            if echo_ratio:
                paths.append((t_arr + echo_delay_s, ev.amplitude_v * echo_ratio))
            for t0, amp in paths:
                i0 = max(int(math.floor(t0 * fs)), 0)
                i1 = min(i0 + support, x.shape[1])
                if i1 <= i0:
                    continue
                t = np.arange(i0, i1) / fs - t0
                if shape == "hp_step":
                    x[k, i0:i1] += amp * hp_step(t, highpass_hz)
                elif shape == "burst":
                    x[k, i0:i1] += amp * tone_burst(t)
                else:
                    raise ValueError(f"unknown shape {shape!r}")
    if noise_rms_v:
        x += np.random.default_rng(seed).normal(0.0, noise_rms_v, x.shape)
    x += np.asarray(dc_v, dtype=np.float64).reshape(-1, 1) if np.ndim(dc_v) else dc_v
    if full_scale_v is not None:
        x = np.clip(x, -full_scale_v, full_scale_v)
    return x.astype(dtype)


def snr_amplitude(snr_db: float, noise_rms_v: float, sample_rate_hz: float,
                  highpass_hz: float = 100e3, window_s: float = 30e-6) -> float:
    """Amplitude of an `hp_step` packet whose SNR (docs/conventions.md: mean power over
    the 4 channels and the 30 us after the earliest arrival / sigma^2) is ``snr_db``
    (computed for zero channel delays)."""
    t = np.arange(int(round(window_s * sample_rate_hz))) / sample_rate_hz
    p_unit = float(np.mean(hp_step(t, highpass_hz) ** 2))
    return noise_rms_v * math.sqrt(10.0 ** (snr_db / 10.0) / p_unit)
