# SPDX-License-Identifier: Apache-2.0
"""Wire layout of protocol version 1: sizes, struct formats, enums, rejection reasons.

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
"""

from __future__ import annotations

import enum
import struct

import numpy as np

from ..geometry import N_CHANNELS

# ---------------------------------------------------------------- sizes and structs
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
