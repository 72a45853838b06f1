"""The node's body fed the demo recording's messages as a transport hands them over: bounded
queues, windows skipped (not queued without end) when the fits fall behind, a clock jumping
back, a late /tf_static, a late IMU and malformed clouds, said and survived; what arrives late
changes no row."""

from __future__ import annotations

import copy
import csv
import math
import time

import numpy as np
import pytest

import torchsoil
from tests.node.bagfeed import DEMO, Published, demo_messages, feed
from torchsoil.geo.gridmap import typestore
from torchsoil.node import messages as m
from torchsoil.node.body import NodeBody, stamp_of
from torchsoil.settings import load_settings

FAST = ["node.queue=100000", "node.map_rate=0", "node.tensorboard=false"]   # nothing dropped: results repeat


def make_body(out, *overrides):
    store = typestore()
    pub = Published(store)
    robot = torchsoil.load_robot(DEMO / "demo.robot.yaml")
    body = NodeBody(robot, load_settings(overrides=[*FAST, *overrides]), out, pub, store, gridmap=True,
                    log=lambda text: None)
    return body, pub


def rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def same_rows(a, b):
    drop = {"latency", "seconds"}
    return [{k: v for k, v in r.items() if k not in drop} for r in a] == \
           [{k: v for k, v in r.items() if k not in drop} for r in b]


@pytest.fixture(scope="module")
def first_seconds():
    return demo_messages(t_max=6.0)


@pytest.fixture(scope="module")
def in_order(first_seconds, tmp_path_factory):
    """The body fed the demo's first 6 s in bag order: its params.csv rows and what it published."""
    out = tmp_path_factory.mktemp("in_order")
    body, pub = make_body(out, "node.map_rate=5")
    body.start()
    feed(body, first_seconds)
    body.stop()
    return rows(out / "params.csv"), pub


def test_rows_are_written_and_published_as_windows_finish(in_order):
    got, pub = in_order
    assert len(got) >= 8
    soil = pub.by_name["soil"]
    assert len(soil) == len(got) == len(pub.by_name["soil_values"])
    for msg, row in zip(soil, got, strict=True):
        values = {kv.key: kv.value for kv in msg.status[0].values}
        assert float(values["s"]) == pytest.approx(float(row["s"]))
        assert float(values["d1"]) == pytest.approx(float(row["d1"]), rel=1e-5, nan_ok=True)
    fitted = [r for r in got if not math.isnan(float(r["d1"]))]
    assert fitted and all(0 < float(r["d1"]) < 0.1 for r in fitted)
    # the terrain near the robot: cloud, rut grid and GridMap on one grid, and the map frame in TF
    cloud, grid, gm = pub.by_name["terrain_cloud"][-1], pub.by_name["rut_grid"][-1], pub.by_name["grid_map"][-1]
    assert cloud.width > 1000 and grid.info.resolution == pytest.approx(gm.info.resolution)
    assert {"h_front", "h_back", "h_delta", "rut_depth", "passes", "d1", "beta"} <= set(gm.layers)
    ruts = np.asarray(grid.data)
    assert (ruts > 0).any() and (ruts == -1).any() and ruts.max() <= 100
    assert pub.by_name["tf"][-1].transforms[0].child_frame_id == "soil_map"


def test_a_late_tf_static_changes_nothing(first_seconds, in_order, tmp_path):
    tf = [msg for msg in first_seconds if msg[0] == "/tf_static"]
    rest = [msg for msg in first_seconds if msg[0] != "/tf_static"]
    late = rest[:300] + tf + rest[300:]            # 2 s of sweeps and IMU samples before the transforms
    assert sum(1 for t, _, _ in rest[:300] if "lidar" in t) >= 20
    body, pub = make_body(tmp_path)
    body.start()
    feed(body, late)
    diag = body.diagnostics()
    body.stop()
    assert same_rows(rows(tmp_path / "params.csv"), in_order[0])
    assert body.health.problems["tf"][0] > 0            # said while it waited
    assert any(s.name == "torchsoil: problems" and "tf" in s.message for s in diag.status)


def test_an_imu_half_a_second_late_changes_nothing(first_seconds, in_order, tmp_path):
    late, held = [], []
    for msg in first_seconds:                  # each IMU sample handed over 50 samples (0.5 s) late
        if msg[0] == "/imu/data":
            held.append(msg)
            if len(held) > 50:
                late.append(held.pop(0))
        else:
            late.append(msg)
    body, _ = make_body(tmp_path)
    body.start()
    feed(body, late + held)
    body.stop()
    assert same_rows(rows(tmp_path / "params.csv"), in_order[0])


def test_a_restarted_node_resumes_without_refitting(first_seconds, in_order, tmp_path):
    body, _ = make_body(tmp_path)                 # a run killed after its first 6 windows
    body.start()
    feed(body, first_seconds)
    body.stop()
    for name in ("params.csv", "reference.csv"):
        lines = (tmp_path / name).read_text().splitlines(keepends=True)
        (tmp_path / name).write_text("".join(lines[:7]))
    body, pub = make_body(tmp_path)
    body.resume = True                            # `torchsoil node --resume`, the recording played again
    body.start()
    feed(body, first_seconds)
    body.stop()
    got = rows(tmp_path / "params.csv")
    assert [r["s"] for r in got] == [r["s"] for r in in_order[0]] and same_rows(got[:6], in_order[0][:6])
    for a, b in zip(got, in_order[0], strict=True):   # warm-started from the last row as written (7 digits)
        for key in ("d1", "d2", "chi", "beta", "residual"):
            assert float(a[key]) == pytest.approx(float(b[key]), rel=1e-4, nan_ok=True)
    assert len(pub.by_name["soil"]) == len(in_order[0]) - 6     # the windows written are not fitted again


