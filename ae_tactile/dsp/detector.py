# SPDX-License-Identifier: Apache-2.0
"""Packet detection on a continuous 4-channel stream, and analysis of triggered windows.

`PacketDetector.process(samples (4, n), first_sample_index)` returns a `PacketBatch` with
every packet whose window is complete; `flush()` ends the stream. The output does not
depend on how the stream is cut into chunks (bit-identical, tested), because every stage
works on the absolute sample-index grid and carries its state:

1. Input check. NaN, +-inf and |x| > max_abs_v are *invalid samples*: counted, replaced
   by the channel's last valid value (so the filter sees no step), and any window that
   touches one is dropped (counted), never published.
2. Trigger path at fs / D (D = 3 at 10 MS/s): sums of D samples on the index grid, then
   the band-pass of ae_tactile/dsp/filters.py with its state carried across calls.
3. Noise floor per channel in blocks of B trigger samples on the grid
   (ae_tactile/dsp/noise.py); the variance of a block is known when it starts.
4. Envelope e[n] = sqrt( (1/4) sum_k y_k[n]^2 / sigma_k^2 ) in noise sigmas (a chi
   distribution with 4 degrees of freedom under noise: P(e >= 5) ~ 1e-20 per sample).
5. Trigger (docs/detection.md):
   - active samples: e >= rearm_sigma; on samples: e >= threshold_sigma;
   - hysteresis with a peak-hold of ``hold`` samples: the trigger is high from the first
     on sample until no active sample occurred for ``hold`` samples; every rising edge
     is an emission candidate (so a second crossing after a quiet gap, however short
     compared with HDT, gets its own window);
   - re-onsets: inside a running packet, per channel, the squared first difference of
     the band-passed signal (in its noise units) that reaches channel_onset_sigma^2 and
     jump_ratio^2 times its exponentially decayed maximum over the last onset_window is
     a channel onset; a channel's second onset in the same hit, >= channel_refractory
     after its first and not within channel_spread after an accepted emission, is a new
     emission (the first difference keeps sharp onsets and drops the slow tail of the
     decaying packet, and looking per channel avoids mistaking a packet's own late
     elements for a new emission);
   - candidates closer than ``min_separation`` to the previous accepted one are the same
     emission; with ``echo_delay_s`` set, candidates at k echo delays after an accepted
     one are wall echoes (counted, no window);
   - AE hits: active samples with gaps <= HDT form one hit; a candidate in the cluster
     of the running hit is an in-hit emission (``in_hit``: an overlapping emission, or an
     echo when echo rejection is off), windowed and counted; a candidate in a later
     cluster starts a new hit unless it falls within HLT after the previous hit ended
     (last active + HDT): then it is locked out (counted, no window).
   Only the (sparse) active samples are visited in Python; everything per sample is numpy.
6. Onset: multichannel AIC (ae_tactile/dsp/onset.py) on the raw samples of
   [crossing - aic_pre, crossing + aic_post), weighted by 1 / sigma_k^2, never earlier
   than the previous emission's crossing + channel_spread; for re-onsets on the first
   difference of the samples, within reonset_aic_pre of the re-onset.
7. Window [onset - pre, onset + post) of the original samples. A packet is released once
   the stream has reached window end + pre + aic_pre + aic_post, by when every other
   emission whose window can intersect it is known, so the overlap flags are final.
8. Features (ae_tactile/dsp/features.py): noise RMS, saturation, peak, polarity, SNR.

A jump in ``first_sample_index`` (a dropped STREAM block) or a step back ends the stream
segment as ``flush()`` does (complete windows are released, windows cut by the gap are
dropped and counted) and starts afresh; the detector is blind until the noise floor is
known again (settle_s + noise_min_blocks blocks, ~0.2-0.3 ms by default).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import signal

from ..geometry import N_CHANNELS
from .batch import PacketBatch
from .config import DetectorConfig
from .features import window_features, window_features_fixed
from .filters import StreamingSOS, design_bandpass_sos, diff_noise_ratio
from .noise import BlockNoiseTracker
from .onset import aic_pick

#: chunks longer than this are processed in pieces (keeps the work arrays in cache)
_MAX_PIECE = 16384

#: median of chi^2_1: median(y^2) = 0.4549 sigma^2 for Gaussian y.
_MEDIAN_CHI2_1 = 0.454936


@dataclass
class DetectorStats:
    """Counters of a `PacketDetector` (since construction or `reset_stats`)."""

    chunks: int = 0  #: process() calls with samples
    samples: int = 0  #: samples per channel received
    invalid_samples: int = 0  #: sample instants with a NaN/inf/absurd value (any channel)
    chunks_with_invalid: int = 0  #: chunks that held invalid samples
    gaps: int = 0  #: forward jumps of first_sample_index (dropped blocks)
    gap_samples: int = 0  #: samples missing in those gaps
    discontinuities: int = 0  #: backward jumps / repeats of first_sample_index
    blind_samples: int = 0  #: samples processed while the noise floor was unknown
    hits: int = 0  #: AE hits (first emission of each hit)
    in_hit_emissions: int = 0  #: emissions detected inside a running hit
    locked_out: int = 0  #: candidates suppressed by the hit lockout time
    echoes: int = 0  #: re-triggers taken for wall echoes (echo_delay_s)
    packets: int = 0  #: windows published
    overlapping_packets: int = 0  #: published windows flagged overlap
    saturated_packets: int = 0  #: published windows flagged saturated
    dropped_invalid: int = 0  #: windows dropped: they touched invalid samples
    dropped_truncated: int = 0  #: windows dropped: cut by a gap, a flush or the stream start

    def as_dict(self) -> dict:
        return asdict(self)


class _Pending:
    __slots__ = ("pid", "crossing", "hit_id", "in_hit", "weights", "aic_lo", "reonset", "onset")

    def __init__(self, pid, crossing, hit_id, in_hit, weights, aic_lo, reonset):
        self.pid = pid
        self.crossing = crossing  # input-sample index of the trigger
        self.hit_id = hit_id
        self.in_hit = in_hit
        self.weights = weights  # 1 / sigma_k^2 for the AIC
        self.aic_lo = aic_lo  # the AIC may not pick before this input index
        self.reonset = reonset  # found by a channel re-onset inside a packet
        self.onset = None


class PacketDetector:
    """Streaming packet detector (see the module docstring and docs/detection.md).

    >>> det = PacketDetector(DetectorConfig(sample_rate_hz=10e6))
    >>> batch = det.process(block_volts, first_sample_index)    # (4, n) float
    >>> last = det.flush()                                       # at the end of the stream
    """

    def __init__(self, config: DetectorConfig | None = None, **overrides):
        if config is None:
            config = DetectorConfig(**overrides)
        elif overrides:
            config = config.replace(**overrides)
        if not isinstance(config, DetectorConfig):
            raise TypeError(f"config must be a DetectorConfig, got {type(config).__name__}")
        self.config = config
        self.sp = config.samples()
        self.sos = design_bandpass_sos(
            self.sp.trigger_rate_hz, config.highpass_hz, config.lowpass_hz, config.filter_order
        )
        self._kon2 = float(config.threshold_sigma) ** 2
        self._koff2 = float(config.rearm_sigma) ** 2
        self._jump2 = float(config.jump_ratio) ** 2
        # per-channel onsets: window offsets, decay weights, noise of the first difference
        self._onset_offs = np.arange(1, self.sp.onset_window + 1)[None, :]
        self._onset_gpow = self.sp.onset_decay ** np.arange(1, self.sp.onset_window + 1)
        self._chk2 = float(config.channel_onset_sigma) ** 2
        self._wd_scale = 4.0 / diff_noise_ratio(self.sos)
        self._aic_range = np.arange(self.sp.aic_pre + self.sp.aic_post)[None, :]
        self._win_range = np.arange(self.sp.window)[None, :]
        self._floor_var = (0.1 * config.lsb_v) ** 2
        self._sat_lo, self._sat_hi = config.saturation_levels_v
        self._invalid_level = config.invalid_level_v
        # filtered energy no valid input can reach (|x| <= max_abs_v, sums of D, gain < 2)
        self._invalid_y2 = (2.0 * self.sp.decim * self._invalid_level) ** 2
        self._filter = StreamingSOS(self.sos, N_CHANNELS)
        self._tracker = BlockNoiseTracker(
            N_CHANNELS,
            config.noise_history_blocks,
            config.noise_min_blocks,
            config.burst_ratio,
            self._floor_var,
            config.noise_epoch_blocks,
        )
        self._empty_batch = PacketBatch.empty(self.sample_rate_hz, self.sp.window)
        self._next_id = 0
        self._hit_id = -1
        self.stats = DetectorStats()
        self._reset_stream()

    # ------------------------------------------------------------------ public API
    @property
    def sample_rate_hz(self) -> float:
        return float(self.config.sample_rate_hz)

    @property
    def window_samples(self) -> int:
        """Samples per channel M of every window (pre + post)."""
        return self.sp.window

    @property
    def noise_sigma_v(self) -> np.ndarray:
        """Noise sigma per channel (4,) of the trigger path (band-passed sums of D
        samples) in use for the current block; NaN while blind."""
        return np.sqrt(self._blk_var)

    @property
    def expected_index(self) -> int | None:
        """first_sample_index the next chunk should have (None before the first one)."""
        return self._expected

    @property
    def pending(self) -> int:
        """Emissions detected whose windows are not released yet."""
        return len(self._pending)

    def reset_stats(self) -> None:
        self.stats = DetectorStats()

    def process(self, samples, first_sample_index) -> PacketBatch:
        """Feed one chunk (4, n) in volts starting at absolute sample ``first_sample_index``.

        Returns the packets completed by this chunk (possibly none). Wrong shapes, dtypes
        or index types raise ValueError; bad sample values are counted, never raised.
        The caller may reuse its buffer afterwards (the detector keeps copies).
        """
        x = self._check_chunk(samples)
        idx = self._check_index(first_sample_index)
        n = x.shape[1]
        if n == 0:
            return self._empty_batch
        self.stats.chunks += 1
        self.stats.samples += n
        first = None
        if self._expected is not None and idx != self._expected:
            if idx > self._expected:
                self.stats.gaps += 1
                self.stats.gap_samples += idx - self._expected
            else:
                self.stats.discontinuities += 1
            first = self._finish()
            self._reset_stream()
        if self._expected is None:
            self._start_stream(idx)
        self._expected = idx + n
        outs = [] if first is None else [first]
        # short chunks are gathered up to min_batch samples (per-call overhead), long ones
        # cut into cache-sized pieces; the result does not depend on either
        if self._inbuf or n < self.sp.min_batch:
            self._inbuf.append(np.array(x, dtype=np.float64, copy=True))
            self._inlen += n
            if self._inlen < self.sp.min_batch:
                return first if first is not None and len(first) else self._empty_batch
            x = np.concatenate(self._inbuf, axis=1) if len(self._inbuf) > 1 else self._inbuf[0]
            n = x.shape[1]
            self._inbuf, self._inlen = [], 0
        for i in range(0, n, _MAX_PIECE):
            self._run(x[:, i : i + _MAX_PIECE])
            outs.append(self._release(final=False))
        outs = [o for o in outs if len(o)]
        if not outs:
            return self._empty_batch
        if len(outs) == 1:
            return outs[0]
        return PacketBatch.concatenate(outs, self.sample_rate_hz, self.sp.window)

    def flush(self) -> PacketBatch:
        """End of stream: release every complete window, drop (and count) the ones the
        end cuts, and reset the stream state (counters and packet ids continue)."""
        out = self._finish()
        self._reset_stream()
        return out

    # ------------------------------------------------------------------ input checks
    @staticmethod
    def _check_chunk(samples) -> np.ndarray:
        try:
            x = np.asarray(samples)
        except Exception as exc:  # noqa: BLE001 - any conversion failure is a bad chunk
            raise ValueError(f"samples must be an array of shape (4, n): {exc}") from None
        if x.dtype == bool or x.dtype.kind not in "fiu":
            raise ValueError(f"samples must be real numbers (float or int), got dtype {x.dtype}")
        if x.ndim != 2 or x.shape[0] != N_CHANNELS:
            raise ValueError(f"samples must have shape (4, n) (channel-major), got {x.shape}")
        return x

    @staticmethod
    def _check_index(first_sample_index) -> int:
        if isinstance(first_sample_index, (bool, np.bool_)) or not isinstance(
            first_sample_index, (int, np.integer)
        ):
            raise ValueError(
                f"first_sample_index must be an integer sample index, got {first_sample_index!r}"
            )
        idx = int(first_sample_index)
        if idx < 0 or idx >= 1 << 62:
            raise ValueError(f"first_sample_index must be in [0, 2^62), got {idx}")
        return idx

    def _sanitize(self, x: np.ndarray, idx: int) -> np.ndarray:
        """float64 copy with invalid samples counted, recorded (absolute ranges) and
        replaced by the channel's last valid value."""
        x = np.array(x, dtype=np.float64, order="C", copy=True)
        bad = ~(np.abs(x) <= self._invalid_level)  # NaN, inf, absurd
        anybad = bad.any(axis=0)
        nbad = int(anybad.sum())
        if nbad == 0:
            return x
        self.stats.chunks_with_invalid += 1
        self.stats.invalid_samples += nbad
        edges = np.flatnonzero(np.diff(np.concatenate([[0], anybad.astype(np.int8), [0]])))
        for s, e in zip(edges[0::2], edges[1::2]):
            self._invalid.append((idx + int(s), idx + int(e)))
        n = x.shape[1]
        pos = np.where(bad, 0, np.arange(1, n + 1))
        np.maximum.accumulate(pos, axis=1, out=pos)
        ext = np.concatenate([self._last_valid[:, None], x], axis=1)
        return np.take_along_axis(ext, pos, axis=1)

    # ------------------------------------------------------------------ state
    def _reset_stream(self) -> None:
        sp = self.sp
        self._filter.reset()
        self._tracker.reset()
        self._expected = None
        self._origin = 0
        self._origin_u = 0
        self._proc_end = 0
        self._lead = np.zeros((N_CHANNELS, 0))  # raw samples of an incomplete group
        self._inbuf: list[np.ndarray] = []  # short chunks waiting for min_batch
        self._inlen = 0
        self._skip = 0
        self._u_next = 0
        self._last_valid = np.zeros(N_CHANNELS)
        self._invalid: list[tuple[int, int]] = []
        self._raw_hist = np.zeros((N_CHANNELS, 0))
        self._raw_hist_prev = self._raw_hist
        self._raw_last = None
        self._blk_y2 = np.zeros((N_CHANNELS, 0))  # y^2 of the current partial block
        self._blk_var = np.full(N_CHANNELS, np.nan)  # variance in use for that block
        self._y_hist = np.zeros((N_CHANNELS, sp.onset_window + 1))
        self._ch_last_event = [0] * N_CHANNELS
        self._ch_last_cluster = [None] * N_CHANNELS
        self._ch_last_cond = [None] * N_CHANNELS
        self._last_active = None
        self._seg_triggered = False
        self._cluster = -1
        self._hit_cluster = None
        self._hit_cluster_last = None
        self._last_cand = None
        self._assign_until = -1
        self._accepted_u: list[int] = []
        self._pending: list[_Pending] = []
        self._recent: list[tuple[int, int]] = []  # (pid, onset) of released/dropped

    def _start_stream(self, idx: int) -> None:
        d = self.sp.decim
        self._origin = idx
        self._origin_u = -(-idx // d)
        self._proc_end = idx
        # samples before the first whole trigger group are never part of the trigger path
        self._skip = (-idx) % d
        u = self._origin_u
        self._u_next = u
        self._blk_y2 = np.zeros((N_CHANNELS, u % self.sp.block))

    def _finish(self) -> PacketBatch:
        if self._expected is None:
            return self._empty_batch
        if self._inbuf:
            x = np.concatenate(self._inbuf, axis=1) if len(self._inbuf) > 1 else self._inbuf[0]
            self._inbuf, self._inlen = [], 0
            outs = []
            for i in range(0, x.shape[1], _MAX_PIECE):
                self._run(x[:, i : i + _MAX_PIECE])
                outs.append(self._release(final=False))
            outs.append(self._release(final=True))
            return PacketBatch.concatenate(outs, self.sample_rate_hz, self.sp.window)
        return self._release(final=True)

    # ------------------------------------------------------------------ core
    def _run(self, x: np.ndarray) -> None:
        """Take the chunk x (4, n) (any real dtype) that starts at self._proc_end."""
        sp = self.sp
        s0 = self._proc_end
        n = x.shape[1]
        if x.dtype != np.float64 or not x.flags.c_contiguous:
            xf = np.ascontiguousarray(x, dtype=np.float64)
        else:
            xf = x
        # Fast path: NaN/inf propagate through the group sums and the filter into the
        # block statistics, which are checked before anything is committed; absurd finite
        # values show as absurd filtered energy. Then the exact check, sanitizing and a
        # second pass from the saved state.
        zi = self._filter.state()
        skip0, lead0 = self._skip, self._lead
        xd, skip_used, lead = self._decimate(xf)
        ok = bool(np.all(np.abs(lead) <= self._invalid_level)) if lead.shape[1] else True
        with np.errstate(all="ignore"):  # NaN/inf/absurd are caught just below
            phase = self._filter_phase(xd) if ok and xd.shape[1] else None
        if not ok or (phase is not None and not phase[-1]):
            self._filter.set_state(zi)
            self._skip, self._lead = skip0, lead0
            xf = self._sanitize(xf, s0)
            xd, skip_used, lead = self._decimate(xf)
            phase = self._filter_phase(xd) if xd.shape[1] else None
        self._last_valid = xf[:, -1].copy()
        self._skip -= skip_used
        self._lead = lead
        if phase is not None:
            u0 = self._u_next
            self._trigger_path(phase, u0)
            self._u_next = u0 + xd.shape[1]
        self._proc_end = s0 + n
        h = sp.history
        # raw samples for windows and AIC: the history before this piece and the piece
        # itself (copied: the caller may reuse its buffer); joined only when needed
        self._raw_hist_prev = self._raw_hist
        if self._pending:
            self._raw_last = xf.copy() if xf is x else xf
        else:
            self._raw_last = None
        if n >= h:
            self._raw_hist = np.array(xf[:, n - h :], dtype=np.float64, copy=True)
        else:
            self._raw_hist = np.concatenate([self._raw_hist, xf], axis=1)[:, -h:]
        if self._invalid:
            self._prune_invalid()

    def _decimate(self, xf: np.ndarray):
        """Group sums of d samples (float64, in sample order) for the groups completed by
        xf, continuing the incomplete group held in self._lead.

        Returns (xd (4, m), samples skipped at the stream start, new lead (4, r < d))."""
        d = self.sp.decim
        n = xf.shape[1]
        skip = min(self._skip, n)
        if d == 1:
            return xf[:, skip:].copy(), skip, self._lead
        lead = self._lead
        r = lead.shape[1]
        avail = n - skip
        if r + avail < d:
            return np.zeros((N_CHANNELS, 0)), skip, np.concatenate([lead, xf[:, skip:]], axis=1)
        parts = []
        pos = skip
        if r:
            g = lead[:, 0]
            for j in range(1, r):
                g = g + lead[:, j]
            for j in range(d - r):
                g = g + xf[:, pos + j]
            parts.append(g[:, None])
            pos += d - r
        m = (n - pos) // d
        if m:
            body = xf[:, pos : pos + m * d]
            s = body[:, 0::d] + body[:, 1::d]
            for j in range(2, d):
                s += body[:, j::d]
            parts.append(s)
        pos += m * d
        xd = parts[0] if len(parts) == 1 else np.concatenate(parts, axis=1)
        if not xd.flags.c_contiguous:
            xd = np.ascontiguousarray(xd)
        return xd, skip, xf[:, pos:].copy()

    def _filter_phase(self, xd: np.ndarray):
        """Band-pass xd (4, m) and square it into whole blocks; block statistics.

        Returns (y, r (4, nbs, B) y^2 with the current block's earlier part in front and
        zeros after the end, ms, pk (4, ncomp) of the completed blocks, finite flag)."""
        b = self.sp.block
        m = xd.shape[1]
        y = self._filter.process(xd, inplace=True)
        p = self._blk_y2.shape[1]  # samples of the current block seen before
        total = p + m
        nbs = -(-total // b)
        ncomp = total // b
        y2pad = np.empty((N_CHANNELS, nbs * b))
        if p:
            y2pad[:, :p] = self._blk_y2
        np.multiply(y, y, out=y2pad[:, p:total])
        if total < nbs * b:
            y2pad[:, total:] = 0.0
        r = y2pad.reshape(N_CHANNELS, nbs, b)
        ms = r[:, :ncomp].mean(axis=-1)
        pk = r[:, :ncomp].max(axis=-1)
        lim = self._invalid_y2
        finite = bool(pk.max() <= lim) if ncomp else True  # False for NaN, inf, absurd
        if finite and total > ncomp * b:
            finite = bool(r[:, ncomp].max() <= lim)
        return y, r, ms, pk, p, finite

    def _trigger_path(self, phase, u0: int) -> None:
        """Noise floor, envelope and trigger on the filtered trigger-path samples (absolute
        trigger indices u0 ..)."""
        sp = self.sp
        b = sp.block
        y, r, ms, pk, p, _ = phase
        m = y.shape[1]
        blk0 = u0 - p  # first trigger index of the first block
        total = p + m
        nbs = r.shape[1]
        ncomp = ms.shape[1]
        if ncomp:
            starts = blk0 + b * np.arange(ncomp)
            missing = starts < self._origin_u + sp.settle
            if self._invalid:
                missing |= self._blocks_touching_invalid(starts, b)
            var_all, _ = self._tracker.update(ms, pk, missing, blk0 // b)
            var = var_all if nbs > ncomp else var_all[:, :ncomp]
            self._blk_var = var_all[:, -1].copy()
        else:
            var = self._blk_var[:, None]
        self._blk_y2 = r.reshape(N_CHANNELS, -1)[:, ncomp * b : total].copy()
        blind = np.isnan(var[0])
        if blind.any():
            nb_blind = int(blind.sum())
            self.stats.blind_samples += sp.decim * (
                nb_blind * b - (p if blind[0] else 0) - ((nbs * b - total) if blind[-1] else 0)
            )
            w = np.where(np.isnan(var), 0.0, 0.25 / np.where(np.isnan(var), 1.0, var))
        else:
            w = 0.25 / var
        e2 = np.einsum("kbn,kb->bn", r, w).reshape(-1)[p:total]
        if self._invalid:
            self._zero_invalid(e2, u0)
        self._trigger(e2, y, u0, w, blk0)
        lh = sp.onset_window + 1
        if m >= lh:
            self._y_hist = y[:, m - lh :].copy()
        else:
            self._y_hist = np.concatenate([self._y_hist, y], axis=1)[:, -lh:]

    def _invalid_u(self):
        """Invalid ranges in trigger-path indices: groups touching an invalid sample."""
        d = self.sp.decim
        return [(s // d, -(-e // d)) for s, e in self._invalid]

    def _blocks_touching_invalid(self, starts: np.ndarray, b: int) -> np.ndarray:
        bad = np.zeros(starts.shape, bool)
        for s, e in self._invalid_u():
            bad |= (starts < e) & (starts + b > s)
        return bad

    def _zero_invalid(self, e2: np.ndarray, u0: int) -> None:
        n = e2.shape[0]
        for s, e in self._invalid_u():
            a, z = max(s - u0, 0), min(e - u0, n)
            if a < z:
                e2[a:z] = 0.0

    def _prune_invalid(self) -> None:
        """Forget invalid ranges no window or trigger block can touch any more."""
        sp = self.sp
        keep_from = self._proc_end - sp.history - sp.window - sp.block_full
        for p in self._pending:
            lo = (p.onset if p.onset is not None else p.crossing + 1 - sp.aic_pre) - sp.pretrigger
            keep_from = min(keep_from, lo)
        self._invalid = [(s, e) for s, e in self._invalid if e > keep_from]

    def _trigger(self, e2: np.ndarray, y: np.ndarray, u0: int, w: np.ndarray, blk0: int) -> None:
        """Schmitt trigger, per-channel re-onsets and AE hit rules on e2 (trigger indices
        from u0); y (4, m) is the band-passed trigger-path signal."""
        sp = self.sp
        act = np.flatnonzero(e2 >= self._koff2)
        if act.size == 0:
            return
        a_abs = act + u0
        on_pos = np.flatnonzero(e2[act] >= self._kon2)
        prev = self._last_active
        gaps = np.empty_like(a_abs)
        gaps[0] = (1 << 40) if prev is None else a_abs[0] - prev
        np.subtract(a_abs[1:], a_abs[:-1], out=gaps[1:])
        seg_start = gaps > sp.hold
        clu_gid = np.cumsum(gaps > sp.hdt)
        clu_gid += self._cluster
        events = []  # (position in act, channel or -1 for a rising edge)
        if on_pos.size:
            seg_id = np.cumsum(seg_start)
            sid = seg_id[on_pos]
            first = np.empty(sid.shape, bool)
            first[0] = True
            np.not_equal(sid[1:], sid[:-1], out=first[1:])
            rising = on_pos[first]
            if self._seg_triggered and not seg_start[0] and sid[0] == 0:
                rising = rising[1:]
            last_sid = int(seg_id[-1])
            self._seg_triggered = bool(
                sid[-1] == last_sid or (last_sid == 0 and self._seg_triggered)
            )
            events.extend((p_, -1) for p_ in rising.tolist())
        elif seg_start.any():
            self._seg_triggered = False
        events.extend(self._channel_onsets(act, a_abs, y, w, blk0))
        if events:
            events.sort()
            self._events(events, a_abs, clu_gid, w, blk0)
        self._last_active = int(a_abs[-1])
        self._cluster = int(clu_gid[-1])
        if self._hit_cluster is not None and self._hit_cluster >= int(clu_gid[0]):
            sel = np.flatnonzero(clu_gid == self._hit_cluster)
            if sel.size:
                self._hit_cluster_last = int(a_abs[sel[-1]])

    def _channel_onsets(self, act, a_abs, y, w, blk0) -> list:
        """Channel onsets on the active samples: [(position in act, channel)].

        z_k[n] = (y_k[n] - y_k[n-1])^2 / sigma_dk^2 (first difference of the band-passed
        signal, in its own noise units) reaches channel_onset_sigma^2 and jump_ratio^2
        times max_{l=1..L} z_k[n-l] g^l (the decayed maximum of the preceding
        onset_window); the first sample of each run is the onset.
        """
        sp = self.sp
        lh = sp.onset_window + 1
        # squared first differences over the span the active samples and their windows need
        lo = int(act[0]) - lh  # may reach into the history
        hi = int(act[-1]) + 1
        if lo >= 0:
            ys = y[:, lo:hi]
        else:
            ys = np.concatenate([self._y_hist[:, lh + lo :], y[:, :hi]], axis=1)
        d = ys[:, 1:] - ys[:, :-1]  # d[j] = y[lo + j + 1] - y[lo + j]
        d *= d
        q = act - (lo + 1)  # d[q] is (y[n] - y[n-1])^2
        # absolute level first (cheap, prunes most samples), then the decayed reference
        wd = w[:, (a_abs - blk0) // sp.block] * self._wd_scale  # 1 / sigma_dk^2, (4, na)
        cur = d[:, q]
        kk, pp = np.nonzero(cur * wd >= self._chk2)
        if kk.size == 0:
            return []
        qq = q[pp]
        ref = (d[kk[:, None], qq[:, None] - self._onset_offs] * self._onset_gpow).max(axis=-1)
        ok = cur[kk, pp] >= self._jump2 * ref
        if not ok.any():
            return []
        kk, pp = kk[ok], pp[ok]
        out = []
        tt = a_abs[pp].tolist()
        last = list(self._ch_last_cond)
        for k, p_, t in zip(kk.tolist(), pp.tolist(), tt):  # channel-major, time order
            lc = last[k]
            if lc is None or t - lc != 1:
                out.append((p_, k))
            last[k] = t
        self._ch_last_cond = last
        return out

    def _events(self, events, a_abs, clu_gid, w, blk0) -> None:
        """Turn rising edges and channel onsets (time order) into emissions.

        A rising edge is a candidate when it is not inside the running hit (its cluster
        of active samples). A channel onset is a candidate (a re-onset: a new emission
        inside a running packet) when the same channel already had an onset in the same
        hit at least channel_refractory earlier, and no emission was accepted within
        channel_spread before it (then it is that emission's late channel).
        Candidates then go through min_separation, the echo rule and the AE hit rules.
        """
        sp = self.sp
        d = sp.decim
        for p_, k in events:
            c = int(a_abs[p_])
            g = int(clu_gid[p_])
            if k >= 0:
                is_re = (
                    self._ch_last_cluster[k] == g
                    and c - self._ch_last_event[k] >= sp.channel_refractory
                )
                if self._ch_last_cluster[k] == g and not is_re:
                    continue  # same burst as before
                self._ch_last_event[k] = c
                self._ch_last_cluster[k] = g
                if not is_re or c <= self._assign_until:
                    continue
            elif g == self._hit_cluster:
                # a threshold re-crossing inside the running hit is the packet's own tail
                # unless a channel onset says otherwise (handled above)
                continue
            if self._last_cand is not None and c - self._last_cand < sp.min_separation:
                continue
            if sp.echo_delay and self._is_echo(c):
                self.stats.echoes += 1
                self._assign_until = c + sp.channel_spread  # its late channels too
                continue
            if g == self._hit_cluster:
                in_hit = True
                self.stats.in_hit_emissions += 1
            else:
                if self._hit_cluster is not None:
                    sel = np.flatnonzero(clu_gid == self._hit_cluster)
                    hl = int(a_abs[sel[-1]]) if sel.size else int(self._hit_cluster_last)
                    if c < hl + sp.hdt + sp.hlt:
                        self.stats.locked_out += 1
                        continue
                in_hit = False
                self.stats.hits += 1
                self._hit_id += 1
                self._hit_cluster = g
            # the previous emission's channels have all arrived by its crossing + spread:
            # the AIC must not pick them
            aic_lo = (
                -1
                if self._last_cand is None
                else (self._last_cand + sp.channel_spread) * d + d - 1
            )
            if k >= 0:
                # a re-onset is timed by the channel's own onset: search close to it (the
                # decaying packet before it would pull the AIC early)
                aic_lo = max(aic_lo, c * d + d - sp.reonset_aic_pre)
            self._last_cand = c
            self._assign_until = c + sp.channel_spread
            if sp.echo_delay:
                self._accepted_u.append(c)
            wc = 4.0 * w[:, (c - blk0) // sp.block]  # 1 / sigma_k^2 (0 if blind)
            # crossing in input samples: the last sample of the trigger group
            self._pending.append(
                _Pending(
                    self._next_id,
                    c * d + d - 1,
                    self._hit_id,
                    in_hit,
                    np.where(wc > 0, wc, 1.0),
                    aic_lo,
                    k >= 0,
                )
            )
            self._next_id += 1

    def _is_echo(self, c: int) -> bool:
        """c lies in [k D - tol, k D + spread + tol] after an accepted crossing (D: echo
        delay, k = 1 .. echo_orders; the echo's first element can be as late as the
        direct wave's last one, hence the spread)."""
        sp = self.sp
        dly, tol = sp.echo_delay, sp.echo_tolerance
        span = self.config.echo_orders * dly + sp.channel_spread + tol
        self._accepted_u = [a for a in self._accepted_u if c - a <= span]
        for a in self._accepted_u:
            dt = c - a
            for k in range(1, self.config.echo_orders + 1):
                if k * dly - tol <= dt <= k * dly + sp.channel_spread + tol:
                    return True
        return False

    def _raw_span(self) -> int:
        """First absolute index of the raw samples held (history + last piece)."""
        held = (
            self._raw_hist_prev.shape[1] + self._raw_last.shape[1]
            if self._raw_last is not None
            else self._raw_hist.shape[1]
        )
        return self._proc_end - held

    def _gather(self, idx: np.ndarray) -> np.ndarray:
        """Raw samples at absolute indices idx (K, L) -> (K, 4, L), from the history and
        the last piece without joining them."""
        last = self._raw_last
        if last is None:
            src = self._raw_hist
            out = src[:, idx - (self._proc_end - src.shape[1])]
        else:
            rel = idx - (self._proc_end - last.shape[1])
            if rel.min() >= 0:
                out = last[:, rel]
            else:
                hist = self._raw_hist_prev
                nl, nh = last.shape[1], hist.shape[1]
                out = np.where(
                    rel >= 0,
                    last[:, np.clip(rel, 0, nl - 1)],
                    hist[:, np.clip(rel + nh, 0, nh - 1)],
                )
        return np.ascontiguousarray(out.transpose(1, 0, 2))

    def _refine(self) -> None:
        """AIC onsets for the pending candidates whose search segment is complete."""
        sp = self.sp
        todo = [
            p
            for p in self._pending
            if p.onset is None and p.crossing + 1 + sp.aic_post <= self._proc_end
        ]
        if not todo:
            return
        ext_start = self._raw_span()
        starts = np.array([p.crossing + 1 - sp.aic_pre for p in todo], dtype=np.int64)
        ok = starts >= max(ext_start, self._origin)
        if not ok.all():
            for p, good in zip(todo, ok.tolist()):
                if not good:  # too close to the stream start: cannot refine
                    p.onset = -1
            todo = [p for p, good in zip(todo, ok.tolist()) if good]
            starts = starts[ok]
            if not todo:
                return
        seg = self._gather(starts[:, None] + self._aic_range)  # (K, 4, L)
        wts = np.stack([p.weights for p in todo])
        re = np.array([p.reonset for p in todo])
        if re.any():
            # inside a decaying packet the AIC works on the first difference, which keeps
            # the new emission's sharp onset and drops the slow tail of the previous one
            dseg = np.diff(seg, axis=-1, prepend=seg[..., :1])
            seg = np.where(re[:, None, None], dseg, seg)
        lo = np.array([p.aic_lo for p in todo], dtype=np.int64) - starts
        m, _ = aic_pick(seg, wts, margin=2, start=np.maximum(lo, 0) if (lo > 0).any() else None)
        for p, st, mm in zip(todo, starts.tolist(), m.tolist()):
            p.onset = st + mm

    def _release(self, final: bool) -> PacketBatch:
        """Refine what can be refined and publish the windows that are final."""
        sp = self.sp
        if not self._pending:
            return self._empty_batch
        # earliest possible onset of each pending packet -> can anything be released?
        lower = min(
            p.onset if p.onset is not None else p.crossing + 1 - sp.aic_pre for p in self._pending
        )
        if not final and lower + sp.posttrigger + sp.release_lag > self._proc_end:
            return self._empty_batch
        self._refine()
        if final:
            for p in self._pending:
                if p.onset is None:
                    p.onset = -1
        known = [p for p in self._pending if p.onset is not None]
        ready = [
            p
            for p in known
            if p.onset < 0 or final or p.onset + sp.posttrigger + sp.release_lag <= self._proc_end
        ]
        if not ready:
            return self._empty_batch
        # neighbours for the overlap flags: recent released + all known pending
        neigh = self._recent + [(p.pid, p.onset) for p in known if p.onset >= 0]
        lo_ok = max(self._origin, self._raw_span())
        cand = []
        drop_trunc = 0
        for p in ready:
            if (
                p.onset < 0
                or p.onset - sp.pretrigger < lo_ok
                or p.onset + sp.posttrigger > self._proc_end
            ):
                drop_trunc += 1
            else:
                cand.append(p)
        ready_ids = {p.pid for p in ready}
        self._pending = [p for p in self._pending if p.pid not in ready_ids]
        horizon = self._proc_end - 4 * sp.window - sp.release_lag
        self._recent = [t for t in self._recent if t[1] > horizon]
        self._recent.extend((p.pid, p.onset) for p in ready if p.onset >= 0)
        self.stats.dropped_truncated += drop_trunc
        if not cand:
            return self._empty_batch
        onset = np.array([p.onset for p in cand], dtype=np.int64)
        start = onset - sp.pretrigger
        win = self._gather(start[:, None] + self._win_range)  # (K, 4, M)
        good = np.abs(win).max(axis=(1, 2)) <= self._invalid_level
        if self._invalid:
            end = start + sp.window
            for a, z in self._invalid:
                good &= ~((start < z) & (end > a))
        if not good.all():
            self.stats.dropped_invalid += int((~good).sum())
            gl = good.tolist()
            cand = [p for p, g in zip(cand, gl) if g]
            if not cand:
                return self._empty_batch
            onset, start, win = onset[good], start[good], win[good]
        k = len(cand)
        m = sp.window
        prev_id = [-1] * k
        next_id = [-1] * k
        clear = [sp.posttrigger] * k
        for i, p in enumerate(cand):
            po, pp = p.onset, p.pid
            for pid, on in neigh:
                if pid == pp:
                    continue
                if abs(on - po) < m:
                    if pp > pid > prev_id[i]:
                        prev_id[i] = pid
                    if pid > pp and (next_id[i] < 0 or pid < next_id[i]):
                        next_id[i] = pid
                if po < on < po + clear[i]:
                    clear[i] = on - po
        prev_id = np.array(prev_id, np.int64)
        next_id = np.array(next_id, np.int64)
        overlap = (prev_id >= 0) | (next_id >= 0)
        feats = window_features_fixed(
            win,
            sp.pretrigger,
            noise_guard=sp.noise_guard,
            peak_window=sp.peak_window,
            polarity_window=sp.polarity_window,
            snr_window=sp.snr_window,
            sat_lo=self._sat_lo,
            sat_hi=self._sat_hi,
            var_floor=self._floor_var * 1e-2,
        )
        self.stats.packets += k
        self.stats.overlapping_packets += int(overlap.sum())
        self.stats.saturated_packets += int(feats["saturated"].sum())
        return PacketBatch(
            sample_rate_hz=self.sample_rate_hz,
            start_index=start,
            samples=win,
            onset_index=np.full(k, sp.pretrigger, np.int64),
            trigger_index=np.array([p.crossing for p in cand], np.int64) - start,
            overlap=overlap,
            overlap_prev_id=prev_id,
            overlap_next_id=next_id,
            clear_after=np.array(clear, np.int64),
            packet_id=np.array([p.pid for p in cand], np.int64),
            hit_id=np.array([p.hit_id for p in cand], np.int64),
            in_hit=np.array([p.in_hit for p in cand], bool),
            valid=np.ones(k, bool),
            **feats,
        )


# ---------------------------------------------------------------------- triggered windows
def analyze_window(
    windows,
    sample_rate_hz: float | None = None,
    *,
    config: DetectorConfig | None = None,
    onset_hint=None,
    start_index=None,
) -> PacketBatch:
    """Onset, noise, saturation, peak, polarity and SNR of already-cut windows.

    For devices that send PACKET frames (windows cut by the device's own trigger), so the
    driver fills the same Packet fields as in STREAM mode. ``windows``: (K, 4, M) or
    (4, M) volts. Per window: band-pass (state started at the first sample's steady
    state), noise sigma per channel from the median of y^2 (robust to the packet), the
    first crossing of threshold_sigma by the channel-RMS envelope (or ``onset_hint``
    (K,) where >= 0, e.g. the device's onset index; or the envelope maximum when nothing
    crosses), then the AIC pick in [crossing - aic_pre, crossing + aic_post) and the
    features of ae_tactile/dsp/features.py. Windows with non-finite samples get
    valid=False and are analysed with those samples set to 0 (never NaN out).
    ``start_index`` (K,) fills the batch's start_index (default 0).
    """
    if config is None:
        config = DetectorConfig(sample_rate_hz=10e6 if sample_rate_hz is None else sample_rate_hz)
    elif sample_rate_hz is not None and float(sample_rate_hz) != float(config.sample_rate_hz):
        config = config.replace(sample_rate_hz=sample_rate_hz)
    try:
        w = np.asarray(windows)
    except Exception as exc:  # noqa: BLE001
        raise ValueError(f"windows must be an array of shape (K, 4, M): {exc}") from None
    if w.dtype == bool or w.dtype.kind not in "fiu":
        raise ValueError(f"windows must be real numbers, got dtype {w.dtype}")
    if w.ndim == 2:
        w = w[None]
    if w.ndim != 3 or w.shape[1] != N_CHANNELS:
        raise ValueError(f"windows must have shape (K, 4, M) or (4, M), got {np.shape(windows)}")
    k, _, m = w.shape
    sp = config.samples()
    length = sp.aic_pre + sp.aic_post
    if m < max(16, length):
        raise ValueError(f"windows of {m} samples are too short (need >= {max(16, length)})")
    w = np.array(w, dtype=np.float64, copy=True)
    lim = config.invalid_level_v
    bad = ~(np.abs(w) <= lim)
    valid = ~bad.any(axis=(1, 2))
    w[bad] = 0.0
    if start_index is None:
        start = np.zeros(k, np.int64)
    else:
        start = np.asarray(start_index, dtype=np.int64).reshape(-1)
        if start.shape != (k,):
            raise ValueError(f"start_index must have shape ({k},), got {np.shape(start_index)}")
    hint = None
    if onset_hint is not None:
        hint = np.asarray(onset_hint).reshape(-1)
        if hint.shape != (k,) or hint.dtype.kind not in "iu":
            raise ValueError(
                f"onset_hint must be {k} integers (negative: none), got {onset_hint!r}"
            )
        hint = hint.astype(np.int64)
    if k == 0:
        return PacketBatch.empty(config.sample_rate_hz, m)

    sos = design_bandpass_sos(
        config.sample_rate_hz, config.highpass_hz, config.lowpass_hz, config.filter_order
    )
    zi = signal.sosfilt_zi(sos)[:, None, None, :] * w[None, :, :, 0, None]
    y, _ = signal.sosfilt(sos, w, axis=-1, zi=zi)
    floor_var = (0.1 * config.lsb_v) ** 2
    var = np.maximum(np.median(y * y, axis=-1) / _MEDIAN_CHI2_1, floor_var)  # (K, 4)
    e2 = y[:, 0] ** 2 * (0.25 / var[:, 0, None])
    for ch in range(1, N_CHANNELS):
        e2 = e2 + y[:, ch] ** 2 * (0.25 / var[:, ch, None])
    above = e2 >= float(config.threshold_sigma) ** 2
    crossing = np.where(above.any(axis=-1), np.argmax(above, axis=-1), np.argmax(e2, axis=-1))
    if hint is not None:
        crossing = np.where((hint >= 0) & (hint < m), hint, crossing)
    seg_start = np.clip(crossing - sp.aic_pre, 0, m - length)
    idx = seg_start[:, None] + np.arange(length)[None, :]
    seg = np.take_along_axis(w, np.broadcast_to(idx[:, None, :], (k, N_CHANNELS, length)), axis=-1)
    pick, _ = aic_pick(seg, 1.0 / var, margin=2)
    onset = (seg_start + pick).astype(np.int64)
    feats = window_features(
        w,
        onset,
        noise_guard=sp.noise_guard,
        peak_window=sp.peak_window,
        polarity_window=sp.polarity_window,
        snr_window=sp.snr_window,
        sat_lo=config.saturation_levels_v[0],
        sat_hi=config.saturation_levels_v[1],
        var_floor=floor_var * 1e-2,
    )
    return PacketBatch(
        sample_rate_hz=float(config.sample_rate_hz),
        start_index=start,
        samples=w,
        onset_index=onset,
        trigger_index=crossing.astype(np.int64),
        overlap=np.zeros(k, bool),
        overlap_prev_id=np.full(k, -1, np.int64),
        overlap_next_id=np.full(k, -1, np.int64),
        clear_after=np.maximum(m - onset, 0).astype(np.int64),
        packet_id=np.full(k, -1, np.int64),
        hit_id=np.full(k, -1, np.int64),
        in_hit=np.zeros(k, bool),
        valid=valid,
        **feats,
    )


__all__ = ["PacketDetector", "DetectorStats", "analyze_window"]
