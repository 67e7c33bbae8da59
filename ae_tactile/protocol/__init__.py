# SPDX-License-Identifier: Apache-2.0
"""Serial protocol between the fingertip and the host (protocol version 1), pure Python.

Normative description: docs/protocol.md. This package never imports rclpy.

Sending::

    from ae_tactile.protocol import AcqMode, Command, FrameEncoder, Packet, encode_frame
    enc = FrameEncoder()                       # device side: seq 0, 1, ...; BOOT on the first
    wire = enc.encode(Packet(samples, 10_000_000, 0.5e-3 / 2048, first_sample_index=k,
                             pre_trigger=100), timestamp_us=t_us & 0xFFFFFFFF)
    wire = encode_frame(Command.start(AcqMode.TRIGGERED, command_id=7), seq=0, timestamp_us=0)

Receiving::

    dec = StreamDecoder()                      # accepts device -> host frames
    for frame in dec.feed(port.read(4096)):    # any chunking; frames in order
        if isinstance(frame.body, Packet): ...frame.body.samples  # (4, N) int16
    dec.stats(); dec.pop_events()              # counters, recent rejections with reasons

Modules, bottom up: `layout` (sizes, struct formats, enums, rejection reasons), `fields`
(the field checks and the bodies' base), `samples` (PACKET, STREAM) and `control`
(STATUS, COMMAND, ACK), `frames` (a whole frame: encoder and single-frame parser),
`unwrap` (sequence numbers and the device clock), `decoder` (the incremental byte-stream
decoder), `crc` and `hexdump` (helpers).
"""

from .control import Ack, Command, Status
from .crc import CRC32_CHECK, crc32, crc32_reference
from .decoder import COUNTER_NAMES, DecoderEvent, StreamDecoder
from .frames import BODY_TYPES, Body, Frame, FrameEncoder, decode_frame, encode_frame
from .hexdump import format_hex, parse_hex
from .layout import (
    CRC_LEN,
    FLAG_BOOT,
    FRAME_OVERHEAD,
    HEADER_LEN,
    MAX_FRAME_LEN,
    MAX_PAYLOAD_LEN,
    MAX_SAMPLES,
    MAX_SERIAL_LEN,
    MAX_THRESHOLD_COUNTS,
    NO_ONSET,
    PACKET_PREFIX_LEN,
    PROTOCOL_VERSION,
    STATUS_PREFIX_LEN,
    STREAM_PREFIX_LEN,
    SYNC,
    AckResult,
    AcqMode,
    DeviceState,
    Direction,
    ErrorBits,
    FrameType,
    Opcode,
    ProtocolError,
    Reason,
    direction_of,
)
from .samples import Packet, StreamBlock
from .unwrap import U32_MODULUS, SequenceTracker, SequenceUpdate, TimestampUnwrapper

__all__ = [
    "CRC32_CHECK",
    "crc32",
    "crc32_reference",
    "COUNTER_NAMES",
    "DecoderEvent",
    "StreamDecoder",
    "BODY_TYPES",
    "CRC_LEN",
    "FLAG_BOOT",
    "FRAME_OVERHEAD",
    "HEADER_LEN",
    "MAX_FRAME_LEN",
    "MAX_PAYLOAD_LEN",
    "MAX_SAMPLES",
    "MAX_SERIAL_LEN",
    "MAX_THRESHOLD_COUNTS",
    "NO_ONSET",
    "PACKET_PREFIX_LEN",
    "PROTOCOL_VERSION",
    "STATUS_PREFIX_LEN",
    "STREAM_PREFIX_LEN",
    "SYNC",
    "Ack",
    "AckResult",
    "AcqMode",
    "Body",
    "Command",
    "DeviceState",
    "Direction",
    "ErrorBits",
    "Frame",
    "FrameEncoder",
    "FrameType",
    "Opcode",
    "Packet",
    "ProtocolError",
    "Reason",
    "Status",
    "StreamBlock",
    "decode_frame",
    "direction_of",
    "encode_frame",
    "format_hex",
    "parse_hex",
    "U32_MODULUS",
    "SequenceTracker",
    "SequenceUpdate",
    "TimestampUnwrapper",
]
