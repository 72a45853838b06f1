"""Levelling the world frame to gravity.

The mapper's world frame is base_link at the first sweep: on a robot that starts on a side
slope it is tilted by the slope, and heights and the angle of repose would be measured
against the slope instead of gravity. With an IMU, gravity is measured in the world frame
over the first seconds: the accelerometer reads the specific force f = a - g, so with the
lidar trajectory's rotations and velocities, mean(g) = mean(a) - mean(R_world_imu f), where
mean(a) = (v(t1) - v(t0)) / (t1 - t0); the robot may move, turn and rock meanwhile. Without
an IMU, the mean ground plane near the start stands in for the horizontal (the run's problems
say so). `level(...)` returns the rotation that turns the world frame upright, about its
origin (yaw kept).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from torchsoil.io.bag import ImuData
from torchsoil.pipeline.reregister import interpolate_poses
from torchsoil.settings import LevelConfig

G = 9.80665  # standard gravity, m/s^2


def levelling_rotation(down: np.ndarray) -> np.ndarray:
    """(3,) direction of gravity in the world (any length) -> (3, 3) rotation R, the smallest
    turning it to (0, 0, -1); R's yaw is zero for small tilts."""
    g = np.asarray(down, dtype=np.float64)
    g = g / np.linalg.norm(g)
    axis = np.cross(g, [0.0, 0.0, -1.0])
    s, c = np.linalg.norm(axis), -g[2]
    if s < 1e-12:
        return np.eye(3)
    return Rotation.from_rotvec(axis / s * np.arctan2(s, c)).as_matrix()


def tilt_deg(R: np.ndarray) -> float:
    """Angle between the z axis turned by R (3, 3) and the z axis, degrees."""
    return float(np.degrees(np.arccos(np.clip(np.asarray(R)[2, 2], -1.0, 1.0))))


def gravity_from_imu(stamps: np.ndarray, poses: np.ndarray, imu: ImuData, base_T_imu: np.ndarray,
                     window: float) -> np.ndarray:
    """Gravity (3,) in the world frame, m/s^2, from the IMU samples within the trajectory's first
    `window` s.

    stamps (S,) [s], poses (S, 4, 4): base_link in the world; base_T_imu (4, 4): the IMU's pose
    in base_link. Raises ValueError when too few samples fall in the window (clock domains
    apart?) or the result is not about 9.8 m/s^2 (units, or a wrong IMU extrinsic).
    """
    t0 = stamps[0]
    t1 = min(t0 + window, stamps[-1])
    h = min(0.5, (t1 - t0) / 3)
    if h <= 0:
        raise ValueError("the trajectory is too short to level by the IMU")
    v0, v1 = (_velocity(stamps, poses, lo, lo + h, base_T_imu[:3, 3]) for lo in (t0, t1 - h))
    a, b = t0 + h / 2, t1 - h / 2
    sel = (imu.t >= a) & (imu.t <= b)
    if sel.sum() < 10:
        raise ValueError(f"{imu.topic}: {int(sel.sum())} IMU samples between t = {a:.3f} and {b:.3f} s "
                         f"(the first sweeps); its stamps run {imu.t[0]:.3f}-{imu.t[-1]:.3f} s: another "
                         "clock than the lidars'?")
    R = interpolate_poses(stamps, poses, imu.t[sel])[:, :3, :3] @ base_T_imu[:3, :3]
    f_world = np.einsum("nij,nj->ni", R, imu.acc[sel])
    g = (v1 - v0) / (b - a) - f_world.mean(0)
    if not 0.9 * G < np.linalg.norm(g) < 1.1 * G or g[2] > 0:
        raise ValueError(f"{imu.topic}: gravity measured as {np.round(g, 2).tolist()} m/s^2 in the first "
                         f"sweep's base_link, not about {G:.2f} m/s^2 downwards: is linear_acceleration in "
                         f"m/s^2 and the extrinsic of frame '{imu.frame}' right?")
    return g


