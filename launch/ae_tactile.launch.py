# SPDX-License-Identifier: Apache-2.0
"""Launch one ae_tactile fingertip: the driver (+ the simulated fingertip).

The driver hosts the whole pipeline (read, localize, detect slip) in-process and
publishes `contacts` (a contact's begin / end), `slip`, `emissions` (every localized
emission with its reading), `contact_state`, `sensor_info` and /diagnostics. With
split_pipeline:=true it publishes raw `packets` only and the separate `localizer` (on
`localized`) and `slip_detector` nodes do the rest (the set-up for replaying bags).

    ros2 launch ae_tactile ae_tactile.launch.py --show-args     # every argument

Every boolean argument takes true/false/1/0 (any case). Arguments are checked before
anything starts (parameter file, scene, rviz2 and `ros2 bag` present): a bad one stops
the launch with a message naming it. Every process is required: when one exits, the
launch stops (with exit code 1 if it failed), so no node is left running alone.

Include it once per finger from a hand's launch file; wrap each include in a scoped
GroupAction so one finger's arguments do not leak into the next include:

    GroupAction([IncludeLaunchDescription(
        PythonLaunchDescriptionSource(<share>/launch/ae_tactile.launch.py),
        launch_arguments={"namespace": "hand/index", "port": "/dev/ae_tactile_index",
                          "use_sim": "false", "frame_id": "index_tip"}.items())])
"""
import atexit
import importlib.util
import os
import shutil
import tempfile

import yaml
from ament_index_python.packages import (
    PackageNotFoundError,
    get_package_prefix,
    get_package_share_directory,
)
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess, OpaqueFunction, Shutdown
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

PACKAGE = "ae_tactile"
TRUE_WORDS, FALSE_WORDS = ("true", "1"), ("false", "0")
#: Topics `record:=true` writes (relative to the namespace) besides /diagnostics.
RECORDED_TOPICS = ["packets", "sensor_info", "contacts", "slip", "emissions", "contact_state",
                   "sim/ground_truth", "sim/scene_truth", "grip_force_command"]


class LaunchArgumentError(RuntimeError):
    """A launch argument that cannot work; the message names it and says why."""


class RequiredProcessFailed(RuntimeError):
    """A process of the launch failed; the launch stops (exit code 1)."""


def _share() -> str:
    return get_package_share_directory(PACKAGE)


def arguments():
    """(name, default, description) of every launch argument."""
    share = _share()
    return [
        ("use_sim", "true", "Serve a simulated scene on a pty instead of reading hardware "
         "(true/false/1/0)"),
        ("port", "/dev/ttyACM0", "Serial port or pyserial URL of the real fingertip "
         "(with use_sim:=false)"),
        ("scene", os.path.join(share, "config", "scenes", "showcase.yaml"),
         "Scene of the simulated fingertip: a YAML path or a built-in name "
         "(showcase, three_pins, texture, ...)"),
        ("params_file", os.path.join(share, "config", "water_skin.yaml"),
         "ROS parameter file with one section per node (/**/driver: ...); "
         "config/silicone.yaml for the silicone fingertip"),
        ("namespace", "", "Namespace of every node and topic: one include per finger"),
        ("frame_id", "ae_tactile_fingertip", "TF frame of the fingertip (sphere centre)"),
        ("split_pipeline", "false", "Run localizer and slip_detector as separate nodes on "
         "the driver's raw packets instead of in the driver (true/false/1/0)"),
        ("wait_for_subscribers", "0", "Driver starts acquiring only once this many "
         "subscribers are matched on `contacts` or `packets` (`packets` only with "
         "split_pipeline:=true, where the localizer counts only once the slip_detector "
         "listens on `localized`, and the slip_detector listens only once something "
         "listens on `contacts`; 0: at once): a managed start loses no first event"),
        ("driver_cpus", "", "CPUs the driver runs on, as for taskset -c ('3', '2-3'; "
         "empty: any): a core of its own per finger keeps the reflex path's latency tail "
         "short (the driver's cpu_affinity parameter)"),
        ("hand_topic", "", "Topic the fingertips of one hand share to drop electrical "
         "interference every fingertip sees at once (absolute, the same in each finger's "
         "include, e.g. /hand/apex_packets; empty: the parameter file's "
         "hand_coincidence_topic)"),
        ("rviz", "false", "Start RViz 2 with config/ae_tactile.rviz (true/false/1/0)"),
        ("record", "false", "Record the package's topics with `ros2 bag record` (MCAP) into "
         "the working directory; packets reliable (true/false/1/0)"),
    ]


