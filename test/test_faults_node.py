# SPDX-License-Identifier: Apache-2.0
"""Issue 39's faults as the driver node shows them: the link's liveness and clock-step
settings are driver parameters, its fault counters reach /diagnostics (a port another
driver owns is an ERROR naming the port), ``--help`` does not start the driver, unknown
parameter names are warned about, and the ``localizer`` node counts oversized packets."""

import os
import subprocess
import sys

import pytest

from conftest import installed_executable, require_ros
from ros_helpers import spin_until


def _driver(ctx, port, *params):
    from rclpy.parameter import Parameter

    from ae_tactile.ros.driver_node import DriverNode

    return DriverNode(
        context=ctx,
        parameter_overrides=[
            Parameter("port", value=str(port)),
            Parameter("pipeline", value=False),  # no localizer warm-up: the link only
            Parameter("diagnostics_period_s", value=0.1),
            *params,
        ],
    )


def test_liveness_and_clock_step_parameters_reach_the_link(ros_context, tmp_path):
    from rclpy.parameter import Parameter

    from ae_tactile.ros.params import ParameterError

    drv = _driver(
        ros_context,
        tmp_path / "no_device",
        Parameter("acquisition_timeout_s", value=4.0),
        Parameter("clock_step_s", value=0.5),
        Parameter("clock_step_frames", value=7),
    )
    try:
        c = drv.link.config
        assert (c.acquisition_timeout_s, c.clock_step_s, c.clock_step_frames) == (4.0, 0.5, 7)
    finally:
        drv.destroy_node()
    drv = _driver(ros_context, tmp_path / "no_device", Parameter("acquisition_timeout_s", value=0))
    try:
        assert drv.link.config.acquisition_timeout_s == 0  # 0: never restarted
    finally:
        drv.destroy_node()
    with pytest.raises(ParameterError, match="acquisition_timeout_s"):
        _driver(ros_context, tmp_path / "no_device", Parameter("acquisition_timeout_s", value=0.5))


def test_expert_marks_and_defaults_follow_the_link():
    require_ros()
    from ae_tactile.link import LinkConfig
    from ae_tactile.ros.driver_params import DRIVER_PARAMS
    from ae_tactile.ros.params import is_expert

    by_name = {p.name: p for p in DRIVER_PARAMS}
    ref = LinkConfig(port="loop://")
    for name in ("acquisition_timeout_s", "clock_step_s", "clock_step_frames"):
        assert by_name[name].default == getattr(ref, name)
    # the README's handful (at most 10) leaves all three to experts, documented in
    # docs/parameters.md and docs/driver.md's fault table
    assert all(is_expert(n) for n in ("acquisition_timeout_s", "clock_step_s",
                                      "clock_step_frames"))


def test_port_owned_by_another_driver_is_a_diagnostics_error_naming_it(ros_context, tmp_path):
    """A port whose lock another link holds: the driver's link status is ERROR, 'port
    busy', naming the port and the owner's pid; the link's fault counters are all there."""
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
    from rclpy.executors import SingleThreadedExecutor

    from ae_tactile.link.port import PortLock

    port = tmp_path / "tty_owned"
    port.write_text("")
    owner = PortLock(str(port))
    got = []
    listener = rclpy.create_node("diag_listener", context=ros_context)
    listener.create_subscription(
        DiagnosticArray,
        "/diagnostics",
        lambda m: got.extend(s for s in m.status if s.name.endswith(": fingertip link")),
        100,
    )
    drv = _driver(ros_context, port)
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(drv)
    ex.add_node(listener)
    try:
        assert spin_until(ex, lambda: any(s.message.startswith("port busy") for s in got))
        st = [s for s in got if s.message.startswith("port busy")][-1]
        assert st.level == DiagnosticStatus.ERROR
        assert str(port) in st.message and f"pid {os.getpid()}" in st.message, st.message
        values = {kv.key: kv.value for kv in st.values}
        for key in ("acquisition_restarts", "acquisition_reconnects", "port_busy", "clock_steps"):
            assert key in values, key
        assert int(values["port_busy"]) >= 1
    finally:
        ex.shutdown()
        drv.destroy_node()
        listener.destroy_node()
        owner.release()


