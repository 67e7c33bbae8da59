# SPDX-License-Identifier: Apache-2.0
"""A whole frame: header fields + body; the encoder and the single-frame parser.

The frame layout, the enums and the rejection reasons are in `layout`; the bodies in
`samples` (PACKET, STREAM) and `control` (STATUS, COMMAND, ACK). This module also
re-exports them, so ``from ae_tactile.protocol.frames import Opcode`` keeps working.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field
from typing import Union

from .control import Ack, Command, Status
from .fields import _Body, _int
from .layout import (
    _HEADER,
    _HEADER_FULL,
    _U8,
    _U32,
    _U32LE,
    CRC_LEN,
    FLAG_BOOT,
    FRAME_OVERHEAD,
    HEADER_LEN,
    KNOWN_FLAGS,
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

__all__ = [
    "BODY_TYPES",
    "CRC_LEN",
    "FLAG_BOOT",
    "FRAME_OVERHEAD",
    "HEADER_LEN",
    "KNOWN_FLAGS",
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
    "Header",
    "Opcode",
    "Packet",
    "ProtocolError",
    "Reason",
    "Status",
    "StreamBlock",
    "decode_frame",
    "direction_of",
    "encode_frame",
    "parse_body",
    "parse_header",
]

Body = Union[Packet, StreamBlock, Status, Command, Ack]
BODY_TYPES: dict[FrameType, type] = {
    cls.frame_type: cls for cls in (Packet, StreamBlock, Status, Command, Ack)
}
_BODY_BY_TYPE_INT: dict[int, type] = {int(k): v for k, v in BODY_TYPES.items()}


# ---------------------------------------------------------------- frame
@dataclass(frozen=True)
class Frame:
    """One frame: header fields + body. Equality ignores the receive-side metadata.

    Parameters
    ----------
    body : Packet, StreamBlock, Status, Command or Ack
        The payload.
    seq : int
        The sender's u32 sequence number.
    timestamp_us : int
        The sender's u32 clock [us] (wraps every 2^32 us = 71.6 min). For PACKET/STREAM
        it is latched at samples[:, 0]; otherwise at frame creation.
    flags : int
        FLAG_BOOT or 0.
    device_time_us : int or None
        Set by StreamDecoder: timestamp_us unwrapped to a monotonic int [us] for this
        sender session (see TimestampUnwrapper); resets when ``restart`` is True.
    dropped_before : int
        Set by StreamDecoder: frames lost (sequence gap) immediately before this one.
    restart : bool
        Set by StreamDecoder: this frame is the first one seen of a new sender session.
    stream_offset : int or None
        Set by StreamDecoder: byte offset of the frame's sync word in its input.
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

    Parameters
    ----------
    body : Packet, StreamBlock, Status, Command or Ack
        The payload (validated when it was constructed).
    seq : int
        u32 sequence number.
    timestamp_us : int
        u32 clock reading [us]; take it modulo 2**32 yourself: out-of-range values raise
        ValueError, they are not wrapped.
    flags : int
        0 or FLAG_BOOT.

    Returns
    -------
    bytes
        HEADER_LEN + payload + CRC_LEN bytes.

    Raises
    ------
    TypeError, ValueError
        Not a frame body, or a header field out of range.
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
    modulo 2^32 and sets FLAG_BOOT on the first frame when ``boot`` is True.

    Parameters
    ----------
    first_seq : int
        Sequence number of the first frame (u32).
    boot : bool
        A freshly started sender: FLAG_BOOT on its first frame (the protocol then expects
        first_seq == 0).
    """

    def __init__(self, first_seq: int = 0, boot: bool = True) -> None:
        self.next_seq = _int("first_seq", first_seq, 0, _U32)
        self._boot_pending = bool(boot)

    def encode(self, body: Body, timestamp_us: int) -> bytes:
        """The wire bytes of the next frame (see `encode_frame`).

        Parameters
        ----------
        body : Packet, StreamBlock, Status, Command or Ack
            The payload.
        timestamp_us : int
            u32 sender clock reading [us].

        Returns
        -------
        bytes
            The frame, numbered with the next sequence number.
        """
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
    """Check the 24 header bytes at ``buf[pos:]`` (sync already located).

    Parameters
    ----------
    buf : bytes-like
        The input.
    pos : int
        Offset of the sync word in ``buf``.

    Returns
    -------
    Header
        The header's fields.

    Raises
    ------
    ProtocolError
        Header CRC, version, flags / reserved byte or payload length wrong.
    """
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
    """Body of a CRC-checked frame from ``buf[off:off+length]``.

    Parameters
    ----------
    frame_type : int
        The header's frame-type byte.
    buf : bytes-like
        The frame; sample arrays are read-only int16 views into it when it is bytes.
    off, length : int
        Offset and length of the payload in ``buf``.

    Returns
    -------
    Packet, StreamBlock, Status, Command or Ack

    Raises
    ------
    ProtocolError
        Unknown frame type, or a payload that violates its layout.
    """
    cls = _BODY_BY_TYPE_INT.get(frame_type)
    if cls is None:
        raise ProtocolError(Reason.UNKNOWN_FRAME_TYPE, f"frame type 0x{frame_type:02x}")
    try:
        return cls._unpack(buf, off, length)
    except (ValueError, TypeError) as exc:
        raise ProtocolError(Reason.BAD_PAYLOAD, f"{cls.frame_type.name}: {exc}") from None


def decode_frame(data) -> Frame:
    """Parse exactly one complete frame; for byte streams use StreamDecoder.

    Parameters
    ----------
    data : bytes-like
        One already delimited frame, sync word to frame CRC.

    Returns
    -------
    Frame
        The frame (its receive-side fields left at their defaults).

    Raises
    ------
    ProtocolError
        On any defect (the reason says which check failed).
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
