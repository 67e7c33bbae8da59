# SPDX-License-Identifier: Apache-2.0
"""One process for the fingertips of a hand: a `DriverNode` per fingertip, each in its own
namespace with its own port, reader thread and pipeline, all spun by one executor.

    hand_driver --fingers /hand/index,/hand/thumb --ros-args --params-file hand.yaml

Every node is named ``driver``; parameters reach each one as they would reach its own
process: ``/**/driver`` sections for all, ``/hand/index/driver`` sections for one (the
port, the frame). Topics, services and diagnostics are those of the one-process-per-finger
layout, so a hand's other nodes cannot tell the difference.

What one process saves and costs: the interpreter, numpy, numba's compiled kernels and
rclpy are loaded once, not once per fingertip (memory), the overlap resolvers share one
worker process (`ae_tactile.pipeline.worker_share`), and one executor serves every
fingertip's timers. The fingertips share one interpreter lock, so their reader threads
take turns: the process uses one core for the Python work of all of them. It suits a hand
whose summed emission rate one core keeps up with; faster fingertips want a process
each (``hand.launch.py one_process:=false``).
"""

from __future__ import annotations

import argparse
import sys

from ae_tactile.pipeline import worker_share
from ae_tactile.ros.driver_node import DriverNode
from ae_tactile.ros.node_help import print_help, split_ros_args, wants_help
from ae_tactile.ros.node_utils import events_executor, run_node
from ae_tactile.ros.params import ParameterError

EXECUTABLE = "hand_driver"


def namespaces(value: str) -> list[str]:
    """The ``--fingers`` value as absolute namespaces, checked: one per fingertip,
    comma-separated, each a valid ROS namespace, none twice.

    Parameters
    ----------
    value : str
        e.g. ``"/hand/index,/hand/thumb"`` (a leading '/' is added where missing).

    Returns
    -------
    list of str
        The namespaces, each starting with '/'.

    Raises
    ------
    ValueError
        An empty list, an invalid name or a repeated one.
    """
    out = []
    for item in value.split(","):
        ns = item.strip().strip("/")
        parts = ns.split("/") if ns else []
        if not parts or any(not p or not (p[0].isalpha() or p[0] == "_")
                            or not all(c.isalnum() or c == "_" for c in p) for p in parts):
            raise ValueError(f"--fingers {value!r}: {item!r} is not a ROS namespace "
                             "(letters, digits, '_', separated by '/')")
        out.append("/" + ns)
    if len(set(out)) != len(out):
        raise ValueError(f"--fingers {value!r} names a fingertip twice")
    return out


def make_drivers(fingers: list[str], nodes: list) -> None:
    """A `DriverNode` per namespace, appended to ``nodes`` as each is made; they must
    agree on ``cpu_affinity`` (it pins the one process)."""
    for ns in fingers:
        nodes.append(DriverNode(namespace=ns))
    pins = {n.p["cpu_affinity"].strip() for n in nodes}
    if len(pins) > 1:
        raise ParameterError(
            f"parameter 'cpu_affinity' differs between the fingertips ({sorted(pins)}): "
            "one process runs on one set of CPUs")


def main(argv: list[str] | None = None) -> int:
    """Entry point: ``--fingers`` before ``--ros-args``; 2 on a bad argument."""
    argv = sys.argv[1:] if argv is None else list(argv)
    own, ros = split_ros_args(argv)
    if wants_help(own):
        print_help(sys.modules[__name__], EXECUTABLE,
                   [("", "DRIVER_PARAMS"),
                    ("localization.", "ae_tactile.ros.params:LOCALIZATION_PARAMS"),
                    ("slip.", "ae_tactile.ros.params:slip_params")])
        print("\nOwn argument (before --ros-args):\n  --fingers NS[,NS...]  namespace of "
              "each fingertip's driver, e.g. /hand/index,/hand/thumb")
        return 0
    parser = argparse.ArgumentParser(prog=EXECUTABLE, add_help=False)
    parser.add_argument("--fingers")
    try:
        opts, rest = parser.parse_known_args(own)
        if rest:
            raise ValueError(f"unrecognized arguments: {' '.join(rest)}")
        if opts.fingers is None:
            raise ValueError("needs --fingers NS[,NS...]")
        fingers = namespaces(opts.fingers)
    except ValueError as exc:
        print(f"{EXECUTABLE}: {exc} (see --help)", file=sys.stderr)
        return 2
    sys.setswitchinterval(0.0005)  # a reader thread gets the GIL back quickly
    worker_share.enable()  # one overlap worker process for all the fingertips
    return run_node(lambda nodes: make_drivers(fingers, nodes), [sys.argv[0], *ros],
                    executor_factory=events_executor, many=True)
