# SPDX-License-Identifier: Apache-2.0
"""Streaming renderer: emissions with integer-nanosecond times -> 4-channel samples.

Any window [n0, n1) of absolute sample indices is rendered by summing only the
emissions whose responses overlap it, so the cost grows with the number of emissions,
not with the silent time between them; a 60 s scene streams chunk by chunk.

Chunk invariance (tested bit for bit): a window equals the same samples of a full
render, because
  * each arrival's response at absolute sample n is computed from the emission's own
    parameters and n - n0, from tables shared by the config (response.py), and is
    exactly zero outside its truncated support;
  * contributions are added by sequential slice additions in one fixed global order
    (emission time, then event id; within an emission path then channel), starting
    from 0.0, so every sample sees the same additions in the same order;
  * noise for absolute sample block b (``noise_block`` samples, all 4 channels) comes
    from its own generator seeded by (seed, b) (numpy SeedSequence -> PCG64), so it
    does not depend on where windows start;
  * quantization and clipping are elementwise and come last;
  * a sample is one fixed sequence of IEEE operations (kernels.py), the same in the
    numba kernel and the numpy reference; no matrix product whose rounding could
    depend on the batch.
Engines (``engine``): 'numba' (compiled, the default when available) and 'numpy' (the
reference); each is chunk-invariant bit for bit; they agree to rounding (docs/simulator.md).
Triggered windows (`TriggeredSource`, render_path 'fast') evaluate only the samples of
each window and draw only its noise (PCG64 jumped ahead), bit-identical to the stream.

Noise is float32 Box-Muller from 23-bit uniforms (exact Gaussian transform of uniforms
on a 2^-23 grid: tails reach ~5.6 sigma), scaled by noise_rms_v and added in float64
(the float32 noise has
~1e-7 relative resolution, far below the ADC step).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ae_tactile.sim.config import SimConfig
from ae_tactile.sim.emission import source_strength_pa_m
from ae_tactile.sim.propagation import compute_arrivals, path_lengths
from ae_tactile.sim.response import (
    KernelInputs,
    SlowTables,
    accumulate,
    arrival_coefficients,
    default_engine,
)

#: Emission types (``EmissionList.kind`` codes index this tuple).
KINDS = ("touch", "release", "micro_slip", "slip", "texture")
KIND_CODE = {k: i for i, k in enumerate(KINDS)}

_NS = 1_000_000_000


@dataclass(frozen=True)
class EmissionList:
    """Ground truth of emissions, columnar and sorted by (time_ns, event_id).

    time_ns        (N,) int64 emission instant
    point_m        (N, 3) contact point on the sensing surface
    kind           (N,) int8 code into KINDS
    strength_pa_m  (N,) signed source strength S = polarity rho v0^2 / a_c; the jump at
                   distance l is S / l (the "amplitude" of the ground truth)
    speed_m_s, curvature_1_m, alpha_1_s   (N,) Eq. 10 event parameters
    event_id       (N,) int64, unique per emission within a scene
    """

    time_ns: np.ndarray
    point_m: np.ndarray
    kind: np.ndarray
    strength_pa_m: np.ndarray
    speed_m_s: np.ndarray
    curvature_1_m: np.ndarray
    alpha_1_s: np.ndarray
    event_id: np.ndarray

    def __len__(self):
        return int(self.time_ns.shape[0])

    @property
    def polarity(self) -> np.ndarray:
        return np.sign(self.strength_pa_m)

    @property
    def kind_names(self) -> list[str]:
        return [KINDS[k] for k in self.kind]

    @classmethod
    def empty(cls) -> "EmissionList":
        z = np.zeros(0)
        return cls(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int8), z, z, z, z,
                   np.zeros(0, np.int64))

    @classmethod
    def create(cls, time_ns, point_m, kind, *, polarity=1, speed_m_s, curvature_1_m, alpha_1_s,
               density_kg_m3, event_id) -> "EmissionList":
        """Build and sort a list; scalars broadcast. ``kind`` names or codes."""
        t = np.atleast_1d(np.asarray(time_ns, dtype=np.int64))
        n = t.shape[0]
        p = np.asarray(point_m, dtype=float).reshape(n, 3)
        if isinstance(kind, str):
            k = np.full(n, KIND_CODE[kind], np.int8)
        else:
            k = np.asarray([KIND_CODE[x] if isinstance(x, str) else int(x)
                            for x in np.atleast_1d(kind)],
                           np.int8)
            k = np.broadcast_to(k, (n,)).copy()
        b = lambda v: np.broadcast_to(np.asarray(v, dtype=float), (n,)).copy()   # noqa: E731
        pol, v, a, al = b(polarity), b(speed_m_s), b(curvature_1_m), b(alpha_1_s)
        s = source_strength_pa_m(v, a, density_kg_m3, pol)
        eid = np.broadcast_to(np.asarray(event_id, dtype=np.int64), (n,)).copy()
        out = cls(t, p, k, s, v, a, al, eid)
        return out.sorted()

    def sorted(self) -> "EmissionList":
        order = np.lexsort((self.event_id, self.time_ns))
        return self.take(order)

    def take(self, idx) -> "EmissionList":
        return EmissionList(*(getattr(self, f)[idx] for f in self.__dataclass_fields__))

    @staticmethod
    def concat(lists) -> "EmissionList":
        lists = [x for x in lists if len(x)]
        if not lists:
            return EmissionList.empty()
        f = EmissionList.__dataclass_fields__
        return EmissionList(*(np.concatenate([getattr(x, k) for x in lists]) for k in f)).sorted()

    def between(self, t0_ns, t1_ns) -> "EmissionList":
        """Emissions with t0 <= time_ns < t1."""
        i0, i1 = np.searchsorted(self.time_ns, [t0_ns, t1_ns], side="left")
        return self.take(slice(int(i0), int(i1)))

    def to_records(self) -> list[dict]:
        """Plain-Python ground-truth records (for YAML/JSON/printing)."""
        return [dict(event_id=int(self.event_id[i]), time_ns=int(self.time_ns[i]),
                     type=KINDS[self.kind[i]], point_m=[float(x) for x in self.point_m[i]],
                     strength_pa_m=float(self.strength_pa_m[i]),
                     speed_m_s=float(self.speed_m_s[i]),
                     curvature_1_m=float(self.curvature_1_m[i]),
                     alpha_1_s=float(self.alpha_1_s[i]))
                for i in range(len(self))]

    def as_arrays(self, prefix="truth_") -> dict:
        """Arrays for ``np.savez`` (kind as codes plus the KINDS table)."""
        d = {prefix + k: getattr(self, k) for k in self.__dataclass_fields__}
        d[prefix + "kind_names"] = np.array(KINDS)
        return d


def sample_index_of_ns(time_ns, sample_rate_hz) -> tuple[np.ndarray, np.ndarray]:
    """(n, frac_s): sample n = floor(t fs) in exact integer arithmetic, and t - n/fs (s)."""
    t = np.asarray(time_ns, dtype=np.int64)
    fs = np.int64(int(round(sample_rate_hz)))
    sec, rem = np.divmod(t, np.int64(_NS))
    prod = rem * fs                              # < 1e9 * fs, fits int64 for fs < 9e9
    n = sec * fs + prod // np.int64(_NS)
    frac = (prod % np.int64(_NS)).astype(float) / (float(_NS) * float(fs))
    return n, frac


def time_ns_of_sample(n, sample_rate_hz) -> np.ndarray:
    """Start time (ns, rounded down) of absolute sample n."""
    n = np.asarray(n, dtype=np.int64)
    fs = np.int64(int(round(sample_rate_hz)))
    sec, rem = np.divmod(n, fs)
    return sec * np.int64(_NS) + (rem * np.int64(_NS)) // fs


class StreamRenderer:
    """Render absolute sample windows of a stream from an `EmissionList`.

    ``noise_rms_v``: sigma per channel (0 = no noise); ``seed`` fixes the noise.
    """

    def __init__(self, config: SimConfig, *, noise_rms_v: float = 0.0, seed: int = 0,
                 noise_block: int = 32768, batch_emissions: int = 32, engine=None):
        if not isinstance(config, SimConfig):
            raise TypeError(f"config must be a SimConfig, got {type(config).__name__}")
        sigma = float(noise_rms_v)
        if not math.isfinite(sigma) or sigma < 0:
            raise ValueError(f"noise_rms_v must be finite and >= 0, got {noise_rms_v!r}")
        self.config = config
        self.noise_rms_v = sigma
        self.seed = int(seed)
        self.noise_block = int(noise_block)
        self.batch_emissions = int(batch_emissions)
        self.engine = default_engine(engine)
        geo = config.geometry
        far = np.array([[0.0, 0.0, geo.radius_m], [geo.radius_m, 0.0, 0.0]])
        max_path = float(path_lengths(far, config).max()) + geo.element_offset_m
        #: emissions earlier than this many samples before a window cannot reach it
        self.lookback_samples = int(math.ceil(max_path / geo.sound_speed_m_s
                                              * config.sample_rate_hz)) \
            + config.max_support_samples + 2
        self._noise_cache: dict[int, np.ndarray] = {}
        self._pcg: dict[int, list] = {}
        self._bm_u = np.empty(2 * self.noise_block, np.float32)
        self._bm_v = np.empty(2 * self.noise_block, np.float32)
        self._tables = SlowTables(config, self.lookback_samples + 2)

    # ------------------------------------------------------------------ signal
    def render_clean(self, emissions: EmissionList, n0: int, n1: int, out=None) -> np.ndarray:
        """Noise-free, unquantized (4, n1 - n0) float64 for absolute samples [n0, n1).

        ``out``: optional preallocated (4, n1 - n0) float64 array to fill (reusing one
        buffer across chunks avoids page-faulting fresh memory on every chunk)."""
        n0, n1 = int(n0), int(n1)
        width = n1 - n0
        if width < 0:
            raise ValueError(f"empty window [{n0}, {n1})")
        if out is None:
            out = np.zeros((4, width))
        else:
            if out.shape != (4, width) or out.dtype != np.float64:
                raise ValueError(f"out must be a float64 array of shape (4, {width})")
            out.fill(0.0)
        if len(emissions) == 0 or width == 0:
            return out
        cfg = self.config
        t_lo, t_hi = time_ns_of_sample([n0 - self.lookback_samples - 1, n1 + 1],
                                       cfg.sample_rate_hz)
        i0, i1 = np.searchsorted(emissions.time_ns, [t_lo, t_hi], side="left")
        n_e, frac = sample_index_of_ns(emissions.time_ns[i0:i1], cfg.sample_rate_hz)
        sel = np.nonzero((n_e >= n0 - self.lookback_samples) & (n_e < n1))[0]
        emissions = emissions.take(slice(int(i0), int(i1)))
        if self.engine == "numba":
            if not out.flags.c_contiguous:
                raise ValueError("out must be C-contiguous")
            if sel.shape[0]:
                ki = KernelInputs.compiled(emissions.point_m[sel], emissions.strength_pa_m[sel],
                                           emissions.alpha_1_s[sel], n_e[sel], frac[sel], cfg,
                                           self._tables)
                ki.call_kernel(out[None], [n0], [0], [ki.n0.shape[0]])
            return out
        for b0 in range(0, sel.shape[0], self.batch_emissions):
            idx = sel[b0:b0 + self.batch_emissions]
            arr = compute_arrivals(emissions.point_m[idx], emissions.strength_pa_m[idx],
                                   emissions.alpha_1_s[idx], cfg)
            ne = n_e[idx][arr.emission]
            co = arrival_coefficients(arr.amplitude_pa, arr.alpha_1_s, arr.att_pole_rad_s,
                                      ne, frac[idx][arr.emission] + arr.delay_s, cfg)
            accumulate(co, arr.channel, cfg, self._tables, out, n0, engine=self.engine)
        return out

    # ------------------------------------------------------------------ noise
    def _noise_block(self, b: int) -> np.ndarray:
        blk = self._noise_cache.get(b)
        if blk is not None:
            return blk
        if len(self._noise_cache) >= 3:
            blk = self._noise_cache.pop(next(iter(self._noise_cache)))   # reuse its memory
        else:
            blk = np.empty((4, self.noise_block), np.float32)
        bitgen = np.random.PCG64(self._block_seed(b))
        h = 2 * self.noise_block
        # 2h uniform float32 in [1, 2) from the top 23 bits of each raw 32-bit word
        words = bitgen.random_raw(h).view(np.uint32)
        words >>= np.uint32(9)
        words |= np.uint32(0x3F800000)
        f = words.view(np.float32)
        u = self._bm_u
        np.subtract(np.float32(2.0), f[:h], out=u)      # (0, 1]
        np.log(u, out=u)
        u *= np.float32(-2.0 * self.noise_rms_v ** 2)
        np.sqrt(u, out=u)                               # sigma sqrt(-2 ln u)
        v = f[h:]
        v *= np.float32(2.0 * np.pi)                    # cos/sin(2 pi f) = of 2 pi (f - 1)
        flat = blk.reshape(-1)
        np.cos(v, out=flat[:h])
        np.sin(v, out=flat[h:])
        flat[:h] *= u
        flat[h:] *= u
        self._noise_cache[b] = blk
        return blk

    def add_noise(self, y: np.ndarray, n0: int) -> None:
        """Add the stream's noise (sigma = noise_rms_v) for absolute samples [n0, n0 + n) to y."""
        if self.noise_rms_v <= 0:
            return
        n1 = n0 + y.shape[1]
        B = self.noise_block
        b = n0 // B
        pos = n0
        while pos < n1:
            blk = self._noise_block(b)
            lo = pos - b * B
            hi = min(B, n1 - b * B)
            y[:, pos - n0:pos - n0 + hi - lo] += blk[:, lo:hi]
            pos += hi - lo
            b += 1

    def _block_seed(self, b: int) -> np.random.SeedSequence:
        """Seed of noise block b: (seed, 0x5EED, b); blocks before sample 0 (a window that
        starts before the scene, e.g. around an emission at t = 0) use (seed, 0x5EEE, -b)."""
        if b >= 0:
            return np.random.SeedSequence([self.seed, 0x5EED, b])
        return np.random.SeedSequence([self.seed, 0x5EEE, -b])

    def _block_words(self, b: int, ranges) -> np.ndarray:
        """uint32 words [lo, hi) of block b's raw stream, for increasing disjoint ranges of
        equal length, as rows (len(ranges), n): PCG64 jumped ahead (``advance``) instead
        of drawing the whole block."""
        ent = self._pcg.get(b)
        if ent is None:
            if len(self._pcg) >= 8:
                self._pcg.pop(next(iter(self._pcg)))
            bg = np.random.PCG64(self._block_seed(b))
            ent = self._pcg[b] = [bg, 0, bg.state]
        bg, pos = ent[0], ent[1]
        if (ranges[0][0] // 2) < pos:             # behind: restart the block's stream
            bg.state = ent[2]
            pos = 0
        n = ranges[0][1] - ranges[0][0]
        out = np.empty((len(ranges), n), np.uint32)
        for i, (lo, hi) in enumerate(ranges):
            r0, r1 = lo // 2, (hi + 1) // 2
            if r0 > pos:
                bg.advance(r0 - pos)
            raw = bg.random_raw(r1 - r0).view(np.uint32)
            out[i] = raw[lo - 2 * r0:lo - 2 * r0 + n]
            pos = r1
        ent[1] = pos
        return out

    def _noise_piece(self, b: int, lo: int, hi: int) -> np.ndarray:
        """Samples [lo, hi) of noise block b, (4, hi - lo) float32, bit-identical to
        ``_noise_block(b)[:, lo:hi]`` (same words, same float32 operations) at a cost
        proportional to hi - lo."""
        B = self.noise_block
        h = 2 * B
        # u of channels (0, 2) at word j, of (1, 3) at word B + j; v at h + those
        words = self._block_words(b, [(lo, hi), (B + lo, B + hi), (h + lo, h + hi),
                                      (h + B + lo, h + B + hi)])
        words >>= np.uint32(9)
        words |= np.uint32(0x3F800000)
        f = words.view(np.float32)
        u = np.subtract(np.float32(2.0), f[:2])
        np.log(u, out=u)
        u *= np.float32(-2.0 * self.noise_rms_v ** 2)
        np.sqrt(u, out=u)
        v = f[2:]
        v *= np.float32(2.0 * np.pi)
        out = np.empty((4, hi - lo), np.float32)
        np.cos(v, out=out[:2])
        np.sin(v, out=out[2:])
        out[:2] *= u
        out[2:] *= u
        return out

    def add_noise_window(self, y: np.ndarray, n0: int) -> None:
        """Same result as `add_noise` (bit for bit), drawing only the noise of [n0, n0 + n):
        the short-window path (triggered packets) that avoids rendering whole blocks."""
        if self.noise_rms_v <= 0:
            return
        n1 = n0 + y.shape[1]
        B = self.noise_block
        pos = n0
        while pos < n1:
            b = pos // B
            lo = pos - b * B
            hi = min(B, n1 - b * B)
            blk = self._noise_cache.get(b)
            piece = blk[:, lo:hi] if blk is not None else self._noise_piece(b, lo, hi)
            y[:, pos - n0:pos - n0 + hi - lo] += piece
            pos += hi - lo

    def noise(self, n0: int, n1: int) -> np.ndarray:
        """The stream's noise (volts, float64 (4, n1 - n0)) for absolute samples [n0, n1)."""
        y = np.zeros((4, n1 - n0))
        self.add_noise(y, n0)
        return y

    # ------------------------------------------------------------------ output
    def render(self, emissions: EmissionList, n0: int, n1: int, *, out=None, return_clean=False):
        """ADC output (volts, (4, n1 - n0) float64) for absolute samples [n0, n1): signal,
        plus noise, then quantization/clipping if on. With ``return_clean`` also the
        noise-free signal. Returns (samples, clipped_any[, clean])."""
        y = self.render_clean(emissions, n0, n1, out=out)
        clean = y.copy() if return_clean else None
        self.add_noise(y, n0)
        if self.config.quantization:
            clipped = _quantize_inplace(y, self.config)
        else:
            fs_v = self.config.adc_full_scale_v
            clipped = bool(y.max(initial=0.0) >= fs_v or y.min(initial=0.0) <= -fs_v)
        return (y, clipped, clean) if return_clean else (y, clipped)


def _quantize_inplace(y: np.ndarray, config) -> bool:
    """codes = clip(round(y / LSB)), y = codes * LSB in place; True if anything clipped."""
    lsb = config.lsb_v
    half = float(1 << (config.adc_bits - 1))
    y *= 1.0 / lsb
    np.rint(y, out=y)
    clipped = bool(y.max(initial=0.0) > half - 1 or y.min(initial=0.0) < -half)
    if clipped:
        np.clip(y, -half, half - 1, out=y)
    y *= lsb
    return clipped


# ---------------------------------------------------------------------- sources
class StaticEmissions:
    """An emission process over a fixed, pre-generated `EmissionList`."""

    def __init__(self, emissions: EmissionList, truth: dict | None = None):
        self.emissions = emissions.sorted()
        self.truth = dict(truth or {})
        self._horizon_ns = None

    def advance(self, t_ns: int) -> EmissionList:
        """Emissions with previous horizon <= time_ns < t_ns (everything before, first call)."""
        lo = np.iinfo(np.int64).min if self._horizon_ns is None else self._horizon_ns
        if self._horizon_ns is not None and t_ns <= self._horizon_ns:
            return EmissionList.empty()
        self._horizon_ns = int(t_ns)
        return self.emissions.between(lo, t_ns)

    def scene_truth(self) -> dict:
        return dict(self.truth)


def _as_process(src):
    if isinstance(src, EmissionList):
        return StaticEmissions(src)
    if hasattr(src, "advance"):
        return src
    raise TypeError("expected an EmissionList or an emission process with advance(t_ns)")


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
    ground truth falling in them. Source: an `EmissionList` or an emission process (an
    object with ``advance(t_ns) -> EmissionList`` returning, deterministically, the
    emissions up to t_ns not returned before; e.g. `generators.IncipientSlipProcess`).
    Memory is bounded: emissions older than the renderer's look-back are dropped.
    """

    def __init__(self, source, config: SimConfig, *, noise_rms_v: float = 0.0, seed: int = 0,
                 start_index: int = 0, keep_clean: bool = False):
        self.process = _as_process(source)
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
    included). ``next_packets(n)`` returns up to n packets in emission order, of emissions
    before ``end_ns`` if given (a scene's source ends with the scene: `Scene.triggered_source`
    sets it to the scene's duration)."""

    def __init__(self, source, config: SimConfig, *, noise_rms_v: float = 0.0, seed: int = 0,
                 pretrigger_s: float = 8e-6, window_s: float = 40e-6, keep_clean: bool = False,
                 render_path: str = "fast", engine=None, end_ns: int | None = None):
        if render_path not in ("fast", "reference"):
            raise ValueError(f"render_path must be 'fast' or 'reference', got {render_path!r}")
        self.process = _as_process(source)
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

    def next_packets(self, n: int, horizon_ns: int | None = None) -> StreamPackets:
        """Up to n packets (fewer if the source ends, or none beyond ``horizon_ns``)."""
        cfg = self.config
        fs = cfg.sample_rate_hz
        geo = cfg.geometry
        step = self._lookahead_ns
        limit = horizon_ns if horizon_ns is not None else None
        if self.end_ns is not None:                # the scene's end: no emission from then on
            limit = self.end_ns if limit is None else min(int(limit), self.end_ns)
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
            samples = np.zeros((k, 4, self.m))
            clean = np.zeros((k, 4, self.m)) if self.keep_clean else None
            sat = np.zeros(k, bool)
            for i in range(k):
                self._ensure(int(time_ns_of_sample(start[i] + self.m, fs)) + step)
                res = self.renderer.render(self._buffer, int(start[i]), int(start[i]) + self.m,
                                           return_clean=self.keep_clean)
                samples[i] = res[0]
                sat[i] = res[1]
                if self.keep_clean:
                    clean[i] = res[2]
        else:
            self._ensure(int(time_ns_of_sample(int(start.max()) + self.m, fs)) + step)
            samples, clean, sat = self._render_windows(start)
        all_first = self._derived[2]
        s0 = (np.searchsorted(all_first, start, side="left")
              if np.all(np.diff(all_first) >= 0) else None)
        if s0 is not None:
            n_over = np.searchsorted(all_first, start + self.m, side="left") - s0 - 1
        else:
            n_over = np.array([int(np.sum((all_first >= s) & (all_first < s + self.m))) - 1
                               for s in start.tolist()], np.int64)
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
