# SPDX-License-Identifier: Apache-2.0
"""Incremental stream decoder: bytes in arbitrary chunks -> validated frames + counters.

Algorithm (decisions depend only on the byte stream, never on how it was split into
reads, so any split gives the same frames, events and final counters):

1. Every sync word is examined once, in stream order. With its 24 header bytes in, the
   header CRC, version, flags/reserved and payload_len <= MAX_PAYLOAD_LEN are checked;
   a failure is a ``header_errors`` rejection and the search goes on ONE byte after the
   sync word (a valid frame starting inside rejected bytes is never skipped). A good
   header makes a *candidate* spanning its claimed length.
2. The next frame delivered is the CRC-valid candidate that ENDS first (ties: the first
   to start). Candidates are CRC-checked in the order of their ends, and only while one
   could still end first; a failure is a ``crc_errors`` rejection.
3. Delivering a frame consumes it whole. Candidates that started before it but end
   after it (a frame cut short by a sender reset, a fake header claiming 64 KiB) are
   given up as ``truncated_frames`` without waiting for, or CRC-checking, their claimed
   length: the first valid frame after a device resumes is delivered as soon as its own
   last byte is in. (A valid frame inside a real frame's payload would win over it; in
   protocol v1 that cannot happen with 12-bit samples, and takes a full CRC-valid frame,
   2^-64, otherwise.) Sync words inside a delivered frame are part of its payload:
   they are neither counted nor reported.
4. CRC good: the sequence number is accounted for even if the payload is then rejected
   (``payload_errors``, ``unknown_frames``, ``wrong_direction``): the frame arrived.
   A frame equal to one of the last ``DUPLICATE_WINDOW`` frames of its sender (same
   sequence number and same frame CRC) is a repeat: counted in ``duplicate_frames``,
   never delivered twice and never taken for a sender restart.

``flush()`` (end of input, or an idle link) gives up the candidates still incomplete
(``truncated_frames``) and discards what remains.

Memory: the buffer holds at most the bytes from the earliest incomplete candidate on
(< MAX_FRAME_LEN) plus the last read; the examined sync words kept with it are at most
one per 4 of those bytes. Cost: one ``bytearray.find`` pass over the input, one header
check per sync word, one CRC per candidate that is checked (fake headers followed by
valid frames are never CRC-checked); consumed bytes are deleted once per ``feed``.
"""

from __future__ import annotations

import struct
import zlib
from collections import deque
from dataclasses import dataclass
from operator import itemgetter
from typing import Callable

from .frames import _BODY_BY_TYPE_INT, Frame, parse_body, parse_header
from .layout import (
    CRC_LEN,
    FLAG_BOOT,
    FRAME_OVERHEAD,
    HEADER_LEN,
    SYNC,
    Direction,
    ProtocolError,
    Reason,
    direction_of,
)
from .unwrap import SequenceTracker, TimestampUnwrapper

_U32LE = struct.Struct("<I")
_END = itemgetter(2)

#: Names of the integer counters reported by ``StreamDecoder.stats()``.
COUNTER_NAMES = (
    "bytes_received",
    "bytes_decoded",
    "bytes_discarded",
    "frames_ok",
    "header_errors",
    "crc_errors",
    "truncated_frames",
    "payload_errors",
    "unknown_frames",
    "wrong_direction",
    "sequence_gaps",
    "dropped_frames",
    "device_restarts",
    "timestamp_backsteps",
    "duplicate_frames",
)

#: How many recent frames per sender are remembered to recognise a repeated frame.
DUPLICATE_WINDOW = 64


@dataclass(frozen=True)
class DecoderEvent:
    """One rejection or notable condition, for logging.

    Parameters
    ----------
    reason : Reason
        Reason code (stable string values, e.g. "frame_crc").
    stream_offset : int
        Byte offset in the decoder's input where it happened (the sync word of the frame
        concerned).
    detail : str
        Human-readable explanation.
    """

    reason: Reason
    stream_offset: int
    detail: str

    def __str__(self) -> str:
        return f"{self.reason.value} at byte {self.stream_offset}: {self.detail}"


def _sync_prefix_tail(buf: bytearray, start: int, end: int) -> int:
    """Length of the longest tail of buf[start:end] that is a proper prefix of SYNC."""
    for k in range(min(len(SYNC) - 1, end - start), 0, -1):
        if buf[end - k : end] == SYNC[:k]:
            return k
    return 0


