# SPDX-License-Identifier: Apache-2.0
"""The three messages cross real DDS between two rclpy nodes, bit-exact."""

import math

import numpy as np
import pytest

from conftest import require_ros
from ros_helpers import spin_until, wait_for_subscribers


@pytest.fixture
def two_nodes(ros_context):
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    sender = Node("test_sender", context=ros_context)
    receiver = Node("test_receiver", context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    executor.add_node(sender)
    executor.add_node(receiver)
    yield sender, receiver, executor
    executor.shutdown()
    sender.destroy_node()
    receiver.destroy_node()


def exchange(two_nodes, msg_type, topic, msg):
    sender, receiver, executor = two_nodes
    received = []
    receiver.create_subscription(msg_type, topic, received.append, 10)
    pub = sender.create_publisher(msg_type, topic, 10)
    assert wait_for_subscribers(executor, pub), "DDS discovery did not match the subscription"
    pub.publish(msg)
    assert spin_until(executor, lambda: len(received) == 1), f"no {msg_type.__name__} received"
    return received[0]


def random_packet(rng, seq, n=400):
    from ae_tactile.ros.conversions import make_packet

    samples = rng.standard_normal((4, n)).astype(np.float32)
    samples[0, :3] = [np.float32(1e-38), np.float32(-3.4e38), np.float32(np.pi)]  # edge values
    packet = make_packet(
        samples,
        stamp_ns=1_700_000_000_123_456_789 + seq,
        sample_rate_hz=10e6,
        onset_index=123,
        sequence_id=2**40 + seq,
        noise_rms_v=0.0125,
        saturated=bool(seq % 2),
    )
    return packet, samples


def test_event_type_constants_exist_and_differ():
    require_ros()
    from ae_tactile.msg import ContactEvent

    values = [
        ContactEvent.TOUCH,
        ContactEvent.DETOUCH,
        ContactEvent.SLIP_PRECURSOR,
        ContactEvent.SLIP,
        ContactEvent.TEXTURE,
    ]
    assert len(set(values)) == 5 and all(v > 0 for v in values)


def test_packet_round_trip_bit_exact(two_nodes):
    from ae_tactile.msg import Packet
    from ae_tactile.ros.conversions import packet_samples, time_msg_to_ns

    packet, samples = random_packet(np.random.default_rng(1), seq=7)
    got = exchange(two_nodes, Packet, "t_packet", packet)
    x = packet_samples(got)
    assert x.dtype == np.float32 and x.shape == (4, 400)
    assert np.array_equal(x.view(np.uint32), samples.view(np.uint32))  # bit-exact
    assert time_msg_to_ns(got.stamp) == 1_700_000_000_123_456_796
    assert got.sequence_id == 2**40 + 7 and got.onset_index == 123 and got.saturated
    assert got.channel_count == 4 and got.sample_rate_hz == 10e6
    assert got.noise_rms_v == np.float32(0.0125)


def test_packet_array_round_trip(two_nodes):
    from ae_tactile.msg import PacketArray
    from ae_tactile.ros.conversions import packet_samples

    rng = np.random.default_rng(2)
    pairs = [random_packet(rng, seq) for seq in range(5)]
    msg = PacketArray()
    msg.header.frame_id = "finger_1/ae_tactile"
    msg.packets = [p for p, _ in pairs]
    msg.packets_dropped = 3
    msg.frames_bad_crc = 2**33
    got = exchange(two_nodes, PacketArray, "t_packets", msg)
    assert got.header.frame_id == "finger_1/ae_tactile"
    assert got.packets_dropped == 3 and got.frames_bad_crc == 2**33
    assert [p.sequence_id for p in got.packets] == [2**40 + s for s in range(5)]
    for p, (_, samples) in zip(got.packets, pairs):
        assert np.array_equal(packet_samples(p).view(np.uint32), samples.view(np.uint32))


def test_contact_event_round_trip(two_nodes):
    from ae_tactile.msg import ContactEvent

    msg = ContactEvent()
    msg.header.frame_id = "fingertip"
    msg.event_type = ContactEvent.SLIP_PRECURSOR
    msg.position.x, msg.position.y, msg.position.z = 2.5e-3, -1e-3, 9.62e-3
    cov = np.arange(9, dtype=np.float64) * 1e-10
    msg.position_covariance = cov
    msg.polar_angle_rad, msg.azimuth_angle_rad = 0.27, -0.38
    msg.tau_x_s, msg.tau_y_s = 248.0227e-9, -99.1e-9
    msg.amplitude_v, msg.confidence = -0.25, 0.875
    msg.packet_ids = [1, 2, 2**63]
    msg.emission_rate_hz = 312.5
    msg.spatial_period_m = math.nan
    msg.slip_direction.x, msg.slip_direction.y, msg.slip_direction.z = 1.0, 0.0, 0.0
    got = exchange(two_nodes, ContactEvent, "t_contacts", msg)
    assert got.event_type == ContactEvent.SLIP_PRECURSOR
    assert (got.position.x, got.position.y, got.position.z) == (2.5e-3, -1e-3, 9.62e-3)
    assert np.array_equal(np.asarray(got.position_covariance), cov)
    assert (got.tau_x_s, got.tau_y_s) == (248.0227e-9, -99.1e-9)
    assert got.amplitude_v == -0.25 and got.confidence == 0.875
    assert list(got.packet_ids) == [1, 2, 2**63]
    assert got.emission_rate_hz == 312.5 and math.isnan(got.spatial_period_m)
    assert got.slip_direction.x == 1.0


def contact_event_fields(m):
    """Every field of a ContactEvent, in order (NaN-aware comparison below)."""
    return [
        m.header.stamp.sec,
        m.header.stamp.nanosec,
        m.header.frame_id,
        m.event_type,
        m.position.x,
        m.position.y,
        m.position.z,
        *(float(v) for v in m.position_covariance),
        m.polar_angle_rad,
        m.azimuth_angle_rad,
        m.tau_x_s,
        m.tau_y_s,
        m.amplitude_v,
        m.confidence,
        len(m.packet_ids),
        *(int(v) for v in m.packet_ids),
        m.emission_rate_hz,
        m.spatial_period_m,
        m.slip_direction.x,
        m.slip_direction.y,
        m.slip_direction.z,
        m.contact_id,
    ]


def same_fields(a, b):
    fa, fb = contact_event_fields(a), contact_event_fields(b)
    return len(fa) == len(fb) and all(
        x == y or (isinstance(x, float) and math.isnan(x) and math.isnan(y))
        for x, y in zip(fa, fb)
    )


def random_contact_records(rng, n):
    from ae_tactile.pipeline import ContactRecord

    for _ in range(n):
        k = int(rng.integers(0, 6))
        nan_or = lambda v: math.nan if rng.uniform() < 0.3 else v  # noqa: E731
        yield ContactRecord(
            event_type=int(rng.integers(1, 6)),
            time_ns=int(rng.integers(0, 2**31 * 10**9)),
            point_m=tuple(float(v) for v in rng.normal(0, 0.01, 3)),
            covariance_m2=rng.normal(size=(3, 3)) * 1e-9,
            packet_ids=tuple(int(v) for v in rng.integers(0, 2**63, k)),
            polar_rad=nan_or(float(rng.uniform(0, 1.5))),
            azimuth_rad=float(rng.uniform(-3.1, 3.1)),
            tau_x_s=nan_or(float(rng.normal(0, 1e-6))),
            tau_y_s=float(rng.normal(0, 1e-6)),
            amplitude_v=float(rng.normal(0, 0.1)),
            confidence=float(rng.uniform()),
            emission_rate_hz=nan_or(float(rng.uniform(0, 1e3))),
            spatial_period_m=nan_or(float(rng.uniform(0, 1e-3))),
            slip_direction=(nan_or(1.0), 0.0, -0.5),
            contact_id=int(rng.integers(0, 2**32)),
        )


def test_contact_event_wire_bytes_are_what_rclpy_serializes():
    """The driver's hand-written CDR of a ContactEvent against rclpy's own serializer:
    same length, and every field the same once deserialized (the padding bytes rclpy
    leaves uninitialised are the only bytes that may differ)."""
    require_ros()
    from rclpy.serialization import deserialize_message, serialize_message

    from ae_tactile.msg import ContactEvent
    from ae_tactile.ros.conversions import ContactEventWire, contact_event_msg

    rng = np.random.default_rng(11)
    for frame_id in ("", "f", "fingertip", "hand/index_distal_link", "doigt_é"):
        wire = ContactEventWire(frame_id)
        for rec in random_contact_records(rng, 200):
            ours = wire.encode(rec)
            theirs = serialize_message(contact_event_msg(rec, frame_id))
            assert len(ours) == len(theirs)
            a = deserialize_message(ours, ContactEvent)
            assert same_fields(a, deserialize_message(theirs, ContactEvent))
            assert a.header.frame_id == frame_id and len(a.packet_ids) == len(rec.packet_ids)


def test_contact_event_wire_bytes_cross_dds(two_nodes):
    """Published as bytes, received as a ContactEvent by a normal subscription: the same
    fields as the message rclpy would have sent (float32 fields rounded on the wire)."""
    from rclpy.serialization import deserialize_message, serialize_message

    from ae_tactile.msg import ContactEvent
    from ae_tactile.ros.conversions import ContactEventWire, contact_event_msg

    for rec in random_contact_records(np.random.default_rng(3), 3):
        got = exchange(two_nodes, ContactEvent, "t_wire", ContactEventWire("tip").encode(rec))
        sent = deserialize_message(serialize_message(contact_event_msg(rec, "tip")), ContactEvent)
        assert same_fields(got, sent)


def test_contact_state_wire_bytes_are_what_rclpy_serializes():
    """ContactStateWire.encode: the same length as rclpy's serialization of
    contact_state_msg and every field the same once deserialized (NaN points included),
    for 0-5 contacts and frame ids of every length mod 8."""
    require_ros()
    from rclpy.serialization import deserialize_message, serialize_message

    from ae_tactile.msg import ContactState
    from ae_tactile.records import ContactSnapshot
    from ae_tactile.ros.conversions import ContactStateWire, contact_state_msg
    from ae_tactile.slip.types import FingerState

    def fields(m):
        out = [m.header.stamp.sec, m.header.stamp.nanosec, m.header.frame_id, m.state,
               m.state_since.sec, m.state_since.nanosec, m.contact_point.x,
               m.contact_point.y, m.contact_point.z, m.slip_emission_rate_hz,
               m.precursor_count, m.contact_id, len(m.contacts)]
        for c in m.contacts:
            out += [c.id, c.position.x, c.position.y, c.position.z, c.state, c.since.sec,
                    c.since.nanosec, c.slip_emission_rate_hz, c.precursor_count]
        return out

    def same(a, b):
        return len(a) == len(b) and all(
            x == y or (isinstance(x, float) and math.isnan(x) and math.isnan(y))
            for x, y in zip(a, b))

    rng = np.random.default_rng(5)
    for frame_id in ("", "f", "tip", "index_tip", "hand/index_distal_link", "doigt_é"):
        wire = ContactStateWire(frame_id)
        for _ in range(60):
            n = int(rng.integers(0, 6))
            point = (np.full(3, np.nan) if rng.uniform() < 0.3
                     else rng.normal(0, 0.01, 3))
            st = FingerState(int(rng.integers(0, 4)), int(rng.integers(-5, 2**31) * 10**9),
                             point, float(rng.uniform(0, 500)), int(rng.integers(0, 99)),
                             int(rng.integers(-1, 50)), n,
                             int(rng.integers(-1, 2) * rng.integers(0, 2**31 * 10**9)))
            now_ns = int(rng.integers(1, 2**31 * 10**9))
            contacts = [ContactSnapshot(int(rng.integers(1, 2**31)),
                                        tuple(float(v) for v in rng.normal(0, 0.01, 3)),
                                        int(rng.integers(0, 4)),
                                        int(rng.integers(0, 2**31 * 10**9)),
                                        float(rng.uniform(0, 500)), int(rng.integers(0, 99)))
                        for _ in range(n)]
            ours = wire.encode(st, now_ns, contacts)
            theirs = serialize_message(contact_state_msg(st, frame_id, now_ns, contacts))
            assert len(ours) == len(theirs), (frame_id, n)
            assert same(fields(deserialize_message(ours, ContactState)),
                        fields(deserialize_message(theirs, ContactState))), (frame_id, n)


def test_reading_and_state_constants_agree_with_the_records():
    """Emission.msg's readings are ae_tactile.records.Reading's values, ContactState.msg's
    states ContactState's, ContactEvent.msg's types EventType's."""
    require_ros()
    from ae_tactile import records
    from ae_tactile.msg import ContactEvent, ContactState, Emission

    for enum, msg in ((records.Reading, Emission), (records.ContactState, ContactState),
                      (records.EventType, ContactEvent)):
        assert {e.name: int(e) for e in enum} == {e.name: getattr(msg, e.name) for e in enum}


def random_emission_records(rng, n):
    from ae_tactile.records import EmissionRecord

    for _ in range(n):
        k = int(rng.integers(0, 4))
        nan_or = lambda v: math.nan if rng.uniform() < 0.3 else v  # noqa: E731
        yield EmissionRecord(
            time_ns=int(rng.integers(0, 2**31 * 10**9)),
            point_m=tuple(float(v) for v in rng.normal(0, 0.01, 3)),
            covariance_m2=rng.normal(size=(3, 3)) * 1e-9,
            packet_ids=tuple(int(v) for v in rng.integers(0, 2**63, k)),
            polarity=int(rng.choice([-1, 0, 1])),
            reading=int(rng.integers(0, 6)),
            contact_id=int(rng.integers(0, 2**32)),
            polar_rad=nan_or(float(rng.uniform(0, 1.5))),
            azimuth_rad=float(rng.uniform(-3.1, 3.1)),
            tau_x_s=nan_or(float(rng.normal(0, 1e-6))),
            tau_y_s=float(rng.normal(0, 1e-6)),
            amplitude_v=float(rng.normal(0, 0.1)),
            confidence=float(rng.uniform()),
            device_time_ns=int(rng.choice([-1, int(rng.integers(0, 2**62))])),
        )


def emission_fields(m):
    """Every field of an Emission, in order, NaN as a string (comparable)."""
    out = [m.header.stamp.sec, m.header.stamp.nanosec, m.header.frame_id, m.device_time_ns,
           *(int(v) for v in m.packet_ids), m.position.x, m.position.y, m.position.z,
           *(float(v) for v in m.position_covariance), m.polar_angle_rad, m.azimuth_angle_rad,
           m.tau_x_s, m.tau_y_s, m.polarity, m.amplitude_v, m.confidence, m.reading,
           m.contact_id]
    return [("nan" if isinstance(v, float) and math.isnan(v) else v) for v in out]


def test_emission_wire_bytes_are_what_rclpy_serializes():
    """The driver's hand-written CDR of an Emission against rclpy's own serializer (same
    length, every field the same once deserialized), and the record read back from the
    message (the slip_detector node's and the bag tools' input) is the record sent."""
    require_ros()
    from rclpy.serialization import deserialize_message, serialize_message

    from ae_tactile.msg import Emission
    from ae_tactile.ros.conversions import EmissionWire, emission_msg, emission_record_of_msg

    rng = np.random.default_rng(12)
    for frame_id in ("", "f", "fingertip", "hand/index_distal_link", "doigt_é"):
        wire = EmissionWire(frame_id)
        for rec in random_emission_records(rng, 200):
            ours = wire.encode(rec)
            theirs = serialize_message(emission_msg(rec, frame_id))
            assert len(ours) == len(theirs)
            a = deserialize_message(ours, Emission)
            assert emission_fields(a) == emission_fields(deserialize_message(theirs, Emission))
            back = emission_record_of_msg(a)
            assert (back.time_ns, back.packet_ids, back.polarity, back.reading, back.contact_id,
                    back.device_time_ns) == (rec.time_ns, rec.packet_ids, rec.polarity,
                                             rec.reading, rec.contact_id, rec.device_time_ns)
            assert back.point_m == rec.point_m


def test_emission_and_contact_state_cross_dds(two_nodes):
    """An Emission published as bytes and a ContactState listing three contacts arrive with
    every field."""
    from rclpy.serialization import deserialize_message, serialize_message

    from ae_tactile.msg import ContactState, Emission
    from ae_tactile.records import ContactSnapshot
    from ae_tactile.ros.conversions import (
        EmissionWire,
        contact_state_msg,
        emission_msg,
        time_msg_to_ns,
    )
    from ae_tactile.slip import SlipDetector

    for rec in random_emission_records(np.random.default_rng(4), 2):
        got = exchange(two_nodes, Emission, "t_emission", EmissionWire("tip").encode(rec))
        sent = deserialize_message(serialize_message(emission_msg(rec, "tip")), Emission)
        assert emission_fields(got) == emission_fields(sent)
    st = SlipDetector().state
    contacts = [ContactSnapshot(i, (x, -2e-3, 9.7e-3), 1 + i % 3, 10**9 + i, 50.0 * i, i)
                for i, x in ((3, 3e-3), (7, 7e-3), (9, 9e-3))]
    got = exchange(two_nodes, ContactState, "t_state",
                   contact_state_msg(st, "tip", 2 * 10**9, contacts))
    assert [(c.id, c.state, time_msg_to_ns(c.since), c.precursor_count) for c in got.contacts] \
        == [(3, 1, 10**9 + 3, 3), (7, 2, 10**9 + 7, 7), (9, 1, 10**9 + 9, 9)]
    assert [(c.position.x, c.slip_emission_rate_hz) for c in got.contacts] == [
        (3e-3, 150.0), (7e-3, 350.0), (9e-3, 450.0)]
    assert got.state == ContactState.NO_CONTACT and got.contact_id == 0


def test_make_packet_rejects_bad_shapes():
    require_ros()
    from ae_tactile.ros.conversions import make_packet

    with pytest.raises(ValueError, match=r"shape \(4, N\)"):
        make_packet(
            np.zeros((3, 10)), stamp_ns=0, sample_rate_hz=1e6, onset_index=0, sequence_id=0
        )
    with pytest.raises(ValueError, match="onset_index"):
        make_packet(
            np.zeros((4, 10)), stamp_ns=0, sample_rate_hz=1e6, onset_index=10, sequence_id=0
        )
