"""The robot's true trajectory: a planar path of straights and arcs, a speed profile, and the
3D attitude the terrain relief imposes on the chassis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from torchsoil.robot import Robot
from torchsoil.settings import TrajectoryConfig, TrajectorySegment, validate
from torchsoil.synth.terrain import Relief


@dataclass(frozen=True)
class Trajectory:
    """True motion of base_link sampled uniformly in time.

    poses: (N, 7) t [s], x, y, z [m], roll, pitch, yaw [rad] (docs/formats.md section 3 rows).
    speed: (N,) forward speed, m/s.   accel: (N,) forward acceleration, m/s^2.
    yaw_rate: (N,) rad/s.             arc: (N,) travelled distance, m.
    """

    poses: np.ndarray
    speed: np.ndarray
    accel: np.ndarray
    yaw_rate: np.ndarray
    arc: np.ndarray

    @property
    def duration(self) -> float:
        return float(self.poses[-1, 0] - self.poses[0, 0])

    def interpolate(self, t: np.ndarray) -> np.ndarray:
        """(M,) times [s] -> (M, 7) poses, linear in position and (unwrapped) angles."""
        t = np.asarray(t, dtype=np.float64)
        tt = self.poses[:, 0]
        out = np.empty((len(t), 7))
        out[:, 0] = t
        for c in range(1, 7):
            out[:, c] = np.interp(t, tt, self.poses[:, c])
        return out


def planar_path(segments, start=(0.0, 0.0, 0.0), ds: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Dense path from segments (TrajectorySegment, or dicts `{straight: L, speed: v}` /
    `{arc: R, angle_deg: a, speed: v}`; a > 0 turns left). Returns (M, 4) [s, x, y, yaw]
    and (M,) commanded speed, m/s."""
    if not segments:
        raise ValueError("trajectory: at least one segment is needed")
    x, y, yaw = (float(v) for v in start)
    rows, speeds = [[0.0, x, y, yaw]], []
    s = 0.0
    for i, seg in enumerate(segments):
        if not isinstance(seg, TrajectorySegment):
            seg = validate(TrajectorySegment, seg, "trajectory", prefix=f"trajectory.segments[{i}].")
        v = seg.speed
        if not v > 0:
            raise ValueError(f"trajectory.segments[{i}]: speed must be > 0 m/s, got {v}")
        if seg.straight is not None:
            L = seg.straight
            curv = 0.0
        else:
            R = seg.arc
            a = math.radians(seg.angle_deg)
            if R <= 0:
                raise ValueError(f"trajectory.segments[{i}]: arc radius must be > 0 m, got {R}")
            L, curv = abs(a) * R, math.copysign(1.0 / R, a)
        if L <= 0:
            raise ValueError(f"trajectory.segments[{i}]: length must be > 0 m")
        n = max(1, int(math.ceil(L / ds)))
        h = L / n
        for _ in range(n):
            if curv == 0.0:
                x += h * math.cos(yaw)
                y += h * math.sin(yaw)
            else:
                ny = yaw + h * curv
                x += (math.sin(ny) - math.sin(yaw)) / curv
                y += -(math.cos(ny) - math.cos(yaw)) / curv
                yaw = ny
            s += h
            rows.append([s, x, y, yaw])
            speeds.append(v)
    speeds = np.array([speeds[0], *speeds])
    return np.array(rows), speeds


def build_trajectory(spec: TrajectoryConfig | dict, relief: Relief, robot: Robot, rate_hz: float = 100.0,
                     start_speed: float | None = None) -> Trajectory:
    """Trajectory from a scenario's `trajectory` section (TrajectoryConfig, or a dict of it).

    spec: start [x, y, yaw_deg], segments, accel_limit m/s^2 (speed changes ramp at this
    rate); start_speed: m/s (default: the first segment's speed, i.e. already moving).
    The chassis height and attitude follow the relief under the four wheel contacts.
    """
    if not isinstance(spec, TrajectoryConfig):
        spec = validate(TrajectoryConfig, spec, "trajectory", prefix="trajectory.")
    st = spec.start
    path, v_cmd = planar_path(spec.segments, (st[0], st[1], math.radians(st[2])))
    a_lim = spec.accel_limit
    s = path[:, 0]
    ds = np.diff(s)
    v = v_cmd.copy()
    v[0] = float(v_cmd[0] if start_speed is None else start_speed)
    # speed changes ramp at a_lim: forward pass (accelerate), backward pass (brake ahead)
    for i in range(1, len(v)):
        v[i] = min(v[i], math.sqrt(v[i - 1] ** 2 + 2 * a_lim * ds[i - 1]))
    for i in range(len(v) - 2, -1, -1):
        v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2 * a_lim * ds[i]))
    v = np.maximum(v, 0.05)
    t_s = np.concatenate([[0.0], np.cumsum(ds * 2 / (v[1:] + v[:-1]))])
    t = np.arange(0.0, t_s[-1], 1.0 / rate_hz)
    sx = np.interp(t, t_s, s)
    x = np.interp(sx, s, path[:, 1])
    y = np.interp(sx, s, path[:, 2])
    yaw = np.interp(sx, s, path[:, 3])
    speed = np.interp(sx, s, v)
    accel = np.gradient(speed, t) if len(t) > 1 else np.zeros_like(t)
    yaw_rate = np.gradient(yaw, t) if len(t) > 1 else np.zeros_like(t)
    z, roll, pitch = chassis_attitude(x, y, yaw, relief, robot)
    poses = np.column_stack([t, x, y, z, roll, pitch, yaw])
    return Trajectory(poses, speed, accel, yaw_rate, sx)


def chassis_attitude(x, y, yaw, relief: Relief, robot: Robot):
    """Height, roll and pitch of base_link resting on the relief (micro-topography ignored).

    base_link sits on the ground plane fitted to the wheel contacts: z is its height under
    the chassis centre. Returns z [m], roll, pitch [rad], each (N,)."""
    c, s = np.cos(yaw), np.sin(yaw)
    gx, gy = relief.gradient(x, y)
    # slope along and across the heading, averaged over the wheel contacts
    wx, wy = robot.wheels[:, 0], robot.wheels[:, 1]
    px = x[:, None] + c[:, None] * wx - s[:, None] * wy
    py = y[:, None] + s[:, None] * wx + c[:, None] * wy
    hz = relief.height(px, py)                                   # (N, K)
    gxw, gyw = relief.gradient(px, py)
    g_fwd = (gxw * c[:, None] + gyw * s[:, None]).mean(1)
    g_left = (-gxw * s[:, None] + gyw * c[:, None]).mean(1)
    z = hz.mean(1) - (wx.mean() * g_fwd + wy.mean() * g_left)
    del gx, gy
    pitch = -np.arctan(g_fwd)                # nose up on a climb: negative pitch (REP 103)
    roll = np.arctan(g_left * np.cos(pitch))  # left side higher: positive roll
    return z, roll, pitch
