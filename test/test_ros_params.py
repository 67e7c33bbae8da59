# SPDX-License-Identifier: Apache-2.0
"""Run-time parameters through the real parameter services: tuning parameters change at
once (validated by the same table), structural ones are read-only with the reason,
integers are accepted for floats; event types agree between the core and the messages."""

import pytest

from conftest import require_ros
from ros_helpers import spin_until


@pytest.fixture
def driver_and_client(ros_context, tmp_path):
    require_ros()
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.parameter_client import AsyncParameterClient

    from ae_tactile.ros.driver_node import DriverNode

    drv = DriverNode(
        context=ros_context,
        parameter_overrides=[
            Parameter("port", value=str(tmp_path / "no_device_here")),
            Parameter("localization.min_snr_db", value=10),
        ],
    )  # an integer for a float
    client_node = __import__("rclpy").create_node("param_client", context=ros_context)
    client = AsyncParameterClient(client_node, drv.get_fully_qualified_name())
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(drv)
    ex.add_node(client_node)
    assert spin_until(ex, lambda: client.services_are_ready())

    def set_params(**values):
        fut = client.set_parameters(
            [Parameter(k.replace("__", "."), value=v) for k, v in values.items()]
        )
        assert spin_until(ex, fut.done)
        return fut.result().results

    yield drv, set_params
    ex.shutdown()
    client_node.destroy_node()
    drv.destroy_node()


def test_tuning_parameters_change_at_once_and_are_validated(driver_and_client):
    drv, set_params = driver_and_client
    loc = drv.pipeline.localizer
    assert loc.min_snr_db == 10.0  # int accepted at start-up
    (r,) = set_params(localization__min_snr_db=20)
    assert r.successful and loc.min_snr_db == 20.0
    (r,) = set_params(localization__min_snr_db=500.0)
    assert not r.successful and "range" in r.reason and loc.min_snr_db == 20.0
    (r,) = set_params(localization__method="gradient")
    assert r.successful and loc.method == "gradient"
    (r,) = set_params(localization__method="magic")
    assert not r.successful and loc.method == "gradient"
    assert loc.interference_echo_min < 0 and loc.echo_min_in_use is None  # learnt, not yet
    (r,) = set_params(localization__interference_echo_min=0.25)
    assert r.successful and loc.echo_min_in_use == 0.25
    (r,) = set_params(localization__interference_echo_min=2.0)
    assert not r.successful and loc.echo_min_in_use == 0.25
    (r,) = set_params(localization__interference_echo_min=0.0)
    assert r.successful and loc.echo_min_in_use is None
    assert loc.interference_timing is True
    (r,) = set_params(localization__interference_timing=False)
    assert r.successful and loc.interference_timing is False
    assert loc.weak_releases is True and loc.weak_release_min_snr_db == -5.0
    r1, r2 = set_params(
        localization__weak_releases=False, localization__weak_release_min_snr_db=-2.0
    )
    assert r1.successful and r2.successful
    assert loc.weak_releases is False and loc.weak_release_min_snr_db == -2.0
    (r,) = set_params(localization__weak_release_min_snr_db=-90.0)  # outside -20 .. 80
    assert not r.successful and loc.weak_release_min_snr_db == -2.0
    # the stated front end: taken (calibrated on the device's touches before it refines),
    # refused by name when it cannot be read, withdrawn with ""
    assert loc.front_end_status().startswith("none")
    (r,) = set_params(localization__front_end="highpass_hz=50e3 highpass_order=1 "
                                                "lowpass_hz=800e3 lowpass_order=2")
    assert r.successful and loc.front_end_status().startswith("calibrating")
    assert loc.localizer.front_end is None  # nothing refined before it is calibrated
    (r,) = set_params(localization__front_end="lowpass_family=elliptic")
    assert not r.successful and "lowpass_family" in r.reason
    assert loc.config.front_end.startswith("highpass_hz=50e3")
    (r,) = set_params(localization__front_end="")
    assert r.successful and loc.front_end_status().startswith("none")
    (r,) = set_params(slip__sliding_speed_m_s=0.02)
    assert r.successful
    assert drv.slip_stage.detector.config.sliding_speed_m_s == pytest.approx(0.02)
    (r,) = set_params(slip__quiet_s=-1.0)
    assert not r.successful


def test_structural_parameters_are_read_only_with_the_reason(driver_and_client):
    drv, set_params = driver_and_client
    (r,) = set_params(port="/dev/ttyUSB9")
    assert not r.successful and "read-only" in r.reason
    assert drv.link_config.port.endswith("no_device_here")
    d = drv.describe_parameter("port")
    assert d.read_only and "start-up" in d.description  # the reason, in the descriptor
    d = drv.describe_parameter("localization.min_snr_db")
    assert not d.read_only and "unit: dB" in d.description and "range" in d.description


def test_pre_trigger_without_packet_length_is_refused(ros_context, tmp_path):
    require_ros()
    from rclpy.parameter import Parameter

    from ae_tactile.ros.driver_node import DriverNode
    from ae_tactile.ros.params import ParameterError

    with pytest.raises(ParameterError, match="packet_samples"):
        DriverNode(
            context=ros_context,
            parameter_overrides=[
                Parameter("port", value=str(tmp_path / "x")),
                Parameter("pre_trigger_samples", value=50),
            ],
        )


