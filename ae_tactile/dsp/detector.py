# SPDX-License-Identifier: Apache-2.0
"""Packet detection on a continuous 4-channel stream (windows the device already cut:
`ae_tactile.dsp.windows.analyze_window`, re-exported here).

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

from ..geometry import N_CHANNELS
from .batch import PacketBatch
from .config import DetectorConfig
from .filters import StreamingSOS, design_bandpass_sos, diff_noise_ratio
from .noise import BlockNoiseTracker
from .release import _ReleaseStage
from .trigger import _Pending, _TriggerStage
from .windows import analyze_window

#: chunks longer than this are processed in pieces (keeps the work arrays in cache)
_MAX_PIECE = 16384



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


class PacketDetector(_TriggerStage, _ReleaseStage):
    """Streaming packet detector (see the module docstring and docs/detection.md).

    >>> det = PacketDetector(DetectorConfig(sample_rate_hz=10e6))
    >>> batch = det.process(block_volts, first_sample_index)    # (4, n) float
    >>> last = det.flush()                                       # at the end of the stream

    The trigger stage (`ae_tactile.dsp.trigger`) and the release stage
    (`ae_tactile.dsp.release`) are mixins holding their steps; the state is the detector's.

    Parameters
    ----------
    config : DetectorConfig, optional
        The settings (SI units); default ``DetectorConfig(**overrides)``.
    **overrides
        Fields of `DetectorConfig` replaced in ``config``.

    Returns
    -------
    PacketDetector
        `process` returns a `PacketBatch` of the packets each chunk completes, `flush`
        those left at the end of the stream; counters in ``stats`` (`DetectorStats`).

    Raises
    ------
    TypeError
        ``config`` is not a `DetectorConfig`.
    ValueError
        An override names no field or has a bad value.
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
        """Feed one chunk of the stream.

        Parameters
        ----------
        samples : array_like, (4, n)
            The chunk [V]; the caller may reuse its buffer afterwards (copies are kept).
        first_sample_index : int
            Absolute index of the chunk's first sample (a jump ends the stream segment).

        Returns
        -------
        PacketBatch
            The packets completed by this chunk (possibly none).

        Raises
        ------
        ValueError
            Wrong shapes, dtypes or index types; bad sample values are counted, never
            raised.
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
        end cuts, and reset the stream state (counters and packet ids continue).

        Returns
        -------
        PacketBatch
            The packets still pending whose windows are complete (possibly none).
        """
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


__all__ = ["PacketDetector", "DetectorStats", "analyze_window"]
