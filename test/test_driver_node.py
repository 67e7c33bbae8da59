# SPDX-License-Identifier: Apache-2.0
"""driver <-> sim_fingertip through real rclpy nodes and a real pty.

End to end: every packet the simulated fingertip sends arrives exactly once, in order,
with exact samples and stamps within 1 ms of the ground truth; faults injected between
them (garbage, CRC errors, a 1 s unplug) show up exactly in the counters and diagnostics;
bad parameters stop the node with the reason; SIGINT stops the executable cleanly.
"""

import os
import signal
import subprocess
import time

import numpy as np
import pytest
import yaml

from conftest import installed_executable
from ros_helpers import children, cpus_allowed, spin_until

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENE = os.path.join(ROOT, "config", "scenes", "random_touches.yaml")


def long_scene(tmp_path, seconds):
    with open(SCENE) as fh:
        spec = dict(yaml.safe_load(fh), duration_s=seconds, name="random_touches_long")
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(spec))
    return str(path)


class System:
    """sim_fingertip + driver + a listener node on one executor."""

    def __init__(self, ctx, tmp_path, scene=SCENE, driver_params=()):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.parameter import Parameter

        from ae_tactile.msg import ContactEvent, PacketArray, SensorInfo
        from ae_tactile.ros.driver_node import DriverNode
        from ae_tactile.ros.node_utils import LATCHED
        from ae_tactile.ros.sim_fingertip_node import SimFingertipNode

        link = str(tmp_path / "fingertip0")
        self.sim = SimFingertipNode(
            context=ctx,
            parameter_overrides=[
                Parameter("scene", value=scene),
                Parameter("link_path", value=link),
            ],
        )
        self.sim.device.record = True
        # The listener exists before the driver starts acquiring: it sees the first packet.
        self.listener = ctx_node = __import__("rclpy").create_node("listener", context=ctx)
        self.arrays, self.truth, self.diag, self.info = [], [], [], []
        self.all_diag = []
        ctx_node.create_subscription(PacketArray, "packets", self.arrays.append, 1000)
        ctx_node.create_subscription(ContactEvent, "sim/ground_truth", self.truth.append, 1000)
        ctx_node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 100)
        ctx_node.create_subscription(SensorInfo, "sensor_info", self.info.append, LATCHED)
        self.driver = DriverNode(
            context=ctx,
            parameter_overrides=[
                Parameter("port", value=link),
                Parameter("reliable_qos", value=True),
                Parameter("diagnostics_period_s", value=0.2),
                Parameter("reconnect_max_s", value=0.4),
                Parameter("wait_for_subscribers", value=1),  # the listener's 'packets'
                *driver_params,
            ],
        )
        self.executor = SingleThreadedExecutor(context=ctx)
        for n in (self.sim, self.driver, self.listener):
            self.executor.add_node(n)

    def _on_diag(self, msg):
        """Keep the driver's link reports (the simulated fingertip publishes its own)."""
        self.all_diag.append(msg)
        if msg.status and msg.status[0].name.endswith(": fingertip link"):
            self.diag.append(msg)

    def spin(self, seconds=None, until=None):
        """Spin ``seconds`` [s], or until ``until()`` holds (a hang guard, not a bound)."""
        if until is not None:
            return spin_until(self.executor, until)
        return spin_until(self.executor, lambda: False, seconds)

    def packets(self):
        return [p for a in self.arrays for p in a.packets]

    def sent(self, fate="sent"):
        return [b for kind, _, b, f in self.sim.device.sent_log if kind == "packet" and f == fate]

    def diag_values(self):
        return {kv.key: kv.value for kv in self.diag[-1].status[0].values}

    def close(self):
        self.executor.shutdown()
        self.driver.destroy_node()
        self.sim.destroy_node()
        self.listener.destroy_node()


@pytest.fixture
def system_factory(ros_context, tmp_path):
    made = []

    def make(**kw):
        s = System(ros_context, tmp_path, **kw)
        made.append(s)
        return s

    yield make
    for s in made:
        s.close()


