# SPDX-License-Identifier: Apache-2.0
"""Property tests of the protocol: round trips and the StreamDecoder against garbage,
bit flips, truncations, arbitrary read splits, concatenations and sequence events."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from ae_tactile.protocol import (
    FLAG_BOOT,
    HEADER_LEN,
    MAX_PAYLOAD_LEN,
    MAX_SAMPLES,
    NO_ONSET,
    SYNC,
    Ack,
    AckResult,
    AcqMode,
    Command,
    DeviceState,
    Direction,
    Frame,
    FrameEncoder,
    Opcode,
    Packet,
    Reason,
    Status,
    StreamBlock,
    StreamDecoder,
    decode_frame,
    encode_frame,
)

SETTINGS = settings(
    max_examples=60,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
U32 = 2**32

# ------------------------------------------------------------------ strategies
sample_arrays = st.integers(1, 24).flatmap(lambda n: hnp.arrays(np.int16, (4, n)))
u32 = st.integers(0, U32 - 1)
rates = st.integers(1, U32 - 1)
gains = st.floats(min_value=2.0**-149, max_value=float(np.finfo(np.float32).max), width=32)


@st.composite
def packets(draw):
    s = draw(sample_arrays)
    n = s.shape[1]
    return Packet(
        s,
        draw(rates),
        draw(gains),
        draw(st.integers(0, 2**64 - 1)),
        draw(st.integers(0, n - 1)),
        draw(st.one_of(st.just(NO_ONSET), st.integers(0, n - 1))),
        draw(st.integers(0, 15)),
    )


@st.composite
def stream_blocks(draw):
    return StreamBlock(
        draw(sample_arrays),
        draw(rates),
        draw(gains),
        draw(st.integers(0, 2**64 - 1)),
        draw(st.integers(0, 15)),
    )


@st.composite
def statuses(draw):
    n = draw(st.integers(1, MAX_SAMPLES))
    return Status(
        draw(st.integers(0, 2**64 - 1)),
        draw(st.sampled_from(DeviceState)),
        draw(rates),
        draw(gains),
        draw(st.integers(1, 32767)),
        n,
        draw(st.integers(0, n - 1)),
        draw(u32),
        draw(u32),
        tuple(draw(st.lists(st.integers(0, 255), min_size=3, max_size=3))),
        draw(
            st.text(st.characters(min_codepoint=0x20, max_codepoint=0x7E), min_size=1, max_size=32)
        ),
    )


@st.composite
def commands(draw):
    op = draw(st.sampled_from(Opcode))
    cid = draw(st.integers(0, 0xFFFF))
    if op is Opcode.START:
        return Command.start(draw(st.sampled_from(AcqMode)), cid)
    if op is Opcode.SET_THRESHOLD:
        return Command.set_threshold(draw(st.integers(1, 32767)), cid)
    if op is Opcode.SET_SAMPLE_RATE:
        return Command.set_sample_rate(draw(rates), cid)
    if op is Opcode.SET_PACKET_LENGTH:
        n = draw(st.integers(1, MAX_SAMPLES))
        return Command.set_packet_length(n, draw(st.integers(0, n - 1)), cid)
    return Command(op, cid)


acks = st.builds(Ack, st.integers(0, 0xFFFF), st.integers(0, 255), st.sampled_from(AckResult), u32)
device_bodies = st.one_of(packets(), stream_blocks(), statuses(), acks)
any_bodies = st.one_of(device_bodies, commands())


def encode_all(bodies, first_seq=0, boot=True, t0=0, dt=100):
    """Frames (as Frame objects) and their wire bytes, numbered by one FrameEncoder."""
    enc = FrameEncoder(first_seq, boot)
    frames, wire = [], []
    for k, body in enumerate(bodies):
        seq, flags = enc.next_seq, FLAG_BOOT if (boot and k == 0) else 0
        ts = (t0 + k * dt) % U32
        wire.append(enc.encode(body, ts))
        frames.append(Frame(body, seq, ts, flags))
    return frames, wire


def check_invariants(dec: StreamDecoder) -> None:
    assert dec.bytes_received == dec.bytes_decoded + dec.bytes_discarded + dec.pending_bytes
    assert len(dec.events) <= dec.events.maxlen


def decode_all(data: bytes, chunks=None, **kw):
    dec = StreamDecoder(**kw)
    out = []
    if chunks is None:
        out += dec.feed(data)
    else:
        pos = 0
        for c in chunks:
            out += dec.feed(data[pos : pos + c])
            pos += c
        out += dec.feed(data[pos:])
    check_invariants(dec)
    before_flush = list(out)
    out += dec.flush()
    check_invariants(dec)
    assert dec.pending_bytes == 0
    return out, before_flush, dec


def raw_frame(ftype, payload, seq=0, ts=0, flags=0, version=1, reserved=0, length=None):
    """Frame bytes with arbitrary header fields but correct CRCs (for crafted rejections)."""
    length = len(payload) if length is None else length
    head = struct.pack("<4sBBBBIII", SYNC, version, ftype, flags, reserved, length, seq, ts)
    hcrc = zlib.crc32(head)
    return head + struct.pack("<I", hcrc) + payload + struct.pack("<I", zlib.crc32(payload, hcrc))


def full(frame: Frame):
    """Everything a decoded frame carries, metadata included (for split-invariance)."""
    return (frame, frame.device_time_us, frame.dropped_before, frame.restart, frame.stream_offset)


def small_packet(k=0, n=8):
    s = (np.arange(4 * n, dtype=np.int16).reshape(4, n) * (k + 1)) % 2000
    return Packet(s.astype(np.int16), 10_000_000, 1e-6, first_sample_index=1000 * k, pre_trigger=2)


# ------------------------------------------------------------------ round trips
@SETTINGS
@given(any_bodies, u32, u32, st.sampled_from([0, FLAG_BOOT]))
def test_round_trip_every_frame_type(body, seq, ts, flags):
    wire = encode_frame(body, seq, ts, flags)
    frame = decode_frame(wire)
    assert frame == Frame(body, seq, ts, flags)
    assert type(frame.body) is type(body)
    assert frame.frame_type == body.frame_type
    assert frame.encode() == wire
    if isinstance(body, (Packet, StreamBlock)):
        assert frame.body.samples.dtype == np.int16
        assert frame.body.samples.shape == (4, body.n_samples)
    # the same through the stream decoder of the right direction
    direction = Direction.HOST_TO_DEVICE if isinstance(body, Command) else Direction.DEVICE_TO_HOST
    out, _, dec = decode_all(wire, direction=direction)
    assert out == [frame] and dec.frames_ok == 1 and dec.bytes_discarded == 0


@SETTINGS
@given(st.lists(device_bodies, min_size=1, max_size=40), u32)
def test_many_frames_in_one_read(bodies, first_seq):
    frames, wire = encode_all(bodies, first_seq, boot=False)
    dec = StreamDecoder()
    out = dec.feed(b"".join(wire))
    assert out == frames
    assert dec.pending_bytes == 0 and dec.dropped_frames == 0 and dec.bytes_discarded == 0
    assert [f.stream_offset for f in out] == list(np.cumsum([0] + [len(w) for w in wire[:-1]]))


# ------------------------------------------------------------------ garbage
@st.composite
def garbage(draw, others):
    """Random bytes, or adversarial: sync fragments, sync + junk, cut-off real frames."""
    kind = draw(st.integers(0, 4))
    if kind == 0:
        return draw(st.binary(max_size=64))
    if kind == 1:
        return SYNC[: draw(st.integers(1, 4))]
    if kind == 2:
        return SYNC + draw(st.binary(max_size=40))
    victim = others[draw(st.integers(0, len(others) - 1))]
    cut = draw(st.integers(1, len(victim) - 1))
    if kind == 3:
        return victim[:cut]  # truncated frame (valid header if cut >= 24)
    b = bytearray(victim)
    bit = draw(st.integers(0, 8 * len(b) - 1))
    b[bit // 8] ^= 1 << (bit % 8)
    return bytes(b)  # corrupted copy of a frame


@SETTINGS
@given(st.data(), st.lists(device_bodies, min_size=1, max_size=8))
def test_garbage_never_loses_a_valid_frame(data, bodies):
    frames, wire = encode_all(bodies, first_seq=data.draw(u32), boot=False)
    # decoys: other frames that must not be decoded when cut or corrupted
    decoys = encode_all(bodies, first_seq=7, boot=False, t0=12345)[1]
    parts = []
    for w in wire:
        parts.append(data.draw(garbage(decoys)))
        parts.append(w)
    parts.append(data.draw(garbage(decoys)))
    stream = b"".join(parts)
    out, before_flush, dec = decode_all(stream)
    assert out == frames
    assert before_flush == frames[: len(before_flush)]
    assert dec.frames_ok == len(frames) and dec.dropped_frames == 0
    assert dec.bytes_decoded == sum(map(len, wire))


@SETTINGS
@given(st.binary(min_size=0, max_size=2000))
def test_pure_garbage_never_crashes_nor_yields_frames(blob):
    out, _, dec = decode_all(blob)
    assert out == []
    assert dec.bytes_discarded == len(blob)


@SETTINGS
@given(st.lists(st.binary(max_size=50), max_size=30))
def test_garbage_full_of_sync_words(pieces):
    blob = SYNC.join(pieces) + SYNC
    frames, wire = encode_all([small_packet(0), small_packet(1)])
    out, _, dec = decode_all(blob + wire[0] + blob + wire[1] + blob)
    assert out == frames
    assert dec.header_errors + dec.truncated_frames >= len(pieces) + 1


# ------------------------------------------------------------------ bit flips
@SETTINGS
@given(st.data(), st.lists(device_bodies, min_size=3, max_size=6))
def test_single_bit_flip_is_detected_and_counted(data, bodies):
    frames, wire = encode_all(bodies, first_seq=data.draw(u32), boot=False)
    k = data.draw(st.integers(1, len(wire) - 2))  # first/last carry the sequence evidence
    bit = data.draw(st.integers(0, 8 * len(wire[k]) - 1))
    bad = bytearray(wire[k])
    bad[bit // 8] ^= 1 << (bit % 8)
    out, _, dec = decode_all(b"".join(wire[:k]) + bytes(bad) + b"".join(wire[k + 1 :]))
    assert out == frames[:k] + frames[k + 1 :]
    assert dec.dropped_frames == 1 and dec.sequence_gaps == 1
    assert out[k].dropped_before == 1
    assert dec.bytes_discarded == len(bad)
    if bit // 8 >= len(SYNC):  # sync intact: a rejection is counted
        assert dec.header_errors + dec.crc_errors >= 1
        reasons = {e.reason for e in dec.events}
        assert reasons & {Reason.HEADER_CRC, Reason.FRAME_CRC}
    if len(SYNC) <= bit // 8 < HEADER_LEN:  # header bit: caught by the header CRC
        assert dec.header_errors >= 1
    assert any(e.reason is Reason.SEQUENCE_GAP for e in dec.events)


# ------------------------------------------------------------------ truncations
@SETTINGS
@given(st.data(), st.lists(device_bodies, min_size=3, max_size=6))
def test_truncated_frame_in_the_middle(data, bodies):
    frames, wire = encode_all(bodies, first_seq=data.draw(u32), boot=False)
    k = data.draw(st.integers(1, len(wire) - 2))
    cut = data.draw(st.integers(0, len(wire[k]) - 1))
    out, _, dec = decode_all(b"".join(wire[:k]) + wire[k][:cut] + b"".join(wire[k + 1 :]))
    assert out == frames[:k] + frames[k + 1 :]
    assert dec.dropped_frames == 1
    assert dec.bytes_discarded == cut
    if cut >= len(SYNC):
        assert dec.header_errors + dec.crc_errors + dec.truncated_frames >= 1


@SETTINGS
@given(st.data(), st.lists(device_bodies, min_size=1, max_size=5))
def test_truncated_last_frame_is_given_up_by_flush(data, bodies):
    frames, wire = encode_all(bodies, boot=True)
    cut = data.draw(st.integers(1, len(wire[-1]) - 1))
    out, before_flush, dec = decode_all(b"".join(wire[:-1]) + wire[-1][:cut])
    assert out == before_flush == frames[:-1]
    assert dec.bytes_discarded == cut
    if cut >= len(SYNC):
        assert dec.truncated_frames == 1
        assert any(e.reason is Reason.TRUNCATED for e in dec.events)


def test_truncated_frame_swallowing_valid_frames_is_recovered():
    """A cut-off PACKET (a device reset mid-frame) whose header claims more bytes than
    follow: the valid frames inside its claimed length are delivered at once, without
    waiting for the claimed length nor for flush()."""
    big = Packet(np.ones((4, 2000), np.int16), 10_000_000, 1e-6)
    frames, wire = encode_all([small_packet(k) for k in range(5)], first_seq=100, boot=False)
    cut = encode_frame(big, 99, 0)[:500]
    dec = StreamDecoder()
    assert dec.feed(cut + b"".join(wire)) == frames  # 16 kB claimed, none waited for
    assert dec.truncated_frames == 1 and dec.crc_errors == 0 and dec.dropped_frames == 0
    assert dec.pending_bytes == 0 and dec.bytes_discarded == len(cut)
    (ev,) = [e for e in dec.events if e.reason is Reason.TRUNCATED]
    assert ev.stream_offset == 0 and "cut short by the valid frame at byte 500" in ev.detail
    # the same, fed a byte at a time: each frame is out as soon as its last byte is in
    dec = StreamDecoder()
    stream = cut + b"".join(wire)
    ends = np.cumsum([len(cut)] + [len(w) for w in wire])[1:]
    got_at = []
    for k in range(len(stream)):
        if dec.feed(stream[k : k + 1]):
            got_at.append(k + 1)
    assert got_at == list(ends)


# ------------------------------------------------------------------ splitting
@SETTINGS
@given(st.data(), st.lists(device_bodies, min_size=1, max_size=6))
def test_any_split_gives_the_same_result_as_one_read(data, bodies):
    frames, wire = encode_all(bodies, boot=True)
    decoys = encode_all(bodies, first_seq=3, boot=False)[1]
    parts = [data.draw(garbage(decoys))]
    for w in wire:
        parts += [w, data.draw(garbage(decoys))]
    stream = b"".join(parts)
    chunks = data.draw(st.lists(st.integers(0, 300), max_size=80))
    one, one_pre, dec1 = decode_all(stream)
    many, many_pre, dec2 = decode_all(stream, chunks)
    assert [full(f) for f in one] == [full(f) for f in many]
    assert one == frames
    assert dec1.stats() == dec2.stats()
    assert [str(e) for e in dec1.events] == [str(e) for e in dec2.events]


def test_byte_by_byte_feed():
    frames, wire = encode_all([small_packet(k) for k in range(3)] + [Ack(1, Opcode.STOP)])
    stream = b"\x00\xae" + b"".join(wire) + b"\xae\x7c"
    dec = StreamDecoder()
    out = []
    for b in stream:
        out += dec.feed(bytes([b]))
    assert out == frames
    assert dec.pending_bytes == 2  # a possible sync prefix is held back
    assert dec.flush() == [] and dec.bytes_discarded == 4


# ------------------------------------------------------------------ sequence numbers
@SETTINGS
@given(
    u32,
    st.lists(st.integers(0, 3), min_size=1, max_size=30),
    st.lists(st.integers(1, 2**31 - 1), max_size=2),
)
def test_sequence_gaps_counted_exactly_across_wrap(first_seq, skips, big_skips):
    enc = FrameEncoder(first_seq, boot=False)
    skips = skips + big_skips
    wire = [enc.encode(small_packet(), 0)]
    for s in skips:
        enc.skip(s)
        wire.append(enc.encode(small_packet(), 0))
    out, _, dec = decode_all(b"".join(wire))
    assert len(out) == len(wire)
    assert dec.dropped_frames == sum(skips)
    assert dec.sequence_gaps == sum(1 for s in skips if s)
    assert [f.dropped_before for f in out] == [0] + skips
    assert dec.device_restarts == 0


def test_sequence_wrap_is_not_a_gap():
    frames, wire = encode_all([small_packet(k) for k in range(6)], first_seq=U32 - 3, boot=False)
    out, _, dec = decode_all(b"".join(wire))
    assert [f.seq for f in out] == [U32 - 3, U32 - 2, U32 - 1, 0, 1, 2]
    assert dec.dropped_frames == 0 and dec.device_restarts == 0


def test_device_restart_with_boot_frame():
    s1, w1 = encode_all([small_packet(k) for k in range(5)], first_seq=0, boot=True, t0=10**9)
    s2, w2 = encode_all([small_packet(k) for k in range(3)], first_seq=0, boot=True, t0=5)
    out, _, dec = decode_all(b"".join(w1 + w2))
    assert out == s1 + s2
    assert dec.device_restarts == 1 and dec.dropped_frames == 0  # not 2^32 - 5 drops
    assert [f.restart for f in out] == [False] * 5 + [True, False, False]
    assert out[5].device_time_us == 5 and out[4].device_time_us == 10**9 + 400
    assert any(e.reason is Reason.SENDER_RESTART for e in dec.events)


def test_device_restart_whose_boot_frame_was_lost():
    s1, w1 = encode_all([small_packet(k) for k in range(10)], first_seq=0, boot=True)
    s2, w2 = encode_all([small_packet(k) for k in range(4)], first_seq=0, boot=True, t0=7)
    out, _, dec = decode_all(b"".join(w1 + w2[1:]))
    assert out == s1 + s2[1:]
    assert dec.device_restarts == 1 and dec.dropped_frames == 1 and out[10].restart
    assert out[10].dropped_before == 1 and out[10].device_time_us == s2[1].timestamp_us


def test_frames_rejected_after_crc_still_count_in_the_sequence():
    enc = FrameEncoder(50, boot=False)
    w0 = enc.encode(small_packet(0), 0)
    bad_payload = raw_frame(0x01, b"\x00" * 30, seq=enc.next_seq)  # PACKET too short
    enc.skip()
    unknown = raw_frame(0x05, b"future frame", seq=enc.next_seq)  # type from a newer firmware
    enc.skip()
    w3 = enc.encode(small_packet(3), 0)
    out, _, dec = decode_all(w0 + bad_payload + unknown + w3)
    assert [f.seq for f in out] == [50, 53]
    assert dec.payload_errors == 1 and dec.unknown_frames == 1
    assert dec.dropped_frames == 0 and out[1].dropped_before == 0
    assert dec.bytes_discarded == len(bad_payload) + len(unknown)
    reasons = [e.reason for e in dec.events]
    assert Reason.BAD_PAYLOAD in reasons and Reason.UNKNOWN_FRAME_TYPE in reasons


@pytest.mark.parametrize(
    "payload, words",
    [
        (
            struct.pack("<IfQHHHBB", 10_000_000, 1e-6, 0, 10, 0, NO_ONSET, 4, 0) + b"\0" * 79,
            "80 sample bytes",
        ),
        (
            struct.pack("<IfQHHHBB", 10_000_000, 1e-6, 0, 2, 0, NO_ONSET, 3, 0) + b"\0" * 12,
            "n_channels",
        ),
        (struct.pack("<IfQHHHBB", 0, 1e-6, 0, 1, 0, NO_ONSET, 4, 0) + b"\0" * 8, "sample_rate_hz"),
        (
            struct.pack("<IfQHHHBB", 10, float("nan"), 0, 1, 0, NO_ONSET, 4, 0) + b"\0" * 8,
            "v_per_count",
        ),
        (struct.pack("<IfQHHHBB", 10, 1.0, 0, 4, 4, NO_ONSET, 4, 0) + b"\0" * 32, "pre_trigger"),
        (struct.pack("<IfQHHHBB", 10, 1.0, 0, 4, 0, 7, 4, 0) + b"\0" * 32, "onset_index"),
        (struct.pack("<IfQHHHBB", 10, 1.0, 0, 0, 0, NO_ONSET, 4, 0), "n_samples"),
    ],
)
def test_inconsistent_packet_payload_is_rejected_with_reason(payload, words):
    good = encode_frame(small_packet(), 1, 0)
    out, _, dec = decode_all(raw_frame(0x01, payload, seq=0) + good)
    assert len(out) == 1 and out[0].seq == 1
    assert dec.payload_errors == 1 and dec.dropped_frames == 0
    (ev,) = [e for e in dec.events if e.reason is Reason.BAD_PAYLOAD]
    assert words in ev.detail and ev.stream_offset == 0


@pytest.mark.parametrize(
    "kw, reason",
    [
        (dict(version=2), Reason.BAD_VERSION),
        (dict(flags=0x02), Reason.BAD_HEADER),
        (dict(reserved=1), Reason.BAD_HEADER),
        (dict(length=MAX_PAYLOAD_LEN + 1), Reason.LENGTH_TOO_LARGE),
    ],
)
def test_bad_header_with_valid_crc_is_rejected_at_once(kw, reason):
    good = encode_frame(small_packet(), 1, 0)
    dec = StreamDecoder()
    out = dec.feed(raw_frame(0x01, b"", **kw) + good)
    assert [f.seq for f in out] == [1]  # no waiting for a bogus length
    assert dec.header_errors == 1 and dec.events[0].reason is reason


def test_random_header_does_not_stall_the_decoder():
    good = encode_frame(small_packet(), 1, 0)
    junk = SYNC + b"\x01\x01\x00\x00" + struct.pack("<I", 60000) + bytes(range(12))
    dec = StreamDecoder()
    assert [f.seq for f in dec.feed(junk + good)] == [1]
    assert dec.header_errors == 1 and dec.events[0].reason is Reason.HEADER_CRC


def test_wrong_direction_frames_are_rejected_and_commands_decode_on_the_device_side():
    cmd = Command.set_sample_rate(2_000_000, command_id=9)
    host = FrameEncoder()
    wire = host.encode(cmd, 0) + host.encode(Command.start(AcqMode.STREAM, 10), 0)
    ack = encode_frame(Ack(9, Opcode.SET_SAMPLE_RATE, AckResult.OK, 2_000_000), 0, 0)
    out, _, dec = decode_all(wire + ack)  # host side decoder
    assert [type(f.body) for f in out] == [Ack] and dec.wrong_direction == 2
    out, _, dec = decode_all(wire + ack, direction=Direction.HOST_TO_DEVICE)  # simulator side
    assert [f.body for f in out] == [cmd, Command.start(AcqMode.STREAM, 10)]
    assert dec.wrong_direction == 1 and out[0].boot
    out, _, dec = decode_all(wire + ack, direction=None)  # both, own sessions
    assert len(out) == 3 and dec.dropped_frames == 0 and dec.wrong_direction == 0


def test_unknown_command_opcode_is_a_payload_error():
    out, _, dec = decode_all(
        raw_frame(0x81, struct.pack("<HB", 3, 99)), direction=Direction.HOST_TO_DEVICE
    )
    assert out == [] and dec.payload_errors == 1
    assert "unknown opcode 99" in dec.events[0].detail


# ------------------------------------------------------------------ clock
@SETTINGS
@given(u32, st.lists(st.integers(0, 2**31 - 1), min_size=1, max_size=20))
def test_device_time_is_unwrapped(t0, steps):
    enc = FrameEncoder(boot=True)
    t = t0
    wire = [enc.encode(small_packet(), t)]
    truth = [t0]
    for s in steps:
        t += s
        truth.append(t)
        wire.append(enc.encode(small_packet(), t % U32))
    out, _, dec = decode_all(b"".join(wire))
    assert [f.device_time_us for f in out] == truth
    assert dec.timestamp_backsteps == 0


def test_timestamp_backstep_is_reported():
    enc = FrameEncoder()
    wire = (
        enc.encode(small_packet(), 1000)
        + enc.encode(small_packet(), 900)
        + enc.encode(small_packet(), 950)
    )
    out, _, dec = decode_all(wire)
    assert [f.device_time_us for f in out] == [1000, 900, 950]
    assert dec.timestamp_backsteps == 1
    assert [e.reason for e in dec.events] == [Reason.TIMESTAMP_BACKSTEP]


# ------------------------------------------------------------------ API edges
def test_events_are_bounded_and_popped():
    seen = []
    dec = StreamDecoder(max_events=4, on_event=seen.append)
    junk = (SYNC + bytes(30)) * 20
    dec.feed(junk)
    assert dec.header_errors == 20 and len(dec.events) == 4 and len(seen) == 20
    assert len(dec.pop_events()) == 4 and not dec.events
    assert "header_crc at byte" in str(seen[0])


@pytest.mark.parametrize("bad", ["text", None, 5, [1, 2]])
def test_feed_rejects_non_bytes(bad):
    with pytest.raises(TypeError, match="feed"):
        StreamDecoder().feed(bad)


@pytest.mark.parametrize(
    "kw, exc",
    [
        (dict(direction="device"), TypeError),
        (dict(max_events=0), ValueError),
        (dict(on_event=3), TypeError),
    ],
)
def test_decoder_parameters_are_checked(kw, exc):
    with pytest.raises(exc):
        StreamDecoder(**kw)


def test_forget_senders_starts_a_fresh_session():
    _, w1 = encode_all([small_packet()] * 3, first_seq=10, boot=False)
    _, w2 = encode_all([small_packet()] * 3, first_seq=500, boot=False)
    dec = StreamDecoder()
    dec.feed(b"".join(w1))
    dec.forget_senders()
    out = dec.feed(b"".join(w2))
    assert len(out) == 3 and dec.dropped_frames == 0 and dec.device_restarts == 0


def test_accepts_memoryview_and_bytearray_reads():
    frames, wire = encode_all([small_packet(k) for k in range(3)])
    data = b"".join(wire)
    dec = StreamDecoder()
    out = dec.feed(memoryview(data)[:100]) + dec.feed(bytearray(data[100:]))
    assert out == frames
    assert not out[0].body.samples.flags.writeable  # read-only views of the frame bytes


def test_memoryview_of_wider_items_counts_bytes():
    frames, wire = encode_all([small_packet(k) for k in range(2)])
    data = b"".join(wire)
    words = np.frombuffer(data + b"\0" * (-len(data) % 4), dtype=np.uint32)
    dec = StreamDecoder()
    assert dec.feed(memoryview(words)) == frames
    check_invariants(dec)
    assert dec.bytes_received == words.nbytes


def test_bodies_are_immutable():
    s = np.zeros((4, 8), np.int16)
    p = Packet(s, 10_000_000, 1e-6)
    s[0, 0] = 99  # the caller's array is not aliased
    assert p.samples[0, 0] == 0 and not p.samples.flags.writeable
    with pytest.raises(ValueError):
        p.samples[0, 0] = 1
    with pytest.raises(AttributeError):
        p.sample_rate_hz = 5
