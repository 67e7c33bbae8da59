# SPDX-License-Identifier: Apache-2.0
"""Frame layout, frame dataclasses, encoder and single-frame parser (protocol version 1).

Every frame, little-endian (docs/protocol.md is the normative description)::

    off  size  field
      0    4   sync          AE 7C 5A C3
      4    1   version       1
      5    1   frame_type    FrameType (bit 7 set = host -> device)
      6    1   flags         bit 0 BOOT (first frame after the sender reset); others 0
      7    1   reserved      0
      8    4   payload_len   u32, <= MAX_PAYLOAD_LEN
     12    4   seq           u32, per sender, +1 per frame, wraps
     16    4   timestamp_us  u32 sender clock in microseconds, wraps every 71.6 min
     20    4   header_crc    CRC-32 of bytes 0..19
     24    L   payload       per frame type
   24+L    4   frame_crc     CRC-32 of bytes 0..19 followed by the payload, i.e. the CRC
                             computation continued from header_crc over the payload

Sample blocks (PACKET, STREAM) are int16 ADC counts, 4 x N, channel-major in the
channel order of ``ae_tactile.geometry`` (k = 0..3 <-> (xi, eta) = (+1,+1),
(+1,-1), (-1,+1), (-1,-1)); volts at the sensor = counts * v_per_count.

Bodies are immutable: their sample arrays are read-only int16 arrays (a private copy of
what the caller passed, or a view of the received frame bytes).

Validation: constructing a frame body checks every field. Wrong Python types raise
TypeError; wrong shapes, dtypes and out-of-range values raise ValueError with the
field name and the allowed range. The decoder builds bodies through the same
checks, so whatever ``encode_frame`` refuses, the decoder rejects (and counts).
"""

from __future__ import annotations

import enum
import math
import struct
import zlib
from dataclasses import dataclass, field, fields
from typing import ClassVar, Union

import numpy as np

from ..geometry import N_CHANNELS

# ---------------------------------------------------------------- constants
PROTOCOL_VERSION = 1
SYNC = b"\xae\x7c\x5a\xc3"
HEADER_LEN = 24
CRC_LEN = 4
FRAME_OVERHEAD = HEADER_LEN + CRC_LEN
#: Largest number of samples per channel in one PACKET or STREAM block.
MAX_SAMPLES = 8192
PACKET_PREFIX_LEN = 24
STREAM_PREFIX_LEN = 20
STATUS_PREFIX_LEN = 36
#: Largest payload any v1 frame may carry (a PACKET of MAX_SAMPLES); longer = header error.
MAX_PAYLOAD_LEN = PACKET_PREFIX_LEN + 2 * N_CHANNELS * MAX_SAMPLES
MAX_FRAME_LEN = FRAME_OVERHEAD + MAX_PAYLOAD_LEN
#: flags bit 0: first frame the sender emits after it (re)started; that frame has seq 0.
FLAG_BOOT = 0x01
KNOWN_FLAGS = FLAG_BOOT
#: PACKET.onset_index value meaning "the device did not estimate an onset".
NO_ONSET = 0xFFFF
MAX_SERIAL_LEN = 32
MAX_THRESHOLD_COUNTS = 32767

_U8, _U16, _U32, _U64 = 0xFF, 0xFFFF, 0xFFFFFFFF, 0xFFFFFFFFFFFFFFFF

_HEADER = struct.Struct("<4sBBBBIII")  # bytes 0..19
_HEADER_FULL = struct.Struct("<4xBBBBIIII")  # bytes 0..23 (with header_crc)
_U32LE = struct.Struct("<I")
_F32 = struct.Struct("<f")
_PACKET = struct.Struct("<IfQHHHBB")  # 24 bytes
_STREAM = struct.Struct("<IfQHBB")  # 20 bytes
_STATUS = struct.Struct("<QIfHHHBBIIBBBB")  # 36 bytes
_COMMAND = struct.Struct("<HB")  # 3 bytes + arguments
_ACK = struct.Struct("<HBBI")  # 8 bytes
_SAMPLE_DTYPE = np.dtype("<i2")

assert _HEADER.size == HEADER_LEN - 4 and _HEADER_FULL.size == HEADER_LEN
assert _PACKET.size == PACKET_PREFIX_LEN and _STREAM.size == STREAM_PREFIX_LEN
assert _STATUS.size == STATUS_PREFIX_LEN


