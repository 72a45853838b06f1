"""A minimal `ros2 bag play` and listener for the tests (rclpy from PyPI has no ros2 CLI).

    python play_ros2.py play BAG [--delay S]   the messages of a rosbag2 at their own pace, as
                                               recorded, once every topic has a subscriber (types
                                               without a class, tf2_msgs in a minimal install, left out)
    python play_ros2.py listen OUT.json        the node's outputs, deserialized by rclpy, until SIGINT
"""

from __future__ import annotations

import argparse
import json
import signal
import time
from pathlib import Path

import rclpy
from rclpy.qos import QoSProfile
from rosbags.highlevel import AnyReader

from torchsoil.node.ros2 import message_class


def play(node, path: Path, delay: float) -> None:
    with AnyReader([path]) as bag:
        pubs = {c.topic: node.create_publisher(message_class(c.msgtype), c.topic, QoSProfile(depth=1000))
                for c in bag.connections if message_class(c.msgtype) is not None}
        t_wait = time.monotonic()
        while any(p.get_subscription_count() == 0 for p in pubs.values()) and time.monotonic() - t_wait < 30:
            time.sleep(0.1)
        time.sleep(delay)
        t0, first = time.perf_counter(), None
        for conn, stamp, raw in bag.messages():
            if conn.topic not in pubs:
                continue
            first = stamp if first is None else first
            wait = (stamp - first) * 1e-9 - (time.perf_counter() - t0)
            if wait > 0:
                time.sleep(wait)
            pubs[conn.topic].publish(bytes(raw))
    time.sleep(1.0)


def listen(node, out: Path) -> None:
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import OccupancyGrid
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import Float64MultiArray

    got = {"soil": [], "values": [], "cloud": [], "grid": [], "diagnostics": []}

    def soil(msg):
        got["soil"].append({kv.key: kv.value for kv in msg.status[0].values} | {"level": int.from_bytes(
            msg.status[0].level, "little") if isinstance(msg.status[0].level, bytes) else int(msg.status[0].level)})

    node.create_subscription(DiagnosticArray, "/torchsoil/soil", soil, 1000)
    node.create_subscription(Float64MultiArray, "/torchsoil/soil/values", lambda m: got["values"].append(
        dict(zip(m.layout.dim[0].label.split(","), list(m.data), strict=True))), 1000)
    node.create_subscription(PointCloud2, "/torchsoil/terrain/cloud", lambda m: got["cloud"].append(
        {"width": m.width, "fields": [f.name for f in m.fields], "frame": m.header.frame_id}), 100)
    node.create_subscription(OccupancyGrid, "/torchsoil/terrain/rut_depth", lambda m: got["grid"].append(
        {"cells": m.info.width * m.info.height, "data": len(m.data), "max": max(m.data)}), 100)
    node.create_subscription(DiagnosticArray, "/diagnostics", lambda m: got["diagnostics"].append(
        {s.name: {kv.key: kv.value for kv in s.values} for s in m.status}), 100)
    stop = []
    signal.signal(signal.SIGINT, lambda *_: stop.append(1))
    while not stop:
        rclpy.spin_once(node, timeout_sec=0.1)
    out.write_text(json.dumps(got))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("mode", choices=["play", "listen"])
    ap.add_argument("path")
    ap.add_argument("--delay", type=float, default=1.0, help="play: wait after the subscribers have come, s")
    args = ap.parse_args()
    rclpy.init()
    node = rclpy.create_node(f"{args.mode}_ros2")
    if args.mode == "play":
        play(node, Path(args.path), args.delay)
    else:
        listen(node, Path(args.path))
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == "__main__":
    main()
