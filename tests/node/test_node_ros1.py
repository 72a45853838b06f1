"""`torchsoil node` in a real ROS 1 graph: a roscore, the node started by the shipped launch file
(configs/ros/torchsoil, lidar topics remapped), the demo recording played by `rosbag play` at
its own pace under those names, the node's topics recorded by `rosbag record` and read back
with ROS's own Python (rosbag, sensor_msgs.point_cloud2). The node writes the same params.csv
rows as `torchsoil estimate` on that bag. ROS 1 comes from Debian's packages (scripts/setup.sh)."""

from __future__ import annotations

import csv
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.node.bagfeed import DEMO

ROOT = Path(__file__).resolve().parents[2]
DEBIAN_ROS = "/usr/lib/python3/dist-packages"
OUTPUT_TOPICS = ["/torchsoil/soil", "/torchsoil/soil/values", "/torchsoil/terrain/cloud",
                 "/torchsoil/terrain/rut_depth", "/diagnostics", "/tf"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait(check, what: str, timeout: float = 60.0, proc=None):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"{what}: the process ended ({proc.returncode})")
        got = check()
        if got:
            return got
        time.sleep(0.3)
    raise AssertionError(f"{what}: not within {timeout:.0f} s")


def _topics(env) -> list[str]:
    r = subprocess.run(["rostopic", "list"], env=env, capture_output=True, text=True)
    return r.stdout.split() if r.returncode == 0 else []


def _rows(path: Path) -> list[dict]:
    with path.open(newline="") as f:
        return [{k: v for k, v in r.items() if k not in ("latency", "seconds")} for r in csv.DictReader(f)]


@pytest.fixture(scope="module")
def ros1_run(tmp_path_factory):
    """The demo played through a roscore to the node: (node run folder, recorded outputs bag,
    the ROS 1 bag played, estimate's run folder on that bag)."""
    for tool in ("roscore", "rosbag", "rostopic"):
        assert subprocess.run(["which", tool], capture_output=True).returncode == 0, \
            f"ROS 1 is not installed ({tool}): run scripts/setup.sh"
    tmp = tmp_path_factory.mktemp("ros1")
    bag = tmp / "demo.bag"
    subprocess.run([sys.executable, "-m", "rosbags.convert", "--src", str(DEMO / "demo"), "--dst", str(bag)],
                   check=True, capture_output=True)
    port = _free_port()
    env = {**os.environ, "ROS_MASTER_URI": f"http://127.0.0.1:{port}", "ROS_HOSTNAME": "127.0.0.1",
           "ROS_HOME": str(tmp / "ros_home"), "PYTHONUNBUFFERED": "1"}
    procs = []
    try:
        procs.append(subprocess.Popen(["roscore", "-p", str(port)], env=env, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL, start_new_session=True))
        _wait(lambda: "/rosout" in _topics(env), "roscore", proc=procs[0])
        out = tmp / "node"
        log = (tmp / "node.log").open("w")
        launch_env = {**env, "ROS_PACKAGE_PATH": str(ROOT / "configs" / "ros"), "TORCHSOIL_PYTHON": sys.executable}
        launch = ["roslaunch", "--sigint-timeout=100", "torchsoil", "torchsoil.launch",   # the shipped launch file
                  f"robot:={DEMO / 'demo.robot.yaml'}", f"out:={out}", "front_topic:=/os_front/points",
                  "back_topic:=/os_back/points", "args:=--set node.queue=1000 --set node.tensorboard=false"]
        node = subprocess.Popen(launch, env=launch_env, cwd=tmp, stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True)
        procs.append(node)
        _wait(lambda: "/torchsoil/soil" in _topics(env), "the node's topics", proc=node)
        recorded = tmp / "outputs.bag"
        rec = subprocess.Popen(["rosbag", "record", "-O", str(recorded), *OUTPUT_TOPICS], env=env,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        procs.append(rec)
        time.sleep(2.0)
        subprocess.run(["rosbag", "play", "-q", "--delay", "2", str(bag), "/lidar_front/points:=/os_front/points",
                        "/lidar_back/points:=/os_back/points"], env=env, check=True, capture_output=True,
                       timeout=120)
        time.sleep(2.0)
        node.send_signal(signal.SIGINT)                 # Ctrl-C: roslaunch stops the node with SIGINT
        node.wait(timeout=150)
        assert "windows written to" in (tmp / "node.log").read_text(), (tmp / "node.log").read_text()[-3000:]
        rec.send_signal(signal.SIGINT)
        rec.wait(timeout=30)
    finally:
        for p in procs[::-1]:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGINT)
                try:
                    p.wait(timeout=15)
                except subprocess.TimeoutExpired:
                    os.killpg(p.pid, signal.SIGKILL)
    est = tmp / "estimate"
    subprocess.run([sys.executable, "-m", "torchsoil", "estimate", str(bag), "--robot", str(DEMO / "demo.robot.yaml"),
                    "--out", str(est), "--no-tensorboard"], cwd=ROOT, check=True, capture_output=True)
    return out, recorded, bag, est


