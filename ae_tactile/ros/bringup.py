"""`bringup`: every node of one fingertip in one process, on a multi-threaded executor.

    bringup [--scene FILE] [--no-sim --port URL] [--namespace NS] [--params-file FILE]
            [--frame-id F] [--method M] [--speed X] [--duration S] [--monitor]
            [--grip-reflex] [--summary-json FILE]

With the simulated fingertip (default) the scene is served on a pty and the driver reads
it exactly as it would read hardware. Composing the nodes in one process gives the
lowest latency on a robot (no inter-process hops) and is what the demo and the
end-to-end tests run; `launch/ae_tactile.launch.py` starts the same nodes as separate
processes where ROS 2 launch is installed. ``--params-file`` takes a ROS parameter file
(`/**:` keys apply to every node, e.g. config/water_skin.yaml).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

import rclpy
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.parameter import Parameter

from ae_tactile.ros.params import ParameterError


def parse_args(argv):
    ap = argparse.ArgumentParser(prog="bringup", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="", help="scene YAML for the simulated fingertip (default: showcase)")
    ap.add_argument("--no-sim", dest="use_sim", action="store_false", help="use real hardware on --port")
    ap.add_argument("--port", default="/dev/ttyACM0", help="serial port or pyserial URL (with --no-sim)")
    ap.add_argument("--namespace", default="", help="ROS namespace of all nodes (one per finger)")
    ap.add_argument("--params-file", default="", help="ROS parameter YAML applied to every node")
    ap.add_argument("--frame-id", default="ae_tactile_fingertip", help="fingertip TF frame")
    ap.add_argument("--method", default="", help="localization estimator (default: the localizer's)")
    ap.add_argument("--speed", type=float, default=1.0, help="simulation playback speed")
    ap.add_argument("--duration", type=float, default=-1.0,
                    help="seconds to run (default with --scene: until it has played; 0: until Ctrl-C)")
    ap.add_argument("--monitor", action="store_true", help="print a live log and a summary vs ground truth")
    ap.add_argument("--grip-reflex", action="store_true", help="run the example grip reflex (closes the loop)")
    ap.add_argument("--reliable", action="store_true", help="reliable QoS on packets (for recording)")
    ap.add_argument("--summary-json", default="", help="write the monitor's summary here")
    return ap.parse_args(argv)


class Bringup:
    """The composed system; `nodes` in start order. Usable from tests."""

    def __init__(self, args, context=None):
        from ae_tactile.ros.driver_node import DriverNode
        from ae_tactile.ros.localizer_node import LocalizerNode
        from ae_tactile.ros.slip_node import SlipDetectorNode
        kw = {"context": context, "namespace": args.namespace} if context else {"namespace": args.namespace}
        self.args = args
        self.nodes = []
        self.sim = None
        self.monitor = None
        self._tmp = None
        if args.use_sim:
            from ae_tactile.ros.sim_fingertip_node import SimFingertipNode, default_scene_path
            self._tmp = tempfile.TemporaryDirectory(prefix="ae_tactile_")
            scene = args.scene or default_scene_path("showcase.yaml")
            self.sim = SimFingertipNode(parameter_overrides=[
                Parameter("scene", value=scene), Parameter("speed", value=float(args.speed)),
                Parameter("link_path", value=os.path.join(self._tmp.name, "fingertip")),
                Parameter("frame_id", value=args.frame_id)], **kw)
            self.nodes.append(self.sim)
            port = self.sim.port
        else:
            port = args.port
        self.driver = DriverNode(parameter_overrides=[
            Parameter("port", value=port), Parameter("frame_id", value=args.frame_id),
            Parameter("reliable_qos", value=bool(args.reliable))], **kw)
        loc_params = [Parameter("method", value=args.method)] if args.method else []
        self.localizer = LocalizerNode(parameter_overrides=loc_params, **kw)
        self.slip = SlipDetectorNode(**kw)
        self.nodes += [self.driver, self.localizer, self.slip]
        if args.grip_reflex:
            from ae_tactile.ros.grip_reflex_node import GripReflexNode
            self.reflex = GripReflexNode(**kw)
            self.nodes.append(self.reflex)
        if args.monitor:
            from ae_tactile.ros.monitor_node import MonitorNode
            self.monitor = MonitorNode(**kw)
            self.nodes.append(self.monitor)
        self.executor = MultiThreadedExecutor(num_threads=4, context=context)
        for n in self.nodes:
            self.executor.add_node(n)

    def scene_done(self) -> bool:
        return self.sim is not None and self.sim.device.finished(time.monotonic_ns())

    def spin(self, duration_s: float) -> None:
        """Spin for duration_s (0: forever); negative: until the scene has played (+0.5 s)."""
        t_end = time.monotonic() + duration_s if duration_s > 0 else None
        done_at = None
        while rclpy.ok(context=self.executor.context):
            self.executor.spin_once(timeout_sec=0.05)
            now = time.monotonic()
            if t_end is not None and now >= t_end:
                return
            if duration_s < 0 and self.sim is not None:
                if done_at is None and self.scene_done():
                    done_at = now
                if done_at is not None and now - done_at > 0.5:
                    return

    def gross_slip_times_ns(self) -> list[int]:
        """Ground-truth gross-slip onsets of the scene, as ROS time (ns)."""
        if self.sim is None or self.sim.device.scene_process is None:
            return []
        truth = self.sim.device.scene_process.scene_truth()
        parts = truth.get("parts", [truth])
        out = []
        for p in parts:
            t = p.get("gross_slip_time_ns")
            if t is not None:
                dev_ns = self.sim.device.device_ns_of_scene(int(t))
                out.append(self.sim.ros_ns_of_device_ns(dev_ns))
        return out

    def close(self) -> None:
        self.executor.shutdown()
        for n in reversed(self.nodes):
            n.destroy_node()
        if self._tmp is not None:
            self._tmp.cleanup()


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ros_args = []
    if "--ros-args" in argv:
        i = argv.index("--ros-args")
        argv, ros_args = argv[:i], argv[i:]
    args = parse_args(argv)
    if args.params_file:
        if not os.path.exists(args.params_file):
            print(f"[ae_tactile] not starting: parameter file {args.params_file} not found", file=sys.stderr)
            return 2
        ros_args = (ros_args or ["--ros-args"]) + ["--params-file", args.params_file]
    sys.setswitchinterval(0.001)      # I/O threads (serial reader, publisher) wake sooner
    rclpy.init(args=["bringup"] + ros_args)
    system = None
    try:
        system = Bringup(args)
        duration = args.duration if args.duration >= 0 or args.use_sim else 0.0
        system.spin(duration)
        if system.monitor is not None:
            from ae_tactile.ros.monitor_node import format_summary
            system.executor.spin_once(timeout_sec=0.1)
            system.monitor._flush()
            summary = system.monitor.summary(system.gross_slip_times_ns())
            print(format_summary(summary), flush=True)
            if args.summary_json:
                with open(args.summary_json, "w") as fh:
                    json.dump(summary, fh, indent=2)
    except ParameterError as exc:
        print(f"[ae_tactile] not starting: {exc}", file=sys.stderr, flush=True)
        return 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if system is not None:
            system.close()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