def test_event_types_agree_between_core_and_messages():
    require_ros()
    from ae_tactile.msg import ContactEvent
    from ae_tactile.msg import ContactState as ContactStateMsg
    from ae_tactile.records import ContactState, EventType

    for t in EventType:
        assert getattr(ContactEvent, t.name) == int(t)
    for s in ContactState:
        assert getattr(ContactStateMsg, s.name) == int(s)


def test_a_fingertip_whose_body_disagrees_with_the_parameters_wins_with_one_warning(
    ros_context, tmp_path
):
    """A water-skin fingertip run with the silicone parameters: the driver warns once and
    localizes with the fingertip's body (and says so on sensor_info)."""
    require_ros()
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from ae_tactile.msg import SensorInfo
    from ae_tactile.ros.driver_node import DriverNode
    from ae_tactile.ros.node_utils import LATCHED
    from ae_tactile.ros.sim_fingertip_node import SimFingertipNode, default_scene_path

    link = str(tmp_path / "fingertip")
    sim = SimFingertipNode(
        context=ros_context,
        parameter_overrides=[
            Parameter("scene", value=default_scene_path("paper_positions.yaml")),
            Parameter("link_path", value=link),
        ],
    )
    drv = DriverNode(
        context=ros_context,
        parameter_overrides=[
            Parameter("port", value=link),
            Parameter("medium", value="silicone"),
            Parameter("sound_speed_m_s", value=1000.0),
        ],
    )
    listener = __import__("rclpy").create_node("info_listener", context=ros_context)
    infos = []
    listener.create_subscription(SensorInfo, "sensor_info", infos.append, LATCHED)
    ex = SingleThreadedExecutor(context=ros_context)
    for n in (sim, drv, listener):
        ex.add_node(n)
    try:
        assert spin_until(ex, lambda: drv._body_warned)
        assert drv.geometry.sound_speed_m_s == pytest.approx(1480.0)
        assert drv.pipeline.localizer.geometry.sound_speed_m_s == pytest.approx(1480.0)
        assert spin_until(ex, lambda: infos and infos[-1].medium == "water_skin")
        assert infos[-1].sound_speed_m_s == pytest.approx(1480.0)
    finally:
        ex.shutdown()
        for n in (listener, drv, sim):
            n.destroy_node()


def _packet_array(ids, *, bad=(), n_samples=400):
    """A PacketArray of simulated touches; packets in ``bad`` get a broken sample rate or
    too few samples."""
    import numpy as np

    from ae_tactile.geometry import FingertipGeometry
    from ae_tactile.msg import PacketArray
    from ae_tactile.ros.conversions import make_packet
    from ae_tactile.sim import SimConfig
    from ae_tactile.sim.triggered import render_triggered

    geo = FingertipGeometry()
    k = min(len(ids), 64)
    tp = render_triggered(
        geo.surface_point_from_xy(np.linspace(-3e-3, 3e-3, k), np.zeros(k)),
        SimConfig(),
        snr_db=30.0,
        rng=4,
    )
    msg = PacketArray()
    msg.header.frame_id = "tip"
    packets = []
    for j, sid in enumerate(ids):
        x = tp.samples_v[j % k]
        fs = tp.sample_rate_hz
        if sid in bad:
            if sid % 2:
                fs = 0.0
            else:
                x = x[:, :3]
        packets.append(
            make_packet(
                x,
                stamp_ns=10**9 + sid * 10**6,
                sample_rate_hz=fs or 1.0,
                onset_index=min(int(tp.onset_index[j % k]), x.shape[1] - 1),
                sequence_id=sid,
            )
        )
        if sid in bad and sid % 2:
            packets[-1].sample_rate_hz = 0.0
    msg.packets = packets
    return msg


def test_localizer_node_rejects_bad_packets_one_by_one_and_counts_missing_ones(ros_context):
    """A PacketArray with a packet at sample rate 0 and one of 3 samples: the good packets
    of the same array are localized, the two bad ones counted by reason; a sequence gap
    (an array that never arrived) is counted as missing packets."""
    require_ros()
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from ae_tactile.msg import Emission, PacketArray
    from ae_tactile.ros.localizer_node import LocalizerNode

    loc = LocalizerNode(context=ros_context)
    node = __import__("rclpy").create_node("packet_source", context=ros_context)
    pub = node.create_publisher(
        PacketArray, "packets", QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    )
    got = []
    node.create_subscription(Emission, "localized", got.append, 100)  # the split path
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(loc)
    ex.add_node(node)
    try:
        assert spin_until(ex, lambda: pub.get_subscription_count() >= 1)
        pub.publish(_packet_array(list(range(8)), bad=(3, 6)))
        assert spin_until(ex, lambda: len(got) >= 6 and loc.idle())
        assert sorted(e.packet_ids[0] for e in got) == [0, 1, 2, 4, 5, 7]
        assert loc.counts["rejected_MALFORMED_sample_rate"] == 1
        assert loc.counts["rejected_MALFORMED_too_short"] == 1
        pub.publish(_packet_array([5000]))  # 4992 packets never arrived
        assert spin_until(ex, lambda: len(got) >= 7 and loc.idle())
        assert loc.counts["packets_missing"] == 5000 - 8
    finally:
        ex.shutdown()
        node.destroy_node()
        loc.destroy_node()
