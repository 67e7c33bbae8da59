# SPDX-License-Identifier: Apache-2.0
"""Sequence-number gap tracking and u32 microsecond-clock unwrapping.

Both are plain state machines fed one frame at a time; ``StreamDecoder`` owns one
of each per direction, and they are public so a driver or a test can use them alone.
"""

from __future__ import annotations

from dataclasses import dataclass

U32_MODULUS = 1 << 32


@dataclass(frozen=True)
class SequenceUpdate:
    """Outcome of ``SequenceTracker.update`` for one received frame.

    dropped: frames missing immediately before this one (exact, wrap-aware).
    restart: this frame starts a new sender session (sender reset).
    note:    human-readable explanation when something other than "in order" happened.
    """

    dropped: int = 0
    restart: bool = False
    note: str | None = None


#: the usual outcome (immutable: one instance serves every frame in order)
_IN_ORDER = SequenceUpdate()


class SequenceTracker:
    """Counts lost frames from a per-sender u32 sequence number.

    Rules (docs/protocol.md, "Sequence numbers"): the sender numbers every frame it
    emits 0, 1, 2, ... modulo 2^32 and sets the BOOT flag on the first frame after it
    resets (that frame has seq 0). With ``expected`` the seq the next frame should carry:

    * BOOT set: a new session. It counts as a restart if an earlier session was seen;
      ``dropped = seq`` (frames 0..seq-1 of the new session, normally 0). Frames the
      old session sent after the last one received are unknowable and not counted.
    * gap g = (seq - expected) mod 2^32 in [1, 2^31): g frames dropped.
    * g >= 2^31 (seq went backwards) without BOOT: the sender reset and its BOOT
      frame was lost. Counted as a restart with ``dropped = seq``: exact if that
      explanation is right (a serial link neither duplicates nor reorders frames).
    """

    def __init__(self, modulus: int = U32_MODULUS) -> None:
        if not isinstance(modulus, int) or modulus < 4:
            raise ValueError(f"modulus must be an integer >= 4, got {modulus!r}")
        self.modulus = modulus
        self.expected: int | None = None
        self.dropped_frames = 0
        self.sequence_gaps = 0
        self.restarts = 0

    def reset(self) -> None:
        """Forget the sender (e.g. after reconnecting to a different device); keeps totals."""
        self.expected = None

    def update(self, seq: int, boot: bool = False) -> SequenceUpdate:
        """Account for one received frame with sequence number ``seq``."""
        m = self.modulus
        if not 0 <= seq < m:
            raise ValueError(f"seq must be in [0, {m - 1}], got {seq}")
        expected = self.expected
        self.expected = (seq + 1) % m
        if boot:
            restart = expected is not None
            self.restarts += restart
            if seq:
                self.dropped_frames += seq
                self.sequence_gaps += 1
            note = None
            if restart or seq:
                note = f"sender restart (BOOT flag), seq {seq}" + (
                    f", {seq} frame(s) of the new session lost" if seq else ""
                )
            return SequenceUpdate(seq, restart, note)
        if expected is None or seq == expected:
            return _IN_ORDER
        gap = (seq - expected) % m
        if gap < m // 2:
            self.dropped_frames += gap
            self.sequence_gaps += 1
            return SequenceUpdate(
                gap, False, f"sequence gap: expected {expected}, got {seq}: {gap} frame(s) dropped"
            )
        self.restarts += 1
        if seq:
            self.dropped_frames += seq
            self.sequence_gaps += 1
        return SequenceUpdate(
            seq,
            True,
            f"seq went back from {expected - 1 if expected else m - 1}"
            f" to {seq} without BOOT flag: assuming a sender restart"
            f" whose BOOT frame was lost ({seq} frame(s) dropped)",
        )


class TimestampUnwrapper:
    """Extends a wrapping ``bits``-bit counter (the u32 microsecond device clock) to an int.

    ``update(raw)`` returns ``value``, which starts at the first raw value of a session
    and then advances by the signed modular step d = (raw - last) mod 2^bits mapped to
    [-2^(bits-1), 2^(bits-1)). Valid while consecutive updates are less than half the
    range apart (2^31 us = 35.8 min for u32 us; the device heartbeat is <= 1 s). A step
    back (d < 0) cannot happen for a monotonic clock in an in-order stream: it is
    followed (value decreases), counted in ``backsteps`` and reported by the return
    of ``update`` so the caller can log it.

    ``restart=True`` (a sender reset detected from the sequence number / BOOT flag)
    starts a new session: the clock restarted at 0, so value = raw again.
    The value is the device's uptime in us only if the session started before the
    first wrap; otherwise it is offset by a multiple of 2^bits (STATUS.uptime_us has
    the full uptime).
    """

    def __init__(self, bits: int = 32) -> None:
        if not isinstance(bits, int) or not 2 <= bits <= 63:
            raise ValueError(f"bits must be an integer in [2, 63], got {bits!r}")
        self.bits = bits
        self._mod = 1 << bits
        self._half = 1 << (bits - 1)
        self.last_raw: int | None = None
        self.value: int | None = None
        self.wraps = 0
        self.backsteps = 0

    def reset(self) -> None:
        """Start over: the next update begins a new session."""
        self.last_raw = None
        self.value = None

    def update(self, raw: int, restart: bool = False) -> int:
        """Unwrapped value for the raw counter reading ``raw`` (0 <= raw < 2^bits)."""
        if not 0 <= raw < self._mod:
            raise ValueError(f"raw counter value must be in [0, {self._mod - 1}], got {raw}")
        last = self.last_raw
        self.last_raw = raw
        if last is None or restart:
            self.value = raw
            return raw
        d = (raw - last) % self._mod
        if d >= self._half:
            d -= self._mod
            self.backsteps += 1
        elif raw < last:
            self.wraps += 1
        self.value += d
        return self.value
