"""Bag reading: ROS 2 sqlite3 / mcap and ROS 1 round trips, and clear errors on bad bags."""

import numpy as np
import pytest

from torchsoil.io.bag import BagError, read_recording
from torchsoil.io.extrinsics import resolve_frames, xyzrpy_matrix
from torchsoil.io.write import _typestore, encode, write_bag

EXT = {"lidar_front": xyzrpy_matrix([0.9, 0.0, 0.8, 0.0, 0.3, 0.0]),
       "lidar_back": xyzrpy_matrix([-0.9, 0.1, 0.8, 0.0, 0.3, np.pi])}


def sweeps(n=3, seed=0, front="/lidar_front/points", back="/lidar_back/points"):
    rng = np.random.default_rng(seed)
    pts, out = [], []
    for k in range(n):
        xyz = rng.normal(size=(32, 3)).astype(np.float32)
        t = np.arange(32, dtype=np.uint32) * 3_000_000     # ns: a 0.1 s sweep
        pts.append(xyz)
        out.append((front, encode(xyz, t, 50 + 0.1 * k, "lidar_front", height=4)))
        out.append((back, encode(-xyz, t, 50.05 + 0.1 * k, "lidar_back", big_endian=True)))
    return out, pts


@pytest.mark.parametrize("storage", ["sqlite3", "mcap", "ros1"])
def test_round_trip(tmp_path, storage):
    msgs, pts = sweeps()
    path = write_bag(tmp_path / ("r.bag" if storage == "ros1" else "r"), msgs, EXT, storage)
    rec = read_recording(path)
    assert len(rec.front) == len(rec.back) == 3 and rec.problems == []
    for k in range(3):
        np.testing.assert_array_equal(rec.front[k].xyz, pts[k])
        np.testing.assert_array_equal(rec.back[k].xyz, -pts[k])
        assert rec.front[k].stamp == pytest.approx(50 + 0.1 * k)
    for frame, T in EXT.items():
        np.testing.assert_allclose(rec.extrinsics[frame], T, atol=1e-12)
    assert rec.duration == pytest.approx(0.25)


def test_missing_topic_is_named(tmp_path):
    msgs, _ = sweeps(back="/other/points")
    path = write_bag(tmp_path / "r", msgs, EXT)
    with pytest.raises(BagError, match="'/lidar_back/points' not found.*/other/points"):
        read_recording(path)


def test_wrong_type_is_named(tmp_path):
    from rosbags.rosbag2 import Writer

    ts = _typestore(False)
    msgs, _ = sweeps()
    path = tmp_path / "r"
    with Writer(path, version=9) as w:
        c = w.add_connection("/lidar_front/points", "sensor_msgs/msg/PointCloud2", typestore=ts)
        for topic, m in msgs:
            if topic == "/lidar_front/points":
                w.write(c, 1, ts.serialize_cdr(m, "sensor_msgs/msg/PointCloud2"))
        s = w.add_connection("/lidar_back/points", "std_msgs/msg/String", typestore=ts)
        w.write(s, 2, ts.serialize_cdr(ts.types["std_msgs/msg/String"](data="x"),
                                       "std_msgs/msg/String"))
    with pytest.raises(BagError, match="'/lidar_back/points' has type std_msgs/msg/String"):
        read_recording(path)


def test_undecodable_sweep_is_skipped_and_reported(tmp_path):
    msgs, _ = sweeps(n=4)
    msgs[2][1].data = msgs[2][1].data[:10]  # front sweep 1 truncated
    rec = read_recording(write_bag(tmp_path / "r", msgs, EXT))
    assert len(rec.front) == 3 and len(rec.back) == 4
    assert len(rec.problems) == 1 and "/lidar_front/points sweep 1" in rec.problems[0]


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_truncated_or_corrupt_bag_raises(tmp_path, storage):
    msgs, _ = sweeps(n=6)
    path = write_bag(tmp_path / "r", msgs, EXT, storage)
    f = next(p for p in path.iterdir() if p.suffix in (".mcap", ".db3"))
    raw = f.read_bytes()
    f.write_bytes(raw[: len(raw) // 2] if storage == "mcap" else raw[:100] + b"\0" * (len(raw) - 100))
    with pytest.raises(BagError, match=str(path)):
        read_recording(path)


def test_missing_bag():
    with pytest.raises(FileNotFoundError, match="nowhere"):
        read_recording("/nowhere/bag")


def test_tf_chains_compose():
    A, B = xyzrpy_matrix([1, 0, 0, 0, 0, 0.5]), xyzrpy_matrix([0, 2, 0, 0.1, 0, 0])
    out = resolve_frames({"mount": ("base_link", A), "lidar": ("mount", B),
                          "orphan": ("elsewhere", A)}, "base_link")
    np.testing.assert_allclose(out["lidar"], A @ B)
    assert "orphan" not in out
