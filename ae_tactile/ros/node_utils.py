"""Shared bits of the nodes: latched QoS, and running a node (or several) with clean exits."""
from __future__ import annotations

import sys
from contextlib import contextmanager

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ae_tactile.ros.params import ParameterError

#: Latched topics (sensor_info, contact_state, sim/port): reliable, transient local, depth 1.
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                     reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


@contextmanager
def ros_session(args=None):
    """rclpy.init ... try_shutdown; yields a dict whose 'exit' is the process exit code:
    2 when a node refused its parameters (message on stderr), 0 on Ctrl-C / shutdown."""
    rclpy.init(args=args)
    state = {"exit": 0}
    try:
        yield state
    except ParameterError as exc:
        print(f"[ae_tactile] not starting: {exc}", file=sys.stderr, flush=True)
        state["exit"] = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        rclpy.try_shutdown()


def run_node(node_factory, args=None) -> int:
    """Spin one node until SIGINT/shutdown and clean up; exit code 2 on a parameter error."""
    node = None
    with ros_session(args) as state:
        try:
            node = node_factory()
            executor = SingleThreadedExecutor()
            executor.add_node(node)
            executor.spin()
        finally:
            if node is not None:
                node.destroy_node()
    return state["exit"]
