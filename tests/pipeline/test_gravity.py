"""Levelling the world frame: gravity from an IMU along a moving trajectory, the ground plane
without one, and the rotation that turns the world upright; expectations worked out by hand."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from torchsoil.io.bag import ImuData
from torchsoil.pipeline.gravity import (
    G,
    gravity_and_bias,
    gravity_from_ground,
    gravity_from_imu,
    level,
    levelling_rotation,
    tilt_deg,
)
from torchsoil.settings import LevelConfig


def test_levelling_rotation_turns_gravity_down_without_yaw():
    roll = np.radians(4.6)
    down = np.array([0.0, -np.sin(roll), -np.cos(roll)]) * G  # a world frame rolled by 4.6 deg
    R = levelling_rotation(down)
    np.testing.assert_allclose(R @ down, [0, 0, -G], atol=1e-12)
    np.testing.assert_allclose(R, Rotation.from_euler("x", roll).as_matrix(), atol=1e-12)
    assert tilt_deg(R) == pytest.approx(4.6)
    np.testing.assert_allclose(levelling_rotation([0, 0, -3.0]), np.eye(3))


def imu_along(roll, accel, base_T_imu, t):
    """The robot stands rolled by `roll` (left side up) and accelerates along its x at `accel`
    m/s^2 from 0.5 m/s. Its true attitude R_true = Rx(roll) in a gravity-aligned world. The
    mapper's world frame is base_link at t = 0, so there the poses are translations along x
    only. An IMU turned by base_T_imu reads f = R_imu^T R_true^T (a - g)."""
    R_true = Rotation.from_euler("x", roll).as_matrix()
    a_world = R_true @ [accel, 0, 0]
    f_base = R_true.T @ (a_world - [0, 0, -G])
    f_imu = base_T_imu[:3, :3].T @ f_base
    stamps = np.arange(0, 3.0, 0.1)
    poses = np.repeat(np.eye(4)[None], len(stamps), 0)
    poses[:, 0, 3] = 0.5 * stamps + 0.5 * accel * stamps**2
    imu = ImuData(t, np.tile(f_imu, (len(t), 1)), np.zeros((len(t), 3)), "imu_link", "/imu/data")
    return stamps, poses, imu


def test_gravity_from_an_accelerating_tilted_robot():
    """In the mapper's frame gravity is R_true^T (0, 0, -G) = (0, -G sin(roll), -G cos(roll)):
    the forward acceleration (1 m/s^2, 6 deg worth if ignored) is taken out by the trajectory."""
    roll = np.radians(4.6)
    base_T_imu = np.eye(4)
    base_T_imu[:3, :3] = Rotation.from_euler("z", np.pi / 2).as_matrix()
    base_T_imu[:3, 3] = [0.2, 0.05, 0.35]
    stamps, poses, imu = imu_along(roll, 1.0, base_T_imu, np.arange(0, 3.0, 0.01))
    g = gravity_from_imu(stamps, poses, imu, base_T_imu, window=2.0)
    np.testing.assert_allclose(g, [0, -G * np.sin(roll), -G * np.cos(roll)], atol=1e-9)
    R = levelling_rotation(g)
    assert tilt_deg(R) == pytest.approx(4.6, abs=1e-6)


def circling(rate, bias, lever, T=30.0):
    """A robot tilted by 4.6 deg of roll and 1.7 deg of pitch in the mapper's frame drives a
    circle of radius 1/rate m at 1 m/s (or straight when rate is 0), its IMU `lever` (3,) m
    from base_link, turned by 90 deg of yaw, with a constant accelerometer bias (3,) m/s^2.
    Positions and their second derivatives are written out by hand (no trajectory code)."""
    L = Rotation.from_euler("xy", [0.08, -0.03]).as_matrix()      # the mapper's world vs gravity
    g_world = L @ [0, 0, -G]
    mount = Rotation.from_euler("z", np.pi / 2).as_matrix()
    base_T_imu = np.eye(4)
    base_T_imu[:3, :3], base_T_imu[:3, 3] = mount, lever

    def state(t):
        yaw = rate * t
        Rz = Rotation.from_euler("z", yaw[:, None]).as_matrix()
        if rate == 0:
            p, a = np.stack([t, 0 * t, 0 * t], -1), np.zeros((len(t), 3))
        else:   # p = (sin(yaw), 1 - cos(yaw)) / rate, a = rate (-sin(yaw), cos(yaw))
            p = np.stack([np.sin(yaw), 1 - np.cos(yaw), 0 * t], -1) / rate
            a = np.stack([-np.sin(yaw), np.cos(yaw), 0 * t], -1) * rate
        a_lever = -rate**2 * (Rz @ (np.array(lever) * [1, 1, 0]))   # centripetal at the lever arm (N, 3)
        return p @ L.T, L @ Rz, (a + a_lever) @ L.T

    stamps, t = np.arange(0, T, 0.1), np.arange(0, T, 0.01)
    p, R, _ = state(stamps)
    poses = np.repeat(np.eye(4)[None], len(stamps), 0)
    poses[:, :3, :3], poses[:, :3, 3] = R, p
    _, Ri, a = state(t)
    f = np.einsum("nji,nj->ni", Ri @ mount, a - g_world) + bias
    return stamps, poses, ImuData(t, f, np.zeros_like(f), "imu_link", "/imu/data"), base_T_imu, g_world


def angle_deg(u, v):
    return float(np.degrees(np.arccos(np.clip(np.dot(u, v) / np.linalg.norm(u) / np.linalg.norm(v), -1, 1))))


def test_a_turn_tells_the_accelerometer_bias_from_gravity():
    """A 2 mg horizontal bias tilts gravity measured over the first seconds by 0.14 deg; on a
    circle the bias turns with the robot while gravity does not, and both come out."""
    bias = np.array([0.02, -0.015, 0.0])
    stamps, poses, imu, base_T_imu, g_true = circling(0.15, bias, [0.2, 0.05, 0.35])
    assert angle_deg(gravity_from_imu(stamps, poses, imu, base_T_imu, 2.0), g_true) > 0.1
    g, b, turn = gravity_and_bias(stamps, poses, imu, base_T_imu, 30.0)
    assert turn == pytest.approx(np.degrees(0.15 * 29.9), abs=0.5)
    assert angle_deg(g, g_true) < 0.005
    np.testing.assert_allclose(b[:2], bias[:2], atol=5e-4)
    # on a straight drive the bias cannot be told from a tilt: none is claimed
    stamps, poses, imu, base_T_imu, g_true = circling(0.0, bias, [0.2, 0.05, 0.35])
    g, b, turn = gravity_and_bias(stamps, poses, imu, base_T_imu, 30.0)
    assert turn < 1e-6 and np.all(b == 0)
    assert angle_deg(g, g_true) == pytest.approx(np.degrees(np.hypot(0.02, 0.015) / G), rel=0.05)


def test_the_imu_lever_arm_on_a_turn_is_not_read_as_tilt():
    """Without a bias, an IMU 0.2 m ahead of base_link on a 0.15 rad/s circle feels 4.5 mm/s^2
    of centripetal acceleration base_link does not: taken from the IMU point's own path."""
    stamps, poses, imu, base_T_imu, g_true = circling(0.15, np.zeros(3), [0.2, 0.05, 0.35])
    g, b, _ = gravity_and_bias(stamps, poses, imu, base_T_imu, 30.0)
    assert angle_deg(g, g_true) < 0.005 and np.abs(b).max() < 2e-4
    assert angle_deg(gravity_from_imu(stamps, poses, imu, base_T_imu, 2.0), g_true) < 0.005