def generate_launch_description():
    return LaunchDescription(
        [DeclareLaunchArgument(name, default_value=default, description=description)
         for name, default, description in arguments()]
        + [OpaqueFunction(function=_setup)])


# ------------------------------------------------------------------ argument checks
def flag(value: str, name: str) -> bool:
    """The one truthiness rule of every boolean argument: true/1 or false/0, any case."""
    word = value.strip().lower()
    if word in TRUE_WORDS:
        return True
    if word in FALSE_WORDS:
        return False
    raise LaunchArgumentError(f"launch argument '{name}' = {value!r} is not a boolean "
                              "(true, false, 1 or 0)")


def _existing_file(path: str, name: str) -> str:
    if not path or not os.path.isfile(path):
        raise LaunchArgumentError(f"launch argument '{name}': file {path!r} not found")
    return os.path.abspath(path)


def _scene_path(value: str) -> str:
    """A scene file, or a built-in scene name resolved in <share>/config/scenes."""
    if os.path.isfile(value):
        return os.path.abspath(value)
    name = value if value.endswith(".yaml") else value + ".yaml"
    builtin = os.path.join(_share(), "config", "scenes", name)
    if os.sep not in value and os.path.isfile(builtin):
        return builtin
    known = sorted(f[:-5] for f in os.listdir(os.path.join(_share(), "config", "scenes"))
                   if f.endswith(".yaml"))
    raise LaunchArgumentError(f"launch argument 'scene': {value!r} is neither a file nor a "
                              f"built-in scene ({', '.join(known)})")


def _count(value: str, name: str) -> int:
    try:
        n = int(value)
    except ValueError:
        n = -1
    if not 0 <= n <= 100:
        raise LaunchArgumentError(f"launch argument '{name}' = {value!r} must be an integer "
                                  "in 0 .. 100")
    return n


def _cpus(value: str) -> str:
    """driver_cpus, checked by the driver's own rule (`node_utils.cpu_list_problem`) before
    anything starts; '' when not given."""
    from ae_tactile.ros.node_utils import cpu_list_problem

    value = value.strip()
    why = cpu_list_problem(value) if value else None
    if why:
        raise LaunchArgumentError(f"launch argument 'driver_cpus' = {value!r}: {why}")
    return value


def _hand_topic(value: str, split: bool) -> str:
    """hand_topic, checked by the driver's own rule (`node_utils.hand_topic_problem`)
    before anything starts; '' when not given."""
    from ae_tactile.ros.node_utils import hand_topic_problem

    value = value.strip()
    why = hand_topic_problem(value)
    if why:
        raise LaunchArgumentError(f"launch argument 'hand_topic' = {value!r}: {why}")
    if value and split:
        raise LaunchArgumentError(
            "launch argument 'hand_topic' needs split_pipeline:=false (the hand's test runs "
            "in the driver's pipeline)")
    return value


def _namespace(value: str) -> str:
    ns = value.strip().strip("/")
    parts = ns.split("/") if ns else []
    if any(not p or not (p[0].isalpha() or p[0] == "_")
           or not all(c.isalnum() or c == "_" for c in p) for p in parts):
        raise LaunchArgumentError(f"launch argument 'namespace' = {value!r} is not a valid "
                                  "ROS namespace (letters, digits, '_', separated by '/')")
    return ns


def _require_package(package: str, why: str, apt: str) -> None:
    try:
        get_package_prefix(package)
    except (PackageNotFoundError, KeyError, ValueError):
        raise LaunchArgumentError(f"{why}, but ROS package '{package}' is not installed "
                                  f"(e.g. apt install ros-$ROS_DISTRO-{apt}); nothing started"
                                  ) from None


def _require_rviz() -> None:
    _require_package("rviz2", "rviz:=true needs RViz 2", "rviz2")


def _require_ros2_bag() -> None:
    if shutil.which("ros2") is None or importlib.util.find_spec("ros2bag") is None:
        raise LaunchArgumentError("record:=true needs `ros2 bag` (Python package ros2bag), "
                                  "which is not installed (e.g. apt install "
                                  "ros-$ROS_DISTRO-rosbag2); nothing started")
    _require_package("rosbag2_storage_mcap", "record:=true writes MCAP",
                     "rosbag2-storage-mcap")


