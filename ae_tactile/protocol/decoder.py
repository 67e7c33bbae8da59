"""Incremental stream decoder: bytes in arbitrary chunks -> validated frames + counters.

Algorithm (decisions depend only on the byte stream, never on how it was split into
reads, so any split gives the same frames, events and final counters):

1. Find the sync word with ``bytearray.find`` from the current position; bytes skipped
   on the way are discarded (counted in ``bytes_discarded``). With no sync in sight, all
   but the longest tail that is a prefix of the sync word are discarded.
2. With 24 header bytes available, check the header CRC, version, flags/reserved and
   payload_len <= MAX_PAYLOAD_LEN. Failure: ``header_errors``, and the search restarts
   ONE byte after the rejected sync word (a valid frame starting inside the rejected
   bytes is never skipped). The header CRC means a corrupted length is caught at once
   instead of stalling the decoder while it waits for up to 64 KiB of "payload".
3. With the whole frame available, check the frame CRC. Failure: ``crc_errors`` and,
   again, restart one byte after the sync word. (A frame cut short by a sender reset
   is followed by the next valid frame inside its claimed length; skipping the whole
   claimed length would lose that frame.)
4. CRC good: the frame is consumed whole. The sequence number is accounted for even
   if the payload is then rejected (``payload_errors``, ``unknown_frames``,
   ``wrong_direction``): the frame arrived, it was not dropped on the link.

Only ``flush()`` (end of input, or the link idle for longer than one frame takes to
send) gives up on an incomplete frame: it counts it in ``truncated_frames``, rescans
the bytes after its sync word, and discards what remains.

Memory: the buffer holds at most one incomplete frame (<= MAX_FRAME_LEN bytes) plus
the last read; consumed bytes are deleted once per ``feed`` (amortised O(1) per byte).
"""
from __future__ import annotations

import struct
import zlib
from collections import deque
from dataclasses import dataclass
from typing import Callable

from .frames import (CRC_LEN, FLAG_BOOT, HEADER_LEN, SYNC, Direction, Frame, ProtocolError,
                     Reason, direction_of, parse_body, parse_header, _BODY_BY_TYPE_INT)
from .unwrap import SequenceTracker, TimestampUnwrapper

_U32LE = struct.Struct("<I")

#: Names of the integer counters reported by ``StreamDecoder.stats()``.
COUNTER_NAMES = (
    "bytes_received", "bytes_decoded", "bytes_discarded", "frames_ok", "header_errors",
    "crc_errors", "truncated_frames", "payload_errors", "unknown_frames", "wrong_direction",
    "sequence_gaps", "dropped_frames", "device_restarts", "timestamp_backsteps",
)


@dataclass(frozen=True)
class DecoderEvent:
    """One rejection or notable condition, for logging.

    reason:        Reason code (stable string values, e.g. "frame_crc").
    stream_offset: byte offset in the decoder's input where it happened (the sync word
                   of the frame concerned).
    detail:        human-readable explanation.
    """

    reason: Reason
    stream_offset: int
    detail: str

    def __str__(self) -> str:
        return f"{self.reason.value} at byte {self.stream_offset}: {self.detail}"


def _sync_prefix_tail(buf: bytearray, start: int, end: int) -> int:
    """Length of the longest tail of buf[start:end] that is a proper prefix of SYNC."""
    for k in range(min(len(SYNC) - 1, end - start), 0, -1):
        if buf[end - k:end] == SYNC[:k]:
            return k
    return 0


