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

With one_process:=true every finger's driver runs in one `hand_driver` process (the
simulated fingertips stay processes of their own): see ae_tactile.ros.hand_driver.
"""
import atexit
import importlib.util
import os
import shutil
import tempfile

import yaml
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
from launch_ros.actions import Node

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
        ("one_process", "false", "Run every finger's driver in one process (hand_driver): "
         "the libraries' memory once for the hand, but the fingers share one core's worth "
         "of Python (true/false/1/0; driver_cpus not with it)"),
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
    if finger_launch.flag(arg("one_process"), "one_process"):
        if any(cpus):
            raise error("launch argument 'driver_cpus' cannot be given with one_process:=true "
                        "(one process for every finger; pin it with taskset or the "
                        "parameter file's cpu_affinity)")
        namespaces = [f"{hand_ns}/{f}" if hand_ns else f for f in fingers]
        return _one_process(finger_launch, fingers, namespaces, use_sim, ports, scenes, arg)
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


def _one_process(finger_launch, fingers, namespaces, use_sim, ports, scenes, arg):
    """A simulated fingertip per finger (with use_sim) and one hand_driver process whose
    DriverNodes get their port and frame from a section per node of a parameter file."""
    params_file = finger_launch._existing_file(arg("params_file"), "params_file")
    wait = finger_launch._count(arg("wait_for_subscribers"), "wait_for_subscribers")
    hand_topic = finger_launch._hand_topic(arg("hand_topic"), False)
    run_dir = tempfile.mkdtemp(prefix="ae_tactile_hand_")
    atexit.register(shutil.rmtree, run_dir, True)
    actions, sections = [], {}
    for k, (finger, ns) in enumerate(zip(fingers, namespaces)):
        frame = f"{finger}_tip"
        port = ports[k]
        if use_sim:
            port = os.path.join(run_dir, f"{finger}_port")
            sim_params = os.path.join(run_dir, f"{finger}_sim.yaml")
            with open(sim_params, "w", encoding="utf-8") as fh:
                yaml.safe_dump({"/**": {"ros__parameters": {
                    "scene": finger_launch._scene_path(scenes[k]), "link_path": port,
                    "frame_id": frame}}}, fh)
            actions.append(Node(
                package=PACKAGE, executable="sim_fingertip", namespace=ns, output="screen",
                parameters=[params_file, sim_params],
                on_exit=finger_launch._required(f"sim_fingertip ({finger})")))
        sections[f"/{ns}/driver"] = {"ros__parameters": {
            "port": port, "frame_id": frame, "pipeline": True,
            "wait_for_subscribers": wait, "reliable_qos": False,
            **({"hand_coincidence_topic": hand_topic} if hand_topic else {})}}
    drivers = os.path.join(run_dir, "drivers.yaml")
    with open(drivers, "w", encoding="utf-8") as fh:
        yaml.safe_dump(sections, fh)
    # no namespace here: it would remap every node of the process; each DriverNode has its own
    actions.append(Node(
        package=PACKAGE, executable="hand_driver", output="screen",
        arguments=["--fingers", ",".join("/" + ns for ns in namespaces)],
        parameters=[params_file, drivers], on_exit=finger_launch._required("hand_driver")))
    return actions
