# SPDX-License-Identifier: Apache-2.0
"""`bringup`: one fingertip's nodes in one process (the demo and the end-to-end tests).

    bringup [--scene FILE] [--no-sim --port URL] [--namespace NS] [--params-file FILE]
            [--frame-id F] [--method M] [--speed X] [--duration S] [--monitor]
            [--grip-reflex] [--split] [--summary-json FILE] [--report-png FILE]

With the simulated fingertip (default) the scene is served on a pty by the
`sim_fingertip` process and the driver reads it exactly as it would read hardware. The
driver localizes and detects slip in-process; ``--split`` runs the velodyne-style split
instead (driver publishing raw packets, separate localizer and slip_detector nodes).
``--params-file`` takes the same parameter file as the launch file (one section per node,
config/water_skin.yaml or config/silicone.yaml; the parameters' defaults are in the code).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from std_msgs.msg import String

from ae_tactile.report import ReportUnavailable, write_run_summary
from ae_tactile.ros.driver_node import DriverNode
from ae_tactile.ros.grip_reflex_node import GripReflexNode
from ae_tactile.ros.localizer_node import LocalizerNode
from ae_tactile.ros.monitor_node import MonitorNode, format_summary, two_hop_floor_ms
from ae_tactile.ros.node_utils import LATCHED, print_stacks_on_signal, ros_session
from ae_tactile.ros.sim_fingertip_node import SimFingertipNode, default_scene_path, scene_body
from ae_tactile.ros.slip_node import SlipDetectorNode


def parse_args(argv):
    ap = argparse.ArgumentParser(prog="bringup", description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--scene", default="", help="scene YAML file or built-in scene name for the simulated "
        "fingertip (default: showcase)"
    )
    ap.add_argument(
        "--no-sim", dest="use_sim", action="store_false", help="use real hardware on --port"
    )
    ap.add_argument(
        "--port", default="/dev/ttyACM0", help="serial port or pyserial URL (with --no-sim)"
    )
    ap.add_argument("--namespace", default="", help="ROS namespace of all nodes (one per finger)")
    ap.add_argument(
        "--params-file",
        default="",
        help="ROS parameter file, one section per node (default: the installed "
        "config/water_skin.yaml, as the launch file; the scene's body wins)",
    )
    ap.add_argument("--frame-id", default="ae_tactile_fingertip", help="fingertip TF frame")
    ap.add_argument(
        "--method", default="", help="localization estimator (default: the localizer's)"
    )
    ap.add_argument("--speed", type=float, default=1.0, help="simulation playback speed")
    ap.add_argument(
        "--duration",
        type=float,
        default=-1.0,
        help="seconds to run (default with --scene: until it has played; 0: until Ctrl-C)",
    )
    ap.add_argument(
        "--monitor", action="store_true", help="print a live log and a summary vs ground truth"
    )
    ap.add_argument(
        "--grip-reflex", action="store_true", help="run the example grip reflex (closes the loop)"
    )
    ap.add_argument(
        "--best-effort",
        dest="reliable",
        action="store_false",
        help="sensor-data (best-effort) QoS on packets instead of reliable",
    )
    ap.add_argument(
        "--sliding-speed",
        type=float,
        default=0.0,
        help="known sliding speed (m/s) for TEXTURE spatial periods (0: unknown)",
    )
    ap.add_argument(
        "--split",
        action="store_true",
        help="separate localizer and slip_detector nodes on the packets topic",
    )
    ap.add_argument("--summary-json", default="", help="write the monitor's summary here")
    ap.add_argument(
        "--report-png", default="", help="write a PNG summary of the run here (monitor)"
    )
    args = ap.parse_args(argv)
    if args.use_sim:
        try:
            args.scene = scene_file(args.scene)
        except ValueError as e:
            ap.error(str(e))  # a clear message, exit code 2, nothing started
    return args


def scene_file(value: str) -> str:
    """The scene to play: a YAML file, or a built-in scene's name (config/scenes; as the
    launch file's ``scene``); empty: the showcase. ValueError naming the built-ins."""
    if not value:
        return default_scene_path("showcase.yaml")
    if os.path.isfile(value):
        return os.path.abspath(value)
    name = value if value.endswith(".yaml") else value + ".yaml"
    builtin = default_scene_path(name)
    if os.sep not in value and os.path.isfile(builtin):
        return builtin
    folder = os.path.dirname(default_scene_path("showcase.yaml"))
    known = sorted(f[:-5] for f in os.listdir(folder) if f.endswith(".yaml")) if os.path.isdir(
        folder) else []
    raise ValueError(f"--scene {value!r} is neither a file nor a built-in scene "
                     f"({', '.join(known)})")


