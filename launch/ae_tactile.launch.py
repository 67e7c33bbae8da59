"""Launch one ae_tactile fingertip: (simulated fingertip +) driver, localizer, slip detector.

Arguments (ros2 launch ae_tactile ae_tactile.launch.py <arg>:=<value>):
  use_sim      true   serve a simulated scene on a pty instead of reading hardware
  port         /dev/ttyACM0   serial port or pyserial URL of the real fingertip (use_sim:=false)
  scene        <share>/config/scenes/showcase.yaml   scene of the simulated fingertip
  params_file  <share>/config/water_skin.yaml        parameters for every node (/**: keys)
  namespace    ""     namespace of every node and topic: one include per finger
  frame_id     ae_tactile_fingertip                  fingertip TF frame
  rviz         false  start RViz with config/ae_tactile.rviz
  record       false  `ros2 bag record` the package's topics (packets reliable for the bag)

Include it once per finger from a hand's launch file, e.g.
  IncludeLaunchDescription(PythonLaunchDescriptionSource(<share>/launch/ae_tactile.launch.py),
      launch_arguments={"namespace": "hand/index", "port": "/dev/ae_tactile_index",
                        "use_sim": "false", "frame_id": "index_tip"}.items())
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess, OpaqueFunction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import Node

TOPICS = ["packets", "sensor_info", "contacts", "slip", "contact_state", "sim/ground_truth",
          "grip_force_command"]


def _record(context):
    if LaunchConfiguration("record").perform(context).lower() != "true":
        return []
    ns = LaunchConfiguration("namespace").perform(context).strip("/")
    topics = [f"/{ns}/{t}" if ns else f"/{t}" for t in TOPICS] + ["/diagnostics"]
    return [ExecuteProcess(cmd=["ros2", "bag", "record", "--storage", "mcap", *topics], output="screen")]


def generate_launch_description():
    share = get_package_share_directory("ae_tactile")
    ns = LaunchConfiguration("namespace")
    params = LaunchConfiguration("params_file")
    frame = LaunchConfiguration("frame_id")
    use_sim = LaunchConfiguration("use_sim")
    sim_link = PythonExpression(["'/tmp/ae_tactile_' + '", ns, "'.replace('/', '_') + '_sim_port'"])
    port = PythonExpression(["'", sim_link, "' if '", use_sim, "'.lower() == 'true' else '",
                             LaunchConfiguration("port"), "'"])
    return LaunchDescription([
        DeclareLaunchArgument("use_sim", default_value="true"),
        DeclareLaunchArgument("port", default_value="/dev/ttyACM0"),
        DeclareLaunchArgument("scene", default_value=os.path.join(share, "config", "scenes", "showcase.yaml")),
        DeclareLaunchArgument("params_file", default_value=os.path.join(share, "config", "water_skin.yaml")),
        DeclareLaunchArgument("namespace", default_value=""),
        DeclareLaunchArgument("frame_id", default_value="ae_tactile_fingertip"),
        DeclareLaunchArgument("rviz", default_value="false"),
        DeclareLaunchArgument("record", default_value="false"),
        Node(package="ae_tactile", executable="sim_fingertip", namespace=ns, output="screen",
             condition=IfCondition(use_sim),
             parameters=[params, {"scene": LaunchConfiguration("scene"), "link_path": sim_link,
                                  "frame_id": frame}]),
        Node(package="ae_tactile", executable="driver", namespace=ns, output="screen",
             parameters=[params, {"port": port, "frame_id": frame,
                                  "reliable_qos": PythonExpression(["'", LaunchConfiguration("record"),
                                                                    "'.lower() == 'true'"])}]),
        Node(package="ae_tactile", executable="localizer", namespace=ns, output="screen", parameters=[params]),
        Node(package="ae_tactile", executable="slip_detector", namespace=ns, output="screen", parameters=[params]),
        Node(package="rviz2", executable="rviz2", namespace=ns, output="screen",
             arguments=["-d", os.path.join(share, "config", "ae_tactile.rviz"), "-f", frame],
             condition=IfCondition(LaunchConfiguration("rviz"))),
        OpaqueFunction(function=_record),
    ])