def test_end_to_end_every_packet_once_in_order_exact_and_stamped(system_factory):
    from ae_tactile.ros.conversions import packet_samples, time_msg_to_ns

    sys_ = system_factory()
    dev = sys_.sim.device
    sys_.spin(until=lambda: dev.finished(time.monotonic_ns()))
    sys_.spin(until=lambda: len(sys_.packets()) >= len(sys_.sent()))  # in flight: arrive
    sys_.spin(0.5)
    sent, pk = sys_.sent(), sys_.packets()
    assert len(sent) >= 30
    assert len(pk) == len(sent)  # exactly once
    assert [p.sequence_id for p in pk] == list(range(len(sent)))  # in order
    for p, s in zip(pk, sent):
        expect = (s.samples.astype(np.float32) * np.float32(s.v_per_count)).astype(np.float32)
        assert np.array_equal(packet_samples(p), expect)  # exact after int16 scaling
    truth = [t for t in sys_.truth if t.confidence > 0]
    assert len(truth) == len(pk)
    err_ms = [
        (
            time_msg_to_ns(p.stamp)
            + p.onset_index * 1e9 / p.sample_rate_hz
            - time_msg_to_ns(t.header.stamp)
        )
        / 1e6
        for p, t in zip(pk, truth)
    ]
    assert max(map(abs, err_ms)) < 1.0, err_ms
    assert all(a.header.frame_id == "ae_tactile_fingertip" for a in sys_.arrays)
    assert sys_.arrays[-1].packets_dropped == 0 and sys_.arrays[-1].frames_bad_crc == 0
    # latched sensor info carries the device's identity and the geometry
    assert sys_.info and sys_.info[-1].serial_number == "AE-SIM-0001"
    assert sys_.info[-1].radius_m == 0.01 and sys_.info[-1].sample_rate_hz == 10e6
    d = sys_.diag_values()
    assert (
        d["state"] == "connected" and d["crc_errors"] == "0" and d["packets_out"] == str(len(pk))
    )


def test_injected_faults_match_counters_and_diagnostics(system_factory, tmp_path):
    from diagnostic_msgs.msg import DiagnosticStatus

    from ae_tactile.protocol import FRAME_OVERHEAD

    sys_ = system_factory(scene=long_scene(tmp_path, 8.0))
    dev, runner = sys_.sim.device, sys_.sim.runner
    assert sys_.spin(until=lambda: len(sys_.packets()) >= 3)
    garbage = bytes(np.random.default_rng(9).integers(0, 256, 3000, dtype=np.uint8))
    dev.inject_garbage(garbage)
    dev.corrupt_next(2)
    assert sys_.spin(until=lambda: len(sys_.sent("corrupted")) == 2 and len(sys_.packets()) >= 8)
    sys_.spin(0.5)
    n_before_unplug = len(sys_.packets())
    n_diag = len(sys_.diag)
    runner.unplug(1.0)
    assert sys_.spin(until=lambda: any(  # link lost, reported
        m.status[0].level == DiagnosticStatus.ERROR for m in sys_.diag[n_diag:]))
    assert sys_.spin(
        until=lambda: (
            sys_.diag_values().get("connects") == "2" and len(sys_.packets()) > n_before_unplug + 3
        ),
    )
    sys_.spin(0.5)
    d = sys_.diag_values()
    corrupt_bytes = sum(FRAME_OVERHEAD + 24 + 8 * s.n_samples for s in sys_.sent("corrupted"))
    assert d["crc_errors"] == "2" and d["dropped_frames"] == "2" and d["packets_dropped"] == "2"
    # Every discarded byte is accounted for: the garbage, the corrupted frames and, when
    # the unplug cut a frame on the wire, that frame's received part (less than a frame).
    cut = int(d["bytes_cut_at_disconnect"])
    assert 0 <= cut < FRAME_OVERHEAD + 24 + 8 * max(s.n_samples for s in sys_.sent())
    assert d["bytes_discarded"] == str(len(garbage) + corrupt_bytes + cut)
    assert d["disconnects"] == "1" and d["connects"] == "2" and d["state"] == "connected"
    assert sys_.diag[-1].status[0].level == DiagnosticStatus.WARN  # errors so far, link up
    last = sys_.arrays[-1]
    assert last.frames_bad_crc == 2 and last.packets_dropped == 2  # visible to subscribers
    # Nothing valid lost: every packet sent intact (before and after the outage) arrives, in
    # order (the scene keeps playing: wait for those sent up to now).
    n_sent = len(sys_.sent())
    assert sys_.spin(until=lambda: len(sys_.packets()) >= n_sent)
    got = [p.sequence_id for p in sys_.packets()]
    assert got == list(range(len(got)))