# ------------------------------------------------------------------ processes
def _required(name: str):
    """on_exit of a required process: stop the launch; a failure makes it exit 1."""
    def on_exit(event, context):
        if context.is_shutdown:
            return None
        if event.returncode != 0:
            raise RequiredProcessFailed(f"{name} exited with code {event.returncode}; "
                                      "stopping every process of this launch")
        return [Shutdown(reason=f"{name} exited")]
    return on_exit


def _setup(context):
    def arg(name):
        return LaunchConfiguration(name).perform(context)

    use_sim = flag(arg("use_sim"), "use_sim")
    split = flag(arg("split_pipeline"), "split_pipeline")
    rviz = flag(arg("rviz"), "rviz")
    record = flag(arg("record"), "record")
    ns = _namespace(arg("namespace"))
    frame = arg("frame_id").strip()
    if not frame:
        raise LaunchArgumentError("launch argument 'frame_id' must not be empty")
    params_file = _existing_file(arg("params_file"), "params_file")
    wait = _count(arg("wait_for_subscribers"), "wait_for_subscribers")
    cpus = _cpus(arg("driver_cpus"))
    hand_topic = _hand_topic(arg("hand_topic"), split)
    scene = _scene_path(arg("scene")) if use_sim else None
    if rviz:
        _require_rviz()
    if record:
        _require_ros2_bag()

    # The pty link and the per-node parameter overrides live in a private directory that
    # is removed when the launch exits: no two launches share them, nothing is left in
    # /tmp (launch_ros would leave a launch_params_* file per dict of parameters).
    run_dir = tempfile.mkdtemp(prefix="ae_tactile_launch_")
    atexit.register(shutil.rmtree, run_dir, True)

    def overrides(node: str, values: dict) -> str:
        path = os.path.join(run_dir, f"{node}.yaml")
        with open(path, "w", encoding="utf-8") as fh:
            yaml.safe_dump({"/**": {"ros__parameters": values}}, fh)
        return path

    actions = []
    if use_sim:
        port = os.path.join(run_dir, "sim_port")
        actions.append(Node(
            package=PACKAGE, executable="sim_fingertip", namespace=ns, output="screen",
            parameters=[params_file, overrides("sim_fingertip", {
                "scene": scene, "link_path": port, "frame_id": frame})],
            on_exit=_required("sim_fingertip")))
    else:
        port = arg("port")
    actions.append(Node(
        package=PACKAGE, executable="driver", namespace=ns, output="screen",
        parameters=[params_file, overrides("driver", {
            "port": port, "frame_id": frame, "pipeline": not split,
            "wait_for_subscribers": wait, "reliable_qos": record,
            # only when given: the parameter file's values stay otherwise
            **({"cpu_affinity": cpus} if cpus else {}),
            **({"hand_coincidence_topic": hand_topic} if hand_topic else {})})],
        on_exit=_required("driver")))
    if split:
        # a managed start is a chain: the slip_detector listens on `localized` only once
        # something listens on `contacts`, the localizer on `packets` (and so counts for the
        # driver's wait) only once the slip_detector listens on `localized`
        chain = {exe: [{"wait_for_subscribers": 1}] if wait else []
                 for exe in ("localizer", "slip_detector")}
        for exe in ("localizer", "slip_detector"):
            actions.append(Node(package=PACKAGE, executable=exe, namespace=ns, output="screen",
                                parameters=[params_file, *chain[exe]], on_exit=_required(exe)))
    if rviz:   # closing RViz ends nothing else
        actions.append(Node(
            package="rviz2", executable="rviz2", namespace=ns, output="screen",
            arguments=["-d", os.path.join(_share(), "config", "ae_tactile.rviz"), "-f", frame]))
    if record:
        topics = [f"/{ns}/{t}" if ns else f"/{t}" for t in RECORDED_TOPICS] + ["/diagnostics"]
        actions.append(ExecuteProcess(
            cmd=["ros2", "bag", "record", "--storage", "mcap", *topics], output="screen",
            name="recorder", on_exit=_required("ros2 bag record")))
    return actions
