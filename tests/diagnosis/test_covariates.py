"""Pose signals: recovered from analytic trajectories; earlier passes on a racetrack loop."""

import math

import numpy as np
import pytest

from tests.drive_by_hand import poses_from, racetrack
from torchsoil.diagnosis.covariates import DriveSignals, pose_signals, window_signals
from torchsoil.robot import paper_platform


def test_circle_speed_turn_rate_and_lateral_accel():
    v, R = 1.2, 4.0
    t = np.arange(0, 10, 0.05)
    a = v * t / R
    sig = pose_signals(poses_from(t, R * np.sin(a), R * (1 - np.cos(a)), a))
    mid = slice(20, -20)
    assert np.allclose(sig["speed"][mid], v, rtol=1e-3)
    assert np.allclose(sig["yaw_rate"][mid], v / R, rtol=1e-3)
    assert np.allclose(sig["lateral_accel"][mid], v * v / R, rtol=2e-3)
    assert np.allclose(sig["arc_length"][-1], v * t[-1], rtol=1e-3)


def test_acceleration_and_traction_demand_with_climb():
    t = np.arange(0, 6, 0.05)
    acc = 0.3
    x = 0.5 * t + 0.5 * acc * t**2
    pitch = np.full_like(t, -0.05)                          # climbing
    sig = pose_signals(poses_from(t, x, 0 * t, 0 * t, pitch=pitch))
    mid = slice(20, -20)
    assert np.allclose(sig["accel"][mid], acc, atol=1e-3)
    assert np.allclose(sig["traction"][mid], acc / 9.81 + math.sin(0.05), atol=1e-3)


def test_passes_count_the_ground_driven_twice_only():
    robot = paper_platform()
    poses = racetrack()
    drive = DriveSignals.from_poses(poses, robot)
    arc = drive.signals["arc_length"]
    first = (arc > 0.5) & (arc < 1.5)                    # driven again at the end
    west = (arc > 4.0 + math.pi * 1.5 + 0.5) & (arc < 4.0 + math.pi * 1.5 + 3.5)   # driven once
    again = arc > arc[-1] - 1.2
    p4 = drive.poses4
    assert (drive.pose_passes(p4[first], robot) == 1).all()
    assert drive.pose_passes(p4[west], robot).max() == 0
    assert (drive.pose_passes(p4[again], robot) == 1).all()
    w = window_signals(drive, [(5.0, 5.8), (arc[-1] - 1.0, arc[-1])], robot)
    assert w["passes"][0] == 0 and w["passes"][1] == pytest.approx(1.0)
    # counted before each pose's own visit (a simulation that drives every visit): the first
    # lap's wheels found fresh ground, the second lap's the first lap's ruts
    assert drive.pose_passes(p4[first], robot, before=True).max() == 0
    assert (drive.pose_passes(p4[again], robot, before=True) == 1).all()
    assert drive.pose_passes(p4[west], robot, before=True).max() == 0


def test_wheel_passes_count_the_front_wheel_for_the_rear_one():
    """Out 6 m along x and back in reverse, axles at +-0.69 m. Counting wheel passes, a rear
    wheel on the way out finds one pass (its front wheel's), and on the way back (the rear
    axle leading) the rear wheel finds two and the front wheel three; counting visits, the
    way back once or not at all (see below). Without `before` the pair shows the last pass, which counts the
    same whichever leg the pose is on."""
    robot = paper_platform()
    t = np.arange(0.0, 12.0 + 1e-9, 0.02)
    x = np.where(t <= 6.0, t, 12.0 - t)
    drive = DriveSignals.from_poses(poses_from(t, x, 0 * t, 0 * t), robot)
    p4 = drive.poses4
    out, back = p4[np.argmin(np.abs(t - 3.0))][None], p4[np.argmin(np.abs(t - 9.0))][None]
    front, rear = robot.wheels[:, 0] > 0, robot.wheels[:, 0] < 0
    for pose, want in ((out, {"front": 0, "rear": 1}), (back, {"front": 3, "rear": 2})):
        got = drive.pose_passes(pose, robot, before=True, by_wheel=True)[:, 0]
        assert got[front] == pytest.approx([want["front"]] * 2, abs=0.01)
        assert got[rear] == pytest.approx([want["rear"]] * 2, abs=0.01)
        last = drive.pose_passes(pose, robot, by_wheel=True)[:, 0]
        assert last[front] == pytest.approx([3, 3], abs=0.01) and last[rear] == pytest.approx([2, 2], abs=0.01)
    # counting robot visits: the front wheels' ground (x 3.69) was left 0.7 m of travel before
    # the robot reversed onto it (one visit), the rear wheels' (x 2.31) 5.3 m before (two)
    assert drive.pose_passes(back, robot, before=True)[:, 0] == pytest.approx([0, 0, 1, 1])


@pytest.mark.parametrize("bad, msg", [(np.zeros((10, 6)), "(N, 7)"), (np.zeros((2, 7)), "at least 3"),
                                      (np.zeros((5, 7)), "time must increase")])
def test_bad_poses_are_named(bad, msg):
    with pytest.raises(ValueError, match=msg.replace("(", r"\(").replace(")", r"\)")):
        pose_signals(bad)


@pytest.mark.parametrize("beside, share", [(0.05, 1.0), (0.21, 0.5), (0.4, 0.0)])
def test_an_old_track_beside_the_wheel_counts_in_part(beside, share):
    """Compaction fades over two wheel widths beside an old footprint (0.14 m wheels)."""
    x = np.arange(0.0, 6.0, 0.02)
    old = np.column_stack([x, np.zeros_like(x)])
    new = np.column_stack([x, np.full_like(x, beside)])
    drive = DriveSignals({}, np.zeros((0, 4)), np.concatenate([old, new]), np.concatenate([x, x + 20.0]),
                         radius=0.07 + 0.28, gap=3.0, inner=0.07)
    got = drive.passes(np.array([[3.0, beside]]), np.array([23.0]))
    assert got[0] == pytest.approx(share, abs=0.02)


def test_a_fields_earlier_passes_add_to_every_count():
    """A layer of 3 passes before the recording (a field's earlier sessions) over the first lap's
    start and nothing elsewhere: counts there are the drive's own plus 3, elsewhere unchanged."""
    robot = paper_platform()
    poses = racetrack()
    plain = DriveSignals.from_poses(poses, robot)
    origin, dx = np.array([-10.0, -10.0]), 0.02
    layer = np.zeros((1000, 1000))
    layer[:, :] = 3.0 * ((origin[0] + np.arange(1000) * dx) < 1.0)[:, None]     # the ground at x < 1 m
    seasoned = DriveSignals.from_poses(poses, robot, prior=(layer, origin, dx))
    pts = np.array([[0.5, 0.0], [3.0, 0.0], [-9.0, 5.0], [50.0, 0.0]])            # the last: off the layer
    arc = np.full(4, plain.signals["arc_length"][-1])
    got = seasoned.passes(pts, arc) - plain.passes(pts, arc)
    np.testing.assert_array_equal(got, [3.0, 0.0, 3.0, 0.0])
    p4 = plain.poses4[:5]
    assert (seasoned.pose_passes(p4, robot, before=True) - plain.pose_passes(p4, robot, before=True) >= 3).all()
