"""ROS 2: ros2 launch /path/to/configs/ros/torchsoil/launch/torchsoil.launch.py robot:=/path/to/my_robot.yaml

Starts `torchsoil node --ros 2` with the parameters in ../config/params.yaml (the settings
tree: `torchsoil settings`) and the lidar and IMU topics remapped (docs/node.md)."""

from pathlib import Path

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration

HERE = Path(__file__).resolve().parents[1]


def generate_launch_description():
    arg = LaunchConfiguration
    return LaunchDescription([
        DeclareLaunchArgument("robot", description="robot description: a shipped name or a YAML path"),
        DeclareLaunchArgument("out", default_value="", description="run folder (default: a new one per start)"),
        DeclareLaunchArgument("params", default_value=str(HERE / "config" / "params.yaml")),
        DeclareLaunchArgument("front_topic", default_value="/lidar_front/points"),
        DeclareLaunchArgument("back_topic", default_value="/lidar_back/points"),
        DeclareLaunchArgument("imu_topic", default_value="/imu/data"),
        DeclareLaunchArgument("rviz", default_value="false"),
        ExecuteProcess(
            cmd=["torchsoil", "node", "--ros", "2", "--robot", arg("robot"), "--config", arg("params"),
                 "--out", arg("out"), "--ros-args",      # an empty --out: a new run folder per start
                 "-r", ["/lidar_front/points:=", arg("front_topic")],
                 "-r", ["/lidar_back/points:=", arg("back_topic")],
                 "-r", ["/imu/data:=", arg("imu_topic")]],
            output="screen", sigterm_timeout="60"),
        ExecuteProcess(cmd=["rviz2", "-d", str(HERE / "rviz" / "torchsoil.rviz")], condition=IfCondition(arg("rviz"))),
    ])