def default_params_file() -> str:
    """config/water_skin.yaml as installed (the launch file's default parameter file)."""
    try:
        # lazy: optional, absent outside an ament environment
        from ament_index_python.packages import get_package_share_directory

        path = os.path.join(get_package_share_directory("ae_tactile"), "config", "water_skin.yaml")
        return path if os.path.exists(path) else ""
    except Exception:  # not in an ament environment
        return ""


def make_executor(context=None):
    """rclpy's EventsExecutor where available (Jazzy+; far less per-callback overhead, which
    is what limits a Python node at hundreds of messages per second), else single-threaded.
    The heavy work runs in the nodes' own threads (link reader, localizer worker), so one
    dispatching thread is enough; rclpy's MultiThreadedExecutor would hurt:
    it spins while a callback group is busy and starves those threads of the GIL."""
    try:
        from rclpy.experimental import EventsExecutor  # lazy: optional, Jazzy and later only

        return EventsExecutor(context=context) if context is not None else EventsExecutor()
    except (ImportError, TypeError):
        return SingleThreadedExecutor(context=context)


def _installed_executable(name: str) -> str:
    """Path of one of this package's node executables (colcon install, or next to us)."""
    try:
        from ament_index_python.packages import get_package_prefix  # lazy: optional (ament)

        path = os.path.join(get_package_prefix("ae_tactile"), "lib", "ae_tactile", name)
        if os.path.exists(path):
            return path
    except Exception:  # not in an ament environment
        pass
    return os.path.join(os.path.dirname(os.path.abspath(sys.argv[0])), name)