# ---------------------------------------------------------------- enums
class FrameType(enum.IntEnum):
    """Frame type byte. Bit 7 clear: device -> host; set: host -> device."""

    PACKET = 0x01  #: triggered acoustic-emission packet
    STREAM = 0x02  #: block of continuous samples
    STATUS = 0x03  #: status / heartbeat (>= 1 Hz in every state, and after GET_STATUS)
    ACK = 0x04  #: acknowledgement of one COMMAND
    COMMAND = 0x81  #: host -> device command


class Direction(enum.Enum):
    DEVICE_TO_HOST = "device_to_host"
    HOST_TO_DEVICE = "host_to_device"


def direction_of(frame_type: int) -> Direction:
    """Direction encoded in bit 7 of a frame-type byte (also for unknown types)."""
    return Direction.HOST_TO_DEVICE if frame_type & 0x80 else Direction.DEVICE_TO_HOST


class AcqMode(enum.IntEnum):
    """Acquisition mode requested by START."""

    TRIGGERED = 1  #: emit a PACKET per threshold crossing
    STREAM = 2  #: emit continuous STREAM blocks


class DeviceState(enum.IntEnum):
    IDLE = 0
    TRIGGERED = 1  #: running, triggered mode
    STREAMING = 2  #: running, stream mode
    ERROR = 3  #: stopped by a fault, see STATUS.error_bits


class Opcode(enum.IntEnum):
    """COMMAND opcodes; arguments in docs/protocol.md, "COMMAND"."""

    START = 1  #: args: mode u8 (AcqMode); resets the sample counter to 0
    STOP = 2  #: no args
    GET_STATUS = 3  #: no args; the device answers ACK then a STATUS frame
    SET_THRESHOLD = 4  #: args: threshold_counts u16 (1..32767)
    SET_SAMPLE_RATE = 5  #: args: sample_rate_hz u32 (>= 1); only while IDLE
    SET_PACKET_LENGTH = 6  #: args: n_samples u16 (1..MAX_SAMPLES), pre_trigger u16 (< n)


class AckResult(enum.IntEnum):
    OK = 0
    UNKNOWN_OPCODE = 1
    BAD_ARGUMENT = 2  #: argument out of the device's range
    BAD_STATE = 3  #: not allowed in the current state (e.g. SET_SAMPLE_RATE while running)
    MALFORMED = 4  #: payload length does not match the opcode
    BUSY = 5
    INTERNAL_ERROR = 6


class ErrorBits(enum.IntFlag):
    """STATUS.error_bits; bits 16..31 are firmware-specific."""

    ADC_OVERRUN = 1 << 0  #: samples lost inside the device
    TX_OVERFLOW = 1 << 1  #: frames dropped by the device (see device_dropped)
    CLOCK_FAULT = 1 << 2
    ANALOG_FAULT = 1 << 3
    CONFIG_DEFAULTS = 1 << 4  #: stored configuration invalid, defaults in use


_OPCODE_ARGS: dict[Opcode, tuple[str, ...]] = {
    Opcode.START: ("mode",),
    Opcode.STOP: (),
    Opcode.GET_STATUS: (),
    Opcode.SET_THRESHOLD: ("threshold_counts",),
    Opcode.SET_SAMPLE_RATE: ("sample_rate_hz",),
    Opcode.SET_PACKET_LENGTH: ("n_samples", "pre_trigger"),
}
_OPCODE_ARG_STRUCT: dict[Opcode, struct.Struct] = {
    Opcode.START: struct.Struct("<B"),
    Opcode.STOP: struct.Struct("<"),
    Opcode.GET_STATUS: struct.Struct("<"),
    Opcode.SET_THRESHOLD: struct.Struct("<H"),
    Opcode.SET_SAMPLE_RATE: struct.Struct("<I"),
    Opcode.SET_PACKET_LENGTH: struct.Struct("<HH"),
}
_ALL_COMMAND_ARGS = ("mode", "threshold_counts", "sample_rate_hz", "n_samples", "pre_trigger")


