# SPDX-License-Identifier: Apache-2.0
"""Launch the fingertips of one hand: one include of ae_tactile.launch.py per finger.

Each finger gets its own driver (its own process), its own port and the namespace
``<namespace>/<finger>``; its TF frame is ``<finger>_tip``.

    ros2 launch ae_tactile hand.launch.py use_sim:=false \\
        fingers:=index,middle,thumb ports:=/dev/ttyACM0,/dev/ttyACM1,/dev/ttyACM2
    ros2 launch ae_tactile hand.launch.py fingers:=index,thumb scenes:=three_pins,texture
    ros2 launch ae_tactile hand.launch.py --show-args     # every argument

Per-finger arguments are comma-separated lists in the order of ``fingers``
(``driver_cpus`` is space-separated, since one CPU list may hold commas). Every argument
is checked before anything starts: a list of the wrong length, a repeated finger or a
bad name stops the launch with a message naming it. As in ae_tactile.launch.py, every
process is required: when one exits, the whole hand stops.
"""
import importlib.util
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import (
    DeclareLaunchArgument,
    GroupAction,
    IncludeLaunchDescription,
    OpaqueFunction,
)
from launch.launch_description_sources import PythonLaunchDescriptionSource
from launch.substitutions import LaunchConfiguration

PACKAGE = "ae_tactile"
FINGER_LAUNCH = "ae_tactile.launch.py"


def _finger_launch_path() -> str:
    return os.path.join(get_package_share_directory(PACKAGE), "launch", FINGER_LAUNCH)


def _finger_launch():
    """ae_tactile.launch.py as a module: its argument checks (one rule for booleans,
    namespaces, CPU lists) and its LaunchArgumentError."""
    spec = importlib.util.spec_from_file_location("ae_tactile_finger_launch",
                                                  _finger_launch_path())
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def arguments():
    """(name, default, description) of every launch argument."""
    share = get_package_share_directory(PACKAGE)
    return [
        ("fingers", "index,middle,thumb", "Names of the hand's fingertips, comma-separated; "
         "each its own driver in <namespace>/<finger> with TF frame <finger>_tip"),
        ("use_sim", "true", "Serve a simulated scene per finger on a pty instead of reading "
         "hardware (true/false/1/0)"),
        ("ports", "", "Serial ports (or pyserial URLs) of the fingertips, comma-separated, "
         "one per finger (with use_sim:=false)"),
        ("scenes", "showcase", "Scene of each simulated fingertip (with use_sim:=true): one "
         "for every finger or a comma-separated list, one per finger"),
        ("namespace", "hand", "Namespace of the hand: finger f runs in <namespace>/f"),
        ("params_file", os.path.join(share, "config", "water_skin.yaml"),
         "ROS parameter file of every finger (/**/driver: ...)"),
        ("driver_cpus", "", "CPUs of each finger's driver, space-separated, one CPU list per "
         "finger as for taskset -c ('0 1 1'; empty: any CPU)"),
        ("wait_for_subscribers", "0", "Each driver starts acquiring only once this many "
         "subscribers are matched on its `contacts` (0: at once)"),
        ("hand_topic", "", "Topic the fingertips share to drop electrical interference they "
         "all see at once (absolute, e.g. /hand/apex_packets; empty: the parameter file's)"),
    ]


def generate_launch_description():
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=default, description=description)
         for name, default, description in arguments()]
        + [OpaqueFunction(function=_setup)])


def _per_finger(value: str, name: str, n: int, error, sep: str | None = ",",
                one_for_all: bool = False) -> list[str]:
    """A per-finger list argument split at ``sep`` (None: at white space) into ``n`` items
    (or one repeated, when ``one_for_all``); an empty value gives n empty items."""
    if not value.strip():
        return [""] * n
    items = [v.strip() for v in value.split(sep)]
    if one_for_all and len(items) == 1:
        return items * n
    if len(items) != n or not all(items):
        raise error(f"launch argument '{name}' = {value!r} must list one value per finger "
                    f"({n}: {'one for all, or ' if one_for_all else ''}in the order of "
                    "'fingers')")
    return items


def _fingers(value: str, error) -> list[str]:
    names = [f.strip() for f in value.split(",")]
    if not value.strip() or any(
            not f or not (f[0].isalpha() or f[0] == "_")
            or not all(c.isalnum() or c == "_" for c in f) for f in names):
        raise error(f"launch argument 'fingers' = {value!r} must be comma-separated names "
                    "(letters, digits, '_'; not starting with a digit)")
    if len(set(names)) != len(names):
        raise error(f"launch argument 'fingers' = {value!r} names a finger twice")
    return names


def _setup(context):
    finger_launch = _finger_launch()
    error = finger_launch.LaunchArgumentError

    def arg(name):
        return LaunchConfiguration(name).perform(context)

    fingers = _fingers(arg("fingers"), error)
    n = len(fingers)
    use_sim = finger_launch.flag(arg("use_sim"), "use_sim")
    hand_ns = finger_launch._namespace(arg("namespace"))
    ports = _per_finger(arg("ports"), "ports", n, error)
    if not use_sim and not all(ports):
        raise error(f"launch argument 'ports' = {arg('ports')!r}: use_sim:=false needs one "
                    f"port per finger ({n}: {', '.join(fingers)})")
    scenes = _per_finger(arg("scenes"), "scenes", n, error, one_for_all=True)
    cpus = _per_finger(arg("driver_cpus"), "driver_cpus", n, error, sep=None)
    source = PythonLaunchDescriptionSource(_finger_launch_path())
    actions = []
    for k, finger in enumerate(fingers):
        args = {
            "namespace": f"{hand_ns}/{finger}" if hand_ns else finger,
            "frame_id": f"{finger}_tip",
            "use_sim": "true" if use_sim else "false",
            "params_file": arg("params_file"),
            "wait_for_subscribers": arg("wait_for_subscribers"),
            "hand_topic": arg("hand_topic"),
            "driver_cpus": cpus[k],
        }
        if use_sim:
            args["scene"] = scenes[k]
        else:
            args["port"] = ports[k]
        # scoped: one finger's arguments do not leak into the next include
        actions.append(GroupAction([IncludeLaunchDescription(
            source, launch_arguments=args.items())], scoped=True))
    return actions