def gravity_and_bias(stamps: np.ndarray, poses: np.ndarray, imu: ImuData, base_T_imu: np.ndarray,
                     span: float, segment: float = 1.0, min_turn: float = 30.0
                     ) -> tuple[np.ndarray, np.ndarray, float]:
    """Gravity (3,) in the world frame and the accelerometer's bias (3,) in the IMU frame,
    m/s^2, from the IMU samples of the trajectory's first `span` s; and the heading change over
    them (degrees, max - min of yaw).

    Over each `segment` s the mean world-frame reading R f = a - g + R b, with a the mean
    acceleration from the lidar trajectory (velocity change over the segment). When the robot
    turns by `min_turn` degrees or more, the segments' rotations differ enough to tell a
    body-fixed bias from the world-fixed gravity: the bias's two components that are
    horizontal in the world are fitted with gravity (a vertical one only scales |g|). On a
    straighter drive a horizontal bias cannot be told from a tilt: the bias is 0 and gravity
    is the segments' mean, as `gravity_from_imu` over the longer span. Arguments as there.
    """
    t0 = stamps[0]
    t1 = min(t0 + span, stamps[-1], imu.t[-1])
    h = 0.25
    edges = np.arange(t0 + h, t1 - h + 1e-9, segment)
    if len(edges) < 3:
        raise ValueError(f"{imu.topic}: the trajectory and IMU overlap for less than {2 * segment + 2 * h:.1f} s")
    v = np.array([_velocity(stamps, poses, e - h, e + h, base_T_imu[:3, 3]) for e in edges])
    sel = (imu.t >= edges[0]) & (imu.t < edges[-1])
    R = interpolate_poses(stamps, poses, imu.t[sel])[:, :3, :3] @ base_T_imu[:3, :3]
    f_world = np.einsum("nij,nj->ni", R, imu.acc[sel])
    seg = np.searchsorted(edges, imu.t[sel], side="right") - 1
    Ms, rhs = [], []
    for j in range(len(edges) - 1):
        m = seg == j
        if m.sum() >= 10:
            Ms.append(R[m].mean(0))
            rhs.append(f_world[m].mean(0) - (v[j + 1] - v[j]) / (edges[j + 1] - edges[j]))
    if len(Ms) < 2:
        raise ValueError(f"{imu.topic}: too few IMU samples along the trajectory's first {span:g} s")
    inside = (stamps >= t0) & (stamps <= t1)
    yaw = np.unwrap(np.arctan2(poses[inside, 1, 0], poses[inside, 0, 0]))
    turn = float(np.degrees(yaw.max() - yaw.min()))
    if turn < min_turn:
        return -np.mean(rhs, axis=0), np.zeros(3), turn
    B = np.mean(Ms, axis=0).T[:, :2]              # IMU-frame directions horizontal in the world
    A = np.vstack([np.hstack([-np.eye(3), M @ B]) for M in Ms])
    x = np.linalg.lstsq(A, np.concatenate(rhs), rcond=None)[0]
    return x[:3], B @ x[3:], turn


def _velocity(stamps: np.ndarray, poses: np.ndarray, lo: float, hi: float, at: np.ndarray) -> np.ndarray:
    """(3,) mean velocity [m/s] over [lo, hi] s of the point `at` (3,) of base_link (the IMU's:
    on a turn it moves otherwise than base_link's origin): the slope of a line fitted to its
    positions there (steadier than a difference of two poses)."""
    t = np.linspace(lo, hi, 11)
    T = interpolate_poses(stamps, poses, t)
    p = T[:, :3, 3] + T[:, :3, :3] @ at
    return np.polyfit(t - t.mean(), p, 1)[0]


def gravity_from_ground(points: np.ndarray, normals: np.ndarray, radius: float) -> np.ndarray:
    """Unit normal (3,) of the mean ground plane within `radius` m (horizontally) of the world
    origin, pointing down: the least-squares plane z = c0 x + c1 y + c2 through the map points
    (M, 3) whose normals (M, 3) are within 25 deg of vertical, refitted twice without the
    points off it (posts, roofs, furrow walls)."""
    near = np.linalg.norm(points[:, :2], axis=1) < radius
    p = points[near & (np.abs(normals[:, 2]) > np.cos(np.radians(25.0)))]
    if len(p) < 50:
        raise ValueError(f"only {len(p)} ground points within {radius} m of the start: cannot level by the "
                         "ground plane")
    A = np.column_stack([p[:, :2], np.ones(len(p))])
    keep = np.ones(len(p), bool)
    for _ in range(3):
        c = np.linalg.lstsq(A[keep], p[keep, 2], rcond=None)[0]
        r = np.abs(p[:, 2] - A @ c)
        keep = r < max(3 * 1.4826 * np.median(r[keep]), 0.02)
    n = np.array([c[0], c[1], -1.0])
    return n / np.linalg.norm(n)


def level(stamps: np.ndarray, poses: np.ndarray, points: np.ndarray, normals: np.ndarray,
          imu: ImuData | None, base_T_imu: np.ndarray | None, cfg: LevelConfig
          ) -> tuple[np.ndarray, list[str]]:
    """Rotation (3, 3) turning the world frame upright, and notes for the run's problems.

    stamps (S,) [s] and poses (S, 4, 4) of the trajectory; points, normals (M, 3) of the
    reference map; imu and base_T_imu (4, 4) when the bag has an IMU. cfg.source: auto (IMU,
    else ground), imu, ground or none.
    """
    if cfg.source == "none":
        return np.eye(3), []
    if imu is not None and cfg.source in ("auto", "imu"):
        return levelling_rotation(gravity_from_imu(stamps, poses, imu, base_T_imu, cfg.window)), []
    if cfg.source == "imu":
        raise ValueError("pipeline.level.source is imu but the recording has no IMU topic "
                         "(sensor_msgs/msg/Imu; pipeline.read.imu_topic)")
    R = levelling_rotation(gravity_from_ground(points, normals, cfg.radius))
    why = "no IMU topic in the recording" if cfg.source == "auto" else "pipeline.level.source is ground"
    return R, [f"{why}: the world frame is levelled by the mean ground plane within {cfg.radius:g} m of the "
               f"start ({tilt_deg(R):.2f} deg from the first sweep's base_link), not by gravity; on a start on "
               "a slope, heights and the angle of repose are then measured against the slope (record a "
               "sensor_msgs/msg/Imu topic to level by gravity)"]