# ---------------------------------------------------------------- errors
class Reason(str, enum.Enum):
    """Why the decoder rejected bytes, or what else it noticed (DecoderEvent.reason)."""

    HEADER_CRC = "header_crc"  #: sync found, header CRC wrong
    BAD_VERSION = "bad_version"  #: header CRC ok, unsupported version
    BAD_HEADER = "bad_header"  #: unknown flag bits / reserved byte not 0
    LENGTH_TOO_LARGE = "length_too_large"  #: payload_len > MAX_PAYLOAD_LEN
    FRAME_CRC = "frame_crc"  #: header ok, frame CRC wrong
    TRUNCATED = "truncated"  #: frame cut short (by a valid frame or the end)
    BAD_PAYLOAD = "bad_payload"  #: CRC ok, payload violates its layout
    UNKNOWN_FRAME_TYPE = "unknown_frame_type"  #: CRC ok, type not known to this version
    WRONG_DIRECTION = "wrong_direction"  #: CRC ok, frame of the other direction
    DUPLICATE = "duplicate"  #: CRC ok, same frame received again (dropped)
    SEQUENCE_GAP = "sequence_gap"  #: frames missing (not a rejection)
    SENDER_RESTART = "sender_restart"  #: sender reset (not a rejection)
    TIMESTAMP_BACKSTEP = "timestamp_backstep"  #: device clock went back (not a rejection)


class ProtocolError(ValueError):
    """A byte string is not a valid frame; ``reason`` says which check failed."""

    def __init__(self, reason: Reason, detail: str) -> None:
        super().__init__(f"{reason.value}: {detail}")
        self.reason = reason
        self.detail = detail


# ---------------------------------------------------------------- validation helpers
def _int(name: str, value, lo: int, hi: int) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an integer, got {type(value).__name__} {value!r}")
    v = int(value)
    if not lo <= v <= hi:
        raise ValueError(f"{name} must be in [{lo}, {hi}], got {v}")
    return v


def _enum(name: str, cls, value):
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be a {cls.__name__}, got {type(value).__name__} {value!r}")
    try:
        return cls(int(value))
    except ValueError:
        allowed = ", ".join(f"{m.name}={m.value}" for m in cls)
        raise ValueError(f"{name} must be one of {allowed}; got {int(value)}") from None


def _v_per_count(value) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(
        value, (int, float, np.integer, np.floating)
    ):
        raise TypeError(f"v_per_count must be a real number, got {type(value).__name__} {value!r}")
    v = float(value)
    try:
        (f32,) = _F32.unpack(_F32.pack(v))  # the value the wire carries
    except OverflowError:
        f32 = math.inf
    if not (math.isfinite(f32) and f32 > 0.0):
        raise ValueError(
            f"v_per_count (volts per ADC count, float32) must be finite and > 0, got {v!r}"
        )
    return f32


def _samples(value) -> np.ndarray:
    try:
        a = np.asarray(value)
    except (ValueError, TypeError) as exc:
        raise ValueError(f"samples must be a (4, N) integer array: {exc}") from None
    if a.ndim != 2 or a.shape[0] != N_CHANNELS:
        raise ValueError(
            f"samples must have shape ({N_CHANNELS}, N), channel-major in the"
            f" channel order of ae_tactile.geometry; got shape {a.shape}"
        )
    n = a.shape[1]
    if not 1 <= n <= MAX_SAMPLES:
        raise ValueError(f"samples per channel N must be in [1, {MAX_SAMPLES}], got {n}")
    if a.dtype == np.int16 and not a.flags.writeable:
        return a  # e.g. decoded: a read-only view of immutable frame bytes
    if a.dtype.kind not in "iu":
        raise ValueError(
            f"samples must have an integer dtype (int16 ADC counts), got {a.dtype};"
            " convert explicitly (e.g. np.rint(x).astype(np.int16))"
        )
    if a.dtype.itemsize > 2 or (a.dtype.kind == "u" and a.dtype.itemsize == 2):
        lo, hi = int(a.min()), int(a.max())
        if lo < -32768 or hi > 32767:
            raise ValueError(f"samples must fit in int16 [-32768, 32767], got range [{lo}, {hi}]")
    a = a.astype(np.int16)  # always a private copy, so the frozen body stays frozen
    a.flags.writeable = False
    return a


def _arrays_equal(a, b) -> bool:
    return a.shape == b.shape and bool(np.array_equal(a, b))