def test_link_counters_make_the_status_warn():
    require_ros()
    from diagnostic_msgs.msg import DiagnosticStatus

    from ae_tactile.ros.diagnostics import link_status

    base = {"state": "connected", "last_error": ""}
    assert link_status("/d", "hw", base, {}, 0).level == DiagnosticStatus.OK
    for key in ("acquisition_restarts", "acquisition_reconnects", "clock_steps"):
        st = link_status("/d", "hw", dict(base, **{key: 1}), {}, 0)
        assert st.level == DiagnosticStatus.WARN and key.replace("_", " ") in st.message


@pytest.mark.parametrize("how", ["python -m", "installed"])
def test_driver_help_prints_usage_and_exits_without_starting(how, tmp_path):
    """``python -m ae_tactile.ros.driver_node --help`` and the installed ``driver --help``
    print the usage with the driver's parameters and exit 0 at once: no node, no port."""
    exe = installed_executable("driver")
    cmd = [exe] if how == "installed" else [sys.executable, "-m", "ae_tactile.ros.driver_node"]
    out = subprocess.run(
        cmd + ["--help"], capture_output=True, text=True, timeout=60,
        cwd=tmp_path,  # the installed package (with its messages), not the source tree
    )
    assert out.returncode == 0, out.stdout + out.stderr
    assert out.stdout.startswith("usage: ros2 run ae_tactile driver "), out.stdout[:300]
    for name in ("port (string", "acquisition_timeout_s", "localization.min_snr_db"):
        assert name in out.stdout, name
    assert "cannot open" not in out.stdout + out.stderr
    assert "driver on" not in out.stdout + out.stderr


def _rosout_listener(ctx, got):
    import rclpy
    from rcl_interfaces.msg import Log
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    node = rclpy.create_node("rosout_listener", context=ctx)
    qos = QoSProfile(
        depth=1000,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )
    node.create_subscription(Log, "/rosout", got.append, qos)
    return node


def test_unknown_parameter_names_are_warned_once_and_the_driver_runs(ros_context, tmp_path):
    """A misspelt name ('localisation.min_snr_db') given to the driver: one WARN on its
    logger (/rosout) naming it and the name meant; the node runs, with its known values."""
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from ae_tactile.ros.driver_node import DriverNode

    logs, diags = [], []
    listener = _rosout_listener(ros_context, logs)
    listener.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 100)
    drv = DriverNode(
        context=ros_context,
        parameter_overrides=[
            Parameter("port", value=str(tmp_path / "no_device")),
            Parameter("diagnostics_period_s", value=0.1),
            Parameter("localisation.min_snr_db", value=12.0),
            Parameter("localization.min_snr_db", value=11.0),
            Parameter("linktimeout_s", value=1.0),
        ],
    )
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(drv)
    ex.add_node(listener)

    def warnings():
        return [m.msg for m in logs if "unknown parameter" in m.msg and m.name == "driver"]

    try:
        assert spin_until(ex, lambda: warnings() and len(diags) >= 3), [m.msg for m in logs]
        spin_until(ex, lambda: False, 0.5)
        (text,) = warnings()  # once
        assert "'localisation.min_snr_db'" in text and "'localization.min_snr_db'?" in text
        assert "'linktimeout_s'" in text and "link_timeout_s" in text
        assert drv.pipeline.localizer.min_snr_db == 11.0
    finally:
        ex.shutdown()
        drv.destroy_node()
        listener.destroy_node()


def test_pipeline_names_given_to_a_raw_driver_are_not_warned_about(ros_context, tmp_path):
    """pipeline:=false with a parameter file written for the full driver: its
    localization.* and slip.* names are the driver's own, not unknown."""
    from rclpy.parameter import Parameter

    from ae_tactile.ros.params import unknown_overrides

    drv = _driver(
        ros_context,
        tmp_path / "no_device",
        Parameter("localization.min_snr_db", value=11.0),
        Parameter("slip.track_window_s", value=0.2),
        Parameter("no_such_name", value=1),
    )
    try:
        from ae_tactile.ros.driver_node import _pipeline_names

        assert unknown_overrides(drv, _pipeline_names()) == ["no_such_name"]
    finally:
        drv.destroy_node()


