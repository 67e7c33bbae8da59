# SPDX-License-Identifier: Apache-2.0
"""The decoder's fast construction of a PACKET body (`Packet._unpack`) gives the body the
checked constructor gives for every wire payload, and rejects the same payloads with the
same message: random valid payloads and each field at and past its bound."""

from __future__ import annotations

import math
import struct
import zlib

import numpy as np
import pytest

from ae_tactile.protocol import NO_ONSET, Packet, ProtocolError, decode_frame
from ae_tactile.protocol.layout import (
    _HEADER,
    _PACKET,
    _U32LE,
    PACKET_PREFIX_LEN,
    PROTOCOL_VERSION,
    SYNC,
    FrameType,
)


def raw_frame(sr, vpc, first, n, pre, onset, sat, samples, nch=4) -> bytes:
    """A CRC-valid PACKET frame carrying exactly these wire fields (no body checks)."""
    payload = _PACKET.pack(sr, vpc, first, n, pre, onset, nch, sat) + samples.tobytes()
    head = _HEADER.pack(SYNC, PROTOCOL_VERSION, FrameType.PACKET, 0, 0, len(payload), 7, 9)
    hcrc = zlib.crc32(head)
    return b"".join((head, _U32LE.pack(hcrc), payload, _U32LE.pack(zlib.crc32(payload, hcrc))))


def checked(sr, vpc, first, pre, onset, sat, samples):
    """The reference: the constructor with every field check (`Packet.__post_init__`)."""
    return Packet(samples.copy(), sr, vpc, first, pre, onset, sat)


def same_body(a: Packet, b: Packet) -> bool:
    for name in ("sample_rate_hz", "v_per_count", "first_sample_index", "pre_trigger",
                 "onset_index", "saturation_mask"):
        x, y = getattr(a, name), getattr(b, name)
        if type(x) is not type(y) or x != y:
            return False
    return (a.samples.dtype == b.samples.dtype and not a.samples.flags.writeable
            and np.array_equal(a.samples, b.samples) and a == b)


def pick(rng, values):
    """One of ``values`` as it is (no numpy conversion of a u64 bound)."""
    return values[int(rng.integers(len(values)))]


def test_random_valid_payloads_decode_to_the_checked_constructors_body():
    rng = np.random.default_rng(40)
    for _ in range(400):
        n = int(rng.integers(1, 600))
        samples = rng.integers(-32768, 32768, (4, n)).astype("<i2")
        sr = pick(rng, [1, 10_000_000, 0xFFFFFFFF, int(rng.integers(1, 2**32))])
        vpc = float(np.float32(pick(rng, [2.0**-11, 1e-38, 3e38, rng.uniform(1e-9, 1.0)])))
        first = pick(rng, [0, 2**64 - 1, int(rng.integers(0, 2**63))])
        pre = int(rng.integers(0, n))
        onset = pick(rng, [NO_ONSET, n - 1, int(rng.integers(0, n))])
        sat = int(rng.integers(0, 16))
        got = decode_frame(raw_frame(sr, vpc, first, n, pre, onset, sat, samples)).body
        assert same_body(got, checked(sr, vpc, first, pre, onset, sat, samples))


@pytest.mark.parametrize(
    "field, value",
    [("sr", 0), ("vpc", 0.0), ("vpc", -1.0), ("vpc", math.inf), ("vpc", -math.inf),
     ("vpc", math.nan), ("pre", 16), ("pre", 17), ("onset", 16), ("onset", NO_ONSET - 1),
     ("sat", 16), ("sat", 255)],
)
def test_each_field_past_its_bound_is_rejected_as_the_checked_constructor_rejects_it(
        field, value):
    n = 16
    samples = np.arange(4 * n, dtype="<i2").reshape(4, n)
    f = dict(sr=10_000_000, vpc=2.0**-11, first=5, pre=3, onset=4, sat=0)
    f[field] = value
    with pytest.raises(ValueError) as ref:
        checked(f["sr"], f["vpc"], f["first"], f["pre"], f["onset"], f["sat"], samples)
    with pytest.raises(ProtocolError) as got:
        decode_frame(raw_frame(f["sr"], f["vpc"], f["first"], n, f["pre"], f["onset"],
                               f["sat"], samples))
    assert str(ref.value) in str(got.value)


def test_a_writeable_buffer_gives_a_private_read_only_copy():
    n = 8
    samples = np.arange(4 * n, dtype="<i2").reshape(4, n)
    frame = bytearray(raw_frame(10_000_000, 2.0**-11, 0, n, 0, NO_ONSET, 0, samples))
    body = Packet._unpack(frame, 24, len(frame) - 28)
    assert not body.samples.flags.writeable
    frame[24 + PACKET_PREFIX_LEN] ^= 0xFF  # the frame's bytes change: the body does not
    assert np.array_equal(body.samples, samples)


def test_the_wire_layout_is_the_one_the_test_builds():
    assert _PACKET.size == PACKET_PREFIX_LEN and struct.calcsize("<IfQHHHBB") == _PACKET.size


def test_a_decoded_frame_is_the_frame_its_constructor_gives():
    from dataclasses import fields

    from ae_tactile.protocol import FrameEncoder, StreamDecoder
    from ae_tactile.protocol.frames import Frame

    enc = FrameEncoder(boot=True)
    body = Packet(np.ones((4, 8), np.int16), 10_000_000, 2.0**-11, first_sample_index=3)
    wire = [enc.encode(body, 100 + k) for k in range(3)]
    enc.skip(2)  # a gap of two frames before the last
    wire.append(enc.encode(body, 200))
    got = StreamDecoder().feed(b"".join(wire))
    offsets = np.cumsum([0] + [len(w) for w in wire])[:-1]
    for f, off in zip(got, offsets):
        want = Frame(f.body, f.seq, f.timestamp_us, f.flags, f.device_time_us,
                     f.dropped_before, f.restart, int(off))
        assert all(getattr(f, a.name) == getattr(want, a.name) for a in fields(Frame))
        assert repr(f) == repr(want) and f == want
    assert [f.dropped_before for f in got] == [0, 0, 0, 2]
    assert [f.device_time_us for f in got] == [100, 101, 102, 200]
    assert [f.restart for f in got] == [False] * 4