class _Body:
    """Common base of the frame bodies (payload dataclasses)."""

    frame_type: ClassVar[FrameType]

    def _pack(self) -> bytes:  # pragma: no cover - every subclass overrides
        raise NotImplementedError

    @classmethod
    def _unpack(cls, buf, off: int, length: int):  # pragma: no cover
        raise NotImplementedError


# ---------------------------------------------------------------- sample blocks
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

    samples:            (4, N) int16 ADC counts, channel-major, 1 <= N <= MAX_SAMPLES.
    sample_rate_hz:     ADC sample rate (Hz), u32 >= 1.
    v_per_count:        input-referred volts per ADC count incl. the analog gain
                        (float32, > 0): volts = samples * v_per_count.
    first_sample_index: device sample counter of samples[:, 0] (u64; 0 at START), so
                        t(sample j) = (first_sample_index + j) / sample_rate_hz after START.
    pre_trigger:        samples before the trigger: the threshold crossing is at
                        samples[:, pre_trigger] (0 <= pre_trigger < N).
    onset_index:        device's onset estimate within the packet (< N), or NO_ONSET.
    saturation_mask:    bit k set if channel k reached the ADC rail in this packet (0..15).
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

    samples:            (4, N) int16 ADC counts, channel-major, 1 <= N <= MAX_SAMPLES.
    sample_rate_hz, v_per_count: as in Packet.
    first_sample_index: device sample counter of samples[:, 0] (u64; 0 at START). The next
                        block of an unbroken stream starts at first_sample_index + N, so
                        the host can detect lost samples exactly and time every sample.
    saturation_mask:    bit k set if channel k reached the ADC rail in this block.
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


# ---------------------------------------------------------------- status
@dataclass(frozen=True)
class Status(_Body):
    """Status / heartbeat (frame type STATUS), sent >= 1 Hz in every state.

    uptime_us:        full 64-bit device clock, us since boot (its low 32 bits equal the
                      header timestamp_us of this frame).
    state:            DeviceState.
    sample_rate_hz, v_per_count: current acquisition settings.
    threshold_counts: trigger threshold |x| >= threshold (ADC counts, 1..32767).
    packet_samples, pre_trigger: PACKET length N and pre-trigger length in effect.
    error_bits:       ErrorBits (bits 16..31 firmware-specific).
    device_dropped:   frames the device discarded since boot because its transmit queue
                      was full (u32). They also show as sequence gaps on the host.
    firmware_version: (major, minor, patch), each 0..255.
    serial_number:    1..32 printable ASCII characters (0x20..0x7E): tells fingertips apart.
    """

    uptime_us: int
    state: DeviceState
    sample_rate_hz: int
    v_per_count: float
    threshold_counts: int
    packet_samples: int
    pre_trigger: int
    error_bits: int
    device_dropped: int
    firmware_version: tuple[int, int, int]
    serial_number: str

    frame_type: ClassVar[FrameType] = FrameType.STATUS

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "uptime_us", _int("uptime_us", self.uptime_us, 0, _U64))
        set_(self, "state", _enum("state", DeviceState, self.state))
        set_(self, "sample_rate_hz", _int("sample_rate_hz", self.sample_rate_hz, 1, _U32))
        set_(self, "v_per_count", _v_per_count(self.v_per_count))
        set_(
            self,
            "threshold_counts",
            _int("threshold_counts", self.threshold_counts, 1, MAX_THRESHOLD_COUNTS),
        )
        n = _int("packet_samples", self.packet_samples, 1, MAX_SAMPLES)
        set_(self, "packet_samples", n)
        set_(self, "pre_trigger", _int("pre_trigger", self.pre_trigger, 0, n - 1))
        set_(self, "error_bits", ErrorBits(_int("error_bits", self.error_bits, 0, _U32)))
        set_(self, "device_dropped", _int("device_dropped", self.device_dropped, 0, _U32))
        fw = self.firmware_version
        if not isinstance(fw, (tuple, list)) or len(fw) != 3:
            raise TypeError(f"firmware_version must be a (major, minor, patch) tuple, got {fw!r}")
        set_(
            self,
            "firmware_version",
            tuple(_int(f"firmware_version[{i}]", v, 0, _U8) for i, v in enumerate(fw)),
        )
        sn = self.serial_number
        if not isinstance(sn, str):
            raise TypeError(f"serial_number must be a str, got {type(sn).__name__}")
        if not 1 <= len(sn) <= MAX_SERIAL_LEN or not all(" " <= ch <= "~" for ch in sn):
            raise ValueError(
                f"serial_number must be 1..{MAX_SERIAL_LEN} printable ASCII characters"
                f" (0x20..0x7E), got {sn!r}"
            )

    def _pack(self) -> bytes:
        sn = self.serial_number.encode("ascii")
        return (
            _STATUS.pack(
                self.uptime_us,
                self.sample_rate_hz,
                self.v_per_count,
                self.threshold_counts,
                self.packet_samples,
                self.pre_trigger,
                self.state,
                N_CHANNELS,
                self.error_bits,
                self.device_dropped,
                *self.firmware_version,
                len(sn),
            )
            + sn
        )

    @classmethod
    def _unpack(cls, buf, off: int, length: int) -> "Status":
        if length < STATUS_PREFIX_LEN:
            raise ValueError(
                f"STATUS payload of {length} bytes is shorter than its"
                f" {STATUS_PREFIX_LEN}-byte prefix"
            )
        (
            up,
            sr,
            vpc,
            thr,
            n,
            pre,
            state,
            nch,
            err,
            dropped,
            fw_major,
            fw_minor,
            fw_patch,
            sn_len,
        ) = _STATUS.unpack_from(buf, off)
        if nch != N_CHANNELS:
            raise ValueError(f"STATUS n_channels must be {N_CHANNELS}, got {nch}")
        if length != STATUS_PREFIX_LEN + sn_len:
            raise ValueError(
                f"STATUS serial_len={sn_len} but the payload holds"
                f" {length - STATUS_PREFIX_LEN} bytes after its prefix"
            )
        start = off + STATUS_PREFIX_LEN
        raw = bytes(buf[start : start + sn_len])
        try:
            sn = raw.decode("ascii")
        except UnicodeDecodeError:
            raise ValueError(f"STATUS serial_number is not ASCII: {raw!r}") from None
        return cls(
            up, state, sr, vpc, thr, n, pre, err, dropped, (fw_major, fw_minor, fw_patch), sn
        )


