# SPDX-License-Identifier: Apache-2.0
"""Stream renderer: emissions with integer-nanosecond times -> 4-channel samples.

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
Triggered windows (`stream.TriggeredSource`, render_path 'fast') evaluate only the samples
of each window and draw only its noise (PCG64 jumped ahead, `add_noise_window`),
bit-identical to the stream.

Noise is float32 Box-Muller from 23-bit uniforms (exact Gaussian transform of uniforms
on a 2^-23 grid: tails reach ~5.6 sigma), scaled by noise_rms_v and added in float64
(the float32 noise has ~1e-7 relative resolution, far below the ADC step).
"""
from __future__ import annotations

import math

import numpy as np

from ae_tactile.sim.config import SimConfig
from ae_tactile.sim.emission_list import EmissionList, sample_index_of_ns, time_ns_of_sample
from ae_tactile.sim.propagation import compute_arrivals, path_lengths
from ae_tactile.sim.response import (
    KernelInputs,
    SlowTables,
    accumulate,
    arrival_coefficients,
    default_engine,
)


class StreamRenderer:
    """Render absolute sample windows of a stream from an `EmissionList`.

    Parameters
    ----------
    config : SimConfig
        The simulated sensor.
    noise_rms_v : float
        Noise sigma per channel [V] (0: no noise).
    seed : int
        Seed of the noise (a window's noise does not depend on where it starts).
    noise_block : int
        Samples per independently seeded noise block.
    batch_emissions : int
        Emissions per batch of the numpy engine.
    engine : {'numba', 'numpy', None}
        None: numba when available (`response.default_engine`).
    """

    def __init__(self, config: SimConfig, *, noise_rms_v: float = 0.0, seed: int = 0,
                 noise_block: int = 32768, batch_emissions: int = 32, engine=None):
        if not isinstance(config, SimConfig):
            raise TypeError(f"config must be a SimConfig, got {type(config).__name__}")
        if not config.streamable:
            raise ValueError("the streaming renderer does not render the power loss law,"
                             " channel mismatch or amplifier noise (render_triggered does)")
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
        """ADC output for absolute samples [n0, n1): signal, plus noise, then quantization
        and clipping if on.

        Parameters
        ----------
        emissions : EmissionList
            Every emission that may reach the window (earlier ones included).
        n0, n1 : int
            Absolute sample indices of the window.
        out : numpy.ndarray, optional
            A C-contiguous float64 (4, n1 - n0) buffer to render into.
        return_clean : bool
            Also return the noise-free, unquantized signal.

        Returns
        -------
        samples : numpy.ndarray
            (4, n1 - n0) float64 [V].
        clipped : bool
            Whether any sample clipped at full scale.
        clean : numpy.ndarray
            (4, n1 - n0) [V], only with ``return_clean``.
        """
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
