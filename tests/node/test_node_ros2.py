"""`torchsoil node --ros 2` in a real ROS 2 graph (rclpy and Fast DDS from PyPI, in the
environment scripts/setup.sh makes at .ros2/): the demo recording published at its own pace,
the node's outputs taken by a listener through rclpy's own deserialization. PyPI has no
tf2_msgs, so the extrinsics are given (the bag's /tf_static values) to the node and to
`torchsoil estimate`, which then write the same params.csv rows."""

from __future__ import annotations

import json
import math
import os
import random
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from scipy.spatial.transform import Rotation

from tests.node.bagfeed import DEMO
from tests.node.test_node_ros1 import _rows

# the long tier (`python3 -m pytest -m long`): ROS 2's play through rclpy takes most of a minute;
# the ROS 1 node (tests/node/test_node_ros1.py) runs in the quick tier
pytestmark = pytest.mark.long

ROOT = Path(__file__).resolve().parents[2]
ROS2_PYTHON = ROOT / ".ros2" / "bin" / "python"
PLAY = Path(__file__).with_name("play_ros2.py")


def bag_extrinsics(bag: Path) -> list[str]:
    """--extrinsic options of every frame in the bag's /tf_static (x y z roll pitch yaw in base_link)."""
    from torchsoil.io.extrinsics import tf_edges

    with AnyReader([bag]) as reader:
        conn = [c for c in reader.connections if c.topic == "/tf_static"]
        _, _, raw = next(reader.messages(connections=conn))
        edges = tf_edges(reader.deserialize(raw, conn[0].msgtype))
    args = []
    for frame, (parent, T) in edges.items():
        assert parent == "base_link"
        args += ["--extrinsic", frame, *map(repr, T[:3, 3].tolist()),
                 *map(repr, Rotation.from_matrix(T[:3, :3]).as_euler("xyz").tolist())]
    return args


@pytest.fixture(scope="module")
def ros2_run(tmp_path_factory):
    assert ROS2_PYTHON.exists(), "no ROS 2 environment at .ros2/: run scripts/setup.sh"
    tmp = tmp_path_factory.mktemp("ros2")
    ext = bag_extrinsics(DEMO / "demo")
    env = {**os.environ, "ROS_DOMAIN_ID": str(random.randint(1, 200)), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
           "PYTHONUNBUFFERED": "1"}
    out, heard = tmp / "node", tmp / "heard.json"
    log = (tmp / "node.log").open("w")
    node = subprocess.Popen([str(ROS2_PYTHON), "-m", "torchsoil", "node", "--ros", "2", "--robot",
                             str(DEMO / "demo.robot.yaml"), "--out", str(out), *ext, "--set", "node.queue=1000",
                             "--set", "node.tensorboard=false", "--set", "node.reliable=true"], cwd=ROOT, env=env,
                            stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    listener = subprocess.Popen([str(ROS2_PYTHON), str(PLAY), "listen", str(heard)], env=env, start_new_session=True)
    try:
        subprocess.run([str(ROS2_PYTHON), str(PLAY), "play", str(DEMO / "demo")], env=env, check=True, timeout=180)
        node.send_signal(signal.SIGINT)
        assert node.wait(timeout=120) == 0, (tmp / "node.log").read_text()
        listener.send_signal(signal.SIGINT)
        listener.wait(timeout=30)
    finally:
        for p in (node, listener):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
    est = tmp / "estimate"
    subprocess.run([sys.executable, "-m", "torchsoil", "estimate", str(DEMO / "demo"), "--robot",
                    str(DEMO / "demo.robot.yaml"), "--out", str(est), "--no-tensorboard", *ext], cwd=ROOT, check=True,
                   capture_output=True)
    return out, json.loads(heard.read_text()), est, (tmp / "node.log").read_text()


def test_the_ros2_node_writes_the_rows_estimate_writes(ros2_run):
    out, _, est, log = ros2_run
    rows = _rows(out / "params.csv")
    for topic in ("/lidar_front/points: 154", "/lidar_back/points: 154", "/imu/data: 1541"):
        assert f"{topic} messages, 0 dropped" in log          # every message came (reliable QoS)
    assert len(rows) >= 40 and rows == _rows(est / "params.csv")


def test_the_ros2_outputs_read_back_through_rclpy(ros2_run):
    out, heard, _, _ = ros2_run
    rows = _rows(out / "params.csv")
    assert len(heard["soil"]) == len(rows) == len(heard["values"])
    for got, row in zip(heard["soil"], rows, strict=True):
        assert float(got["s"]) == pytest.approx(float(row["s"]))
        assert got["level"] == (1 if row["flags"] else 0)
    d1 = [v["d1"] for v in heard["values"]]
    assert np.allclose(d1, [float(r["d1"]) for r in rows], rtol=1e-6, equal_nan=True)
    assert heard["cloud"] and heard["cloud"][-1]["fields"] == ["x", "y", "z", "h_delta", "rut_depth"]
    assert heard["cloud"][-1]["frame"] == "soil_map" and heard["cloud"][-1]["width"] > 1000
    grid = heard["grid"][-1]
    assert grid["cells"] == grid["data"] and 0 < grid["max"] <= 100
    estimator = heard["diagnostics"][-1]["torchsoil: estimator"]
    assert int(estimator["windows"]) >= len(rows) - 2 and int(estimator["skipped"]) == 0
    assert not math.isnan(float(estimator["latency_median_s"]))