def test_localizer_node_counts_every_packet_of_an_oversized_message(ros_context):
    """One PacketArray (reliable, ~1.7 MB) with good packets around a packet of 100,000
    samples, one whose sizes disagree and one claiming 3 channels:
    every packet is counted, each bad one with its reason (in /diagnostics too), and the
    good neighbours are localized and published."""
    import numpy as np
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from test_ros_params import _packet_array

    from ae_tactile.msg import Emission, PacketArray
    from ae_tactile.ros.conversions import make_packet
    from ae_tactile.ros.localizer_node import LocalizerNode

    loc = LocalizerNode(
        context=ros_context,
        parameter_overrides=[
            Parameter("reliable_qos", value=True),
            Parameter("diagnostics_period_s", value=0.1),
        ],
    )
    node = rclpy.create_node("packet_source", context=ros_context)
    pub = node.create_publisher(
        PacketArray, "packets", QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    )
    got, diags = [], []
    node.create_subscription(Emission, "localized", got.append, 100)  # the split path
    node.create_subscription(
        DiagnosticArray,
        "/diagnostics",
        lambda m: diags.extend(s for s in m.status if s.name.endswith(": localization")),
        100,
    )
    msg = _packet_array([0, 1, 2, 6, 7])
    good = list(msg.packets)
    huge = make_packet(
        np.zeros((4, 100_000), np.float32),
        stamp_ns=10**9 + 3 * 10**6,
        sample_rate_hz=10e6,
        onset_index=100,
        sequence_id=3,
    )
    sizes_disagree = make_packet(
        np.zeros((4, 400), np.float32), stamp_ns=10**9 + 4 * 10**6, sample_rate_hz=10e6,
        onset_index=100, sequence_id=4,
    )
    sizes_disagree.samples_per_channel = 100_000
    three_channels = make_packet(
        np.zeros((4, 400), np.float32), stamp_ns=10**9 + 5 * 10**6, sample_rate_hz=10e6,
        onset_index=100, sequence_id=5,
    )
    three_channels.channel_count = 3
    msg.packets = good[:3] + [huge, sizes_disagree, three_channels] + good[3:]
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(loc)
    ex.add_node(node)
    try:
        assert spin_until(ex, lambda: pub.get_subscription_count() >= 1)
        pub.publish(msg)
        assert spin_until(ex, lambda: loc.counts["packets"] >= 8 and loc.idle()), dict(
            loc.counts
        )
        assert loc.counts["packets"] == 8
        assert loc.counts["rejected_MALFORMED_too_long"] == 1
        assert loc.counts["rejected_MALFORMED_inconsistent"] == 2
        assert loc.counts["packets_missing"] == 0
        assert spin_until(ex, lambda: len(got) >= 5)
        assert sorted(e.packet_ids[0] for e in got) == [0, 1, 2, 6, 7]
        assert spin_until(
            ex,
            lambda: diags
            and {kv.key: kv.value for kv in diags[-1].values}.get("rejected_MALFORMED_too_long")
            == "1",
        )
        assert "3 rejected" in diags[-1].message, diags[-1].message
    finally:
        ex.shutdown()
        node.destroy_node()
        loc.destroy_node()