class StreamDecoder:
    """Incremental decoder of one byte stream (one serial port, one direction); not thread-safe.

    direction: frames accepted; the other direction's frames are rejected and counted
               (``wrong_direction``). ``None`` accepts both, each with its own sequence
               tracker and clock unwrapper (e.g. to re-parse a loop-back capture).
    max_events: size of the bounded ``events`` deque of recent DecoderEvents.
    on_event:  optional callback called with each DecoderEvent as it happens
               (e.g. a throttled ROS logger). Exceptions from it propagate.

    Counters (ints, attributes; ``stats()`` returns them as a dict):
      bytes_received   all bytes fed
      bytes_decoded    bytes of frames returned
      bytes_discarded  everything else consumed: garbage, rejected frames
                       (bytes_received == bytes_decoded + bytes_discarded + pending_bytes)
      frames_ok        frames returned
      header_errors    sync word found but header rejected (CRC/version/flags/length)
      crc_errors       header fine, frame CRC wrong
      truncated_frames incomplete frames given up by flush()
      payload_errors   CRC fine but payload inconsistent (e.g. n_samples vs length)
      unknown_frames   CRC fine, frame type unknown to protocol v1 (skipped whole)
      wrong_direction  CRC fine, frame of the other direction
      sequence_gaps    gap events; dropped_frames: frames missing by sequence number
      device_restarts  sender restarts seen (BOOT flag, or seq going backwards)
      timestamp_backsteps  device clock stepped back within a session
    """

    def __init__(self, direction: Direction | None = Direction.DEVICE_TO_HOST,
                 max_events: int = 64,
                 on_event: Callable[[DecoderEvent], None] | None = None) -> None:
        if direction is not None and not isinstance(direction, Direction):
            raise TypeError(f"direction must be a Direction or None, got {direction!r}")
        if isinstance(max_events, bool) or not isinstance(max_events, int) or max_events < 1:
            raise ValueError(f"max_events must be an integer >= 1, got {max_events!r}")
        if on_event is not None and not callable(on_event):
            raise TypeError("on_event must be callable or None")
        self.direction = direction
        self.events: deque[DecoderEvent] = deque(maxlen=max_events)
        self.on_event = on_event
        self._buf = bytearray()
        self._base = 0   # stream offset of _buf[0]
        self._need = 0   # len(_buf) needed before processing can make progress
        self._sessions: dict[Direction, tuple[SequenceTracker, TimestampUnwrapper]] = {}
        for name in COUNTER_NAMES:
            setattr(self, name, 0)

    # ------------------------------------------------------------ public API
    def feed(self, data) -> list[Frame]:
        """Append ``data`` (bytes-like) to the stream; return the frames it completed, in order."""
        if isinstance(data, str) or not isinstance(data, (bytes, bytearray, memoryview)):
            raise TypeError(f"feed() takes bytes, bytearray or memoryview, got {type(data).__name__}")
        self._buf += data
        self.bytes_received += data.nbytes if isinstance(data, memoryview) else len(data)
        if len(self._buf) < self._need:
            return []
        return self._process(final=False)

    def flush(self) -> list[Frame]:
        """Declare the end of the input: decode what can be decoded, give up the rest.

        Call at end of file/stream, before reconnecting, or when the link has been idle
        for longer than the transmission time of a MAX_FRAME_LEN frame. An incomplete
        frame is counted in ``truncated_frames``; valid frames after it are returned.
        The buffer is empty afterwards; sequence/clock sessions are kept.
        """
        return self._process(final=True)

    def forget_senders(self) -> None:
        """Forget sequence and clock sessions (the next frame starts fresh, no drops counted).

        Use when a different device may now be on the port; counters are kept.
        """
        self._sessions.clear()

    @property
    def pending_bytes(self) -> int:
        """Bytes held back waiting for the rest of a frame (or a possible sync prefix)."""
        return len(self._buf)

    def stats(self) -> dict[str, int]:
        """Snapshot of all counters (COUNTER_NAMES) as a dict, plus pending_bytes."""
        d = {name: getattr(self, name) for name in COUNTER_NAMES}
        d["pending_bytes"] = len(self._buf)
        return d

    def pop_events(self) -> list[DecoderEvent]:
        """Return and clear the recent events (oldest first; at most max_events kept)."""
        out = list(self.events)
        self.events.clear()
        return out

    # ------------------------------------------------------------ internals
    def _event(self, reason: Reason, offset: int, detail: str) -> None:
        ev = DecoderEvent(reason, offset, detail)
        self.events.append(ev)
        if self.on_event is not None:
            self.on_event(ev)

    def _process(self, final: bool) -> list[Frame]:
        buf = self._buf
        n = len(buf)
        base = self._base
        pos = 0
        need = 0
        out: list[Frame] = []
        mv = memoryview(buf)
        try:
            while True:
                i = buf.find(SYNC, pos)
                if i < 0:
                    keep = 0 if final else _sync_prefix_tail(buf, pos, n)
                    self.bytes_discarded += n - keep - pos
                    pos = n - keep
                    break
                if i > pos:
                    self.bytes_discarded += i - pos
                    pos = i
                if n - i < HEADER_LEN:
                    if not final:
                        need = HEADER_LEN
                        break
                    self._give_up(i, base, f"input ended {n - i} bytes into a header")
                    pos = i + 1
                    continue
                try:
                    h = parse_header(buf, i)
                except ProtocolError as exc:
                    self.header_errors += 1
                    self.bytes_discarded += 1
                    self._event(exc.reason, base + i, exc.detail)
                    pos = i + 1
                    continue
                end = i + HEADER_LEN + h.payload_len + CRC_LEN
                if end > n:
                    if not final:
                        need = end - i
                        break
                    self._give_up(i, base, f"input ended {n - i} of {end - i} bytes into a frame"
                                           f" (seq {h.seq})")
                    pos = i + 1
                    continue
                (fcrc,) = _U32LE.unpack_from(buf, end - CRC_LEN)
                crc = zlib.crc32(mv[i + HEADER_LEN:end - CRC_LEN], h.header_crc)
                if crc != fcrc:
                    self.crc_errors += 1
                    self.bytes_discarded += 1
                    self._event(Reason.FRAME_CRC, base + i,
                                f"frame CRC 0x{fcrc:08x} != computed 0x{crc:08x}"
                                f" ({end - i} bytes, header seq {h.seq}); rescanning from the next byte")
                    pos = i + 1
                    continue
                pos = end
                frame = self._accept(h, mv, i, end, base + i)
                if frame is not None:
                    out.append(frame)
        finally:
            mv.release()
        del buf[:pos]
        self._base = base + pos
        self._need = need
        return out

    def _give_up(self, i: int, base: int, detail: str) -> None:
        self.truncated_frames += 1
        self.bytes_discarded += 1
        self._event(Reason.TRUNCATED, base + i, detail)

    def _accept(self, h, mv: memoryview, i: int, end: int, offset: int) -> Frame | None:
        size = end - i
        ftype = h.frame_type
        d = direction_of(ftype)
        if self.direction is not None and d is not self.direction:
            self.wrong_direction += 1
            self.bytes_discarded += size
            self._event(Reason.WRONG_DIRECTION, offset,
                        f"frame type 0x{ftype:02x} travels {d.value}, this decoder accepts"
                        f" {self.direction.value}")
            return None
        session = self._sessions.get(d)
        if session is None:
            session = self._sessions[d] = (SequenceTracker(), TimestampUnwrapper())
        tracker, unwrapper = session
        boot = bool(h.flags & FLAG_BOOT)
        su = tracker.update(h.seq, boot)
        if su.dropped:
            self.dropped_frames += su.dropped
            self.sequence_gaps += 1
        if su.restart:
            self.device_restarts += 1
        if su.note:
            self._event(Reason.SENDER_RESTART if su.restart else Reason.SEQUENCE_GAP, offset, su.note)
        backsteps = unwrapper.backsteps
        last_raw = unwrapper.last_raw
        t = unwrapper.update(h.timestamp_us, restart=su.restart or boot)
        if unwrapper.backsteps != backsteps:
            self.timestamp_backsteps += 1
            self._event(Reason.TIMESTAMP_BACKSTEP, offset,
                        f"device clock went back from {last_raw} to {h.timestamp_us} us"
                        f" without a restart (seq {h.seq})")
        if ftype not in _BODY_BY_TYPE_INT:
            self.unknown_frames += 1
            self.bytes_discarded += size
            self._event(Reason.UNKNOWN_FRAME_TYPE, offset,
                        f"frame type 0x{ftype:02x} ({size} bytes, seq {h.seq}) is not defined in"
                        " protocol v1; skipped whole")
            return None
        fb = bytes(mv[i:end])
        try:
            body = parse_body(ftype, fb, HEADER_LEN, h.payload_len)
        except ProtocolError as exc:
            self.payload_errors += 1
            self.bytes_discarded += size
            self._event(exc.reason, offset, f"{exc.detail} (seq {h.seq})")
            return None
        self.frames_ok += 1
        self.bytes_decoded += size
        return Frame(body, h.seq, h.timestamp_us, h.flags, t, su.dropped, su.restart, offset)