class Bringup:
    """The composed system; `nodes` in start order. Usable from tests.

    The simulated fingertip is a device, not part of the host: by default it runs as its
    own process (the `sim_fingertip` executable), serving a pty like USB hardware, so it
    does not share the host process's interpreter; ``sim_in_process`` keeps it in this
    process (tests that reach into the device).
    """

    def __init__(self, args, context=None, sim_in_process: bool = False):
        kw = {"namespace": args.namespace}
        if context is not None:
            kw["context"] = context
        self.args = args
        self.nodes = []
        self.sim = None
        self.sim_process = None
        self.monitor = None
        self.reflex = None
        self.scene_info = None
        self._tmp = None
        if args.use_sim:
            scene = scene_file(args.scene)
            port = self._start_sim(scene, kw, sim_in_process)
            sensor = [Parameter(k, value=v) for k, v in scene_body(scene).items()]
        else:
            port, sensor = args.port, []
        self.driver = DriverNode(parameter_overrides=self._driver_params(port, sensor), **kw)
        self.nodes.append(self.driver)
        self.localizer = self.slip = None
        if args.split:
            self._add_split_nodes(kw)
        self.driver.create_subscription(String, "sim/scene_truth", self._on_scene_info, LATCHED)
        if args.grip_reflex:
            self.reflex = GripReflexNode(**kw)
            self.nodes.append(self.reflex)
        if args.monitor:
            self.monitor = MonitorNode(**kw)
            self.nodes.append(self.monitor)
        self.executor = make_executor(context)
        for n in self.nodes:
            self.executor.add_node(n)

    def _start_sim(self, scene: str, kw: dict, sim_in_process: bool) -> str:
        """The simulated fingertip on a pty (its own process, or this one); returns the
        port the driver opens."""
        args = self.args
        self._tmp = tempfile.TemporaryDirectory(prefix="ae_tactile_")
        port = os.path.join(self._tmp.name, "fingertip")
        sim_params = {
            "scene": scene,
            "speed": float(args.speed),
            "link_path": port,
            "frame_id": args.frame_id,
        }
        if sim_in_process:
            self.sim = SimFingertipNode(
                parameter_overrides=[Parameter(k, value=v) for k, v in sim_params.items()],
                **kw,
            )
            self.nodes.append(self.sim)
            return port
        cmd = [_installed_executable("sim_fingertip"), "--ros-args"]
        for k, v in dict(sim_params, exit_with_parent=True).items():
            cmd += ["-p", f"{k}:={v}"]
        if args.namespace:
            cmd += ["-r", f"__ns:=/{args.namespace.strip('/')}"]
        self.sim_process = subprocess.Popen(cmd, stdout=sys.stdout, stderr=sys.stderr)
        t_end = time.monotonic() + 20.0
        while (
            not os.path.exists(port)
            and time.monotonic() < t_end
            and self.sim_process.poll() is None
        ):
            time.sleep(0.02)
        if not os.path.exists(port):
            raise RuntimeError(
                f"the simulated fingertip did not start (exit code {self.sim_process.poll()})"
            )
        return port

    def _driver_params(self, port: str, sensor: list) -> list:
        """The driver's parameters: the simulated sensor's body (so that the latched
        sensor_info, hence the localizer, matches the fingertip being played, as a user
        would pick config/water_skin.yaml or config/silicone.yaml for hardware), the port
        and what the command line asks."""
        args = self.args
        params = sensor + [
            Parameter("port", value=port),
            Parameter("frame_id", value=args.frame_id),
            Parameter("pipeline", value=not args.split),
            Parameter("wait_for_subscribers", value=1 if (args.monitor or args.split) else 0),
        ]
        if args.split:
            params.append(Parameter("reliable_qos", value=bool(args.reliable)))
        elif args.method:
            params.append(Parameter("localization.method", value=args.method))
        if args.sliding_speed and not args.split:
            params.append(Parameter("slip.sliding_speed_m_s", value=float(args.sliding_speed)))
        return params

    def _add_split_nodes(self, kw: dict) -> None:
        """The velodyne-style split: separate localizer and slip_detector nodes."""
        args = self.args
        loc_params = [Parameter("reliable_qos", value=bool(args.reliable)),
                      Parameter("wait_for_subscribers", value=1)]  # the slip_detector
        if args.method:
            loc_params.append(Parameter("localization.method", value=args.method))
        self.localizer = LocalizerNode(parameter_overrides=loc_params, **kw)
        slip_params = (
            [Parameter("slip.sliding_speed_m_s", value=float(args.sliding_speed))]
            if args.sliding_speed
            else []
        )
        if args.monitor:  # its `contacts` subscription: the chain of a managed start
            slip_params.append(Parameter("wait_for_subscribers", value=1))
        self.slip = SlipDetectorNode(parameter_overrides=slip_params, **kw)
        self.nodes += [self.localizer, self.slip]

    def _on_scene_info(self, msg) -> None:
        try:
            self.scene_info = json.loads(msg.data)
        except ValueError:
            pass

    def scene_done(self) -> bool:
        """The simulated fingertip has played its whole scene (sim/scene_truth received)."""
        return bool(self.scene_info and self.scene_info.get("finished"))

    def events_published(self) -> int:
        """Localized emissions published so far (driver, or the separate localizer)."""
        if self.localizer is not None:
            return self.localizer.counts["published_events"]
        return self.driver.published_emissions

    def drained(self) -> bool:
        """Nothing queued anywhere (the simulated fingertip's output, the port, a frame half
        read: a starved sender can hold a frame back for a second), and every event passed
        on."""
        link = self.driver.link
        if link.decoder.pending_bytes or link.unread_bytes():
            return False
        if self.sim is not None and self.sim.runner.pending_out_bytes:
            return False
        if self.localizer is not None:
            return (
                self.driver.link.stats()["queue_depth"] == 0
                and self.localizer.idle()
                and self.slip.received >= self.localizer.counts["published_events"]
            )
        return self.driver.pipeline is None or self.driver.pipeline.idle()

    def spin(
        self, duration_s: float, drain_timeout_s: float = 10.0, stop: threading.Event | None = None
    ) -> None:
        """Spin for duration_s (0: forever); negative: until the scene has played and the
        pipeline has drained (quiet for 0.3 s; at most drain_timeout_s after the end); and
        never past ``stop`` (a stop signal: it ends the loop within 0.05 s)."""
        t_end = time.monotonic() + duration_s if duration_s > 0 else None
        done_at = quiet_since = None
        last_count = -1
        while rclpy.ok(context=self.executor.context) and not (stop is not None and stop.is_set()):
            self.executor.spin_once(timeout_sec=0.05)
            now = time.monotonic()
            if t_end is not None and now >= t_end:
                return
            if duration_s < 0 and self.args.use_sim:
                if done_at is None and self.scene_done():
                    done_at = now
                if done_at is not None:
                    count = self.driver.link.stats()["packets_out"] + self.events_published()
                    busy = count != last_count or not self.drained()
                    last_count = count
                    quiet_since = None if busy else (quiet_since or now)
                    if (
                        quiet_since and now - quiet_since > 0.3
                    ) or now - done_at > drain_timeout_s:
                        return

    def gross_slip_times_ns(self) -> list[int]:
        """Ground-truth gross-slip onsets of the scene (ROS time, ns), from sim/scene_truth."""
        if not self.scene_info:
            return []
        truth = self.scene_info.get("truth", {})
        parts = truth.get("parts", [truth])
        return [
            int(p["gross_slip_time_ns"]) for p in parts if p.get("gross_slip_time_ns") is not None
        ]

    def slip_part_starts_ns(self) -> list[int]:
        """Start (ROS ns) of each scene part that has a gross slip (0 if not a composite)."""
        if not self.scene_info:
            return []
        truth = self.scene_info.get("truth", {})
        parts = truth.get("parts", [truth])
        return [
            int(p.get("start_time_ns") or 0)
            for p in parts
            if p.get("gross_slip_time_ns") is not None
        ]

    def scene_truth(self) -> dict | None:
        """The scene's truth (ROS ns), from sim/scene_truth; None before it came."""
        return self.scene_info.get("truth") if self.scene_info else None

    def write_report(self, path: str, summary: dict) -> None:
        """PNG summary of the run (ae_tactile.report; needs matplotlib)."""
        data = self.monitor.report_data(summary.get("truth"))
        geo = self.driver.geometry
        lat = summary.get("latency_ms", {})
        title = (
            f"{self.scene_info.get('scene', '') if self.scene_info else ''}: "
            f"{summary['emissions']['matched']}/{summary['emissions']['truth']} emissions found, "
            f"RMS {summary['emissions']['rms_position_error_mm'] * 1e3:.0f} um"
            + (f", latency median {lat['median']:.2f} ms" if lat else "")
        )
        tr = summary.get("truth") or {}
        if tr.get("state_right_share") is not None:
            title += (f"\ncontact state right {100 * tr['state_right_share']:.0f} % of the time, "
                      f"{tr['false_alarms']} false slip alarms")
        try:
            write_run_summary(
                path,
                data["events"],
                truth=data["truth"],
                contact_state=data["contact_state"],
                truth_state=data.get("truth_state"),
                emissions=data["emissions"],
                radius_m=geo.radius_m,
                element_offset_m=geo.element_offset_m,
                title=title,
            )
            print(f"[ae_tactile] picture of the run: {path}", flush=True)
        except ReportUnavailable as exc:
            print(f"[ae_tactile] no PNG summary: {exc}", file=sys.stderr)

    def close(self) -> None:
        self.executor.shutdown()
        for n in reversed(self.nodes):
            n.destroy_node()
        if self.sim_process is not None and self.sim_process.poll() is None:
            self.sim_process.send_signal(signal.SIGINT)
            try:
                self.sim_process.wait(5.0)
            except subprocess.TimeoutExpired:
                self.sim_process.kill()
        if self._tmp is not None:
            self._tmp.cleanup()


