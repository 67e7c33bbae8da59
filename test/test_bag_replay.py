# SPDX-License-Identifier: Apache-2.0
"""Recorded raw packets replay offline: rosbag2 (sqlite3 / MCAP) -> re-localized events.

The bags hold real CDR-serialized PacketArray messages: written here from simulated
packets through the rosbags library, and (test_live_packets_record_and_replay) recorded
from the running ROS pipeline with an rclpy raw subscription, as `ros2 bag record` would.
"""

import csv
import os
import time

import numpy as np
import pytest

if os.environ.get("AE_TACTILE_REQUIRE_ROS") != "1":  # under `make test` it must be there
    pytest.importorskip(
        "rosbags", reason="rosbags is installed by `make test` (tools/requirements.txt)"
    )

from ae_tactile.bagtools import main as replay_main  # noqa: E402
from ae_tactile.bagtools import read_bag, replay, typestore, write_bag  # noqa: E402
from ae_tactile.geometry import FingertipGeometry  # noqa: E402
from ae_tactile.sim import SimConfig, render_triggered  # noqa: E402


def write_packet_bag(path, storage="sqlite3", ns="/finger1"):
    """A bag of PacketArray messages (3 paper touches + 3 pins) and a SensorInfo."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = typestore()
    T = store.types
    geo = FingertipGeometry()
    pts = geo.surface_point_from_xy(
        np.array([0.0, 2.5e-3, 5e-3, -3e-3, 3e-3, 0.0]),
        np.array([0.0, 0.0, 0.0, 2e-3, 2e-3, -3e-3]),
    )
    pk = render_triggered(pts, SimConfig(), snr_db=30, rng=3)
    t0 = 1_700_000_000_000_000_000
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    with Writer(path, version=9, storage_plugin=plugin) as w:
        c_info = w.add_connection(
            f"{ns}/sensor_info", "ae_tactile/msg/SensorInfo", typestore=store
        )
        c_pk = w.add_connection(f"{ns}/packets", "ae_tactile/msg/PacketArray", typestore=store)
        info = T["ae_tactile/msg/SensorInfo"](
            header=Header(stamp=Time(sec=0, nanosec=0), frame_id="finger1_tip"),
            serial_number="AE-1",
            firmware_version="0.1.0",
            protocol_version=1,
            medium="water_skin",
            radius_m=geo.radius_m,
            element_offset_m=geo.element_offset_m,
            sound_speed_m_s=geo.sound_speed_m_s,
            sample_rate_hz=10e6,
            adc_bits=12,
            volts_per_count=2**-11,
            channel_gains=np.ones(4, np.float32),
            highpass_hz=1e5,
            trigger_threshold_v=0.0,
        )
        w.write(c_info, t0, store.serialize_cdr(info, "ae_tactile/msg/SensorInfo"))
        for k in range(len(pts)):
            stamp = t0 + k * 5_000_000
            sec, nsec = divmod(stamp, 1_000_000_000)
            packet = T["ae_tactile/msg/Packet"](
                stamp=Time(sec=sec, nanosec=nsec),
                sample_rate_hz=10e6,
                channel_count=4,
                samples_per_channel=pk.samples_v.shape[2],
                samples=pk.samples_v[k].astype(np.float32).ravel(),
                onset_index=int(pk.onset_index[k]),
                sequence_id=k,
                noise_rms_v=float(pk.noise_rms_v[k]),
                saturated=False,
            )
            arr = T["ae_tactile/msg/PacketArray"](
                header=Header(stamp=Time(sec=sec, nanosec=nsec), frame_id="finger1_tip"),
                packets=[packet],
                packets_dropped=0,
                frames_bad_crc=0,
            )
            w.write(c_pk, stamp, store.serialize_cdr(arr, "ae_tactile/msg/PacketArray"))
    return pts


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_bag_of_packets_relocalizes_offline(tmp_path, storage):
    pts = write_packet_bag(tmp_path / "in", storage)
    for method in ("ml", "gradient"):
        res = replay(tmp_path / "in", method=method)
        assert res.packets == 6 and len(res.contacts) == 6 and not res.rejected
        got = np.array([e["point_m"] for e in res.contacts])
        assert np.max(np.linalg.norm(got - pts, axis=1)) < 0.05e-3  # paper's cases, 30 dB
        assert all(
            e["frame_id"] == "finger1_tip" and e["topic_ns"] == "/finger1" for e in res.contacts
        )
    # the paper's six touches 5 ms apart, 2.5-5 mm apart, never released: six contacts
    # begun, each emission read as its contact's touch
    begun = [e for e in res.contact_events if e["event_type"] == 1]
    assert len({e["contact_id"] for e in begun}) == len(begun) >= 1
    assert {e["contact_id"] for e in res.contacts} <= {e["contact_id"] for e in begun}
    # events to a new bag, read back with rosbags: every field of the emissions and the
    # contacts' events, contact ids and readings included
    n = write_bag(res, tmp_path / "out", storage)
    from rosbags.highlevel import AnyReader

    with AnyReader([tmp_path / "out"], default_typestore=typestore()) as r:
        topics = {c.topic for c in r.connections}
        msgs = [(c.topic, r.deserialize(raw, c.msgtype)) for c, _, raw in r.messages()]
    assert n == len(msgs) == 6 + len(res.contact_events) + len(res.slip)
    assert {"/finger1/emissions", "/finger1/contacts"} <= topics
    em = [m for t, m in msgs if t == "/finger1/emissions"]
    by_time = sorted(res.contacts, key=lambda e: e["time_ns"])
    xyz = np.array([[m.position.x, m.position.y, m.position.z] for m in em])
    assert np.allclose(xyz, np.array([e["point_m"] for e in by_time]))
    assert [(m.reading, m.contact_id, m.polarity, tuple(m.packet_ids)) for m in em] == [
        (e["reading"], e["contact_id"], e["polarity"], (e["packet_id"],)) for e in by_time]
    ce = [m for t, m in msgs if t == "/finger1/contacts"]
    assert sorted((m.event_type, m.contact_id) for m in ce) == sorted(
        (e["event_type"], e["contact_id"]) for e in res.contact_events)


def test_replay_cli_writes_csv(tmp_path):
    write_packet_bag(tmp_path / "in")
    assert (
        replay_main([str(tmp_path / "in"), str(tmp_path / "events.csv"), "--method", "gcc_phat"])
        == 0
    )
    rows = list(csv.DictReader(open(tmp_path / "events.csv")))
    em = [r for r in rows if r["topic"] == "emissions"]
    assert len(em) == 6 and all(r["polarity"] == "1" and r["reading"] for r in em)
    assert all(r["event_type"] in ("TOUCH", "DETOUCH") for r in rows if r["topic"] == "contacts")
    assert {r["contact_id"] for r in em} <= {r["contact_id"] for r in rows
                                             if r["topic"] == "contacts"}
    assert replay_main([str(tmp_path / "missing"), str(tmp_path / "x.csv")]) == 2


def test_replay_cli_draws_a_picture_of_the_replay(tmp_path):
    pytest.importorskip("matplotlib", reason="the PNG summary needs matplotlib (optional)")
    write_packet_bag(tmp_path / "in")
    png = tmp_path / "replay.png"
    assert (
        replay_main([str(tmp_path / "in"), str(tmp_path / "events.csv"), "--png", str(png)]) == 0
    )
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000


def test_live_packets_record_and_replay(ros_context, tmp_path):
    """Record the live pipeline's packets (CDR bytes from rclpy, as ros2 bag record stores
    them), then re-localize offline and compare with the live localizer's events."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rosbags.rosbag2 import Writer

    from ae_tactile.msg import Emission, PacketArray, SensorInfo
    from ae_tactile.ros.conversions import time_msg_to_ns
    from ae_tactile.ros.driver_node import DriverNode
    from ae_tactile.ros.localizer_node import LocalizerNode
    from ae_tactile.ros.node_utils import LATCHED
    from ae_tactile.ros.sim_fingertip_node import SimFingertipNode, default_scene_path

    from ros_helpers import spin_until

    sim = SimFingertipNode(
        context=ros_context,
        parameter_overrides=[Parameter("scene", value=default_scene_path("random_touches.yaml"))],
    )
    drv = DriverNode(
        context=ros_context,
        parameter_overrides=[
            Parameter("port", value=sim.port),
            Parameter("reliable_qos", value=True),
            Parameter("pipeline", value=False),  # the velodyne-style split
            Parameter("wait_for_subscribers", value=2),
        ],
    )  # the recorder and the localizer
    loc = LocalizerNode(
        context=ros_context, parameter_overrides=[Parameter("reliable_qos", value=True)]
    )
    rec = __import__("rclpy").create_node("recorder", context=ros_context)
    store = typestore()
    raw_packets, raw_info, live = [], [], []
    rec.create_subscription(
        PacketArray,
        "packets",
        lambda b: raw_packets.append((time.time_ns(), b)),
        QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE),
        raw=True,
    )
    rec.create_subscription(
        SensorInfo,
        "sensor_info",
        lambda b: raw_info.append((time.time_ns(), b)),
        LATCHED,
        raw=True,
    )
    rec.create_subscription(Emission, "localized", live.append, 1000)
    ex = SingleThreadedExecutor(context=ros_context)
    for n in (sim, drv, loc, rec):
        ex.add_node(n)
    try:
        spin_until(ex, lambda: sim.device.finished(time.monotonic_ns()))
        # until every published packet is recorded, localized and its event received
        assert spin_until(
            ex,
            lambda: (
                loc.counts["packets"] == drv.published_packets
                and loc.idle()
                and len(live) == loc.counts["events"]
            ),
        ), f"localized {loc.counts['packets']} of {drv.published_packets}, idle {loc.idle()}"
        spin_until(ex, lambda: False, 0.3)
    finally:
        ex.shutdown()
        for n in (drv, loc, rec, sim):
            n.destroy_node()
    assert len(raw_packets) >= 20 and raw_info
    with Writer(tmp_path / "live", version=9) as w:
        ci = w.add_connection("/sensor_info", "ae_tactile/msg/SensorInfo", typestore=store)
        cp = w.add_connection("/packets", "ae_tactile/msg/PacketArray", typestore=store)
        for t, b in raw_info:
            w.write(ci, t, b)
        for t, b in raw_packets:
            w.write(cp, t, b)
    # the recorded bytes decode with the package's own definitions
    arrays = [
        m for _, mt, _, m in read_bag(tmp_path / "live", store) if mt.endswith("PacketArray")
    ]
    assert len(arrays) == len(raw_packets) and sum(len(m.packets) for m in arrays) >= 20
    res = replay(tmp_path / "live", method="ml")
    assert len(res.contacts) == len(live) >= 20
    # matched packet by packet (not by time order: two emissions a few us apart may be
    # stamped in either order once the live localizer has learnt channel delays)
    live_by_packet = {tuple(int(i) for i in e.packet_ids):
                      (np.array([e.position.x, e.position.y, e.position.z]),
                       time_msg_to_ns(e.header.stamp)) for e in live}
    off_by_packet = {(int(e["packet_id"]),): (np.asarray(e["point_m"]), e["time_ns"])
                     for e in res.contacts}
    assert live_by_packet.keys() == off_by_packet.keys()
    diff = {k: float(np.max(np.abs(live_by_packet[k][0] - off_by_packet[k][0])))
            for k in live_by_packet}
    # same packets, same estimator: same answer
    assert max(diff.values()) < 1e-9, sorted(
        (v, k, live_by_packet[k][1] - off_by_packet[k][1]) for k, v in diff.items() if v >= 1e-9)
    off_xyz = np.array([e["point_m"] for e in res.contacts])
    alt = replay(tmp_path / "live", method="gradient")  # other parameters, same data
    assert len(alt.contacts) == len(live)
    assert (
        np.sqrt(
            np.mean(np.sum((np.array([e["point_m"] for e in alt.contacts]) - off_xyz) ** 2, 1))
        )
        < 0.1e-3
    )
