"""One synthetic drive written in every lidar driver's time and stamp convention gives the same
terrain pair as in the recorder's own (Ouster) layout; read the old way (point times ignored,
header stamps taken as sweep starts) it does not."""

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from tests.synth.test_recording import SCN
from torchsoil.pipeline.run import process_bag
from torchsoil.robot import Robot
from torchsoil.settings import PipelineConfig, ReadConfig, TopicTime
from torchsoil.synth.bagwriter import TYPESTORE
from torchsoil.synth.conventions import CONVENTIONS, rewrite_recording
from torchsoil.synth.record import make_recording, sidecar

TOPICS = ("/lidar_front/points", "/lidar_back/points")
# the targets: terrain within 1 mm RMS, trajectory within 1 cm. The pipeline is made
# repeatable to point-time roundings (7 ns float32, 240 ns float64 absolute seconds): measured
# 0.15 mm RMS at most; a lost de-skew or a wrong pairing moves cells by 4-6 mm.
MEDIAN_M, RMS_M, TRAJ_M = 0.001, 0.001, 0.01


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """3 s at 1 m/s (30 sweeps per lidar, 512 columns) in the Ouster layout, and its terrain pair."""
    root = tmp_path_factory.mktemp("conv")
    make_recording(SCN, root / "ouster", seed=3, duration=3.0)
    robot = Robot.from_yaml(sidecar(root / "ouster", "robot.yaml"))
    return root, robot, process_bag(root / "ouster", robot)


def on_common_cells(a, b) -> np.ndarray:
    """H of two terrain pairs (same dx) on the cells both measured: (K, 2, 2) [f/b, this/ref]."""
    o = np.round((np.asarray(a.origin) - np.asarray(b.origin)) / b.dx).astype(int)
    out = []
    for key in ("h_front", "h_back"):
        x, y = getattr(a, key), getattr(b, key)
        X = np.full(y.shape, np.nan, np.float32)
        i0, j0 = max(o[0], 0), max(o[1], 0)
        i1, j1 = min(y.shape[0], o[0] + x.shape[0]), min(y.shape[1], o[1] + x.shape[1])
        X[i0:i1, j0:j1] = x[i0 - o[0]:i1 - o[0], j0 - o[1]:j1 - o[1]]
        out.append((X, y))
    return out


def differences(res, ref):
    """median |dH|, RMS dH (m) of H_f and H_b on common cells, and the largest trajectory gap (m)."""
    stats = []
    for x, y in on_common_cells(res.terrain, ref.terrain):
        d = (x - y)[np.isfinite(x) & np.isfinite(y)]
        assert len(d) > 5000
        stats += [float(np.median(np.abs(d))), float(np.sqrt(np.mean(d ** 2)))]
    p, q = res.terrain.poses, ref.terrain.poses
    assert len(p) == len(q)
    np.testing.assert_allclose(p[:, 0], q[:, 0], atol=1e-5)          # the same sweep times
    return stats, float(np.abs(p[:, 1:4] - q[:, 1:4]).max())


@pytest.mark.parametrize("convention", [c for c in CONVENTIONS if c != "ouster"])
def test_every_convention_gives_the_ouster_terrain(drive, convention):
    root, robot, ref = drive
    rewrite_recording(root / "ouster", root / convention, convention)
    res = process_bag(root / convention, robot)
    assert res.problems == ref.problems          # nothing new to say about the recording
    (med_f, rms_f, med_b, rms_b), traj = differences(res, ref)
    assert med_f < MEDIAN_M and med_b < MEDIAN_M, (med_f, med_b)
    assert rms_f < RMS_M and rms_b < RMS_M, (rms_f, rms_b)
    assert traj < TRAJ_M


def test_the_old_reading_of_mixed_stamps_is_caught(drive):
    """Front start-stamped, back end-stamped, point times ignored (as before): the comparison fails."""
    root, robot, ref = drive
    rewrite_recording(root / "ouster", root / "mixed_old", "mixed")
    old = PipelineConfig(read=ReadConfig(times={t: TopicTime(time_field="none") for t in TOPICS}))
    res = process_bag(root / "mixed_old", robot, old)
    (med_f, _, med_b, _), _ = differences(res, ref)
    assert med_f > 2 * MEDIAN_M and med_b > 2 * MEDIAN_M


@pytest.mark.parametrize("convention, msgtype, time_field", [
    ("velodyne", "sensor_msgs/msg/PointCloud2", "time"), ("livox_custom", "livox_ros_driver2/msg/CustomMsg", None)])
def test_recorder_writes_a_convention(tmp_path, convention, msgtype, time_field):
    make_recording(SCN, tmp_path / "r", seed=1, duration=0.2, convention=convention)
    with AnyReader([tmp_path / "r"], default_typestore=TYPESTORE) as r:
        types = {c.topic: c.msgtype for c in r.connections}
        msg = next(r.deserialize(raw, c.msgtype) for c, _, raw in r.messages() if c.topic == TOPICS[1])
    assert types[TOPICS[0]] == types[TOPICS[1]] == msgtype
    if time_field:
        assert time_field in [f.name for f in msg.fields] and "t" not in [f.name for f in msg.fields]
    else:
        assert msg.timebase == msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        assert min(p.offset_time for p in msg.points) == 0 and msg.point_num == len(msg.points) > 1000
    with pytest.raises(ValueError, match="unknown convention 'sick'"):
        make_recording(SCN, tmp_path / "s", convention="sick")
