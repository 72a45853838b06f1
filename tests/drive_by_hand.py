"""Drives built by hand, with the physics each one should show worked out from kinematics.

Poses follow docs/formats.md section 3 (rows t, x, y, z, roll, pitch, yaw) in ROS REP 103:
x forward, y left, z up, and roll, pitch, yaw as rotations about the FIXED axes X, Y, Z in
that order, i.e. R = Rz(yaw) Ry(pitch) Rx(roll) = scipy `Rotation.from_euler("xyz", ...)`.
The attitude is never written down as an angle: it is built as a rotation matrix from the
direction of travel and the ground normal, and scipy turns it into roll, pitch, yaw.

The expected signals come from the specific force f = a - g_vec (what an accelerometer on
the chassis reads; g_vec = (0, 0, -g)), expressed in the body axes:

- traction demand, in g: x_body . f / g. The wheels must push the chassis forward with this
  force per unit weight: to accelerate (a along x) and to lift it up a slope (gravity has a
  component -g sin(grade) along a nose-up x axis).
- lateral load, in g: y_body . f / g. The tyres must hold the chassis toward its left with
  this force per unit weight, so the load moves onto the RIGHT wheels when it is > 0: in a
  left turn (centripetal acceleration toward the left, the right wheels are the outer ones)
  and on a slope whose left side is higher (gravity pulls toward the right, downhill side).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

G = 9.80665  # m/s^2, standard gravity (the code may use 9.81: 0.03 % apart)
DT = 0.02    # s between poses


def body_axes(forward, up) -> np.ndarray:
    """(N, 3, 3) rotation matrices whose columns are the body x (along `forward`), y (left)
    and z (along `up` made orthogonal to x) axes in the world frame."""
    fwd = np.atleast_2d(np.asarray(forward, np.float64))
    up = np.broadcast_to(np.asarray(up, np.float64), fwd.shape)
    x = fwd / np.linalg.norm(fwd, axis=1, keepdims=True)
    z = up - np.sum(up * x, axis=1, keepdims=True) * x
    z = z / np.linalg.norm(z, axis=1, keepdims=True)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


def rpy(R: np.ndarray) -> np.ndarray:
    """(N, 3, 3) -> (N, 3) roll, pitch, yaw in REP 103 fixed axes (scipy extrinsic 'xyz')."""
    return Rotation.from_matrix(R).as_euler("xyz")


class Drive(NamedTuple):
    """A hand-built drive.

    poses: (N, 7) docs/formats.md rows. R: (N, 3, 3) body axes in the world. speed: (N,) speed along
    the path, m/s. accel: (N,) rate of change of that speed, m/s^2. yaw_rate: (N,) rad/s.
    a_world: (N, 3) acceleration of base_link in the world, m/s^2.
    """

    name: str
    poses: np.ndarray
    R: np.ndarray
    speed: np.ndarray
    accel: np.ndarray
    yaw_rate: np.ndarray
    a_world: np.ndarray

    @property
    def specific_force(self) -> np.ndarray:
        """(N, 3) accelerometer reading a - g_vec in the BODY axes, m/s^2."""
        f = self.a_world - np.array([0.0, 0.0, -G])
        return np.einsum("nji,nj->ni", self.R, f)

    @property
    def traction(self) -> np.ndarray:
        """Traction demand in g: forward specific force / g (> 0: the wheels must push)."""
        return self.specific_force[:, 0] / G

    @property
    def lateral_load(self) -> np.ndarray:
        """Lateral load in g: leftward specific force / g (> 0: load moves to the right wheels)."""
        return self.specific_force[:, 1] / G

    @property
    def roll(self):
        return self.poses[:, 4]

    @property
    def pitch(self):
        return self.poses[:, 5]

    def interior(self, margin_s: float = 1.0) -> np.ndarray:
        """Boolean mask of poses at least `margin_s` from both ends (derivatives are exact there)."""
        t = self.poses[:, 0]
        return (t >= t[0] + margin_s) & (t <= t[-1] - margin_s)


def _drive(name, t, p, v_world, a_world, up, speed, accel, yaw_rate) -> Drive:
    R = body_axes(v_world, up)
    poses = np.column_stack([t, p, rpy(R)])
    return Drive(name, poses, R, speed, accel, yaw_rate, a_world)


def straight(name: str, heading: float, grade: float, v0: float, a: float, duration: float = 5.0) -> Drive:
    """Straight drive on a plane rising `grade` (rise over horizontal run) along the direction
    of travel, with speed along the path v0 + a t. heading: direction of travel, rad."""
    t = np.arange(0.0, duration + 1e-9, DT)
    u = np.array([math.cos(heading), math.sin(heading), grade])
    u = u / np.linalg.norm(u)                                    # unit direction of travel
    s = v0 * t + 0.5 * a * t**2
    up = np.array([-grade * math.cos(heading), -grade * math.sin(heading), 1.0])   # plane normal
    return _drive(name, t, s[:, None] * u, np.broadcast_to(u, (len(t), 3)), (a * np.ones_like(t))[:, None] * u,
                  up, v0 + a * t, a * np.ones_like(t), np.zeros_like(t))


def turn(name: str, v: float, radius: float, left: bool = True, duration: float = 8.0) -> Drive:
    """Constant-speed circle on flat ground, starting at the origin heading +x; the centre is
    `radius` to the left (left turn) or to the right."""
    t = np.arange(0.0, duration + 1e-9, DT)
    sgn = 1.0 if left else -1.0
    a = v * t / radius                                           # angle travelled
    c = np.array([0.0, sgn * radius, 0.0])                       # turn centre
    p = np.column_stack([radius * np.sin(a), sgn * radius * (1 - np.cos(a)), 0 * t])
    vel = np.column_stack([v * np.cos(a), sgn * v * np.sin(a), 0 * t])
    acc = (c - p) / radius * v**2 / radius                       # centripetal, toward the centre
    return _drive(name, t, p, vel, acc, [0.0, 0.0, 1.0], v + 0 * t, 0 * t, sgn * v / radius + 0 * t)


def side_slope(name: str, cross_grade: float, heading: float = 0.0, v: float = 0.0, duration: float = 4.0) -> Drive:
    """On a plane whose LEFT side (seen along `heading`) is higher by `cross_grade` per metre,
    standing still (v = 0) or driving straight along the contour line at speed v."""
    t = np.arange(0.0, duration + 1e-9, DT)
    fwd = np.array([math.cos(heading), math.sin(heading), 0.0])  # along the contour: level
    left = np.array([-math.sin(heading), math.cos(heading), 0.0])
    up = np.array([0.0, 0.0, 1.0]) - cross_grade * left          # normal of z = cross_grade * (left . p)
    p = v * t[:, None] * fwd
    return _drive(name, t, p, np.broadcast_to(fwd, (len(t), 3)), np.zeros((len(t), 3)), up,
                  v + 0 * t, 0 * t, 0 * t)


def catalogue() -> dict[str, Drive]:
    """The situations of the by-hand tests, by name."""
    drives = [
        straight("climb_10pct", heading=0.6, grade=0.10, v0=1.0, a=0.0),
        straight("descend_10pct", heading=0.6 + math.pi, grade=-0.10, v0=1.0, a=0.0),
        straight("accelerate", heading=0.0, grade=0.0, v0=0.5, a=0.5, duration=4.0),
        straight("brake", heading=0.0, grade=0.0, v0=2.5, a=-0.5, duration=4.0),
        turn("turn_left", v=1.5, radius=5.0, left=True),
        turn("turn_right", v=1.5, radius=5.0, left=False),
        side_slope("side_slope_left_high", cross_grade=0.10),
        side_slope("side_slope_left_high_driving", cross_grade=0.10, heading=2.0, v=0.8),
    ]
    return {d.name: d for d in drives}


def reversing_straight(name: str, heading: float, grade: float, v0: float, a: float, duration: float = 4.0) -> Drive:
    """Driving BACKWARDS in a straight line: the body x axis points along `heading`, the robot
    moves the other way with speed v0 + a t (a > 0: speeding up backwards), on a plane rising
    `grade` along the direction of TRAVEL (grade > 0: reversing uphill, nose pointing down)."""
    t = np.arange(0.0, duration + 1e-9, DT)
    u = np.array([-math.cos(heading), -math.sin(heading), grade])
    u = u / np.linalg.norm(u)                                    # unit direction of travel
    s = v0 * t + 0.5 * a * t**2
    up = np.array([grade * math.cos(heading), grade * math.sin(heading), 1.0])    # plane normal
    return _drive(name, t, s[:, None] * u, np.broadcast_to(-u, (len(t), 3)), (a * np.ones_like(t))[:, None] * u,
                  up, v0 + a * t, a * np.ones_like(t), np.zeros_like(t))


def reversing_turn(name: str, v: float, yaw_rate: float, duration: float = 8.0) -> Drive:
    """Driving BACKWARDS at speed v on flat ground while the heading turns at `yaw_rate`
    (> 0: counter-clockwise). The velocity is -v x_body, so its rate of change is
    yaw_rate z x (-v x_body) = -v yaw_rate y_body: for yaw_rate > 0 the turn centre is on the
    robot's RIGHT and the outer wheels are the LEFT ones."""
    t = np.arange(0.0, duration + 1e-9, DT)
    w = yaw_rate
    psi = w * t
    p = np.column_stack([-(v / w) * np.sin(psi), -(v / w) * (1 - np.cos(psi)), 0 * t])
    x_body = np.column_stack([np.cos(psi), np.sin(psi), 0 * t])
    y_body = np.column_stack([-np.sin(psi), np.cos(psi), 0 * t])
    return _drive(name, t, p, x_body, -v * w * y_body, [0.0, 0.0, 1.0], v + 0 * t, 0 * t, w + 0 * t)


