"""Registration through the turns robots make (keyhole and headland turns): a steering step
(the yaw rate flips sign between two sweeps), a lidar that goes silent during a turn, and a
gap in both; scored against the toy scene's exact poses."""

import numpy as np
import pytest

from tests.pipeline.toyscene import ToyScene
from torchsoil.io.trajectory import rows_to_poses
from torchsoil.pipeline import mapping
from torchsoil.pipeline.mapping import _arc_motion, _motion_over, _velocity
from torchsoil.pipeline.run import process_bag
from torchsoil.robot import paper_platform
from torchsoil.settings import PipelineConfig

YAW_RATE = 0.7   # rad/s: 40 deg/s, a 1.43 m radius at 1 m/s


def errors(res, scene):
    """Per pose: |yaw error| deg and horizontal position error m, first pose aligned."""
    tp = res.terrain
    est = rows_to_poses(tp.poses)
    true = scene.pose(tp.poses[:, 0] - 100.0)
    W = true[0] @ np.linalg.inv(est[0]) @ est
    yaw = np.arctan2(W[:, 1, 0], W[:, 0, 0]) - np.arctan2(true[:, 1, 0], true[:, 0, 0])
    return np.degrees(np.abs(np.angle(np.exp(1j * yaw)))), np.linalg.norm(W[:, :2, 3] - true[:, :2, 3], axis=1)


def run(tmp_path, config=None, duration=3.5, **kw):
    scene = ToyScene(columns=256, **{"yaw_rate": YAW_RATE, **kw})
    scene.write(tmp_path / "bag", duration)
    return process_bag(tmp_path / "bag", paper_platform(), config), scene


def test_a_constant_turn_is_an_arc():
    """The motion model at constant rates moves on the circle (x = R sin(wt), y = R (1 - cos(wt)))
    even over a long interval, and _velocity inverts it."""
    w, v, dt = 0.7, 1.0, 2.0
    M = _arc_motion([0.0, 0.0, w], [v, 0.0, 0.0], dt)
    R = v / w
    assert M[:2, 3] == pytest.approx([R * np.sin(w * dt), R * (1 - np.cos(w * dt))], abs=1e-12)
    assert np.arctan2(M[1, 0], M[0, 0]) == pytest.approx(w * dt)
    rates = _velocity(np.eye(4), M, dt)
    assert np.allclose(_motion_over(rates, dt), M, atol=1e-12)
    assert np.allclose(_motion_over(rates, dt / 2)[:2, 3], [R * np.sin(w), R * (1 - np.cos(w))], atol=1e-12)


def test_a_steering_step_is_followed(tmp_path):
    """The yaw rate flips from +40 to -40 deg/s between two sweeps: the constant-velocity
    prediction is 8 deg off. Registered again from other starts, the trajectory stays within
    1 deg and 5 cm; without the retry (one start only) it is left several degrees off."""
    res, scene = run(tmp_path, flip=1.5)
    yaw, pos = errors(res, scene)
    assert yaw.max() < 1.0 and pos.max() < 0.05
    flags = res.terrain.extras["scan_flags"]
    assert np.any(flags & mapping.RETRIED)
    assert not any("retried" in p for p in res.problems)     # a retry that registered is no problem

    cfg = PipelineConfig()
    once = cfg.model_copy(update={"mapping": cfg.mapping.model_copy(
        update={"retry_turn": 179.0, "retry_cost": 1e9, "max_yaw_rate": 1e-3})})
    res1, _ = run(tmp_path / "once", once, flip=1.5)
    assert errors(res1, scene)[0].max() > 3.0


def test_a_silent_front_lidar_in_a_turn_leaves_the_map_going(tmp_path):
    """The front lidar publishes nothing for 1 s of a turn: the back sweeps are mapped alone
    (flagged missing_front) and the trajectory stays right."""
    res, scene = run(tmp_path, silent={"lidar_front": (1.5, 2.5)})
    yaw, pos = errors(res, scene)
    assert yaw.max() < 1.0 and pos.max() < 0.05
    assert any("missing_front" in p for p in res.problems)
    assert not any("gap" in p for p in res.problems)


