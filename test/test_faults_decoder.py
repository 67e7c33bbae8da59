# SPDX-License-Identifier: Apache-2.0
"""Hostile input to the StreamDecoder: repeated frames, frames cut by a device reset,
fake headers claiming 64 KiB, floods of them. Every valid frame comes out once, as soon
as its own last byte is in; every other byte is accounted for; memory stays bounded."""

from __future__ import annotations

import struct
import zlib

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ae_tactile.protocol import (
    MAX_FRAME_LEN,
    MAX_PAYLOAD_LEN,
    SYNC,
    DeviceState,
    FrameEncoder,
    Packet,
    Reason,
    Status,
    StreamDecoder,
)

SETTINGS = settings(
    max_examples=40,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


def packet(k: int, n: int = 16) -> Packet:
    s = ((np.arange(4 * n).reshape(4, n) * (k + 3)) % 4000 - 2000).astype(np.int16)
    return Packet(s, 10_000_000, 1e-6, first_sample_index=1000 * k, pre_trigger=2)


def status(uptime_us: int) -> Status:
    return Status(
        uptime_us, DeviceState.IDLE, 10_000_000, 1e-6, 200, 400, 100, 0, 0, (1, 0, 0), "AE-0001"
    )


def wire_of(n: int, first_seq: int = 0, boot: bool = False, t0: int = 0) -> list[bytes]:
    enc = FrameEncoder(first_seq, boot)
    return [enc.encode(packet(k), (t0 + 100 * k) & 0xFFFFFFFF) for k in range(n)]


def fake_header(seq: int = 0, length: int = MAX_PAYLOAD_LEN, ftype: int = 0x01) -> bytes:
    """24 header bytes with a VALID header CRC claiming ``length`` payload bytes."""
    head = struct.pack("<4sBBBBIII", SYNC, 1, ftype, 0, 0, length, seq, 0)
    return head + struct.pack("<I", zlib.crc32(head))


def feed_in(dec: StreamDecoder, data: bytes, chunks: list[int]) -> list:
    """Feed data in the given chunk sizes (cycled); return [(frame, end offset of the read)]."""
    out, pos, k = [], 0, 0
    while pos < len(data):
        c = max(1, chunks[k % len(chunks)]) if chunks else len(data)
        k += 1
        for f in dec.feed(data[pos : pos + c]):
            out.append((f, min(pos + c, len(data))))
        pos += c
    return out


def accounted(dec: StreamDecoder) -> bool:
    return dec.bytes_received == dec.bytes_decoded + dec.bytes_discarded + dec.pending_bytes


# ------------------------------------------------------------------ repeated frames
@SETTINGS
@given(st.data(), st.integers(0, 2**32 - 1))
def test_a_repeated_frame_is_a_duplicate_never_a_restart_nor_delivered_twice(data, first_seq):
    wire = wire_of(12, first_seq)
    # repeat some frames: right after themselves, or a few frames later (within the window)
    stream, n_repeats = [], 0
    for k, w in enumerate(wire):
        stream.append(w)
        for back in data.draw(st.lists(st.integers(0, min(k, 5)), max_size=2)):
            stream.append(wire[k - back])
            n_repeats += 1
    dec = StreamDecoder()
    out = [f for f, _ in feed_in(dec, b"".join(stream), data.draw(st.lists(st.integers(1, 700))))]
    out += dec.flush()
    assert [f.seq for f in out] == [(first_seq + k) % 2**32 for k in range(12)]
    assert dec.duplicate_frames == n_repeats
    assert dec.device_restarts == 0 and dec.dropped_frames == 0 and dec.sequence_gaps == 0
    assert not any(f.restart for f in out)
    assert accounted(dec) and dec.pending_bytes == 0
    assert sum(e.reason is Reason.DUPLICATE for e in dec.events) == min(n_repeats, 64)


def test_same_sequence_number_with_other_content_is_not_a_duplicate():
    """A device that really restarted (BOOT lost) reuses sequence numbers with another
    clock: that is a restart, not a duplicate."""
    first = wire_of(5, 0, boot=True, t0=10_000_000)
    again = wire_of(3, 0, boot=True, t0=50)[1:]  # seq 1, 2 again, new clock
    dec = StreamDecoder()
    out = dec.feed(b"".join(first + again))
    assert len(out) == 7 and dec.duplicate_frames == 0 and dec.device_restarts == 1


# ------------------------------------------------------------------ device reset mid-frame
@SETTINGS
@given(st.data())
def test_frame_cut_by_a_device_reset_does_not_hold_back_the_next_frames(data):
    big = FrameEncoder(77, False).encode(Packet(np.ones((4, 8192), np.int16), 10_000_000, 1e-6), 5)
    cut = big[: data.draw(st.integers(24, len(big) - 1))]  # header complete: a candidate
    boot = FrameEncoder(0, True)
    after = [boot.encode(status(1500), 1500)]
    after += [boot.encode(packet(k), 2000 + k) for k in range(4)]
    stream = cut + b"".join(after)
    chunks = data.draw(st.lists(st.integers(1, 5000), min_size=1, max_size=20))
    dec = StreamDecoder()
    got = feed_in(dec, stream, chunks)
    ends = list(np.cumsum([len(cut)] + [len(w) for w in after])[1:])
    # each frame is out in the read that brought its last byte (no wait for 64 KiB)
    assert [f.seq for f, _ in got] == [0, 1, 2, 3, 4]
    assert all(at < end + max(chunks) for (_, at), end in zip(got, ends))
    assert all(at >= end for (_, at), end in zip(got, ends))
    # given up as cut short, or (when it claims to end before a valid frame does) as a bad CRC
    assert dec.truncated_frames + dec.crc_errors == 1 and dec.header_errors == 0
    assert got[0][0].boot and dec.dropped_frames == 0
    assert accounted(dec) and dec.pending_bytes == 0


# ------------------------------------------------------------------ fake headers
@SETTINGS
@given(st.data())
def test_fake_64k_headers_before_every_frame_cost_no_crc_and_no_delay(data):
    wire = wire_of(20, 1000)
    fakes = [fake_header(seq=k) for k in range(20)]
    stream = b"".join(f + w for f, w in zip(fakes, wire))
    chunks = data.draw(st.lists(st.integers(1, 3000), max_size=30))
    dec = StreamDecoder()
    got = feed_in(dec, stream, chunks)
    one = StreamDecoder()
    one_out = one.feed(stream)
    assert [f for f, _ in got] == one_out and len(one_out) == 20
    assert [f.seq for f in one_out] == list(range(1000, 1020))
    ends = np.cumsum([len(f) + len(w) for f, w in zip(fakes, wire)])
    assert all(at >= end for (_, at), end in zip(got, ends))
    # each fake is given up when the frame after it is complete: never CRC-checked
    assert dec.truncated_frames == 20 and dec.crc_errors == 0 and dec.header_errors == 0
    assert dec.stats() == one.stats()
    assert [str(e) for e in dec.events] == [str(e) for e in one.events]
    assert accounted(dec) and dec.pending_bytes == 0


@SETTINGS
@given(
    st.lists(st.tuples(st.integers(0, 3), st.integers(0, 200)), max_size=60),
    st.lists(st.integers(1, 9000), min_size=1, max_size=10),
)
def test_floods_of_fake_headers_never_crash_and_memory_stays_bounded(pieces, chunks):
    rng = np.random.default_rng(len(pieces))
    parts = []
    for kind, size in pieces:
        if kind == 0:
            parts.append(fake_header(length=int(rng.integers(0, MAX_PAYLOAD_LEN + 1))))
        elif kind == 1:
            parts.append(fake_header(ftype=int(rng.integers(0, 256))) + rng.bytes(size))
        elif kind == 2:
            parts.append(SYNC + rng.bytes(size))
        else:
            parts.append(rng.bytes(size))
    valid = wire_of(3, 5)
    stream = b"".join(parts) + valid[0] + b"".join(parts) + valid[1] + valid[2]
    dec = StreamDecoder()
    pos, k, out, worst = 0, 0, [], 0
    while pos < len(stream):
        c = chunks[k % len(chunks)]
        k += 1
        out += dec.feed(stream[pos : pos + c])
        pos += c
        worst = max(worst, dec.pending_bytes)
        assert len(dec._items) <= dec.pending_bytes // 4 + 1
    out += dec.flush()
    assert [f.seq for f in out][-3:] == [5, 6, 7]
    assert worst < MAX_FRAME_LEN + max(chunks)
    assert accounted(dec) and dec.pending_bytes == 0


def test_every_rejection_kind_is_counted_once():
    """One of each: bad header, bad frame CRC, cut-short frame, duplicate, end of input."""
    w = wire_of(4, 10)
    bad_crc = bytearray(w[1])
    bad_crc[-1] ^= 0xFF
    junk_header = SYNC + bytes(20)
    stream = (
        junk_header
        + w[0]
        + bytes(bad_crc)
        + fake_header(99)
        + w[2]
        + w[2]
        + w[3]
        + fake_header(98, length=100)
    )
    dec = StreamDecoder()
    out = dec.feed(stream) + dec.flush()
    assert [f.seq for f in out] == [10, 12, 13]
    assert (dec.header_errors, dec.crc_errors, dec.truncated_frames, dec.duplicate_frames) == (
        1,
        1,
        2,
        1,
    )
    assert dec.dropped_frames == 1  # seq 11, whose CRC failed
    assert accounted(dec) and dec.bytes_decoded == len(w[0]) + len(w[2]) + len(w[3])