# ---------------------------------------------------------------- commands
@dataclass(frozen=True)
class Command(_Body):
    """Host -> device command (frame type COMMAND); the device answers one ACK.

    command_id: u16 chosen by the host, echoed in the ACK (the host increments it).
    opcode:     Opcode; exactly the arguments of that opcode are given, others None:
                START: mode; SET_THRESHOLD: threshold_counts (1..32767);
                SET_SAMPLE_RATE: sample_rate_hz (>= 1);
                SET_PACKET_LENGTH: n_samples (1..MAX_SAMPLES), pre_trigger (< n_samples).
    Prefer the constructors ``Command.start(...)``, ``Command.stop(...)``, ...
    """

    opcode: Opcode
    command_id: int = 0
    mode: AcqMode | None = None
    threshold_counts: int | None = None
    sample_rate_hz: int | None = None
    n_samples: int | None = None
    pre_trigger: int | None = None

    frame_type: ClassVar[FrameType] = FrameType.COMMAND

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        op = _enum("opcode", Opcode, self.opcode)
        set_(self, "opcode", op)
        set_(self, "command_id", _int("command_id", self.command_id, 0, _U16))
        needed = _OPCODE_ARGS[op]
        for name in _ALL_COMMAND_ARGS:
            given = getattr(self, name) is not None
            if given and name not in needed:
                raise ValueError(
                    f"{op.name} takes no argument {name!r}"
                    f" (its arguments: {', '.join(needed) or 'none'})"
                )
            if not given and name in needed:
                raise ValueError(f"{op.name} requires argument {name!r}")
        if op is Opcode.START:
            set_(self, "mode", _enum("mode", AcqMode, self.mode))
        elif op is Opcode.SET_THRESHOLD:
            set_(
                self,
                "threshold_counts",
                _int("threshold_counts", self.threshold_counts, 1, MAX_THRESHOLD_COUNTS),
            )
        elif op is Opcode.SET_SAMPLE_RATE:
            set_(self, "sample_rate_hz", _int("sample_rate_hz", self.sample_rate_hz, 1, _U32))
        elif op is Opcode.SET_PACKET_LENGTH:
            n = _int("n_samples", self.n_samples, 1, MAX_SAMPLES)
            set_(self, "n_samples", n)
            set_(self, "pre_trigger", _int("pre_trigger", self.pre_trigger, 0, n - 1))

    @classmethod
    def start(cls, mode: AcqMode, command_id: int = 0) -> "Command":
        return cls(Opcode.START, command_id, mode=mode)

    @classmethod
    def stop(cls, command_id: int = 0) -> "Command":
        return cls(Opcode.STOP, command_id)

    @classmethod
    def get_status(cls, command_id: int = 0) -> "Command":
        return cls(Opcode.GET_STATUS, command_id)

    @classmethod
    def set_threshold(cls, threshold_counts: int, command_id: int = 0) -> "Command":
        return cls(Opcode.SET_THRESHOLD, command_id, threshold_counts=threshold_counts)

    @classmethod
    def set_sample_rate(cls, sample_rate_hz: int, command_id: int = 0) -> "Command":
        return cls(Opcode.SET_SAMPLE_RATE, command_id, sample_rate_hz=sample_rate_hz)

    @classmethod
    def set_packet_length(cls, n_samples: int, pre_trigger: int, command_id: int = 0) -> "Command":
        return cls(
            Opcode.SET_PACKET_LENGTH, command_id, n_samples=n_samples, pre_trigger=pre_trigger
        )

    @property
    def args(self) -> tuple[int, ...]:
        """The opcode's arguments in wire order."""
        return tuple(int(getattr(self, name)) for name in _OPCODE_ARGS[self.opcode])

    def _pack(self) -> bytes:
        return _COMMAND.pack(self.command_id, self.opcode) + _OPCODE_ARG_STRUCT[self.opcode].pack(
            *self.args
        )

    @classmethod
    def _unpack(cls, buf, off: int, length: int) -> "Command":
        if length < _COMMAND.size:
            raise ValueError(f"COMMAND payload of {length} bytes is shorter than 3")
        cid, op = _COMMAND.unpack_from(buf, off)
        try:
            opcode = Opcode(op)
        except ValueError:
            raise ValueError(f"COMMAND {cid}: unknown opcode {op}") from None
        st = _OPCODE_ARG_STRUCT[opcode]
        if length != _COMMAND.size + st.size:
            raise ValueError(
                f"COMMAND {cid} {opcode.name}: payload must be {_COMMAND.size + st.size}"
                f" bytes, got {length}"
            )
        values = st.unpack_from(buf, off + _COMMAND.size)
        return cls(opcode, cid, **dict(zip(_OPCODE_ARGS[opcode], values)))


