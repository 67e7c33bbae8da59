# SPDX-License-Identifier: Apache-2.0
"""Protocol v1: the document's byte-exact examples, the CRC, encode-side validation,
single-frame parsing and the sequence / clock state machines."""

from __future__ import annotations

import re
import shutil
import subprocess
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from ae_tactile.geometry import N_CHANNELS
from ae_tactile.protocol import (
    CRC32_CHECK,
    FLAG_BOOT,
    FRAME_OVERHEAD,
    HEADER_LEN,
    MAX_FRAME_LEN,
    MAX_PAYLOAD_LEN,
    MAX_SAMPLES,
    PROTOCOL_VERSION,
    SYNC,
    Ack,
    AckResult,
    AcqMode,
    Command,
    DeviceState,
    ErrorBits,
    Frame,
    FrameEncoder,
    FrameType,
    Opcode,
    Packet,
    ProtocolError,
    Reason,
    SequenceTracker,
    Status,
    StreamBlock,
    StreamDecoder,
    TimestampUnwrapper,
    crc32,
    crc32_reference,
    decode_frame,
    encode_frame,
    format_hex,
    parse_hex,
)

DOC = Path(__file__).resolve().parents[1] / "docs" / "protocol.md"
U32 = 2**32
SETTINGS = settings(max_examples=50, deadline=None)


def doc_text() -> str:
    return DOC.read_text(encoding="utf-8")


def doc_examples() -> dict[str, bytes]:
    """The hex dumps that follow '<!-- example: NAME -->' markers in docs/protocol.md."""
    found = re.findall(r"<!-- example: (\w+) -->\s*```text\n(.*?)```", doc_text(), re.S)
    return {name: parse_hex(dump) for name, dump in found}


# The values docs/protocol.md states in prose for each example.
DOC_EXAMPLE_FRAMES = {
    "packet": Frame(
        Packet(
            np.array(
                [[12, -7, 310, -1024], [9, -3, 288, -950], [-4, 2, -150, 700], [0, 5, -131, 655]],
                np.int16,
            ),
            sample_rate_hz=10_000_000,
            v_per_count=2.0**-20,
            first_sample_index=1_234_567,
            pre_trigger=1,
            onset_index=2,
            saturation_mask=0,
        ),
        seq=42,
        timestamp_us=123_456_789,
        flags=0,
    ),
    "status": Frame(
        Status(
            uptime_us=1500,
            state=DeviceState.IDLE,
            sample_rate_hz=10_000_000,
            v_per_count=2.0**-20,
            threshold_counts=200,
            packet_samples=400,
            pre_trigger=100,
            error_bits=0,
            device_dropped=0,
            firmware_version=(1, 0, 0),
            serial_number="AE-0001",
        ),
        seq=0,
        timestamp_us=1500,
        flags=FLAG_BOOT,
    ),
    "command": Frame(Command.start(AcqMode.TRIGGERED, command_id=7), seq=3, timestamp_us=0),
    "ack": Frame(Ack(7, Opcode.START, AckResult.OK, 1), seq=43, timestamp_us=123_460_000),
}


# ------------------------------------------------------------------ the document
def test_doc_examples_decode_to_the_stated_values():
    examples = doc_examples()
    assert set(examples) == set(DOC_EXAMPLE_FRAMES)
    for name, wire in examples.items():
        frame = decode_frame(wire)
        assert frame == DOC_EXAMPLE_FRAMES[name], name
        assert encode_frame(frame.body, frame.seq, frame.timestamp_us, frame.flags) == wire, name
        # and through the stream decoder with garbage around it
        dec = StreamDecoder(direction=None)
        assert dec.feed(b"\x00junk" + wire + SYNC[:3]) == [frame]


def test_doc_packet_example_details():
    wire = doc_examples()["packet"]
    body = decode_frame(wire).body
    assert body.samples.dtype == np.int16 and body.samples.shape == (4, 4)
    assert body.samples[3, 3] == 655 and body.samples[0, 3] == -1024  # channel-major
    hcrc = zlib.crc32(wire[:20])
    fcrc = zlib.crc32(wire[24:-4], hcrc)
    text = doc_text()
    assert f"0x{hcrc:08X}" in text and f"0x{fcrc:08X}" in text  # the CRCs quoted in prose
    assert wire[:4] == SYNC and "AE 7C 5A C3" in text
    assert (
        f"MAX_PAYLOAD_LEN = {MAX_PAYLOAD_LEN}" in text
        and f"MAX_FRAME_LEN = {MAX_FRAME_LEN}" in text
    )
    assert f"MAX_SAMPLES = {MAX_SAMPLES}" in text