def test_localizer_listens_on_packets_only_once_localized_has_its_subscriber(ros_context):
    """wait_for_subscribers:=1 (the split launch's managed start): the localizer does not
    subscribe to `packets` (so a driver waiting for it does not start) until something
    listens on `localized`; then it subscribes and the first packet comes out localized."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from test_ros_params import _packet_array

    from ae_tactile.msg import Emission, PacketArray
    from ae_tactile.ros.localizer_node import LocalizerNode

    loc = LocalizerNode(
        context=ros_context,
        parameter_overrides=[Parameter("reliable_qos", value=True),
                             Parameter("wait_for_subscribers", value=1)],
    )
    node = rclpy.create_node("packet_source", context=ros_context)
    pub = node.create_publisher(
        PacketArray, "packets", QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    )
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(loc)
    ex.add_node(node)
    try:
        # same-process discovery matches within milliseconds; nothing may match meanwhile
        spin_until(ex, lambda: pub.get_subscription_count() > 0, 1.0)
        assert pub.get_subscription_count() == 0
        got = []
        node.create_subscription(Emission, "localized", got.append, 100)
        assert spin_until(ex, lambda: pub.get_subscription_count() >= 1)
        pub.publish(_packet_array([0]))
        assert spin_until(ex, lambda: len(got) >= 1), dict(loc.counts)
        assert got[0].packet_ids[0] == 0
    finally:
        ex.shutdown()
        node.destroy_node()
        loc.destroy_node()


def test_slip_detector_listens_on_localized_only_once_contacts_has_its_subscriber(ros_context):
    """wait_for_subscribers:=1 on the slip_detector (the split launch's managed start): no
    subscription on `localized` until something listens on `contacts`; then a compression
    published on `localized` comes out as the contact's TOUCH."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from ae_tactile.msg import ContactEvent, Emission
    from ae_tactile.ros.driver_params import EMISSION_QOS, EVENT_QOS
    from ae_tactile.ros.slip_node import SlipDetectorNode

    det = SlipDetectorNode(
        context=ros_context, parameter_overrides=[Parameter("wait_for_subscribers", value=1)]
    )
    node = rclpy.create_node("emission_source", context=ros_context)
    pub = node.create_publisher(Emission, "localized", EMISSION_QOS)
    ex = SingleThreadedExecutor(context=ros_context)
    ex.add_node(det)
    ex.add_node(node)
    try:
        spin_until(ex, lambda: pub.get_subscription_count() > 0, 1.0)
        assert pub.get_subscription_count() == 0
        got = []
        node.create_subscription(ContactEvent, "contacts", got.append, EVENT_QOS)
        assert spin_until(ex, lambda: pub.get_subscription_count() >= 1)
        msg = Emission()
        msg.header.stamp = node.get_clock().now().to_msg()  # as the localizer stamps it
        msg.header.frame_id = "tip"
        msg.position.x, msg.position.y, msg.position.z = 1e-3, 0.0, 9.9e-3
        msg.position_covariance = [1e-10, 0.0, 0.0, 0.0, 1e-10, 0.0, 0.0, 0.0, 1e-10]
        msg.polarity = 1
        msg.confidence = 1.0
        msg.packet_ids = [7]
        pub.publish(msg)
        assert spin_until(ex, lambda: got), (dict(det.stage.counts), det.received)
        assert got[0].event_type == ContactEvent.TOUCH and got[0].contact_id >= 1
    finally:
        ex.shutdown()
        node.destroy_node()
        det.destroy_node()


@pytest.mark.parametrize(
    "module, given, meant",
    [
        ("slip_node", "slip.trak_window_s", "slip.track_window_s"),
        ("localizer_node", "localisation.min_snr_db", "localization.min_snr_db"),
        ("grip_reflex_node", "initial_forse_n", "initial_force_n"),
    ],
)
def test_every_node_warns_once_about_a_parameter_it_does_not_have(tmp_path, module, given, meant):
    """The other nodes, started as a user starts them (a process, ``--ros-args -p``), warn
    once about a misspelt name, naming the one meant, and keep running until SIGINT."""
    import signal
    import time

    require_ros()
    log = tmp_path / "node.log"
    with open(log, "w") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", f"ae_tactile.ros.{module}", "--ros-args",
             "-p", f"{given}:=1.0", "-r", f"__ns:=/t{os.getpid()}"],
            stdout=out, stderr=subprocess.STDOUT, cwd=tmp_path,
        )
    try:
        deadline = time.monotonic() + 120.0  # a generous wait on a condition, not a bound
        while time.monotonic() < deadline and "unknown parameter" not in log.read_text():
            assert proc.poll() is None, log.read_text()
            time.sleep(0.1)
        text = log.read_text()
        assert proc.poll() is None, text  # still running
    finally:
        proc.send_signal(signal.SIGINT)
        code = proc.wait(timeout=60)
    lines = [ln for ln in log.read_text().splitlines() if "unknown parameter" in ln]
    assert len(lines) == 1, text
    assert f"'{given}'" in lines[0] and f"'{meant}'?" in lines[0], lines[0]
    assert code == 0, text
