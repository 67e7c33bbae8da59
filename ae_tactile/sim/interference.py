# SPDX-License-Identifier: Apache-2.0
"""Common-mode electrical interference packets (not acoustic: rendered here, not by the
acoustic renderer): one waveform on all four channels, the front end's noise and ADC.

Waveforms (``kind``), amplitude ``amplitude_v`` at the ADC:
  spike     a Gaussian pulse of FWHM 30 .. 300 ns (ESD, a gate driver's spike)
  edge      a switching edge: a step (rise 20 .. 200 ns) settling with time constant
            5 .. 50 us, with ringing at 1.5 .. 5 MHz decaying in 0.3 .. 2 us
  ringing   a damped sinusoid at 1.5 .. 5 MHz, decay 0.5 .. 5 us
Coupling (``coupling``):
  adc       added after the front end's filters (ADC lines, ground bounce): the
            waveform keeps its own spectrum
  input     added at the amplifier's input: shaped by the device's own analog chain
            (`ae_tactile.sim.frontend.analog_stages`: high-pass or RC stages, the
            anti-alias family and order, the amplifier pole), so its spectrum is an
            acoustic packet's band
Each channel gets the common waveform times a gain 1 + N(0, ``gain_mismatch``), then
independent white noise of ``noise_rms_v`` and the ADC's quantization and clipping.

``burst_times_s`` gives trigger times of a switching source: bursts at ``rate_hz``
(1 Hz .. 10 kHz), periodic with timing jitter or Poisson. ``shared_clock_burst_times_ns``
puts one source's bursts on the host's monotonic clock, the same for every simulated
fingertip of the machine that draws them with the same seed: the fingertips of one hand
under one motor driver.

The returned ``TriggeredPackets`` have the triggered renderer's format (onset after
``pretrigger_s``), NaN points and delays, polarity 0.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import signal

from ae_tactile.sim.config import SimConfig
from ae_tactile.sim.frontend import analog_stages, quantize
from ae_tactile.sim.triggered import TriggeredPackets

KINDS = ("spike", "edge", "ringing")
COUPLINGS = ("adc", "input")


def _rng(rng):
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)


def burst_times_s(
    duration_s: float,
    rate_hz: float,
    *,
    periodic: bool = True,
    jitter_s: float = 0.0,
    start_s: float = 0.0,
    rng=None,
) -> np.ndarray:
    """Burst times (s) in [start_s, duration_s): periodic at ``rate_hz`` (jitter: Gaussian
    std ``jitter_s``) or Poisson."""
    g = _rng(rng)
    if not (rate_hz > 0 and duration_s > start_s):
        return np.zeros(0)
    if periodic:
        t = (
            start_s
            + g.uniform(0, 1.0 / rate_hz)
            + np.arange(int((duration_s - start_s) * rate_hz) + 1) / rate_hz
        )
        t = t + g.normal(0.0, jitter_s, t.size) if jitter_s > 0 else t
    else:
        n = g.poisson(rate_hz * (duration_s - start_s))
        t = np.sort(g.uniform(start_s, duration_s, n))
    return np.sort(t[(t >= start_s) & (t < duration_s)])


SHARED_BLOCK_NS = 1_000_000_000  # the shared clock's bursts are drawn per second of it


def shared_clock_burst_times_ns(
    from_ns: int,
    to_ns: int,
    rate_hz: float,
    *,
    periodic: bool = True,
    jitter_s: float = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """One source's burst times (ns, int64) in [from_ns, to_ns) of the host's monotonic
    clock, a function of the clock and ``seed`` alone: periodic at phase + k / rate (the
    phase drawn from the seed; jitter drawn per burst from (seed, second of the clock)),
    or Poisson, drawn per second of the clock from (seed, that second)."""
    from_ns, to_ns = int(from_ns), int(to_ns)
    if not (rate_hz > 0 and to_ns > from_ns):
        return np.zeros(0, np.int64)
    out = []
    period_ns = 1e9 / rate_hz
    phase_ns = np.random.default_rng([int(seed), 83]).uniform(0, period_ns)
    for block in range(from_ns // SHARED_BLOCK_NS, (to_ns - 1) // SHARED_BLOCK_NS + 1):
        b0, b1 = block * SHARED_BLOCK_NS, (block + 1) * SHARED_BLOCK_NS
        g = np.random.default_rng([int(seed), 84, block])
        if periodic:
            k = np.arange(
                math.ceil((b0 - phase_ns) / period_ns), math.ceil((b1 - phase_ns) / period_ns)
            )
            t = phase_ns + k * period_ns
            if jitter_s > 0:
                t = t + g.normal(0.0, jitter_s * 1e9, t.size)
        else:
            t = np.sort(g.uniform(b0, b1, g.poisson(rate_hz * SHARED_BLOCK_NS * 1e-9)))
        out.append(t)
    t = np.round(np.concatenate(out)).astype(np.int64)
    return np.sort(t[(t >= from_ns) & (t < to_ns)])


def _waveforms(kind, n, t, g):
    """(n, M) unit-amplitude waveforms starting at t = 0 (t: (M,) seconds, may be < 0)."""
    tt = t[None, :]
    after = tt >= 0
    if kind == "spike":
        fwhm = np.exp(g.uniform(math.log(30e-9), math.log(300e-9), n))[:, None]
        sig = fwhm / 2.355
        w = np.exp(-0.5 * ((tt - 3 * sig) / sig) ** 2)
    elif kind == "edge":
        rise = np.exp(g.uniform(math.log(20e-9), math.log(200e-9), n))[:, None]
        tau = np.exp(g.uniform(math.log(5e-6), math.log(50e-6), n))[:, None]
        f = g.uniform(1.5e6, 5e6, n)[:, None]
        dec = g.uniform(0.3e-6, 2e-6, n)[:, None]
        step = 0.5 * (1 + np.tanh(tt / rise))
        w = step * np.exp(-np.maximum(tt, 0) / tau)
        w = w + after * 0.3 * np.sin(2 * np.pi * f * tt) * np.exp(-np.maximum(tt, 0) / dec)
    elif kind == "ringing":
        f = g.uniform(1.5e6, 5e6, n)[:, None]
        dec = np.exp(g.uniform(math.log(0.5e-6), math.log(5e-6), n))[:, None]
        w = after * np.sin(2 * np.pi * f * tt) * np.exp(-np.maximum(tt, 0) / dec)
    else:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    peak = np.abs(w).max(axis=1, keepdims=True)
    return w / np.where(peak > 0, peak, 1.0)


def _front_end_filter(w, config: SimConfig):
    """``w`` (n, M) through the device's own analog chain (`analog_stages`: its high-pass,
    RC stages, anti-alias family and order, amplifier pole), discretized by the bilinear
    transform at the sample rate, as an interference entering the amplifier's input meets
    it; unit peak."""
    fs = float(config.sample_rate_hz)
    stages = analog_stages(config)
    z = np.concatenate([st[0] for st in stages]).astype(complex)
    p = np.concatenate([st[1] for st in stages]).astype(complex)
    k = float(np.prod([st[2] for st in stages]))
    sos = signal.zpk2sos(*signal.bilinear_zpk(z, p, k, fs))
    w = signal.sosfilt(sos, w, axis=-1)
    peak = np.abs(w).max(axis=1, keepdims=True)
    return w / np.where(peak > 0, peak, 1.0)


def _unit_windows(n, kind, coupling, cfg, m_len, pre, g):
    """(n, M) unit-peak waveforms in their windows, each starting a random fraction of a
    sample after ``pre`` samples; 'input' coupling filtered by the front end."""
    fs = float(cfg.sample_rate_hz)
    frac = g.uniform(0, 1, n)
    kinds = g.choice(KINDS, n) if kind == "mixed" else np.full(n, kind)
    # a long pre-roll so 'input' coupling sees the filters' full transient
    roll = int(round(60e-6 * fs))
    t = (np.arange(-roll, m_len)[None, :] - pre - frac[:, None]) / fs
    w = np.zeros((n, roll + m_len))
    for k in KINDS:
        sel = kinds == k
        if sel.any():
            w[sel] = np.concatenate([_waveforms(k, 1, t[i], g) for i in np.flatnonzero(sel)])
    if coupling == "input" and n:
        w = _front_end_filter(w, cfg)
    return w[:, roll:]


def render_interference(
    n: int,
    config: SimConfig | None = None,
    *,
    kind="mixed",
    coupling="adc",
    amplitude_v=None,
    noise_rms_v: float = 0.0,
    gain_mismatch: float = 0.01,
    pretrigger_s: float = 8e-6,
    window_s: float = 40e-6,
    rng=None,
) -> TriggeredPackets:
    """Common-mode interference packets (waveforms and coupling: the module docstring).

    Parameters
    ----------
    n : int
        Number of packets.
    config : SimConfig, optional
        The simulated sensor (default ``SimConfig()``).
    kind : str
        One of `KINDS`, or 'mixed' (a uniform choice per packet).
    coupling : {'adc', 'input'}
        After the front end's filters, or at the amplifier input (filtered by them).
    amplitude_v : float or array_like, optional
        Peak at the ADC [V], scalar or (n,); None: log-uniform over 10 .. 300 noise sigmas
        (0.01 .. 0.3 V without noise).
    noise_rms_v : float
        White noise sigma per channel [V].
    gain_mismatch : float
        Relative std of each channel's gain on the common waveform.
    pretrigger_s, window_s : float
        Window start before the burst, and window length [s].
    rng : int, numpy.random.Generator or None
        Seed or generator of every draw.

    Returns
    -------
    TriggeredPackets
        The triggered renderer's format, with NaN points and delays and polarity 0.
    """
    cfg = SimConfig() if config is None else config
    g = _rng(rng)
    if coupling not in COUPLINGS:
        raise ValueError(f"coupling must be one of {COUPLINGS}, got {coupling!r}")
    n = int(n)
    fs = float(cfg.sample_rate_hz)
    m_len = int(round(window_s * fs))
    pre = int(round(pretrigger_s * fs))
    if n < 0 or m_len <= pre + 1:
        raise ValueError("need n >= 0 and a window longer than the pretrigger")
    w = _unit_windows(n, kind, coupling, cfg, m_len, pre, g)
    if amplitude_v is None:
        lo, hi = (10 * noise_rms_v, 300 * noise_rms_v) if noise_rms_v > 0 else (0.01, 0.3)
        amplitude_v = np.exp(g.uniform(math.log(lo), math.log(hi), n))
    amp = np.broadcast_to(np.asarray(amplitude_v, float), (n,)) * g.choice([-1.0, 1.0], n)
    gains = 1.0 + gain_mismatch * g.normal(size=(n, 4))
    clean = (amp[:, None, None] * gains[:, :, None]) * w[:, None, :]
    noisy = clean + (g.normal(0.0, noise_rms_v, clean.shape) if noise_rms_v > 0 else 0.0)
    samples, clipped = quantize(noisy, cfg)
    nanv = np.full((n, 3), np.nan)
    return TriggeredPackets(
        samples_v=samples,
        clean_v=clean,
        sample_rate_hz=fs,
        onset_index=np.full(n, pre + 1, np.int64),
        points_m=nanv,
        delays_s=np.zeros((n, 2)),
        twist_s=np.zeros(n),
        arrival_times_s=np.zeros((n, 4)),
        emission_time_s=np.full(n, np.nan),
        noise_rms_v=np.full(n, float(noise_rms_v)),
        snr_db=np.full(n, np.nan),
        signal_power_v2=np.full(n, np.nan),
        saturated=clipped.any(axis=(1, 2)),
        polarity=np.zeros(n),
    )


def scene_bursts(truth: dict) -> list[dict]:
    """Interference burst specs of a scene truth (an 'interference' scene, or the parts of
    a composite one, times shifted onto the scene's timeline): [{times_ns, kind, coupling,
    amplitude_snr_db, seed}]."""
    if truth.get("generator") == "interference":
        return [dict(truth, times_ns=np.asarray(truth["burst_times_ns"], np.int64))]
    # (a composite scene's parts: shared-clock bursts are not offered there)
    out = []
    for part in truth.get("parts", []):
        if part.get("generator") == "interference":
            out.append(
                dict(
                    part,
                    times_ns=np.asarray(part["burst_times_ns"], np.int64) + int(part["offset_ns"]),
                )
            )
    return out


class InterferenceSource:
    """The interference packets of a scene, in time order: ``next_packets(horizon_ns)``
    returns (trigger times (N,) int ns of the packets' onsets, TriggeredPackets) of the
    bursts before ``horizon_ns`` not returned yet. Amplitude: ``amplitude_snr_db`` above
    ``noise_rms_v`` (the scene's noise; 1 mV if the scene has none). The window's first
    sample is ``pretrigger_s`` before the burst, as the triggered renderer's windows.
    ``host_t0_ns``: the host's monotonic clock at scene time 0 (the simulated device's
    start), for bursts on the shared clock (``shared_clock``); without it, the scene's own
    clock stands in for the host's."""

    def __init__(
        self,
        scene,
        *,
        pretrigger_s: float = 8e-6,
        window_s: float = 40e-6,
        host_t0_ns: int | None = None,
    ):
        self.config = scene.config
        self.noise_rms_v = float(scene.noise_rms_v or 0.0)
        self.pre, self.win = pretrigger_s, window_s
        truth = scene.process.scene_truth()
        self.bursts = scene_bursts(truth)
        self.seed = int(scene.seed)
        self.host_t0_ns = 0 if host_t0_ns is None else int(host_t0_ns)
        self._h = np.iinfo(np.int64).min

    def _shared(self, b: dict, horizon_ns: int) -> np.ndarray:
        """Scene times (ns) of a shared-clock source's bursts in [last horizon, horizon)."""
        lo = max(self._h, int(b["burst_start_time_ns"]))
        hi = min(int(horizon_ns), int(b["burst_end_time_ns"]))
        t = shared_clock_burst_times_ns(
            self.host_t0_ns + lo,
            self.host_t0_ns + hi,
            b["rate_hz"],
            periodic=b["periodic"],
            jitter_s=b["jitter_s"],
            seed=b["shared_seed"],
        )
        return t - self.host_t0_ns

    def next_packets(self, horizon_ns: int):
        """The bursts before ``horizon_ns`` not returned yet, rendered.

        Parameters
        ----------
        horizon_ns : int
            Scene time [ns] up to which bursts are due.

        Returns
        -------
        times_ns : numpy.ndarray
            (N,) int64 scene times of the packets' onsets [ns], sorted.
        packets : TriggeredPackets or None
            The packets in that order; None when no burst is due.
        """
        times, parts = [], []
        for i, b in enumerate(self.bursts):
            if b.get("shared_clock"):
                sel = self._shared(b, horizon_ns)
            else:
                t = b["times_ns"]
                sel = t[(t >= self._h) & (t < horizon_ns)]
            if sel.size == 0:
                continue
            ref = self.noise_rms_v if self.noise_rms_v > 0 else 1e-3
            amp = ref * 10 ** (b["amplitude_snr_db"] / 20.0)
            rng = np.random.default_rng([self.seed, 91, i, int(sel[0])])
            parts.append(
                render_interference(
                    sel.size,
                    self.config,
                    kind=b["kind"],
                    coupling=b["coupling"],
                    amplitude_v=amp,
                    noise_rms_v=self.noise_rms_v,
                    pretrigger_s=self.pre,
                    window_s=self.win,
                    rng=rng,
                )
            )
            times.append(sel)
        self._h = max(self._h, int(horizon_ns))
        if not parts:
            return np.zeros(0, np.int64), None
        t = np.concatenate(times)
        order = np.argsort(t, kind="stable")
        cat = {
            f: np.concatenate([getattr(p, f) for p in parts])[order]
            for f in (
                "samples_v",
                "clean_v",
                "onset_index",
                "points_m",
                "delays_s",
                "twist_s",
                "arrival_times_s",
                "emission_time_s",
                "noise_rms_v",
                "snr_db",
                "signal_power_v2",
                "saturated",
                "polarity",
            )
        }
        return t[order], TriggeredPackets(sample_rate_hz=parts[0].sample_rate_hz, **cat)