@dataclass(frozen=True)
class Ack(_Body):
    """Device's answer to one COMMAND (frame type ACK).

    command_id: echo of Command.command_id.
    opcode:     echo of the opcode byte (an Opcode, or the raw int for UNKNOWN_OPCODE).
    result:     AckResult.
    value:      u32, the setting in effect after the command: START -> mode,
                SET_THRESHOLD -> threshold_counts, SET_SAMPLE_RATE -> sample_rate_hz
                actually used (the device may round to a rate it supports),
                SET_PACKET_LENGTH -> n_samples | pre_trigger << 16; STOP, GET_STATUS -> 0.
    """

    command_id: int
    opcode: int
    result: AckResult = AckResult.OK
    value: int = 0

    frame_type: ClassVar[FrameType] = FrameType.ACK

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "command_id", _int("command_id", self.command_id, 0, _U16))
        op = _int("opcode", self.opcode, 0, _U8)
        set_(self, "opcode", Opcode(op) if op in Opcode._value2member_map_ else op)
        set_(self, "result", _enum("result", AckResult, self.result))
        set_(self, "value", _int("value", self.value, 0, _U32))

    @property
    def ok(self) -> bool:
        return self.result is AckResult.OK

    def _pack(self) -> bytes:
        return _ACK.pack(self.command_id, self.opcode, self.result, self.value)

    @classmethod
    def _unpack(cls, buf, off: int, length: int) -> "Ack":
        if length != _ACK.size:
            raise ValueError(f"ACK payload must be {_ACK.size} bytes, got {length}")
        return cls(*_ACK.unpack_from(buf, off))