def test_a_gap_in_both_lidars_is_flagged_and_bridged(tmp_path):
    """Both lidars silent for 1 s of a turn: the first sweep after the gap is flagged (its
    windows are flagged by the estimator) and registered from an arc, not a straight line."""
    res, scene = run(tmp_path, silent={"lidar_front": (1.5, 2.5), "lidar_back": (1.5, 2.5)})
    yaw, pos = errors(res, scene)
    assert yaw.max() < 1.0 and pos.max() < 0.05
    gap = [p for p in res.problems if p.endswith(": gap")]
    assert len(gap) == 1 and "t = 2.60" in gap[0]


def test_a_rate_gyro_predicts_the_steering_step(tmp_path):
    """With an IMU (mounted turned 90 deg about z: its rates must be turned into base_link) the
    rotation between sweeps is measured, not guessed: the steering step is followed within
    0.4 deg, closer than the same bag with the gyro ignored."""
    res, scene = run(tmp_path, flip=1.5, imu_rate=100.0)
    yaw, pos = errors(res, scene)
    assert yaw.max() < 0.4 and pos.max() < 0.03
    cfg = PipelineConfig()
    blind = cfg.model_copy(update={"mapping": cfg.mapping.model_copy(update={"use_gyro": False})})
    yaw_blind, _ = errors(process_bag(tmp_path / "bag", paper_platform(), blind), scene)
    assert yaw_blind.max() > 1.5 * yaw.max()


def test_a_crab_drive_is_tracked(tmp_path):
    """Four-wheel crab steering: the robot travels 20 deg off its heading while turning at
    11 deg/s; the motion model carries the sideways velocity and the trajectory holds."""
    res, scene = run(tmp_path, crab=np.radians(20.0), yaw_rate=0.2)
    yaw, pos = errors(res, scene)
    assert yaw.max() < 0.5 and pos.max() < 0.03


def test_a_map_broken_between_visits_flags_the_later_visit():
    """The foreign out-and-back pair with its way back moved 5 cells across the drive (as a
    map broken in the turn leaves it): check_visits says so and flags the sweeps of the second
    visit over that ground, and only those; the pair as made passes."""
    from pathlib import Path

    from torchsoil.io.terrain_pair import TerrainPair
    from torchsoil.pipeline.checks import check_visits

    pair = TerrainPair.load(Path(__file__).resolve().parents[3] / "shared/foreign/multi_pass_hardening.npz")
    stamps = pair.poses[:, 0].copy()
    pair.extras.update(scan_stamps=stamps, scan_flags=np.zeros(len(stamps), np.int64))
    assert check_visits(pair, 0.04) == [] and not pair.extras["scan_flags"].any()
    back = np.isfinite(pair.visit_time[1])
    t0, t1 = np.nanmin(pair.visit_time[1]), np.nanmax(pair.visit_time[1])
    moved = pair.visit_front.copy()
    if abs(np.cos(np.median(pair.poses[:, 6]))) < 0.3:    # the drive runs along y: move along x
        moved[1][5:], moved[1][:5] = pair.visit_front[1][:-5], np.nan
    else:
        moved[1][:, 5:], moved[1][:, :5] = pair.visit_front[1][:, :-5], np.nan
    pair.visit_front = moved
    problems = check_visits(pair, 0.04)
    assert len(problems) == 1 and "10 cm" in problems[0] and "map broke" in problems[0]
    hit = (pair.extras["scan_flags"] & mapping.MAP_CONFLICT) != 0
    assert hit.any() and np.all((stamps[hit] >= t0) & (stamps[hit] <= t1)) and back.any()
    assert pair.extras["visit_shift"][0] == pytest.approx([0.1, 0.0], abs=1e-9) or \
        pair.extras["visit_shift"][0] == pytest.approx([0.0, 0.1], abs=1e-9)