def test_invalid_parameters_stop_the_node_with_the_reason(ros_context):
    from rclpy.parameter import Parameter

    from ae_tactile.ros.driver_node import DriverNode
    from ae_tactile.ros.params import ParameterError

    cases = [
        ("mode", "burst", "mode"),
        ("baudrate", 10, "baudrate"),
        ("port", " ", "port"),
        ("channel_gains", [1.0, 1.0, -1.0, 1.0], "channel_gains"),
    ]
    for name, value, needle in cases:
        with pytest.raises(ParameterError, match=needle):
            DriverNode(context=ros_context, parameter_overrides=[Parameter(name, value=value)])


def _driver_on_a_missing_port(*args, preexec_fn=None, while_running=None):
    """Run the installed driver on a missing port (with ``args``, more -p options) until
    it says so through its logger, call ``while_running(pid)``, then Ctrl-C it. Waits for
    the message, not for a fixed time (start-up includes compiling the localizer).
    Returns (exit code, output, what while_running returned)."""
    import threading

    exe = installed_executable("driver")
    cmd = [exe, "--ros-args", "-p", "port:=/nonexistent/ttyACM7"]
    for a in args:
        cmd += ["-p", a]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            preexec_fn=preexec_fn)
    lines, seen = [], threading.Event()

    def read():
        for line in proc.stdout:
            lines.append(line)
            if "cannot open /nonexistent/ttyACM7" in line:
                seen.set()

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    got = None
    try:
        assert seen.wait(120.0), "".join(lines)
        if while_running is not None:
            got = while_running(proc.pid)
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(30)
        reader.join(10)
    return proc.returncode, "".join(lines), got


def test_driver_executable_exits_cleanly_on_sigint(tmp_path):
    """Started on a missing port, the driver says so (through its logger), keeps retrying,
    and Ctrl-C ends it with exit code 0 and no traceback."""
    code, out, _ = _driver_on_a_missing_port()
    assert code == 0, out
    assert "Traceback" not in out


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="needs two CPUs to pin one")
def test_cpu_affinity_pins_every_thread_of_the_driver_and_its_overlap_worker(tmp_path):
    """cpu_affinity:=N: once the driver runs (it reports the missing port), every thread of
    its process (the reader's, DDS's, the overlap resolver's) and its overlap worker
    process may run on CPU N only, also when it was started on another CPU (as a launch
    or benchmark that runs elsewhere starts it); the worker runs as SCHED_IDLE."""
    before = os.sched_getaffinity(0)
    cpu, elsewhere = max(before), min(before)

    def look(pid):
        workers = children(pid)
        allowed = cpus_allowed(pid)
        for w in workers:
            allowed |= cpus_allowed(w)
        # on a core of its own, the overlap worker yields to the reader at once
        idle = [os.sched_getscheduler(w) == os.SCHED_IDLE for w in workers]
        return len(os.listdir(f"/proc/{pid}/task")), workers, allowed, idle

    code, out, (threads, workers, allowed, idle) = _driver_on_a_missing_port(
        f"cpu_affinity:={cpu}", preexec_fn=lambda: os.sched_setaffinity(0, {elsewhere}),
        while_running=look,
    )
    assert threads >= 4 and len(workers) == 1, (threads, workers)  # reader, DDS, resolver
    assert allowed == {str(cpu)}, allowed
    assert idle == [True]
    assert code == 0, out


#: [s] a driver that refuses its parameters exits in about a second; this only catches a
#: hang (its imports alone took over 20 s at load 24)
HANG_S = 300


def test_driver_executable_refuses_a_cpu_it_cannot_run_on():
    exe = installed_executable("driver")
    cpu = os.cpu_count()  # one more than the machine has
    out = subprocess.run(
        [exe, "--ros-args", "-p", f"cpu_affinity:={cpu}"], capture_output=True, text=True,
        timeout=HANG_S,
    )
    assert out.returncode == 2
    assert "'cpu_affinity'" in out.stderr and "not on this machine" in out.stderr, out.stderr


