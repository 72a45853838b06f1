"""The live node's body (torchsoil.node.body) fed the bench's 20 s `road` recording (5 s when
quick) at the recording's own pace and at 4x, as a transport hands messages over (here in
the same process, without ROS: the transport adds the (de)serialization only).

`node_latency_s_median_1x` / `_max_1x`: from the arrival of the sweep that completed a
window's ground to its published estimate; `node_windows_skipped_1x`, `node_sweeps_dropped_1x`
(both 0 when the computer keeps up); the same at 4x, where it cannot: the figures say how it
degrades (sweeps dropped at the queue, windows published as skipped) and
`node_queue_max_sweeps_4x` that the queue stays bounded (node.queue per lidar).
`node_terrain_ms_median`: building the terrain messages near the robot (node.map_rate)."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path


def _messages(bag: Path) -> list[tuple[float, str, str, object]]:
    from rosbags.highlevel import AnyReader

    out = []
    with AnyReader([bag]) as reader:
        for conn, stamp, raw in reader.messages():
            out.append((stamp * 1e-9, conn.topic, conn.msgtype, reader.deserialize(raw, conn.msgtype)))
    return out


def _play(robot, messages, rate: float, out: Path) -> dict[str, float]:
    import numpy as np

    from torchsoil.geo.gridmap import typestore
    from torchsoil.node.body import NodeBody
    from torchsoil.settings import load_settings

    store = typestore()
    terrain: list[float] = []
    body = NodeBody(robot, load_settings(overrides=["node.tensorboard=false"]), out,
                    lambda name, msgtype, msg: store.serialize_cdr(msg, msgtype), store, gridmap=True,
                    log=lambda text: None)
    publish_terrain = body.publish_terrain

    def timed():
        t = time.perf_counter()
        publish_terrain()
        terrain.append(time.perf_counter() - t)

    body.publish_terrain = timed
    body.start()
    queued = 0
    t0, first = time.perf_counter(), messages[0][0]
    for stamp, topic, msgtype, msg in messages:
        wait = (stamp - first) / rate - (time.perf_counter() - t0)
        if wait > 0:
            time.sleep(wait)
        body.receive(topic, msgtype, msg)
        queued = max(queued, max(body.waiting.values()))
    body.stop()
    lat = np.asarray(body.latency) if body.latency else np.full(1, np.nan)
    return {"latency_s_median": float(np.median(lat)), "latency_s_max": float(np.max(lat)),
            "windows": float(body.windows), "windows_skipped": float(body.skipped),
            "sweeps_dropped": float(sum(body.health.dropped.values())), "queue_max_sweeps": float(queued),
            "terrain_ms_median": 1e3 * float(np.median(terrain)) if terrain else float("nan")}


def run(quick: bool = False) -> dict[str, float]:
    from torchsoil.bench.pipeline import _recording

    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        bag, robot = _recording(Path(tmp) / "road", 5.0 if quick else 20.0)
        messages = _messages(bag)
        for rate in (1, 4):
            got = _play(robot, messages, float(rate), Path(tmp) / f"node_{rate}x")
            for key in ("latency_s_median", "latency_s_max", "windows", "windows_skipped", "sweeps_dropped"):
                out[f"node_{key}_{rate}x"] = got[key]
            if rate == 1:
                out["node_terrain_ms_median"] = got["terrain_ms_median"]
            else:
                out["node_queue_max_sweeps_4x"] = got["queue_max_sweeps"]
    return out