def poses_from(t, x, y, yaw, roll=None, pitch=None):
    """(N, 7) docs/formats.md poses from their columns (z = 0; roll, pitch 0 unless given)."""
    z = np.zeros_like(t)
    return np.column_stack([t, x, y, z, z if roll is None else roll, z if pitch is None else pitch, yaw])


def racetrack(R=1.5, L=4.0, v=1.0, dt=0.05, offset=0.0):
    """East along y = 0 for L, half circle left, west along y = 2R, half circle left (radius
    R - offset / 2), east again along y = offset."""
    pts = []
    R2 = R - offset / 2
    s = np.arange(0, 2 * L + math.pi * (R + R2) + L / 2, v * dt)
    for si in s:
        if si < L:
            pts.append((si, 0.0, 0.0))
        elif si < L + math.pi * R:
            a = (si - L) / R
            pts.append((L + R * math.sin(a), R - R * math.cos(a), a))
        elif si < 2 * L + math.pi * R:
            pts.append((L - (si - L - math.pi * R), 2 * R, math.pi))
        elif si < 2 * L + math.pi * (R + R2):
            a = (si - 2 * L - math.pi * R) / R2
            pts.append((-R2 * math.sin(a), 2 * R - R2 + R2 * math.cos(a), math.pi + a))
        else:
            pts.append((si - 2 * L - math.pi * (R + R2), offset, 2 * math.pi))
    p = np.array(pts)
    return poses_from(s / v, p[:, 0], p[:, 1], p[:, 2])