def test_malformed_clouds_are_said_and_skipped(first_seconds, tmp_path):
    msgs = list(first_seconds)
    fronts = [k for k, (t, _, _) in enumerate(msgs) if t == "/lidar_front/points"]
    no_x = copy.deepcopy(msgs[fronts[20]][2])
    no_x.fields = [f for f in no_x.fields if f.name != "x"]
    short = copy.deepcopy(msgs[fronts[21]][2])
    short.data = short.data[: len(short.data) // 3 + 1]
    all_nan = copy.deepcopy(msgs[fronts[22]][2])
    data = np.asarray(all_nan.data, np.uint8).copy().reshape(-1, all_nan.point_step)
    for f in all_nan.fields:
        if f.name in "xyz":                        # FLOAT32 coordinates set to NaN
            data[:, f.offset:f.offset + 4] = np.frombuffer(np.float32(np.nan).tobytes(), np.uint8)
    all_nan.data = data.ravel()
    for k, bad in zip(fronts[20:23], (no_x, short, all_nan), strict=True):
        msgs[k] = (msgs[k][0], msgs[k][1], bad)
    body, _ = make_body(tmp_path)
    body.start()
    feed(body, msgs)
    body.stop()
    assert body.health.problems["cloud"][0] >= 2
    assert "error" not in body.health.problems
    got = rows(tmp_path / "params.csv")
    assert len(got) >= 8 and sum(not math.isnan(float(r["d1"])) for r in got) >= 5


def test_a_clock_jumping_back_ends_the_drive_and_begins_another(first_seconds, in_order, tmp_path):
    body, _ = make_body(tmp_path)
    body.start()
    feed(body, first_seconds + first_seconds)   # the bag played again, as `rosbag play -l` does
    body.stop()
    assert body.health.problems["clock"][0] >= 1
    assert same_rows(rows(tmp_path / "params.csv"), in_order[0])
    assert same_rows(rows(tmp_path / "restart_001" / "params.csv"), in_order[0])
    assert (tmp_path / "summary.md").exists() and (tmp_path / "restart_001" / "summary.md").exists()


def test_fits_behind_skip_windows_instead_of_queueing_them(first_seconds, tmp_path, monkeypatch):
    from torchsoil.estimate.live import WindowFitter

    fit = WindowFitter.__call__

    def slow(self, *args):
        time.sleep(1.5)
        return fit(self, *args)

    monkeypatch.setattr(WindowFitter, "__call__", slow)
    body, pub = make_body(tmp_path, "estimator.online.max_pending=1")
    body.start()
    feed(body, first_seconds)
    pending = sum(1 for f, pair in body.run.live.pending if pair is not None and not f.done())
    body.stop()
    got = rows(tmp_path / "params.csv")
    s = [float(r["s"]) for r in got]
    assert s == sorted(s) and len(set(s)) == len(s)          # every window once, in order
    skipped = [r for r in got if r["flags"] == "skipped_behind"]
    assert skipped and all(math.isnan(float(r["d1"])) for r in skipped)
    assert len(skipped) < len(got)                            # the others fitted
    assert pending <= 1
    levels = [msg.status[0].level for msg in pub.by_name["soil"]]
    assert levels.count(m.STALE) == len(skipped)
    status = {st.name: st for st in body.diagnostics().status}["torchsoil: estimator"]
    assert status.level == m.WARN and f"{len(skipped)} skipped" in status.message


def test_the_queue_is_bounded_and_thins_both_lidars_alike(tmp_path):
    body, _ = make_body(tmp_path)
    body.cfg = body.cfg.replace(queue=4)
    lidars = ("/lidar_front/points", "/lidar_back/points")
    msgs = [msg for msg in demo_messages(t_max=2.0) if msg[0] in (*lidars, "/imu/data")]
    for topic, msgtype, msg in msgs:              # no processing thread: nothing is taken
        body.receive(topic, msgtype, msg)
    assert body.keep_every > 1                    # behind: one sweep in keep_every periods is kept
    kept = {t: [stamp_of(item[2]) for item in body.queue if item[0] == t] for t in lidars}
    for t in lidars:
        fed = sum(1 for topic, _, _ in msgs if topic == t)
        assert body.waiting[t] == len(kept[t]) <= 4 and body.health.dropped[t] == fed - len(kept[t])
    assert kept[lidars[0]] == kept[lidars[1]]      # the same sweeps of both: they still pair up
    assert kept[lidars[0]] == sorted(kept[lidars[0]]) and kept[lidars[0]][-1] >= 1.9 + stamp_of(msgs[0][2])
    assert sum(1 for item in body.queue if item[0] == "/imu/data") == sum(1 for t, _, _ in msgs if t == "/imu/data")


def test_a_silent_lidar_is_a_warning(tmp_path):
    body, _ = make_body(tmp_path)
    front = next(msg for msg in demo_messages(t_max=0.5) if msg[0] == "/lidar_front/points")
    body.receive(*front)
    body.health.arrivals["/lidar_front/points"][-1] -= 5.0       # its last sweep 5 s ago
    status = {st.name: st for st in body.diagnostics().status}
    front_status = status["torchsoil: input /lidar_front/points"]
    back_status = status["torchsoil: input /lidar_back/points"]
    assert front_status.level == m.WARN and "silent for 5" in front_status.message
    assert back_status.level == m.ERROR and back_status.message == "no message yet"
