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
    assert spin_until(ex, lambda: client.services_are_ready(), 20.0)

    def set_params(**values):
        fut = client.set_parameters(
            [Parameter(k.replace("__", "."), value=v) for k, v in values.items()]
        )
        assert spin_until(ex, fut.done, 20.0)
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
    from ae_tactile.pipeline import EventType
    from ae_tactile.slip.types import SlipEventType

    for t in EventType:
        assert getattr(ContactEvent, t.name) == int(t)
    for t in SlipEventType:
        assert EventType[t.name] == int(t)


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
        assert spin_until(ex, lambda: drv._body_warned, 30.0)
        assert drv.geometry.sound_speed_m_s == pytest.approx(1480.0)
        assert drv.pipeline.localizer.geometry.sound_speed_m_s == pytest.approx(1480.0)
        assert spin_until(ex, lambda: infos and infos[-1].medium == "water_skin", 20.0)
        assert infos[-1].sound_speed_m_s == pytest.approx(1480.0)
    finally:
        ex.shutdown()
        for n in (listener, drv, sim):
            n.destroy_node()
