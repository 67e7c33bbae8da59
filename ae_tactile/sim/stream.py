# SPDX-License-Identifier: Apache-2.0
"""The simulator's sources: a continuous stream (`StreamingSource.next_chunk`) and the
triggered windows cut from it around each emission (`TriggeredSource.next_packets`, the
virtual device's path). Both pull emissions from an emission process as time advances
and render them with a `renderer.StreamRenderer` (chunk invariance, engines and noise
are described there).

The stream's ground truth and renderer are re-exported here: `EmissionList`, `KINDS`,
`KIND_CODE`, `StaticEmissions`, `sample_index_of_ns`, `time_ns_of_sample`,
`StreamRenderer`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ae_tactile.sim.config import SimConfig
from ae_tactile.sim.emission_list import (
    KIND_CODE,
    KINDS,
    EmissionList,
    StaticEmissions,
    as_process,
    sample_index_of_ns,
    time_ns_of_sample,
)
from ae_tactile.sim.propagation import compute_arrivals
from ae_tactile.sim.renderer import StreamRenderer
from ae_tactile.sim.response import KernelInputs, accumulate, arrival_coefficients

__all__ = [
    "KINDS", "KIND_CODE", "EmissionList", "StaticEmissions", "sample_index_of_ns",
    "time_ns_of_sample", "StreamRenderer", "Chunk", "StreamingSource", "StreamPackets",
    "TriggeredSource",
]


@dataclass
class Chunk:
    """``samples_v`` (4, n) ADC volts for absolute samples [start_index, start_index + n);
    ``emissions``: ground truth of the emissions whose time falls in the chunk."""

    samples_v: np.ndarray
    start_index: int
    start_time_ns: int
    sample_rate_hz: float
    emissions: EmissionList
    clipped: bool
    clean_v: np.ndarray | None = None


class StreamingSource:
    """Continuous 4-channel stream: ``next_chunk(n)`` returns the next n samples and the
    ground truth falling in them. Memory is bounded: emissions older than the renderer's
    look-back are dropped.

    Parameters
    ----------
    source : EmissionList or emission process
        The emissions, or an object with ``advance(t_ns) -> EmissionList`` returning,
        deterministically, the emissions up to t_ns not returned before (e.g.
        `incipient_slip.IncipientSlipProcess`).
    config : SimConfig
        The simulated sensor.
    noise_rms_v : float
        Noise sigma per channel [V] (0: no noise).
    seed : int
        Seed of the stream's noise.
    start_index : int
        Absolute index of the first sample served.
    keep_clean : bool
        Also return the noise-free signal of each chunk (``Chunk.clean_v``).
    """

    def __init__(self, source, config: SimConfig, *, noise_rms_v: float = 0.0, seed: int = 0,
                 start_index: int = 0, keep_clean: bool = False):
        self.process = as_process(source)
        self.config = config
        self.renderer = StreamRenderer(config, noise_rms_v=noise_rms_v, seed=seed)
        self.position = int(start_index)
        self.keep_clean = keep_clean
        self._buffer = EmissionList.empty()

    @property
    def time_ns(self) -> int:
        """Start time (ns) of the next sample."""
        return int(time_ns_of_sample(self.position, self.config.sample_rate_hz))

    def _pull(self, n1: int) -> EmissionList:
        # emissions before the chunk's end time; a later one (>= t(n1)) cannot reach these
        # samples, its travel time being longer than a sample period
        t_end = int(time_ns_of_sample(n1, self.config.sample_rate_hz))
        new = self.process.advance(t_end)
        if len(new):
            self._buffer = EmissionList.concat([self._buffer, new])
        return new

    def next_chunk(self, n_samples: int, out=None) -> Chunk:
        """The next ``n_samples`` samples of the stream and the emissions falling in them.

        Parameters
        ----------
        n_samples : int
            Samples per channel (> 0).
        out : numpy.ndarray, optional
            A C-contiguous float64 (4, n_samples) buffer to render into (reusing one buffer
            across chunks avoids page-faulting fresh memory).

        Returns
        -------
        Chunk
            ADC output [V], its position and time, and the ground truth.
        """
        n = int(n_samples)
        if n <= 0:
            raise ValueError(f"n_samples must be positive, got {n_samples!r}")
        n0, n1 = self.position, self.position + n
        fs = self.config.sample_rate_hz
        self._pull(n1)
        t0, t1 = (int(x) for x in time_ns_of_sample([n0, n1], fs))
        res = self.renderer.render(self._buffer, n0, n1, out=out, return_clean=self.keep_clean)
        truth = self._buffer.between(t0, t1)
        # drop emissions that can no longer reach future samples
        t_keep = int(time_ns_of_sample(n1 - self.renderer.lookback_samples - 1, fs))
        self._buffer = self._buffer.between(t_keep, np.iinfo(np.int64).max)
        self.position = n1
        return Chunk(samples_v=res[0], start_index=n0, start_time_ns=t0, sample_rate_hz=fs,
                     emissions=truth, clipped=res[1], clean_v=res[2] if self.keep_clean else None)


@dataclass(frozen=True)
class StreamPackets:
    """Triggered windows cut from a stream, one per emission (hardware-trigger view).

    samples_v (N, 4, M), clean_v (N, 4, M) or None, start_index (N,) absolute first sample,
    onset_index (N,) first sample at/after the earliest direct arrival (window-relative),
    arrival_times_s (N, 4) direct arrivals relative to the window's first sample,
    delays_s (N, 2) exact (tau_x, tau_y), emissions (the triggering emissions' truth),
    n_overlapping (N,) other emissions whose direct arrivals fall inside the window,
    saturated (N,).
    """

    samples_v: np.ndarray
    clean_v: np.ndarray | None
    sample_rate_hz: float
    start_index: np.ndarray
    onset_index: np.ndarray
    arrival_times_s: np.ndarray
    delays_s: np.ndarray
    emissions: EmissionList
    n_overlapping: np.ndarray
    saturated: np.ndarray

    def __len__(self):
        return int(self.samples_v.shape[0])


class TriggeredSource:
    """Windows around each emission, as an ideal hardware trigger would capture them: the
    window starts ``pretrigger_s`` before the emission's earliest direct arrival and holds
    ``window_s`` of the *stream* (overlapping emissions, echoes and the stream's noise
    included). ``next_packets(n)`` returns up to n packets in emission order.

    Parameters
    ----------
    source : EmissionList or emission process
        As for `StreamingSource`.
    config : SimConfig
        The simulated sensor.
    noise_rms_v, seed : float, int
        The stream's noise sigma per channel [V] and seed.
    pretrigger_s, window_s : float
        Window start before the earliest direct arrival, and window length [s].
    keep_clean : bool
        Also return the noise-free windows (``StreamPackets.clean_v``).
    render_path : {'fast', 'reference'}
        'fast' renders only each window's samples and noise; 'reference' renders each
        window with the stream renderer. Both give the same bits.
    engine : {'numba', 'numpy', None}
        Renderer engine (None: numba when available, `response.default_engine`).
    end_ns : int, optional
        No packet for emissions from this time on [ns] (a scene's source ends with the
        scene: `Scene.triggered_source` sets it to the scene's duration).
    """

    def __init__(self, source, config: SimConfig, *, noise_rms_v: float = 0.0, seed: int = 0,
                 pretrigger_s: float = 8e-6, window_s: float = 40e-6, keep_clean: bool = False,
                 render_path: str = "fast", engine=None, end_ns: int | None = None):
        if render_path not in ("fast", "reference"):
            raise ValueError(f"render_path must be 'fast' or 'reference', got {render_path!r}")
        self.process = as_process(source)
        self.config = config
        self.render_path = render_path
        self.end_ns = None if end_ns is None else int(end_ns)
        self.renderer = StreamRenderer(config, noise_rms_v=noise_rms_v, seed=seed, engine=engine)
        fs = config.sample_rate_hz
        self.pre = int(round(pretrigger_s * fs))
        self.m = int(round(window_s * fs))
        if self.m <= self.pre:
            raise ValueError("window_s must exceed pretrigger_s")
        self.keep_clean = keep_clean
        self._buffer = EmissionList.empty()
        self._derived = self._derive(self._buffer)
        self._next = 0                    # index into _buffer of the next emission to serve
        self._horizon_ns = 0
        self._lookahead_ns = int(1e9 * (self.m / fs + 10 * config.max_support_s)) + 1
        _ = config.frontend.fast_basis        # the config's tables now, not at the first packet

    def _derive(self, em: EmissionList):
        """Per-emission (sample index n_e, fraction frac_s, absolute first-arrival sample)."""
        fs = self.config.sample_rate_hz
        ne, frac = sample_index_of_ns(em.time_ns, fs)
        first = ne + np.ceil((frac + self.config.geometry.arrival_times_s(em.point_m).min(axis=1))
                             * fs) if len(em) else np.zeros(0)
        return ne, frac, first

    def _ensure(self, t_ns):
        if t_ns > self._horizon_ns:
            new = self.process.advance(t_ns)
            self._horizon_ns = t_ns
            if len(new):
                old = self._buffer
                self._buffer = EmissionList.concat([old, new])
                appended = (len(old) == 0 or (new.time_ns[0], new.event_id[0])
                            > (old.time_ns[-1], old.event_id[-1]))
                if appended:        # the usual case: derived columns of the new ones only
                    d = self._derive(new)
                    self._derived = tuple(np.concatenate([a, b]) for a, b in zip(self._derived, d))
                else:
                    self._derived = self._derive(self._buffer)

    def _drop(self, n: int):
        self._buffer = self._buffer.take(slice(n, None))
        self._derived = tuple(a[n:] for a in self._derived)

    def _render_windows(self, start):
        """Fast path: all windows [start_i, start_i + M) at once, bit-identical to
        rendering each from the stream (`StreamRenderer.render`): one set of arrival
        coefficients for every emission reaching any window, only the window's columns
        of each response evaluated (compiled kernel), only the window's noise drawn.
        Returns (samples (k, 4, M), clean or None, saturated (k,))."""
        cfg = self.config
        r = self.renderer
        k, m = start.shape[0], self.m
        out = np.zeros((k, 4, m))
        buf = self._buffer
        if len(buf):
            ne_all, frac_all, _ = self._derived
            i0, i1 = np.searchsorted(ne_all, [int(start.min()) - r.lookback_samples,
                                              int(start.max()) + m], side="left")
            i0, i1 = int(i0), int(i1)
        else:
            i0 = i1 = 0
        if i1 > i0:
            ne, frac = ne_all[i0:i1], frac_all[i0:i1]
            sl = slice(i0, i1)
            e_lo = np.searchsorted(ne, start - r.lookback_samples, side="left")
            e_hi = np.searchsorted(ne, start + m, side="left")
            if r.engine == "numba":
                ki = KernelInputs.compiled(buf.point_m[sl], buf.strength_pa_m[sl],
                                           buf.alpha_1_s[sl], ne, frac, cfg, r._tables)
                per = ki.n0.shape[0] // (i1 - i0)         # arrivals per emission
                ki.call_kernel(out, start, e_lo * per, e_hi * per)
            else:
                arr = compute_arrivals(buf.point_m[sl], buf.strength_pa_m[sl], buf.alpha_1_s[sl],
                                       cfg)
                co = arrival_coefficients(arr.amplitude_pa, arr.alpha_1_s, arr.att_pole_rad_s,
                                          ne[arr.emission], frac[arr.emission] + arr.delay_s, cfg)
                per = len(arr) // (i1 - i0)
                for i in range(k):
                    sl = slice(int(e_lo[i]) * per, int(e_hi[i]) * per)
                    accumulate(co.take(sl), arr.channel[sl], cfg, r._tables, out[i], int(start[i]),
                               engine="numpy")
        clean = out.copy() if self.keep_clean else None
        for i in range(k):
            r.add_noise_window(out[i], int(start[i]))
        if cfg.quantization:
            lsb = cfg.lsb_v
            half = float(1 << (cfg.adc_bits - 1))
            out *= 1.0 / lsb
            np.rint(out, out=out)
            sat = (out.max(axis=(1, 2)) > half - 1) | (out.min(axis=(1, 2)) < -half)
            if np.any(sat):
                np.clip(out, -half, half - 1, out=out)
            out *= lsb
        else:
            fs_v = cfg.adc_full_scale_v
            sat = ((out.max(axis=(1, 2), initial=0.0) >= fs_v)
                   | (out.min(axis=(1, 2), initial=0.0) <= -fs_v))
        return out, clean, sat

    def _empty_packets(self) -> StreamPackets:
        z = np.zeros((0, 4, self.m))
        i0 = np.zeros(0, np.int64)
        return StreamPackets(samples_v=z, clean_v=z.copy() if self.keep_clean else None,
                             sample_rate_hz=self.config.sample_rate_hz, start_index=i0,
                             onset_index=i0.copy(), arrival_times_s=np.zeros((0, 4)),
                             delays_s=np.zeros((0, 2)), emissions=EmissionList.empty(),
                             n_overlapping=i0.copy(), saturated=np.zeros(0, bool))

    def _fill(self, n: int, limit) -> None:
        """Pull emissions from the process until n are waiting to be served, the horizon
        reaches ``limit`` [ns], or a static list is exhausted."""
        step = self._lookahead_ns
        while len(self._buffer) - self._next < n:
            target = self._horizon_ns + 100 * step
            if limit is not None:
                target = min(target, int(limit))
            if target <= self._horizon_ns:
                break
            before = len(self._buffer)
            self._ensure(target)
            if (len(self._buffer) == before and limit is None
                    and isinstance(self.process, StaticEmissions)):
                if self._horizon_ns > int(self.process.emissions.time_ns.max(initial=0)):
                    break

    def _render_reference(self, start):
        """Reference path: each window [start_i, start_i + M) rendered by the stream renderer.
        Returns (samples (k, 4, M), clean or None, saturated (k,))."""
        fs = self.config.sample_rate_hz
        k = start.shape[0]
        samples = np.zeros((k, 4, self.m))
        clean = np.zeros((k, 4, self.m)) if self.keep_clean else None
        sat = np.zeros(k, bool)
        for i in range(k):
            self._ensure(int(time_ns_of_sample(start[i] + self.m, fs)) + self._lookahead_ns)
            res = self.renderer.render(self._buffer, int(start[i]), int(start[i]) + self.m,
                                       return_clean=self.keep_clean)
            samples[i] = res[0]
            sat[i] = res[1]
            if self.keep_clean:
                clean[i] = res[2]
        return samples, clean, sat

    def _n_overlapping(self, start):
        """Per window (k,): the other buffered emissions whose first direct arrival falls
        inside it."""
        all_first = self._derived[2]
        if np.all(np.diff(all_first) >= 0):
            s0 = np.searchsorted(all_first, start, side="left")
            return np.searchsorted(all_first, start + self.m, side="left") - s0 - 1
        return np.array([int(np.sum((all_first >= s) & (all_first < s + self.m))) - 1
                         for s in start.tolist()], np.int64)

    def next_packets(self, n: int, horizon_ns: int | None = None) -> StreamPackets:
        """The next packets, in emission order.

        Parameters
        ----------
        n : int
            Most packets returned.
        horizon_ns : int, optional
            No packet for emissions from this time on [ns] (the device's "now"); fewer
            packets when the source ends.

        Returns
        -------
        StreamPackets
            Up to ``n`` windows with their ground truth (empty when none is due).
        """
        cfg = self.config
        fs = cfg.sample_rate_hz
        geo = cfg.geometry
        limit = horizon_ns if horizon_ns is not None else None
        if self.end_ns is not None:                # the scene's end: no emission from then on
            limit = self.end_ns if limit is None else min(int(limit), self.end_ns)
        self._fill(n, limit)
        take = list(range(self._next, min(len(self._buffer), self._next + n)))
        if limit is not None:
            take = [i for i in take if self._buffer.time_ns[i] < limit]
        if not take:
            return self._empty_packets()
        em = self._buffer.take(np.array(take, dtype=np.int64))
        k = len(em)
        sel = np.array(take, dtype=np.int64)
        n_e, frac = self._derived[0][sel], self._derived[1][sel]
        direct = geo.arrival_times_s(em.point_m)
        first = frac + direct.min(axis=1)
        onset_abs = n_e + np.ceil(first * fs - 1e-9).astype(np.int64)
        start = onset_abs - self.pre
        if self.render_path == "reference":
            samples, clean, sat = self._render_reference(start)
        else:
            self._ensure(int(time_ns_of_sample(int(start.max()) + self.m, fs))
                         + self._lookahead_ns)
            samples, clean, sat = self._render_windows(start)
        n_over = self._n_overlapping(start)
        self._next += k
        # drop served emissions that can no longer reach future windows (later emissions'
        # windows may start a little earlier than this batch's: travel times differ)
        t_keep = int(time_ns_of_sample(int(start.min()) - 2 * self.renderer.lookback_samples, fs))
        drop = int(np.searchsorted(self._buffer.time_ns[:self._next], t_keep))
        if drop:
            self._drop(drop)
            self._next -= drop
        arrival = (n_e - start)[:, None] / fs + frac[:, None] + direct
        delays = geo.delays_from_arrival_times(direct)[:, :2]      # = geo.exact_delays_s
        return StreamPackets(samples_v=samples, clean_v=clean, sample_rate_hz=fs,
                             start_index=start, onset_index=onset_abs - start,
                             arrival_times_s=arrival, delays_s=delays,
                             emissions=em, n_overlapping=n_over, saturated=sat)
