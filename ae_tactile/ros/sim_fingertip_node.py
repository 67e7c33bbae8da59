# SPDX-License-Identifier: Apache-2.0
"""`sim_fingertip` node: a simulated fingertip serving the serial protocol on a pty or TCP port.

Plays a scene (config/scenes/*.yaml) in real time, or at ``speed`` x real time, through
`ae_tactile.virtual_device` (firmware model + transport), so the `driver` node can be
pointed at it exactly as at hardware. The port (a pty path, or the stable symlink
``link_path``, or ``socket://host:port``) is logged and published latched on
``sim/port``. The scene's ground truth is published as ContactEvents on
``sim/ground_truth``, stamped with the ROS time at which each emission is played (the
same clock the driver maps device time to): micro-slips as SLIP_PRECURSOR, releases as
DETOUCH; ``packet_ids`` holds the scene's emission id; ``confidence`` is 1 for emissions
the device captured and 0 for those it could not (below threshold, not acquiring).
Closed loop: a std_msgs/Float64 on ``grip_force_command`` (N) sets the scene's normal
load P (incipient-slip scenes), as a hand's grip would. When the scene has been played,
``sim/scene_truth`` (std_msgs/String, JSON, latched) carries its truth (e.g. gross-slip
times as ROS time) and the load changes applied.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import Float64, String

from ae_tactile.msg import ContactEvent
from ae_tactile.records import ContactRecord
from ae_tactile.ros.conversions import contact_event_msg
from ae_tactile.ros.node_utils import LATCHED, run_node
from ae_tactile.ros.params import Param, ParameterError, declare
from ae_tactile.sim.scene import load_scene
from ae_tactile.virtual_device import DeviceRunner, PtyTransport, TcpTransport, VirtualFingertip

#: Ground truth is kept for late joiners (a monitor or recorder that starts after the scene).
TRUTH_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=5000,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)

KIND_TO_EVENT = {
    "touch": ContactEvent.TOUCH,
    "release": ContactEvent.DETOUCH,
    "micro_slip": ContactEvent.SLIP_PRECURSOR,
    "slip": ContactEvent.SLIP,
    "texture": ContactEvent.TEXTURE,
}


def default_scene_path(name: str = "random_touches.yaml") -> str:
    """A scene shipped with the package (install share dir, else the source tree)."""
    here = os.path.dirname(os.path.abspath(__file__))
    candidates = [os.path.join(here, "..", "..", "config", "scenes", name)]
    try:
        # lazy: optional, absent outside an ament environment (pip install)
        from ament_index_python.packages import get_package_share_directory

        candidates.insert(
            0, os.path.join(get_package_share_directory("ae_tactile"), "config", "scenes", name)
        )
    except Exception:  # ament index not available (pip install): fall back to the source tree
        pass
    for c in candidates:
        if os.path.exists(c):
            return os.path.normpath(c)
    return name


SIM_PARAMS = [
    Param("scene", "", "Scene YAML file (config/scenes/*.yaml); empty = random_touches.yaml"),
    Param(
        "transport",
        "pty",
        "Serve the protocol on a pseudo-terminal ('pty') or a TCP port ('tcp')",
        choices=("pty", "tcp"),
    ),
    Param("link_path", "", "pty only: stable symlink to the pty (like a udev rule); empty = none"),
    Param("tcp_port", 0, "tcp only: port on 127.0.0.1 (0 = pick a free one)", 0, 65535),
    Param("speed", 1.0, "Playback speed (1 = real time)", 0.001, 1000.0),
    Param(
        "serial_number",
        "AE-SIM-0001",
        "Serial number the virtual device reports",
        check=lambda v: (
            None
            if 1 <= len(v) <= 32 and v.isprintable() and v.isascii()
            else "1..32 printable ASCII"
        ),
    ),
    Param("packet_samples", 400, "Samples per channel of a triggered packet", 16, 8192),
    Param("pre_trigger_samples", 80, "Samples before the earliest arrival in a packet", 0, 8191),
    Param("threshold_counts", 0, "Trigger threshold (ADC counts); 0 = 6 noise sigma", 0, 32767),
    Param("stream_block_samples", 2000, "Samples per channel of a STREAM block", 1, 8192),
    Param("frame_id", "ae_tactile_fingertip", "Frame of the ground-truth ContactEvents"),
    Param("exit_when_done", False, "Shut down once the scene has been played"),
    Param(
        "exit_with_parent",
        False,
        "Shut down when the process that started this one ends (bringup sets it: a "
        "bringup killed outright leaves no simulator running)",
    ),
]


def scene_body(scene_path: str) -> dict:
    """The simulated fingertip's body (medium and geometry), as the driver compares it with
    its parameters."""
    cfg = load_scene(scene_path).config
    g = cfg.geometry
    medium = cfg.medium.name if hasattr(cfg.medium, "name") else str(cfg.medium)
    return {
        "medium": medium,
        "radius_m": float(g.radius_m),
        "element_offset_m": float(g.element_offset_m),
        "sound_speed_m_s": float(g.sound_speed_m_s),
        "highpass_hz": float(cfg.highpass_hz),
    }


class SimFingertipNode(Node):
    def __init__(self, **kwargs):
        super().__init__("sim_fingertip", **kwargs)
        p = self.p = declare(self, SIM_PARAMS)
        scene = p["scene"] or default_scene_path()
        try:
            self.device = VirtualFingertip(
                scene,
                serial_number=p["serial_number"],
                speed=p["speed"],
                packet_samples=p["packet_samples"],
                pre_trigger=p["pre_trigger_samples"],
                threshold_counts=p["threshold_counts"] or None,
                stream_block_samples=p["stream_block_samples"],
            )
        except (ValueError, OSError) as exc:
            raise ParameterError(f"parameter 'scene' = {scene!r}: {exc}") from exc
        if p["transport"] == "pty":
            self.transport = PtyTransport(link_path=p["link_path"] or None)
        else:
            self.transport = TcpTransport(port=p["tcp_port"])
        self.runner = DeviceRunner(self.device, self.transport)
        self.pub_port = self.create_publisher(String, "sim/port", LATCHED)
        self.pub_truth = self.create_publisher(ContactEvent, "sim/ground_truth", TRUTH_QOS)
        self.pub_port.publish(String(data=self.transport.port))
        self.truth_published = 0
        self.load_changes: list[tuple[int, float]] = []  # (scene ns, P) applied
        self.create_subscription(Float64, "grip_force_command", self._on_grip_force, LATCHED)
        self.pub_scene = self.create_publisher(String, "sim/scene_truth", LATCHED)
        self.sensor_body = scene_body(scene)
        self.pub_scene.publish(
            String(data=json.dumps({"finished": False, "sensor": self.sensor_body}))
        )
        self.scene_finished = False
        self.create_timer(0.01, self._publish_truth)
        self.create_timer(0.1, self._check_finished)
        self.pub_diag = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_timer(1.0, self._publish_diagnostics)
        self._parent_pid = os.getppid()
        if p["exit_with_parent"]:
            self.create_timer(0.5, self._check_parent)
        self.runner.start()
        self.get_logger().info(
            f"simulated fingertip '{self.device.spec.get('name', scene)}' serving on "
            f"{self.transport.port} (speed x{p['speed']:g})"
        )

    @property
    def port(self) -> str:
        return self.transport.port

    def ros_ns_of_device_ns(self, device_ns: int) -> int:
        """ROS time of a device-clock instant (the device clock is this host's monotonic clock)."""
        return int(device_ns) + self._clock_offset_ns()

    _offset = (0, -(10**18))  # (ROS - monotonic offset, monotonic time it was taken)

    def _clock_offset_ns(self) -> int:
        """ROS time - monotonic time, from the tightest of a few bracketed readings (a
        thread preempted between two clock reads on a busy machine would otherwise shift
        the ground truth by milliseconds); refreshed every second."""
        t_mono = time.monotonic_ns()
        if t_mono - self._offset[1] < 1_000_000_000:
            return self._offset[0]
        best = None
        for _ in range(5):
            a = time.monotonic_ns()
            ros = self.get_clock().now().nanoseconds
            b = time.monotonic_ns()
            if best is None or b - a < best[0]:
                best = (b - a, ros - (a + b) // 2)
        self._offset = (best[1], t_mono)
        return best[1]

    def scene_truth_ros(self) -> dict:
        """The scene's truth with every *_time_ns and every *_intervals_ns' [start, end]
        (scene time) as ROS time (ns)."""
        proc = self.device.scene_process
        truth = proc.scene_truth() if proc is not None else {}

        def ros(v):
            return None if v is None else self.ros_ns_of_device_ns(
                self.device.device_ns_of_scene(int(v)))

        def conv_value(k, v):
            if k.endswith("_time_ns") and v is not None:
                return ros(v)
            if k.endswith("_intervals_ns") and isinstance(v, list):
                return [[ros(a) for a in iv] for iv in v]
            return conv(v)

        def conv(obj):
            if isinstance(obj, dict):
                return {k: conv_value(k, v) for k, v in obj.items()}
            if isinstance(obj, list):
                return [conv(v) for v in obj]
            return obj

        return conv(truth)

    def _publish_diagnostics(self) -> None:
        dev = self.device
        st = DiagnosticStatus(
            level=DiagnosticStatus.OK,
            name=f"{self.get_fully_qualified_name()}: simulated fingertip",
            hardware_id=self.p["serial_number"],
            message=("scene played" if self.scene_finished else f"serving on {self.port}"),
        )
        st.values = [
            KeyValue(key="port", value=self.port),
            KeyValue(key="scene", value=str(dev.spec.get("name", ""))),
            KeyValue(key="truth_events_published", value=str(self.truth_published)),
            KeyValue(key="medium", value=str(self.sensor_body.get("medium", ""))),
        ]
        msg = DiagnosticArray(status=[st])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.pub_diag.publish(msg)

    def _check_finished(self) -> None:
        # finished() reads a few fields the device loop sets atomically: no lock, so this
        # timer never waits for a render (a callback blocked in an executor makes rclpy's
        # MultiThreadedExecutor spin and starve every other thread of the GIL).
        if self.scene_finished or not self.device.finished(time.monotonic_ns()):
            return
        self._publish_truth()
        self.scene_finished = True
        info = {
            "finished": True,
            "scene": self.device.spec.get("name", ""),
            "sensor": self.sensor_body,
            "truth": self.runner.call(self.scene_truth_ros),
            "load_changes": [[int(t), float(p)] for t, p in self.load_changes],
        }
        self.pub_scene.publish(String(data=json.dumps(info, default=float)))
        self.get_logger().info("scene played to the end")
        if self.p["exit_when_done"]:
            raise SystemExit(0)

    def _check_parent(self) -> None:
        """The starting process is gone (this one was re-parented): shut down."""
        if os.getppid() != self._parent_pid:
            self.get_logger().warning(
                f"the process that started the simulated fingertip ({self._parent_pid}) "
                "ended: shutting down"
            )
            raise SystemExit(0)

    def _on_grip_force(self, msg: Float64) -> None:
        """Closed loop: the commanded grip force becomes the scene's normal load P (N)."""
        try:
            at = self.runner.call(
                self.device.set_normal_load, float(msg.data), time.monotonic_ns()
            )
        except ValueError as exc:
            self.get_logger().warning(
                f"grip_force_command {msg.data} N ignored: {exc}", throttle_duration_sec=5.0
            )
            return
        self.load_changes.append((at, float(msg.data)))
        self.get_logger().info(
            f"normal load set to {msg.data:.2f} N at scene time {at * 1e-9:.4f} s"
        )

    def _publish_truth(self) -> None:
        for t in self.device.pop_truth():
            x, y, z = (float(v) for v in t.point_m)
            rec = ContactRecord(
                event_type=int(KIND_TO_EVENT[t.kind]),
                time_ns=int(self.ros_ns_of_device_ns(t.device_time_ns)),
                point_m=(x, y, z),
                covariance_m2=np.zeros((3, 3)),  # the truth: exact
                packet_ids=(int(t.event_id),),
                polar_rad=math.atan2(math.hypot(x, y), z),
                azimuth_rad=math.atan2(y, x),
                amplitude_v=float(np.sign(t.amplitude_pa_m)),  # polarity only
                confidence=1.0 if t.captured else 0.0,
            )
            ev = contact_event_msg(rec, self.p["frame_id"])
            self.pub_truth.publish(ev)
            self.truth_published += 1

    def destroy_node(self):
        if not hasattr(self, "runner"):  # constructor stopped early (bad parameter)
            return super().destroy_node()
        self.runner.stop()
        return super().destroy_node()


def main(args=None) -> int:
    return run_node(SimFingertipNode, args)


if __name__ == "__main__":
    sys.exit(main())
