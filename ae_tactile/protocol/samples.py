# SPDX-License-Identifier: Apache-2.0
"""The two sample-block bodies: PACKET (one triggered window) and STREAM (continuous).

Bodies are immutable: their sample arrays are read-only int16 arrays (a private copy of
what the caller passed, or a view of the received frame bytes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import ClassVar

import numpy as np

from ..geometry import N_CHANNELS
from .fields import _arrays_equal, _Body, _int, _samples, _v_per_count
from .layout import (
    _PACKET,
    _SAMPLE_DTYPE,
    _STREAM,
    _U16,
    _U32,
    _U64,
    MAX_SAMPLES,
    NO_ONSET,
    PACKET_PREFIX_LEN,
    STREAM_PREFIX_LEN,
    FrameType,
)


class _SampleBlock(_Body):
    """What PACKET and STREAM bodies share: (4, N) int16 samples with a gain, equality by
    every dataclass field (arrays compared by shape and value)."""

    __hash__ = None  # type: ignore[assignment]  (holds an array)

    @property
    def n_samples(self) -> int:
        """Samples per channel N."""
        return self.samples.shape[1]

    def volts(self) -> np.ndarray:
        """Samples in volts at the sensor, float64 (4, N): samples * v_per_count."""
        return self.samples * self.v_per_count

    def __eq__(self, other) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return all(
            _arrays_equal(a, b) if isinstance(a, np.ndarray) else a == b
            for a, b in ((getattr(self, f.name), getattr(other, f.name)) for f in fields(self))
        )


@dataclass(frozen=True, eq=False)
class Packet(_SampleBlock):
    """Triggered acoustic-emission packet (frame type PACKET).

    Parameters
    ----------
    samples : array_like, shape (4, N)
        ADC counts (int16 range), channel-major, 1 <= N <= MAX_SAMPLES.
    sample_rate_hz : int
        ADC sample rate [Hz], u32 >= 1.
    v_per_count : float
        Input-referred volts per ADC count incl. the analog gain [V] (float32, > 0):
        volts = samples * v_per_count.
    first_sample_index : int
        Device sample counter of samples[:, 0] (u64; 0 at START), so
        t(sample j) = (first_sample_index + j) / sample_rate_hz after START.
    pre_trigger : int
        Samples before the trigger: the threshold crossing is at samples[:, pre_trigger]
        (0 <= pre_trigger < N).
    onset_index : int
        The device's onset estimate within the packet (< N), or NO_ONSET.
    saturation_mask : int
        Bit k set if channel k reached the ADC rail in this packet (0..15).

    Raises
    ------
    TypeError, ValueError
        A field of the wrong type or out of its range (the message names it).
    """

    samples: np.ndarray
    sample_rate_hz: int
    v_per_count: float
    first_sample_index: int = 0
    pre_trigger: int = 0
    onset_index: int = NO_ONSET
    saturation_mask: int = 0

    frame_type: ClassVar[FrameType] = FrameType.PACKET

    def __post_init__(self) -> None:
        s = _samples(self.samples)
        object.__setattr__(self, "samples", s)
        n = s.shape[1]
        object.__setattr__(
            self, "sample_rate_hz", _int("sample_rate_hz", self.sample_rate_hz, 1, _U32)
        )
        object.__setattr__(self, "v_per_count", _v_per_count(self.v_per_count))
        object.__setattr__(
            self,
            "first_sample_index",
            _int("first_sample_index", self.first_sample_index, 0, _U64),
        )
        object.__setattr__(self, "pre_trigger", _int("pre_trigger", self.pre_trigger, 0, n - 1))
        onset = _int("onset_index", self.onset_index, 0, _U16)
        if onset != NO_ONSET and onset >= n:
            raise ValueError(f"onset_index must be < N = {n} or NO_ONSET (0xFFFF), got {onset}")
        object.__setattr__(self, "onset_index", onset)
        object.__setattr__(
            self, "saturation_mask", _int("saturation_mask", self.saturation_mask, 0, 15)
        )

    def _pack(self) -> bytes:
        s = self.samples
        return (
            _PACKET.pack(
                self.sample_rate_hz,
                self.v_per_count,
                self.first_sample_index,
                s.shape[1],
                self.pre_trigger,
                self.onset_index,
                N_CHANNELS,
                self.saturation_mask,
            )
            + s.astype(_SAMPLE_DTYPE, copy=False).tobytes()
        )

    @classmethod
    def _unpack(cls, buf, off: int, length: int) -> "Packet":
        if length < PACKET_PREFIX_LEN:
            raise ValueError(
                f"PACKET payload of {length} bytes is shorter than its"
                f" {PACKET_PREFIX_LEN}-byte prefix"
            )
        sr, vpc, first, n, pre, onset, nch, sat = _PACKET.unpack_from(buf, off)
        samples = _unpack_samples("PACKET", buf, off, length, PACKET_PREFIX_LEN, n, nch)
        if (0 < sr and 0.0 < vpc < math.inf and pre < n and (onset < n or onset == NO_ONSET)
                and sat <= 15 and not samples.flags.writeable and samples.dtype == np.int16):
            # the usual frame: the wire's types and field widths hold every other bound, so
            # `__post_init__` would keep each field as it is; it runs (and raises) otherwise
            body = object.__new__(cls)
            body.__dict__.update(
                samples=samples, sample_rate_hz=sr, v_per_count=vpc, first_sample_index=first,
                pre_trigger=pre, onset_index=onset, saturation_mask=sat,
            )
            return body
        return cls(samples, sr, vpc, first, pre, onset, sat)


def _unpack_samples(
    kind: str, buf, off: int, length: int, prefix: int, n: int, nch: int
) -> np.ndarray:
    if nch != N_CHANNELS:
        raise ValueError(f"{kind} n_channels must be {N_CHANNELS}, got {nch}")
    if not 1 <= n <= MAX_SAMPLES:
        raise ValueError(f"{kind} n_samples must be in [1, {MAX_SAMPLES}], got {n}")
    if length != prefix + 2 * nch * n:
        raise ValueError(
            f"{kind} n_samples={n} x {nch} channels x 2 bytes = {2 * nch * n} sample"
            f" bytes, but the payload holds {length - prefix} after its prefix"
        )
    return np.frombuffer(buf, dtype=_SAMPLE_DTYPE, count=nch * n, offset=off + prefix).reshape(
        nch, n
    )


@dataclass(frozen=True, eq=False)
class StreamBlock(_SampleBlock):
    """Block of continuous samples (frame type STREAM).

    Parameters
    ----------
    samples : array_like, shape (4, N)
        ADC counts (int16 range), channel-major, 1 <= N <= MAX_SAMPLES.
    sample_rate_hz : int
        ADC sample rate [Hz], as in `Packet`.
    v_per_count : float
        Volts per ADC count [V], as in `Packet`.
    first_sample_index : int
        Device sample counter of samples[:, 0] (u64; 0 at START). The next block of an
        unbroken stream starts at first_sample_index + N, so the host can detect lost
        samples exactly and time every sample.
    saturation_mask : int
        Bit k set if channel k reached the ADC rail in this block (0..15).

    Raises
    ------
    TypeError, ValueError
        A field of the wrong type or out of its range.
    """

    samples: np.ndarray
    sample_rate_hz: int
    v_per_count: float
    first_sample_index: int = 0
    saturation_mask: int = 0

    frame_type: ClassVar[FrameType] = FrameType.STREAM

    def __post_init__(self) -> None:
        object.__setattr__(self, "samples", _samples(self.samples))
        object.__setattr__(
            self, "sample_rate_hz", _int("sample_rate_hz", self.sample_rate_hz, 1, _U32)
        )
        object.__setattr__(self, "v_per_count", _v_per_count(self.v_per_count))
        object.__setattr__(
            self,
            "first_sample_index",
            _int("first_sample_index", self.first_sample_index, 0, _U64),
        )
        object.__setattr__(
            self, "saturation_mask", _int("saturation_mask", self.saturation_mask, 0, 15)
        )

    @property
    def next_sample_index(self) -> int:
        """first_sample_index of the block that follows this one without a gap."""
        return self.first_sample_index + self.samples.shape[1]

    def _pack(self) -> bytes:
        s = self.samples
        return (
            _STREAM.pack(
                self.sample_rate_hz,
                self.v_per_count,
                self.first_sample_index,
                s.shape[1],
                N_CHANNELS,
                self.saturation_mask,
            )
            + s.astype(_SAMPLE_DTYPE, copy=False).tobytes()
        )

    @classmethod
    def _unpack(cls, buf, off: int, length: int) -> "StreamBlock":
        if length < STREAM_PREFIX_LEN:
            raise ValueError(
                f"STREAM payload of {length} bytes is shorter than its"
                f" {STREAM_PREFIX_LEN}-byte prefix"
            )
        sr, vpc, first, n, nch, sat = _STREAM.unpack_from(buf, off)
        samples = _unpack_samples("STREAM", buf, off, length, STREAM_PREFIX_LEN, n, nch)
        return cls(samples, sr, vpc, first, sat)