class StreamDecoder:
    """Incremental decoder of one byte stream (one serial port, one direction); not thread-safe.

    Parameters
    ----------
    direction : Direction or None
        Frames accepted; the other direction's frames are rejected and counted
        (``wrong_direction``). ``None`` accepts both, each with its own sequence tracker
        and clock unwrapper (e.g. to re-parse a loop-back capture).
    max_events : int
        Size of the bounded ``events`` deque of recent DecoderEvents.
    on_event : callable or None
        Called with each DecoderEvent as it happens (e.g. a throttled ROS logger).
        Exceptions from it propagate.

    Counters (ints, attributes; ``stats()`` returns them as a dict):
      bytes_received   all bytes fed
      bytes_decoded    bytes of frames returned
      bytes_discarded  everything else consumed: garbage, rejected frames
                       (bytes_received == bytes_decoded + bytes_discarded + pending_bytes)
      frames_ok        frames returned
      header_errors    sync word found but header rejected (CRC/version/flags/length)
      crc_errors       header fine, frame CRC wrong
      truncated_frames incomplete frames given up (cut short by a valid frame, or flush())
      payload_errors   CRC fine but payload inconsistent (e.g. n_samples vs length)
      unknown_frames   CRC fine, frame type unknown to protocol v1 (skipped whole)
      wrong_direction  CRC fine, frame of the other direction
      sequence_gaps    gap events; dropped_frames: frames missing by sequence number
      device_restarts  sender restarts seen (BOOT flag, or seq going backwards)
      timestamp_backsteps  device clock stepped back within a session
      duplicate_frames frames received again (same seq and CRC as a recent one), dropped
    """

    def __init__(
        self,
        direction: Direction | None = Direction.DEVICE_TO_HOST,
        max_events: int = 64,
        on_event: Callable[[DecoderEvent], None] | None = None,
    ) -> None:
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
        self._base = 0  # stream offset of _buf[0]
        self._need = 0  # len(_buf) needed before processing can make progress
        self._scan = 0  # stream offset of the first position not yet searched for SYNC
        self._wait_end = 0  # earliest end (stream offset) of a pending candidate, 0: none
        # Examined sync words not yet resolved, in stream order: [offset, header or None,
        # end offset (or Reason if the header was rejected), CRC-failure detail or None].
        self._items: list[list] = []
        self._cands: list[list] = []  # the items with a good header, CRC not failed
        self._sessions: dict[Direction, tuple] = {}
        for name in COUNTER_NAMES:
            setattr(self, name, 0)

    # ------------------------------------------------------------ public API
    def feed(self, data) -> list[Frame]:
        """Append bytes to the stream.

        Parameters
        ----------
        data : bytes, bytearray or memoryview
            The next bytes of the stream, any chunking.

        Returns
        -------
        list of Frame
            The frames these bytes completed, in stream order.
        """
        if isinstance(data, str) or not isinstance(data, (bytes, bytearray, memoryview)):
            raise TypeError(
                f"feed() takes bytes, bytearray or memoryview, got {type(data).__name__}"
            )
        buf = self._buf
        buf += data
        self.bytes_received += data.nbytes if isinstance(data, memoryview) else len(data)
        n = len(buf)
        if n < self._need:
            return []
        if self._wait_end and self._base + n < self._wait_end:
            # A candidate is pending and none can complete yet: only a new sync word in
            # the new bytes could change anything (the same outcome as _process, cheaper).
            start = self._scan - self._base
            if buf.find(SYNC, start) < 0:
                scan = max(start, n - len(SYNC) + 1)
                self._scan = self._base + scan
                self._need = min(self._wait_end - self._base, scan + FRAME_OVERHEAD)
                return []
        return self._process(final=False)

    def flush(self) -> list[Frame]:
        """Declare the end of the input: decode what can be decoded, give up the rest.

        Call at end of file/stream, before reconnecting, or when the link has been idle
        for longer than the transmission time of a MAX_FRAME_LEN frame. An incomplete
        frame is counted in ``truncated_frames``; valid frames after it are returned.
        The buffer is empty afterwards; sequence/clock sessions are kept.

        Returns
        -------
        list of Frame
            The valid frames still in the buffer, in stream order.
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
        """Snapshot of the counters.

        Returns
        -------
        dict of str to int
            Every counter of COUNTER_NAMES, plus ``pending_bytes``.
        """
        d = {name: getattr(self, name) for name in COUNTER_NAMES}
        d["pending_bytes"] = len(self._buf)
        return d

    def pop_events(self) -> list[DecoderEvent]:
        """Return and clear the recent events.

        Returns
        -------
        list of DecoderEvent
            Oldest first; at most ``max_events`` are kept.
        """
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
        """Deliver the frames now complete, then settle what stays pending (or, if
        ``final``, give it up); consumed bytes leave the buffer."""
        buf = self._buf
        base = self._base
        mv = memoryview(buf)
        try:
            out, pos = self._deliver(buf, mv)
            if final:
                pos = self._give_up_rest(buf, pos)
            else:
                pos = self._keep_pending(buf, pos)
        finally:
            mv.release()
        del buf[: pos - base]
        self._base = pos
        if self._scan < pos:
            self._scan = pos
        return out

    def _deliver(self, buf: bytearray, mv: memoryview) -> tuple[list[Frame], int]:
        """Frames complete in the buffer, in the order of rule 2; returns them and the
        stream offset up to which the bytes are consumed."""
        base, n = self._base, len(buf)
        end_abs = base + n
        items, cands = self._items, self._cands
        pos = base  # stream offset: bytes before it are consumed
        out: list[Frame] = []
        while True:
            self._examine(buf, mv, base, n)
            best = self._first_complete_frame(mv, base, end_abs)
            if best is None:
                return out, pos
            bj, h, be, _ = best
            if items[0][0] < bj:
                self._commit(bj, bj)
            # sync words inside the delivered frame are payload: forget them
            k = 1
            for k in range(1, len(items) + 1):
                if k == len(items) or items[k][0] >= be:
                    break
            del items[:k]
            k = 0
            for c in cands:
                if c[0] >= be:
                    break
                k += 1
            del cands[:k]
            self.bytes_discarded += bj - pos
            pos = be
            if self._scan < be:
                self._scan = be
            frame = self._accept(h, mv, bj - base, be - base, bj)
            if frame is not None:
                out.append(frame)

    def _give_up_rest(self, buf: bytearray, pos: int) -> int:
        """End of input: every sync word and candidate still open is given up (counted);
        returns the new consumed offset (everything)."""
        base, n = self._base, len(buf)
        end_abs = base + n
        items, cands = self._items, self._cands
        j = buf.find(SYNC, self._scan - base)
        while j >= 0:  # sync words whose header never came
            items.append(
                [base + j, None, Reason.TRUNCATED, f"input ended {n - j} bytes into a header"]
            )
            j = buf.find(SYNC, j + 1)
        for c in cands:
            if c[3] is None:
                c[3] = (
                    f"input ended {end_abs - c[0]} of {c[2] - c[0]} bytes into a frame"
                    f" (seq {c[1].seq})"
                )
        self._commit(end_abs, None)
        cands.clear()
        self.bytes_discarded += end_abs - pos
        self._scan = end_abs
        self._need = 0
        self._wait_end = 0
        return end_abs

    def _keep_pending(self, buf: bytearray, pos: int) -> int:
        """Keep from the earliest candidate, or a header / sync prefix still coming;
        returns the new consumed offset and sets how many bytes the next step needs."""
        base, n = self._base, len(buf)
        items, cands = self._items, self._cands
        scan_rel = self._scan - base
        j = buf.find(SYNC, scan_rel)
        keep = base + (j if j >= 0 else n - _sync_prefix_tail(buf, scan_rel, n))
        need = keep + FRAME_OVERHEAD
        self._wait_end = 0
        if cands:
            keep = min(keep, cands[0][0])
            self._wait_end = min(c[2] for c in cands)
            need = min(need, self._wait_end)
        if items and items[0][0] < keep:
            self._commit(keep, None)
        if keep > pos:
            self.bytes_discarded += keep - pos
            pos = keep
        self._need = need - pos
        return pos

    def _examine(self, buf: bytearray, mv: memoryview, base: int, n: int) -> None:
        """Check the header of every new sync word whose 24 header bytes are in."""
        items, cands = self._items, self._cands
        j = self._scan - base
        while True:
            j = buf.find(SYNC, j)
            if j < 0:
                j = max(self._scan - base, n - len(SYNC) + 1)
                break
            if n - j < HEADER_LEN:
                break
            try:
                h = parse_header(buf, j)
            except ProtocolError as exc:
                items.append([base + j, None, exc.reason, exc.detail])
            else:
                it = [base + j, h, base + j + HEADER_LEN + h.payload_len + CRC_LEN, None]
                items.append(it)
                cands.append(it)
            j += 1
        self._scan = base + j

    def _first_complete_frame(self, mv: memoryview, base: int, end_abs: int):
        """The CRC-valid complete candidate that ends first (rule 2), or None."""
        cands = self._cands
        if not cands:
            return None
        c = cands[0]
        if c[2] <= end_abs and (len(cands) == 1 or cands[1][0] >= c[2]):
            # the usual case: the earliest candidate is complete and no other can end first
            i, e = c[0] - base, c[2] - base
            (fcrc,) = _U32LE.unpack_from(mv, e - CRC_LEN)
            if zlib.crc32(mv[i + HEADER_LEN : e - CRC_LEN], c[1].header_crc) == fcrc:
                return c
        while cands:
            bound = None
            complete = []
            for c in cands:  # stream order
                if bound is not None and c[0] >= bound:
                    break  # starts after a complete one ends: cannot win
                e = c[2]
                if e <= end_abs:
                    complete.append(c)
                    if bound is None or e < bound:
                        bound = e
            if not complete:
                return None
            if len(complete) > 1:
                complete.sort(key=_END)
            for c in complete:
                i, e = c[0] - base, c[2] - base
                (fcrc,) = _U32LE.unpack_from(mv, e - CRC_LEN)
                crc = zlib.crc32(mv[i + HEADER_LEN : e - CRC_LEN], c[1].header_crc)
                if crc == fcrc:
                    return c
                c[3] = (
                    f"frame CRC 0x{fcrc:08x} != computed 0x{crc:08x} ({e - i} bytes,"
                    f" header seq {c[1].seq}); rescanning from the next byte"
                )
                cands.remove(c)
        return None

    def _commit(self, upto: int, cut_by: int | None) -> None:
        """Count and report the examined sync words before stream offset ``upto``
        (``cut_by``: offset of the valid frame that cuts short the candidates there)."""
        items = self._items
        k = 0
        for it in items:
            off, h, x, detail = it
            if off >= upto:
                break
            k += 1
            if h is None:
                if x is Reason.TRUNCATED:
                    self.truncated_frames += 1
                else:
                    self.header_errors += 1
                self._event(x, off, detail)
            elif detail is not None and detail.startswith("frame CRC"):
                self.crc_errors += 1
                self._event(Reason.FRAME_CRC, off, detail)
            else:
                self.truncated_frames += 1
                self._event(
                    Reason.TRUNCATED,
                    off,
                    detail
                    or f"frame claiming {x - off} bytes (seq {h.seq}) cut short by the"
                    f" valid frame at byte {cut_by}",
                )
        if k:
            del items[:k]
            cands = self._cands
            if cands and cands[0][0] < upto:
                cands[:] = [c for c in cands if c[0] >= upto]

    def _accept(self, h, mv: memoryview, i: int, end: int, offset: int) -> Frame | None:
        size = end - i
        ftype = h.frame_type
        d = direction_of(ftype)
        if self.direction is not None and d is not self.direction:
            self.wrong_direction += 1
            self.bytes_discarded += size
            self._event(
                Reason.WRONG_DIRECTION,
                offset,
                f"frame type 0x{ftype:02x} travels {d.value}, this decoder accepts"
                f" {self.direction.value}",
            )
            return None
        session = self._sessions.get(d)
        if session is None:
            session = self._sessions[d] = (SequenceTracker(), TimestampUnwrapper(), {})
        tracker, unwrapper, recent = session
        key = (h.seq, _U32LE.unpack_from(mv, end - CRC_LEN)[0])
        if key in recent:
            self.duplicate_frames += 1
            self.bytes_discarded += size
            self._event(
                Reason.DUPLICATE, offset, f"frame seq {h.seq} received again (same CRC); dropped"
            )
            return None
        recent[key] = None
        if len(recent) > DUPLICATE_WINDOW:
            del recent[next(iter(recent))]
        boot = bool(h.flags & FLAG_BOOT)
        su = tracker.update(h.seq, boot)
        if su.dropped:
            self.dropped_frames += su.dropped
            self.sequence_gaps += 1
        if su.restart:
            self.device_restarts += 1
        if su.note:
            self._event(
                Reason.SENDER_RESTART if su.restart else Reason.SEQUENCE_GAP, offset, su.note
            )
        backsteps = unwrapper.backsteps
        last_raw = unwrapper.last_raw
        t = unwrapper.update(h.timestamp_us, restart=su.restart or boot)
        if unwrapper.backsteps != backsteps:
            self.timestamp_backsteps += 1
            self._event(
                Reason.TIMESTAMP_BACKSTEP,
                offset,
                f"device clock went back from {last_raw} to {h.timestamp_us} us"
                f" without a restart (seq {h.seq})",
            )
        if ftype not in _BODY_BY_TYPE_INT:
            self.unknown_frames += 1
            self.bytes_discarded += size
            self._event(
                Reason.UNKNOWN_FRAME_TYPE,
                offset,
                f"frame type 0x{ftype:02x} ({size} bytes, seq {h.seq}) is not defined in"
                " protocol v1; skipped whole",
            )
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
        # `Frame` has no checks of its own: its fields set at once, not one by one through
        # the frozen dataclass's __init__
        frame = object.__new__(Frame)
        frame.__dict__.update(
            body=body, seq=h.seq, timestamp_us=h.timestamp_us, flags=h.flags,
            device_time_us=t, dropped_before=su.dropped, restart=su.restart,
            stream_offset=offset,
        )
        return frame
