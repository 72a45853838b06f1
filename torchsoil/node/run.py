"""`torchsoil node`: the run folder claimed as `estimate` claims its own, then the transport
of the ROS that is installed (ROS 2's rclpy first, then ROS 1's rospy) started."""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

from torchsoil.jobs import provenance
from torchsoil.jobs.estimate import OUTPUTS
from torchsoil.robot import Robot
from torchsoil.settings import Settings


def ros_version(asked: str = "auto") -> int:
    """1 or 2: `asked`, or with auto the ROS this shell has (ROS_VERSION, then which of rclpy and
    rospy imports; ROS 2 first)."""
    if asked in ("1", "2"):
        return int(asked)
    if os.environ.get("ROS_VERSION") in ("1", "2"):
        return int(os.environ["ROS_VERSION"])
    if importlib.util.find_spec("rclpy") is not None:
        return 2
    from torchsoil.node.ros1 import import_rospy

    try:
        import_rospy()
        return 1
    except ImportError:
        raise ImportError("neither ROS 2 (rclpy) nor ROS 1 (rospy) is installed: source your ROS setup, or on "
                          "Debian `apt install ros-core python3-rospy` (docs/node.md)") from None


def run_node(robot: Robot, settings: Settings, out: str | Path, ros: str = "auto", resume: bool = False,
             overwrite: bool = False, argv: list[str] | None = None, threads: int | None = 1) -> int:
    """Run the node into run folder `out` until shut down (SIGINT, SIGTERM); argv: ROS
    arguments (remappings). An out holding another run is refused unless `overwrite`;
    `resume` continues its params.csv (the same messages replayed from their start); threads:
    torch intra-op threads (1, as `estimate`: the same rows; None: torch's default)."""
    version = ros_version(ros)
    out = Path(out)
    written = out / "params.csv"
    if written.exists() and not (resume or overwrite) and len(written.read_text().splitlines()) > 1:
        raise FileExistsError(f"{out} holds a run's windows already (params.csv): give --resume to continue it "
                              "(its recording replayed), --overwrite to replace it, or another --out")
    from torchsoil import __version__

    used = {name: getattr(settings, name).model_dump(mode="json") for name in ("sim", "estimator", "pipeline")}
    record = {"job": "node", "input": {"path": f"ROS {version} topics", "key": "ros"},
              "robot": robot.to_dict(), "settings": used, "torchsoil": __version__}
    provenance.claim(out, record, resume=resume, overwrite=overwrite, outputs=(*OUTPUTS, "restart_001"))
    if version == 1:
        from torchsoil.node import ros1 as transport
    else:
        from torchsoil.node import ros2 as transport
    from torchsoil.jobs.common import torch_threads

    with torch_threads(threads):
        return transport.run(robot, settings, out, resume=resume, argv=argv)