def test_doc_c_reference_crc_matches_zlib(tmp_path):
    """Compile the C snippet of docs/protocol.md and run it on the example frames."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler")
    code = re.search(r"<!-- c-reference -->\s*```c\n(.*?)```", doc_text(), re.S).group(1)
    main = r"""
#include <stdio.h>
int main(void) {
    static uint8_t buf[1 << 17]; size_t n = fread(buf, 1, sizeof buf, stdin);
    uint32_t h = crc32_update(0, buf, 20);
    uint32_t f = crc32_update(h, buf + 24, n - 28);
    printf("%08x %08x %08x\n", crc32_update(0, (const uint8_t *)"123456789", 9), h, f);
    return 0;
}
"""
    src = tmp_path / "crc.c"
    src.write_text(code + main)
    exe = tmp_path / "crc"
    subprocess.run(
        [cc, "-std=c99", "-O1", "-Wall", "-Werror", "-o", str(exe), str(src)],
        check=True,
        capture_output=True,
    )
    for wire in doc_examples().values():
        out = subprocess.run(
            [str(exe)], input=wire, capture_output=True, check=True
        ).stdout.split()
        check, h, f = (int(x, 16) for x in out)
        assert check == CRC32_CHECK
        assert h == int.from_bytes(wire[20:24], "little")
        assert f == int.from_bytes(wire[-4:], "little")


# ------------------------------------------------------------------ CRC and hex dumps
def test_crc_check_value():
    assert crc32(b"123456789") == CRC32_CHECK == crc32_reference(b"123456789") == 0xCBF43926


@SETTINGS
@given(st.binary(max_size=300), st.binary(max_size=100))
def test_reference_crc_equals_zlib_and_runs_in_pieces(a, b):
    assert crc32_reference(a) == zlib.crc32(a)
    assert crc32_reference(b, crc32_reference(a)) == zlib.crc32(a + b)


@SETTINGS
@given(st.binary(max_size=200))
def test_hex_dump_round_trip(data):
    assert parse_hex(format_hex(data)) == data


def test_parse_hex_rejects_malformed_dumps():
    with pytest.raises(ValueError, match="not a hex dump line"):
        parse_hex("0000: ae 7c zz")
    with pytest.raises(ValueError, match="offset"):
        parse_hex("0000: " + "00 " * 16 + "\n0020: 01")
    with pytest.raises(ValueError, match="width"):
        format_hex(b"x", width=0)


@SETTINGS
@given(
    st.integers(1, 64).flatmap(
        lambda n: hnp.arrays(np.int16, (4, n), elements=st.integers(-2048, 2047))
    )
)
def test_sync_word_cannot_occur_in_12_bit_samples(samples):
    assert SYNC not in samples.astype("<i2").tobytes()


# ------------------------------------------------------------------ encode-side validation
def pk(**kw):
    args = dict(samples=np.zeros((4, 8), np.int16), sample_rate_hz=10_000_000, v_per_count=1e-6)
    args.update(kw)
    return Packet(**args)


def status(**kw):
    args = dict(
        uptime_us=0,
        state=DeviceState.IDLE,
        sample_rate_hz=10_000_000,
        v_per_count=1e-6,
        threshold_counts=100,
        packet_samples=400,
        pre_trigger=100,
        error_bits=0,
        device_dropped=0,
        firmware_version=(1, 2, 3),
        serial_number="AE-1",
    )
    args.update(kw)
    return Status(**args)


@pytest.mark.parametrize(
    "make, exc, words",
    [
        (lambda: pk(samples=np.zeros((3, 8), np.int16)), ValueError, "shape (4, N)"),
        (lambda: pk(samples=np.zeros((8, 4), np.int16)), ValueError, "shape (4, N)"),
        (lambda: pk(samples=np.zeros(32, np.int16)), ValueError, "shape (4, N)"),
        (lambda: pk(samples=np.zeros((4, 0), np.int16)), ValueError, "[1, 8192]"),
        (lambda: pk(samples=np.zeros((4, MAX_SAMPLES + 1), np.int16)), ValueError, "[1, 8192]"),
        (lambda: pk(samples=np.zeros((4, 8))), ValueError, "integer dtype"),
        (lambda: pk(samples=np.zeros((4, 8), bool)), ValueError, "integer dtype"),
        (lambda: pk(samples=np.full((4, 8), 40000, np.int32)), ValueError, "fit in int16"),
        (lambda: pk(samples=np.full((4, 8), 40000, np.uint16)), ValueError, "fit in int16"),
        (lambda: pk(samples=[[1, 2], [3]]), ValueError, "samples"),
        (lambda: pk(samples="abcd"), ValueError, "shape"),
        (lambda: pk(sample_rate_hz=0), ValueError, "sample_rate_hz"),
        (lambda: pk(sample_rate_hz=2**32), ValueError, "sample_rate_hz"),
        (lambda: pk(sample_rate_hz=1e7), TypeError, "sample_rate_hz"),
        (lambda: pk(sample_rate_hz=True), TypeError, "sample_rate_hz"),
        (lambda: pk(v_per_count=float("nan")), ValueError, "v_per_count"),
        (lambda: pk(v_per_count=-1e-6), ValueError, "v_per_count"),
        (lambda: pk(v_per_count=1e39), ValueError, "v_per_count"),
        (lambda: pk(v_per_count=1e-50), ValueError, "v_per_count"),
        (lambda: pk(v_per_count="1e-6"), TypeError, "v_per_count"),
        (lambda: pk(first_sample_index=-1), ValueError, "first_sample_index"),
        (lambda: pk(first_sample_index=2**64), ValueError, "first_sample_index"),
        (lambda: pk(pre_trigger=8), ValueError, "pre_trigger"),
        (lambda: pk(onset_index=8), ValueError, "onset_index"),
        (lambda: pk(saturation_mask=16), ValueError, "saturation_mask"),
        (lambda: StreamBlock(np.zeros((4, 2, 2), np.int16), 10, 1.0), ValueError, "shape"),
        (lambda: StreamBlock(np.zeros((4, 2), np.float32), 10, 1.0), ValueError, "integer dtype"),
        (lambda: status(serial_number=""), ValueError, "serial_number"),
        (lambda: status(serial_number="x" * 33), ValueError, "serial_number"),
        (lambda: status(serial_number="fingertip\u00e9"), ValueError, "printable ASCII"),
        (lambda: status(serial_number=b"AE-1"), TypeError, "serial_number"),
        (lambda: status(state=7), ValueError, "IDLE=0"),
        (lambda: status(threshold_counts=0), ValueError, "threshold_counts"),
        (lambda: status(threshold_counts=40000), ValueError, "threshold_counts"),
        (lambda: status(pre_trigger=400), ValueError, "pre_trigger"),
        (lambda: status(firmware_version=(1, 2)), TypeError, "firmware_version"),
        (lambda: status(firmware_version=(1, 2, 256)), ValueError, "firmware_version[2]"),
        (lambda: status(error_bits=-1), ValueError, "error_bits"),
        (lambda: Command(Opcode.START), ValueError, "requires argument 'mode'"),
        (
            lambda: Command(Opcode.STOP, mode=AcqMode.STREAM),
            ValueError,
            "takes no argument 'mode'",
        ),
        (lambda: Command(99), ValueError, "opcode"),
        (lambda: Command.start(3), ValueError, "mode"),
        (lambda: Command.set_threshold(0), ValueError, "threshold_counts"),
        (lambda: Command.set_sample_rate(0), ValueError, "sample_rate_hz"),
        (lambda: Command.set_packet_length(100, 100), ValueError, "pre_trigger"),
        (lambda: Command.set_packet_length(MAX_SAMPLES + 1, 0), ValueError, "n_samples"),
        (lambda: Command.stop(command_id=70000), ValueError, "command_id"),
        (lambda: Ack(1, Opcode.START, result=9), ValueError, "result"),
        (lambda: Ack(1, 256), ValueError, "opcode"),
        (lambda: Ack(1, 1, value=-1), ValueError, "value"),
        (lambda: encode_frame(pk(), seq=-1, timestamp_us=0), ValueError, "seq"),
        (lambda: encode_frame(pk(), seq=0, timestamp_us=U32), ValueError, "timestamp_us"),
        (lambda: encode_frame(pk(), seq=0, timestamp_us=0, flags=2), ValueError, "FLAG_BOOT"),
        (lambda: encode_frame("payload", seq=0, timestamp_us=0), TypeError, "body"),
        (lambda: FrameEncoder(first_seq=U32), ValueError, "first_seq"),
    ],
)
def test_encode_validation_errors(make, exc, words):
    with pytest.raises(exc) as info:
        make()
    assert words in str(info.value)


def test_samples_are_converted_from_other_integer_dtypes():
    s = np.arange(-16, 16, dtype=np.int64).reshape(4, 8)
    p = pk(samples=s)
    assert p.samples.dtype == np.int16 and np.array_equal(p.samples, s)
    big_endian = s.astype(">i2")
    assert decode_frame(encode_frame(pk(samples=big_endian), 0, 0)).body == p
    assert np.allclose(p.volts(), s * float(np.float32(1e-6)))


def test_v_per_count_is_stored_as_the_float32_the_wire_carries():
    p = pk(v_per_count=0.1)
    assert p.v_per_count == float(np.float32(0.1)) != 0.1
    assert decode_frame(encode_frame(p, 0, 0)).body == p


def test_packet_equality_compares_samples():
    a = pk(samples=np.zeros((4, 8), np.int16))
    assert a == pk(samples=np.zeros((4, 8), np.int32))
    assert a != pk(samples=np.ones((4, 8), np.int16))
    assert a != pk(samples=np.zeros((4, 9), np.int16))
    assert a != StreamBlock(np.zeros((4, 8), np.int16), 10_000_000, 1e-6)
    with pytest.raises(TypeError):
        hash(a)


def test_status_and_ack_field_types():
    s = decode_frame(
        encode_frame(status(error_bits=int(ErrorBits.TX_OVERFLOW) | (1 << 20)), 0, 0)
    ).body
    assert s.state is DeviceState.IDLE and ErrorBits.TX_OVERFLOW in s.error_bits
    assert s.error_bits & (1 << 20)  # firmware-specific bits kept, not rejected
    a = decode_frame(encode_frame(Ack(5, 200, AckResult.UNKNOWN_OPCODE), 0, 0)).body
    assert a.opcode == 200 and a.result is AckResult.UNKNOWN_OPCODE and not a.ok
    a = decode_frame(encode_frame(Ack(5, 5, AckResult.OK, 2_000_000), 0, 0)).body
    assert a.opcode is Opcode.SET_SAMPLE_RATE and a.ok


def test_command_wire_sizes_and_args():
    cases = {
        Command.start(AcqMode.STREAM): (2,),
        Command.stop(): (),
        Command.get_status(): (),
        Command.set_threshold(300): (300,),
        Command.set_sample_rate(2_000_000): (2_000_000,),
        Command.set_packet_length(400, 100): (400, 100),
    }
    sizes = {
        Opcode.START: 1,
        Opcode.STOP: 0,
        Opcode.GET_STATUS: 0,
        Opcode.SET_THRESHOLD: 2,
        Opcode.SET_SAMPLE_RATE: 4,
        Opcode.SET_PACKET_LENGTH: 4,
    }
    for cmd, args in cases.items():
        assert cmd.args == args
        wire = encode_frame(cmd, 0, 0)
        assert len(wire) == FRAME_OVERHEAD + 3 + sizes[cmd.opcode]
        assert decode_frame(wire).body == cmd


def test_frame_sizes_match_the_document():
    n = 400
    assert (
        len(encode_frame(pk(samples=np.zeros((4, n), np.int16)), 0, 0)) == 3252 == 28 + 24 + 8 * n
    )
    assert (
        len(encode_frame(StreamBlock(np.zeros((4, n), np.int16), 1, 1.0), 0, 0)) == 28 + 20 + 8 * n
    )
    assert len(encode_frame(status(serial_number="AE-0001"), 0, 0)) == 28 + 36 + 7
    assert len(encode_frame(Ack(0, 1), 0, 0)) == 28 + 8
    big = encode_frame(pk(samples=np.zeros((4, MAX_SAMPLES), np.int16)), 0, 0)
    assert len(big) == MAX_FRAME_LEN and MAX_PAYLOAD_LEN == 24 + 8 * MAX_SAMPLES
    assert HEADER_LEN == 24 and PROTOCOL_VERSION == 1 and N_CHANNELS == 4
    assert {int(t) for t in FrameType} == {0x01, 0x02, 0x03, 0x04, 0x81}


def test_frame_encoder_numbers_frames_and_sets_boot_once():
    enc = FrameEncoder(first_seq=U32 - 1)
    f = [decode_frame(enc.encode(Ack(0, 1), 0)) for _ in range(3)]
    assert [x.seq for x in f] == [U32 - 1, 0, 1]
    assert [x.boot for x in f] == [True, False, False]
    enc.skip(5)
    assert enc.next_seq == 7


# ------------------------------------------------------------------ single-frame parsing
def test_decode_frame_errors_have_reasons():
    wire = encode_frame(pk(), 1, 2)
    cases = [
        (wire[:10], Reason.TRUNCATED),
        (wire[:-1], Reason.TRUNCATED),
        (wire + b"\0", Reason.BAD_HEADER),
        (b"\0" + wire[1:], Reason.BAD_HEADER),
        (wire[:-1] + bytes([wire[-1] ^ 1]), Reason.FRAME_CRC),
        (wire[:9] + bytes([wire[9] ^ 4]) + wire[10:], Reason.HEADER_CRC),
    ]
    for data, reason in cases:
        with pytest.raises(ProtocolError) as info:
            decode_frame(data)
        assert info.value.reason is reason
        assert isinstance(info.value, ValueError)


def test_header_of_one_frame_with_payload_of_another_is_rejected():
    """frame_crc continues from header_crc, so header and payload are bound together."""
    a = encode_frame(pk(samples=np.zeros((4, 8), np.int16)), 1, 100)
    b = encode_frame(pk(samples=np.ones((4, 8), np.int16)), 2, 200)
    with pytest.raises(ProtocolError) as info:
        decode_frame(a[:HEADER_LEN] + b[HEADER_LEN:])
    assert info.value.reason is Reason.FRAME_CRC


# ------------------------------------------------------------------ state machines
def test_sequence_tracker_rules():
    t = SequenceTracker()
    assert t.update(5).dropped == 0  # first frame: no history
    assert t.update(6) == t.update(7).__class__()  # in order
    u = t.update(10)
    assert (u.dropped, u.restart) == (2, False) and "2 frame(s) dropped" in u.note
    u = t.update(0, boot=True)
    assert (u.dropped, u.restart) == (0, True)
    u = t.update(3)
    assert u.dropped == 2
    u = t.update(1)  # back without BOOT
    assert (u.dropped, u.restart) == (1, True)
    assert (t.dropped_frames, t.sequence_gaps, t.restarts) == (5, 3, 2)
    t.reset()
    assert t.update(1000).dropped == 0
    with pytest.raises(ValueError):
        t.update(U32)
    with pytest.raises(ValueError):
        SequenceTracker(modulus=2)


@SETTINGS
@given(st.integers(0, 2**16 - 1), st.lists(st.integers(0, 2**15 - 1), max_size=30))
def test_sequence_tracker_small_modulus_wraps(first, gaps):
    t = SequenceTracker(modulus=2**16)
    seq = first
    t.update(seq)
    for g in gaps:
        seq = (seq + g + 1) % 2**16
        assert t.update(seq).dropped == g
    assert t.dropped_frames == sum(gaps) and t.restarts == 0


@SETTINGS
@given(st.integers(0, U32 - 1), st.lists(st.integers(-(2**31), 2**31 - 1), max_size=30))
def test_timestamp_unwrapper_follows_signed_steps(start, steps):
    u = TimestampUnwrapper()
    truth = start
    assert u.update(start) == start
    for s in steps:
        truth += s
        assert u.update(truth % U32) == truth
    assert u.backsteps == sum(1 for s in steps if s < 0)


def test_timestamp_unwrapper_wrap_and_restart():
    u = TimestampUnwrapper()
    assert u.update(U32 - 10) == U32 - 10
    assert u.update(5) == U32 + 5 and u.wraps == 1
    assert u.update(100, restart=True) == 100
    assert u.update(U32 - 1) == -1 and u.backsteps == 1  # a step of -101 (mod 2^32)
    u.reset()
    assert u.update(7) == 7
    with pytest.raises(ValueError):
        u.update(-1)
    with pytest.raises(ValueError):
        TimestampUnwrapper(bits=64)
    small = TimestampUnwrapper(bits=8)
    assert [small.update(v) for v in (250, 3, 200)] == [250, 259, 200]