Body = Union[Packet, StreamBlock, Status, Command, Ack]
BODY_TYPES: dict[FrameType, type] = {
    cls.frame_type: cls for cls in (Packet, StreamBlock, Status, Command, Ack)
}
_BODY_BY_TYPE_INT: dict[int, type] = {int(k): v for k, v in BODY_TYPES.items()}


# ---------------------------------------------------------------- frame
@dataclass(frozen=True)
class Frame:
    """One frame: header fields + body. Equality ignores the receive-side metadata.

    seq:          sender's u32 sequence number.
    timestamp_us: sender's u32 microsecond clock (wraps every 2^32 us = 71.6 min). For
                  PACKET/STREAM it is latched at samples[:, 0]; otherwise at frame creation.
    flags:        FLAG_BOOT or 0.

    Set by StreamDecoder (defaults when built by hand):
    device_time_us: timestamp_us unwrapped to a monotonic int for this sender session
                    (see TimestampUnwrapper); resets when ``restart`` is True.
    dropped_before: frames lost (sequence gap) immediately before this one.
    restart:        this frame is the first one seen of a new sender session.
    stream_offset:  byte offset of the frame's sync word in the decoder's input.
    """

    body: Body
    seq: int
    timestamp_us: int
    flags: int = 0
    device_time_us: int | None = field(default=None, compare=False)
    dropped_before: int = field(default=0, compare=False)
    restart: bool = field(default=False, compare=False)
    stream_offset: int | None = field(default=None, compare=False)

    @property
    def frame_type(self) -> FrameType:
        return self.body.frame_type

    @property
    def boot(self) -> bool:
        return bool(self.flags & FLAG_BOOT)

    def encode(self) -> bytes:
        return encode_frame(
            self.body, seq=self.seq, timestamp_us=self.timestamp_us, flags=self.flags
        )


def encode_frame(body: Body, seq: int, timestamp_us: int, flags: int = 0) -> bytes:
    """Complete wire bytes of one frame: header, payload of ``body``, CRC-32.

    body:         Packet, StreamBlock, Status, Command or Ack (validated on construction).
    seq:          u32 sequence number; timestamp_us: u32 clock reading (take it modulo
                  2**32 yourself: out-of-range values raise ValueError, they are not wrapped).
    flags:        0 or FLAG_BOOT.
    """
    if not isinstance(body, _Body) or type(body) not in BODY_TYPES.values():
        raise TypeError(
            f"body must be one of Packet, StreamBlock, Status, Command, Ack;"
            f" got {type(body).__name__}"
        )
    seq = _int("seq", seq, 0, _U32)
    timestamp_us = _int("timestamp_us", timestamp_us, 0, _U32)
    flags = _int("flags", flags, 0, _U8)
    if flags & ~KNOWN_FLAGS:
        raise ValueError(
            f"flags may only contain FLAG_BOOT (0x01) in protocol v{PROTOCOL_VERSION},"
            f" got 0x{flags:02x}"
        )
    payload = body._pack()
    head = _HEADER.pack(
        SYNC, PROTOCOL_VERSION, body.frame_type, flags, 0, len(payload), seq, timestamp_us
    )
    hcrc = zlib.crc32(head)
    return b"".join((head, _U32LE.pack(hcrc), payload, _U32LE.pack(zlib.crc32(payload, hcrc))))


class FrameEncoder:
    """Sender side with its own sequence counter (for firmware simulators and the host).

    ``encode(body, timestamp_us)`` numbers frames ``first_seq, first_seq + 1, ...``
    modulo 2^32 and sets FLAG_BOOT on the first frame when ``boot`` is True (a freshly
    started sender; the protocol then expects first_seq == 0).
    """

    def __init__(self, first_seq: int = 0, boot: bool = True) -> None:
        self.next_seq = _int("first_seq", first_seq, 0, _U32)
        self._boot_pending = bool(boot)

    def encode(self, body: Body, timestamp_us: int) -> bytes:
        data = encode_frame(
            body, self.next_seq, timestamp_us, FLAG_BOOT if self._boot_pending else 0
        )
        self._boot_pending = False
        self.next_seq = (self.next_seq + 1) & _U32
        return data

    def skip(self, n: int = 1) -> None:
        """Consume n sequence numbers without sending (models frames dropped in the sender)."""
        self.next_seq = (self.next_seq + _int("n", n, 0, _U32)) & _U32