def test_driver_executable_refuses_bad_parameter():
    exe = installed_executable("driver")
    out = subprocess.run(
        [exe, "--ros-args", "-p", "mode:=burst"], capture_output=True, text=True,
        timeout=HANG_S,
    )
    assert out.returncode == 2
    assert "not starting" in out.stderr and "'mode'" in out.stderr


def test_hand_parameters_are_checked_and_tunable(ros_context, tmp_path):
    from rclpy.parameter import Parameter

    from ae_tactile.ros.driver_node import DriverNode
    from ae_tactile.ros.params import ParameterError

    link = str(tmp_path / "nowhere")
    with pytest.raises(ParameterError, match="hand_coincidence_topic"):
        DriverNode(context=ros_context, parameter_overrides=[
            Parameter("port", value=link), Parameter("hand_coincidence_topic", value="hand")])
    with pytest.raises(ParameterError, match="hand coincidence"):
        DriverNode(context=ros_context, parameter_overrides=[
            Parameter("port", value=link),
            Parameter("hand_coincidence_topic", value="/hand/apex_packets"),
            Parameter("hand_coincidence_window_s", value=0.005),
            Parameter("hand_coincidence_wait_s", value=0.001)])
    drv = DriverNode(context=ros_context, parameter_overrides=[
        Parameter("port", value=link),
        Parameter("hand_coincidence_topic", value="/hand/apex_packets")])
    try:
        ok = drv.set_parameters([Parameter("hand_coincidence_window_s", value=0.0005)])[0]
        assert ok.successful and drv.pipeline.hand.window_ns == 500_000
        bad = drv.set_parameters([Parameter("hand_coincidence_wait_s", value=0.0002)])[0]
        assert not bad.successful and "wait_s" in bad.reason
        assert drv.pipeline.hand.wait_ns == 5_000_000  # unchanged
        longest = drv.set_parameters([Parameter("hand_coincidence_wait_s", value=1.0)])[0]
        assert longest.successful and drv.pipeline.hand.wait_ns == 1_000_000_000
    finally:
        drv.destroy_node()


def test_the_driver_keeps_what_it_learnt_about_its_device_per_serial_number(
        system_factory, tmp_path):
    """The driver saves the pipeline's learnt models of the device (calibration_dir, one
    file per serial number) at shutdown, shows the file in /diagnostics, and a driver
    started again on the same device loads it (calibration_reset:=true does not)."""
    import json

    from rclpy.parameter import Parameter

    cal = tmp_path / "cal"
    params = (Parameter("calibration_dir", value=str(cal)),)

    def localization_values(s):
        for msg in reversed(s.all_diag):
            for st in msg.status:
                if st.name.endswith(": localization"):
                    return {kv.key: kv.value for kv in st.values}
        return {}

    first = system_factory(driver_params=params)
    dev = first.sim.device
    first.spin(until=lambda: dev.finished(time.monotonic_ns()))
    first.spin(until=lambda: "calibration_file" in localization_values(first)
               and "AE-SIM-0001" in localization_values(first)["calibration_file"])
    # one file per serial number and body: radius, element offset, sound speed
    g = first.driver.pipeline.localizer.geometry
    name = (f"AE-SIM-0001_R{g.radius_m * 1e3:g}mm_a{g.element_offset_m * 1e3:g}mm"
            f"_c{g.sound_speed_m_s:g}")
    assert localization_values(first)["calibration_file"] == str(cal / f"{name}.json")
    first.close()
    doc = json.loads((cal / f"{name}.json").read_text())
    assert doc["serial"] == name and "interference_echo" in doc["sections"]

    for reset, loaded in ((False, True), (True, False)):
        s = system_factory(driver_params=params + (Parameter("calibration_reset", value=reset),))
        s.spin(until=lambda s=s: "calibration_loaded" in localization_values(s))
        got = localization_values(s)["calibration_loaded"]
        assert (got != "(none)") == loaded, (reset, got)
        s.close()
