# SPDX-License-Identifier: Apache-2.0
"""Decoded sample frames -> packet records stamped in host time.

A PACKET frame (triggered mode) is one record; STREAM blocks (stream mode) go through
the packet detector, which cuts windows out of the continuous samples. Device time
becomes host time through the link's clock mapping.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ae_tactile.protocol import NO_ONSET, Packet, StreamBlock
from ae_tactile.timesync import DeviceClockMapper

from .config import LinkConfig
from .frontend import packet_volts_noise_onset


@dataclass
class PacketRecord:
    """One packet ready to publish.

    Parameters
    ----------
    stamp_ns : int
        Host time of samples_v[:, 0] [ns].
    samples_v : numpy.ndarray, shape (4, N), float32
        The samples [V].
    sample_rate_hz : float
        Sample rate [Hz].
    onset_index : int
        Onset of the emission in the window [samples].
    sequence_id : int
        The link's running packet number.
    noise_rms_v : float
        Pre-trigger noise RMS [V].
    saturated : bool
        A channel reached the ADC rail.
    device_sample_index : int
        Device sample counter of samples_v[:, 0].
    """

    stamp_ns: int
    samples_v: np.ndarray
    sample_rate_hz: float
    onset_index: int
    sequence_id: int
    noise_rms_v: float
    saturated: bool
    device_sample_index: int


@dataclass
class PacketBatch:
    """The packets of one read cycle, with the running loss counters at that time.

    Parameters
    ----------
    receive_ns : int
        Host time the bytes were read [ns].
    packets : list of PacketRecord
        The packets, in arrival order.
    packets_dropped : int
        Packets lost so far (see `FingertipLink.packets_dropped`).
    frames_bad_crc : int
        Frames rejected for a wrong CRC so far.
    """

    receive_ns: int
    packets: list[PacketRecord]
    packets_dropped: int
    frames_bad_crc: int


class PacketBuilder:
    """Turns PACKET bodies and STREAM blocks into `PacketRecord`s (the link's reader thread).

    Parameters
    ----------
    config : LinkConfig
        Its ``adc_bits`` and ``detector`` settings are used in stream mode.
    mapper : DeviceClockMapper
        Device time -> host time.
    counters : dict
        The link's counters (``stream_gaps``, ``stream_samples_lost`` are counted here).
    emit : callable
        Called with the records the detector still held when a stream ends (a gap, a
        reconnect, a restart): they are handed on at once.
    """

    def __init__(
        self,
        config: LinkConfig,
        mapper: DeviceClockMapper,
        counters: dict,
        emit: Callable[[list[PacketRecord]], None],
    ):
        self.config = config
        self.mapper = mapper
        self.counters = counters
        self._emit = emit
        self._next_sequence_id = 0
        self._detector = None
        self._detector_key = None
        #: first_sample_index the next STREAM block should have (None: not known)
        self.stream_next_index: int | None = None
        #: (sample index, device ns, fs) of the last STREAM block: times the detector's
        #: windows
        self.stream_ref: tuple[int, int, float] | None = None

    def _next_id(self) -> int:
        sid = self._next_sequence_id
        self._next_sequence_id += 1
        return sid

    def packet(self, body: Packet, device_ns: int) -> PacketRecord:
        """The record of one PACKET whose first sample was taken at ``device_ns`` [ns]."""
        volts, noise, onset = packet_volts_noise_onset(
            body.samples, body.v_per_count, body.pre_trigger
        )
        if body.onset_index != NO_ONSET:
            onset = int(body.onset_index)
        return PacketRecord(
            stamp_ns=self.mapper.to_host_ns(device_ns),
            samples_v=volts,
            sample_rate_hz=float(body.sample_rate_hz),
            onset_index=onset,
            sequence_id=self._next_id(),
            noise_rms_v=noise,
            saturated=bool(body.saturation_mask),
            device_sample_index=int(body.first_sample_index),
        )

    def end_stream(self) -> None:
        """End the detector's stream (gap, reconnect, restart): complete windows it still
        holds are handed on, windows the gap cuts are dropped (counted by the detector)."""
        det, self._detector = self._detector, None
        if det is None or self.stream_ref is None:
            return
        records = self._records_from_batch(det.flush(), *self.stream_ref)
        if records:
            self._emit(records)

    def stream(self, body: StreamBlock, device_ns: int) -> list[PacketRecord]:
        """The records the detector completes with one STREAM block (first sample at
        ``device_ns`` [ns]); a gap in the sample counter is counted."""
        from ae_tactile.dsp import PacketDetector  # lazy: stream mode only; dsp loads scipy

        fs = float(body.sample_rate_hz)
        full_scale_v = float(body.v_per_count) * 2 ** (self.config.adc_bits - 1)
        if self._detector is None or self._detector_key != (fs, full_scale_v):
            self.end_stream()
            self._detector = PacketDetector(
                sample_rate_hz=fs,
                full_scale_v=full_scale_v,
                adc_bits=self.config.adc_bits,
                **self.config.detector,
            )
            self._detector_key = (fs, full_scale_v)
            self.stream_next_index = None
        first = int(body.first_sample_index)
        if self.stream_next_index is not None and first != self.stream_next_index:
            self.counters["stream_gaps"] += 1
            self.counters["stream_samples_lost"] += max(first - self.stream_next_index, 0)
        self.stream_next_index = body.next_sample_index
        self.stream_ref = (first, device_ns, fs)
        batch = self._detector.process(body.samples * np.float32(body.v_per_count), first)
        return self._records_from_batch(batch, first, device_ns, fs)

    def _records_from_batch(
        self, batch, ref_index: int, ref_device_ns: int, fs: float
    ) -> list[PacketRecord]:
        """PacketRecords of a detector batch; sample index -> device time through the
        reference (sample ref_index was taken at device time ref_device_ns)."""
        out = []
        for k in range(len(batch.start_index)):
            if not bool(batch.valid[k]):
                continue
            start = int(batch.start_index[k])
            start_ns = ref_device_ns + int(round((start - ref_index) * 1e9 / fs))
            out.append(
                PacketRecord(
                    stamp_ns=self.mapper.to_host_ns(start_ns),
                    samples_v=np.asarray(batch.samples[k], dtype=np.float32),
                    sample_rate_hz=fs,
                    onset_index=int(batch.onset_index[k]),
                    sequence_id=self._next_id(),
                    noise_rms_v=float(batch.noise_rms_v[k]),
                    saturated=bool(batch.saturated[k]),
                    device_sample_index=start,
                )
            )
        return out