def _report(system: Bringup, args) -> None:
    """The monitor's summary against the ground truth: printed, and as asked a PNG and a
    JSON file."""
    system.executor.spin_once(timeout_sec=0.1)
    system.monitor._flush()
    summary = system.monitor.summary(system.gross_slip_times_ns(), system.slip_part_starts_ns(),
                                     system.scene_truth())
    summary["floor_two_hop_ms"] = two_hop_floor_ms()
    print(format_summary(summary), flush=True)
    if args.report_png:
        system.write_report(args.report_png, summary)
    if args.summary_json:
        with open(args.summary_json, "w") as fh:
            json.dump(summary, fh, indent=2)


def main(argv=None) -> int:
    print_stacks_on_signal()
    argv = sys.argv[1:] if argv is None else argv
    ros_args = []
    if "--ros-args" in argv:
        i = argv.index("--ros-args")
        argv, ros_args = argv[:i], argv[i:]
    args = parse_args(argv)
    if not args.params_file:  # the launch file's default too: one place for defaults
        args.params_file = default_params_file()
    if args.params_file:
        if not os.path.exists(args.params_file):
            print(
                f"[ae_tactile] not starting: parameter file {args.params_file} not found",
                file=sys.stderr,
            )
            return 2
        ros_args = (ros_args or ["--ros-args"]) + ["--params-file", args.params_file]
    sys.setswitchinterval(0.0002)  # I/O threads (serial reader, publisher) get the GIL sooner
    system = None
    with ros_session(["bringup"] + ros_args) as state:
        try:
            system = Bringup(args)
            # a stop signal no longer raises here (raised inside rclpy's C++ calls it would
            # come out as another error): the loop sees it within 0.05 s
            state["interrupt"] = False
            if state["stop"].is_set():
                return state["exit"]
            print("[ae_tactile] bringup: every node up, spinning", flush=True)
            duration = args.duration if args.duration >= 0 or args.use_sim else 0.0
            system.spin(duration, stop=state["stop"])
            if system.monitor is not None:
                _report(system, args)
        finally:
            state["arm_cleanup_deadline"]()
            if system is not None:
                system.close()
    return state["exit"]


if __name__ == "__main__":
    sys.exit(main())
