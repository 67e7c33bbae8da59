# SPDX-License-Identifier: Apache-2.0
"""`PacketBatch`: the windows the detector cuts (or the triggered windows it analyses)."""
from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from ..geometry import N_CHANNELS

_FIELD_DTYPES = {
    "start_index": np.int64,
    "samples": np.float64,
    "onset_index": np.int64,
    "trigger_index": np.int64,
    "noise_rms_v": np.float64,
    "noise_rms_channel_v": np.float64,
    "saturated": bool,
    "saturated_channels": bool,
    "peak_amplitude_v": np.float64,
    "polarity": np.int8,
    "snr_db": np.float64,
    "overlap": bool,
    "overlap_prev_id": np.int64,
    "overlap_next_id": np.int64,
    "clear_after": np.int64,
    "packet_id": np.int64,
    "hit_id": np.int64,
    "in_hit": bool,
    "valid": bool,
}


@dataclass(frozen=True)
class PacketBatch:
    """K packet windows of M samples, and what the detector knows about each.

    sample_rate_hz       (float) of the samples.
    start_index          (K,) int64 absolute sample index of each window's first sample
                         (stream index of the device; 0-based window index for
                         `analyze_window` unless given).
    samples              (K, 4, M) float64: the ORIGINAL input samples (volts), channel
                         order of ae_tactile.geometry; no filtering applied.
    onset_index          (K,) int64 onset within the window (AIC pick, ~half a sample).
                         For stream windows it is always the pre-trigger length.
    trigger_index        (K,) int64 threshold crossing within the window.
    noise_rms_v          (K,) float64 sqrt(mean_k var_k) of the pre-onset samples
                         (mean removed; full band as received).
    noise_rms_channel_v  (K, 4) float64 per-channel pre-onset noise RMS.
    saturated            (K,) bool any sample of the window at an ADC rail.
    saturated_channels   (K, 4) bool per channel.
    peak_amplitude_v     (K,) float64 max |x - pre-onset mean| within peak_window after onset.
    polarity             (K,) int8 sign of the largest |channel sum| within
                         polarity_window after the onset: +1 compression (touch),
                         -1 rarefaction (release), 0 if undetermined.
    snr_db               (K,) float64 10 log10(P_signal / sigma^2) over snr_window after the
                         onset (P_signal: mean power minus the noise variance; floored).
    overlap              (K,) bool another detected emission's window intersects this one
                         (|onset_i - onset_j| < M).
    overlap_prev_id      (K,) int64 packet_id of the latest earlier such emission, -1 if none.
    overlap_next_id      (K,) int64 packet_id of the earliest later one, -1 if none.
    clear_after          (K,) int64 samples from the onset to the next emission's onset
                         (capped at the post-trigger length): the part of the window after
                         the onset that holds no other emission's onset.
    packet_id            (K,) int64 per detector, increasing in detection order; ids of
                         emissions that were dropped (invalid input, cut by a gap) are
                         skipped, so overlap ids may name a packet that was not published.
    hit_id               (K,) int64 AE hit the emission belongs to (see docs/detection.md).
    in_hit               (K,) bool the emission started while an AE hit was in progress
                         (a re-trigger: an overlapping emission, or an echo).
    valid                (K,) bool False only for `analyze_window` windows that held
                         non-finite samples (their features are computed on zeros).
    """

    sample_rate_hz: float
    start_index: np.ndarray
    samples: np.ndarray
    onset_index: np.ndarray
    trigger_index: np.ndarray
    noise_rms_v: np.ndarray
    noise_rms_channel_v: np.ndarray
    saturated: np.ndarray
    saturated_channels: np.ndarray
    peak_amplitude_v: np.ndarray
    polarity: np.ndarray
    snr_db: np.ndarray
    overlap: np.ndarray
    overlap_prev_id: np.ndarray
    overlap_next_id: np.ndarray
    clear_after: np.ndarray
    packet_id: np.ndarray
    hit_id: np.ndarray
    in_hit: np.ndarray
    valid: np.ndarray

    def __len__(self) -> int:
        return int(self.start_index.shape[0])

    @property
    def n_samples(self) -> int:
        """Samples per channel M of the windows."""
        return int(self.samples.shape[2])

    @classmethod
    def empty(cls, sample_rate_hz: float, n_samples: int = 0) -> "PacketBatch":
        kw = {}
        for name, dt in _FIELD_DTYPES.items():
            if name == "samples":
                kw[name] = np.zeros((0, N_CHANNELS, int(n_samples)), dt)
            elif name in ("noise_rms_channel_v", "saturated_channels"):
                kw[name] = np.zeros((0, N_CHANNELS), dt)
            else:
                kw[name] = np.zeros(0, dt)
        return cls(sample_rate_hz=float(sample_rate_hz), **kw)

    @classmethod
    def concatenate(cls, batches, sample_rate_hz: float | None = None,
                    n_samples: int | None = None) -> "PacketBatch":
        """One batch from several with the same rate and window length (empty ones skipped)."""
        batches = [b for b in batches if b is not None]
        nonempty = [b for b in batches if len(b)]
        if sample_rate_hz is None:
            if not batches:
                raise ValueError("need sample_rate_hz to concatenate no batches")
            sample_rate_hz = batches[0].sample_rate_hz
        if not nonempty:
            m = n_samples if n_samples is not None else (batches[0].n_samples if batches else 0)
            return cls.empty(sample_rate_hz, m)
        if len(nonempty) == 1:
            return nonempty[0]
        m = {b.n_samples for b in nonempty}
        if len(m) != 1:
            raise ValueError(f"cannot concatenate windows of different lengths {sorted(m)}")
        kw = {name: np.concatenate([getattr(b, name) for b in nonempty], axis=0)
              for name in _FIELD_DTYPES}
        return cls(sample_rate_hz=float(sample_rate_hz), **kw)

    def select(self, index) -> "PacketBatch":
        """Sub-batch by boolean mask or integer index array."""
        kw = {name: getattr(self, name)[index] for name in _FIELD_DTYPES}
        return PacketBatch(sample_rate_hz=self.sample_rate_hz, **kw)

    def equals(self, other: "PacketBatch") -> bool:
        """Bit-exact equality of every field (used by the chunk-invariance tests)."""
        if self.sample_rate_hz != other.sample_rate_hz:
            return False
        for f in fields(self):
            if f.name == "sample_rate_hz":
                continue
            a, b = getattr(self, f.name), getattr(other, f.name)
            if a.shape != b.shape or a.dtype != b.dtype or a.tobytes() != b.tobytes():
                return False
        return True