# ---------------------------------------------------------------- single-frame parsing
class Header:
    """Parsed, validated header fields (internal helper shared with the decoder)."""

    __slots__ = ("frame_type", "flags", "payload_len", "seq", "timestamp_us", "header_crc")

    def __init__(
        self,
        frame_type: int,
        flags: int,
        payload_len: int,
        seq: int,
        timestamp_us: int,
        header_crc: int,
    ):
        self.header_crc = header_crc
        self.frame_type = frame_type
        self.flags = flags
        self.payload_len = payload_len
        self.seq = seq
        self.timestamp_us = timestamp_us


def parse_header(buf, pos: int = 0) -> Header:
    """Check the 24 header bytes at ``buf[pos:]`` (sync already located). Raises ProtocolError."""
    version, ftype, flags, reserved, length, seq, ts, hcrc = _HEADER_FULL.unpack_from(buf, pos)
    with memoryview(buf) as mv:
        crc = zlib.crc32(mv[pos : pos + HEADER_LEN - 4])
    if crc != hcrc:
        raise ProtocolError(Reason.HEADER_CRC, f"header CRC 0x{hcrc:08x} != computed 0x{crc:08x}")
    if version != PROTOCOL_VERSION:
        raise ProtocolError(
            Reason.BAD_VERSION,
            f"protocol version {version}, this decoder speaks {PROTOCOL_VERSION}",
        )
    if flags & ~KNOWN_FLAGS or reserved:
        raise ProtocolError(
            Reason.BAD_HEADER,
            f"unknown flag bits 0x{flags & ~KNOWN_FLAGS:02x} / reserved byte 0x{reserved:02x}",
        )
    if length > MAX_PAYLOAD_LEN:
        raise ProtocolError(
            Reason.LENGTH_TOO_LARGE, f"payload_len {length} > MAX_PAYLOAD_LEN {MAX_PAYLOAD_LEN}"
        )
    return Header(ftype, flags, length, seq, ts, hcrc)


def parse_body(frame_type: int, buf, off: int, length: int) -> Body:
    """Body of a CRC-checked frame from ``buf[off:off+length]``. Raises ProtocolError.

    Sample arrays are read-only int16 views into ``buf`` when ``buf`` is bytes.
    """
    cls = _BODY_BY_TYPE_INT.get(frame_type)
    if cls is None:
        raise ProtocolError(Reason.UNKNOWN_FRAME_TYPE, f"frame type 0x{frame_type:02x}")
    try:
        return cls._unpack(buf, off, length)
    except (ValueError, TypeError) as exc:
        raise ProtocolError(Reason.BAD_PAYLOAD, f"{cls.frame_type.name}: {exc}") from None


def decode_frame(data) -> Frame:
    """Parse exactly one complete frame (bytes-like). Raises ProtocolError on any defect.

    For byte streams use StreamDecoder; this is for single, already delimited frames.
    """
    data = bytes(data)
    if len(data) < FRAME_OVERHEAD:
        raise ProtocolError(
            Reason.TRUNCATED, f"{len(data)} bytes, a frame has at least {FRAME_OVERHEAD}"
        )
    if data[:4] != SYNC:
        raise ProtocolError(
            Reason.BAD_HEADER, f"does not start with the sync word {SYNC.hex(' ')}"
        )
    h = parse_header(data, 0)
    end = HEADER_LEN + h.payload_len + CRC_LEN
    if len(data) != end:
        raise ProtocolError(
            Reason.TRUNCATED if len(data) < end else Reason.BAD_HEADER,
            f"header says the frame has {end} bytes, got {len(data)}",
        )
    (fcrc,) = _U32LE.unpack_from(data, end - CRC_LEN)
    crc = zlib.crc32(memoryview(data)[HEADER_LEN : end - CRC_LEN], h.header_crc)
    if crc != fcrc:
        raise ProtocolError(Reason.FRAME_CRC, f"frame CRC 0x{fcrc:08x} != computed 0x{crc:08x}")
    body = parse_body(h.frame_type, data, HEADER_LEN, h.payload_len)
    return Frame(body, h.seq, h.timestamp_us, h.flags)