def test_the_node_writes_the_rows_estimate_writes(ros1_run):
    out, _, _, est = ros1_run
    node_rows, est_rows = _rows(out / "params.csv"), _rows(est / "params.csv")
    assert len(node_rows) >= 40
    assert node_rows == est_rows
    assert (out / "summary.md").exists() and (out / "terrain_pair.npz").exists() and (out / "run.json").exists()


def test_its_topics_read_back_with_ros_own_tools(ros1_run):
    out, recorded, _, _ = ros1_run
    if DEBIAN_ROS not in sys.path:
        sys.path.append(DEBIAN_ROS)
    import rosbag
    import sensor_msgs.point_cloud2 as pc2

    by_topic: dict[str, list] = {}
    with rosbag.Bag(str(recorded)) as b:
        for topic, msg, _ in b.read_messages():
            by_topic.setdefault(topic, []).append(msg)
    rows = _rows(out / "params.csv")
    soil = by_topic["/torchsoil/soil"]
    assert len(soil) == len(rows) == len(by_topic["/torchsoil/soil/values"])
    values = {kv.key: kv.value for kv in soil[10].status[0].values}
    assert float(values["s"]) == pytest.approx(float(rows[10]["s"]))
    assert float(values["beta"]) == pytest.approx(float(rows[10]["beta"]), rel=1e-5, nan_ok=True)
    arr = by_topic["/torchsoil/soil/values"][10]
    names = arr.layout.dim[0].label.split(",")
    assert float(rows[10]["d1"]) == pytest.approx(arr.data[names.index("d1")], rel=1e-5, nan_ok=True)
    cloud = by_topic["/torchsoil/terrain/cloud"][-1]
    pts = np.array(list(pc2.read_points(cloud, field_names=("x", "y", "z", "h_delta", "rut_depth"))))
    assert len(pts) > 1000 and np.isfinite(pts[:, :4]).all()
    assert np.nanmax(pts[:, 4]) > 0.005                        # ruts, metres
    grid = by_topic["/torchsoil/terrain/rut_depth"][-1]
    assert grid.info.width * grid.info.height == len(grid.data) and max(grid.data) <= 100
    assert cloud.header.frame_id == grid.header.frame_id == "soil_map"
    tf = by_topic["/tf"][-1].transforms[0]
    assert (tf.header.frame_id, tf.child_frame_id) == ("base_link", "soil_map")
    names = {s.name for msg in by_topic["/diagnostics"] for s in msg.status}
    assert {"torchsoil: input /lidar_front/points", "torchsoil: estimator", "torchsoil: problems"} <= names
    last = {s.name: s for s in by_topic["/diagnostics"][-1].status}
    front = {kv.key: kv.value for kv in last["torchsoil: input /lidar_front/points"].values}
    assert int(front["messages"]) == 154 and int(front["dropped"]) == 0
