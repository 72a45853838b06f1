"""The shipped ROS package folder (configs/ros/torchsoil): its parameters are the settings tree's
defaults, and the ROS 2 launch file's command is one `torchsoil node` accepts, with the
parameters and remappings it declares. (ROS 2's `launch` is not on PyPI: the launch file is
run here against a stand-in of the four `launch` names it uses. The ROS 1 launch file is run
by roslaunch itself in test_node_ros1.)"""

from __future__ import annotations

import importlib.util
import sys
import types
from pathlib import Path

from torchsoil.cli import parser
from torchsoil.settings import Settings, load_settings

PACKAGE = Path(__file__).resolve().parents[2] / "configs" / "ros" / "torchsoil"


def test_params_are_the_node_settings():
    assert load_settings(PACKAGE / "config" / "params.yaml").node == Settings().node


class _Config:
    def __init__(self, name):
        self.name = name


class _Action:
    def __init__(self, *args, **kwargs):
        self.args, self.kwargs = args, kwargs


def _stand_in(monkeypatch) -> None:
    names = {"launch": {"LaunchDescription": lambda actions: actions},
             "launch.actions": {"DeclareLaunchArgument": _Action, "ExecuteProcess": _Action},
             "launch.conditions": {"IfCondition": _Action},
             "launch.substitutions": {"LaunchConfiguration": _Config}}
    for module, attrs in names.items():
        m = types.ModuleType(module)
        m.__dict__.update(attrs)
        monkeypatch.setitem(sys.modules, module, m)


def test_ros2_launch_runs_torchsoil_node_with_its_params_and_remaps(monkeypatch):
    _stand_in(monkeypatch)
    spec = importlib.util.spec_from_file_location("torchsoil_launch", PACKAGE / "launch" / "torchsoil.launch.py")
    launch = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(launch)
    actions = launch.generate_launch_description()
    given = {"robot": "my_robot.yaml", "front_topic": "/os/points"}
    values = {a.args[0]: a.kwargs.get("default_value") for a in actions if "description" in a.kwargs
              or "default_value" in a.kwargs} | given

    def text(part) -> str:
        if isinstance(part, _Config):
            return values[part.name]
        return "".join(text(p) for p in part) if isinstance(part, list) else part

    node = next(a for a in actions if a.kwargs.get("cmd", [""])[0] == "torchsoil")
    argv = [text(p) for p in node.kwargs["cmd"]]
    args = parser().parse_args(argv[1:])
    assert (args.command, args.ros, args.robot) == ("node", "2", "my_robot.yaml")
    assert args.out == "" and Path(args.config[0]).resolve() == (PACKAGE / "config" / "params.yaml").resolve()
    assert args.ros2_args == ["-r", "/lidar_front/points:=/os/points", "-r", "/lidar_back/points:=/lidar_back/points",
                              "-r", "/imu/data:=/imu/data"]