def test_imu_readings_that_are_not_gravity_are_refused():
    stamps, poses, imu = imu_along(0.0, 0.0, np.eye(4), np.arange(0, 3.0, 0.01))
    in_g = ImuData(imu.t, imu.acc / G, imu.gyro, imu.frame, imu.topic)  # in g, not m/s^2
    with pytest.raises(ValueError, match=r"/imu/data: gravity measured as .* not about 9.81 m/s\^2"):
        gravity_from_imu(stamps, poses, in_g, np.eye(4), 2.0)
    upside_down = np.diag([1.0, -1.0, -1.0, 1.0])  # extrinsic wrong by 180 deg of roll
    with pytest.raises(ValueError, match="extrinsic of frame 'imu_link'"):
        gravity_from_imu(stamps, poses, imu, upside_down, 2.0)
    other_clock = ImuData(imu.t + 1e9, imu.acc, imu.gyro, imu.frame, imu.topic)
    with pytest.raises(ValueError, match="0 IMU samples .* another clock"):
        gravity_from_imu(stamps, poses, other_clock, np.eye(4), 2.0)


def test_ground_plane_of_a_side_slope_with_posts():
    """Ground z = 0.08 y (an 8 % side slope) with 3 mm noise, and a post and a roof that the
    fit must leave out: normal (0, 0.08, -1) / |.|."""
    rng = np.random.default_rng(0)
    xy = rng.uniform(-8, 8, (4000, 2))
    ground = np.column_stack([xy, 0.08 * xy[:, 1] + rng.normal(0, 0.003, len(xy))])
    normals = np.tile([0.0, -0.08, 1.0], (len(ground), 1))
    post = np.column_stack([np.full(300, 2.0), np.full(300, 1.0), np.linspace(0, 2, 300)])
    roof = np.column_stack([rng.uniform(-3, -1, (300, 2)), np.full(300, 2.5)])
    pts = np.concatenate([ground, post, roof])
    nrm = np.concatenate([normals, np.tile([1.0, 0, 0], (300, 1)), np.tile([0, 0, 1.0], (300, 1))])
    down = gravity_from_ground(pts, nrm, radius=6.0)
    np.testing.assert_allclose(down, np.array([0, 0.08, -1]) / np.hypot(1, 0.08), atol=5e-4)


def test_level_without_imu_says_so_and_none_keeps_the_frame():
    rng = np.random.default_rng(1)
    xy = rng.uniform(-5, 5, (1000, 2))
    pts = np.column_stack([xy, 0.05 * xy[:, 0]])
    nrm = np.tile([0.0, 0, 1.0], (len(pts), 1))
    stamps, poses = np.arange(3) * 0.1, np.repeat(np.eye(4)[None], 3, 0)
    R, notes = level(stamps, poses, pts, nrm, None, None, LevelConfig())
    assert tilt_deg(R) == pytest.approx(np.degrees(np.arctan(0.05)), abs=1e-6)
    assert len(notes) == 1 and "no IMU topic" in notes[0] and "ground plane" in notes[0]
    R, notes = level(stamps, poses, pts, nrm, None, None, LevelConfig(source="none"))
    assert notes == [] and np.array_equal(R, np.eye(3))
    with pytest.raises(ValueError, match="source is imu but the recording has no IMU"):
        level(stamps, poses, pts, nrm, None, None, LevelConfig(source="imu"))
