"""De-skew: undo the motion distortion of a sweep with a constant-velocity motion model.

Each point of a sweep is captured at its own time (the PointCloud2 `t` field). With the
robot moving by `motion` (a (4, 4) transform of the robot frame, new-in-old) over `dt`
seconds at constant velocity, the robot frame at time tau after the reference time is
exp(tau / dt * log(motion)); a point p measured then sits at R(tau) p + s(tau) in the
reference frame.
"""

from __future__ import annotations

import numpy as np

from torchsoil.pipeline import _kernels as _k


def relative_motion(T_prev: np.ndarray, T_curr: np.ndarray) -> np.ndarray:
    """(4, 4) world poses of the robot at two times -> (4, 4) motion T_prev^-1 T_curr."""
    return np.linalg.inv(T_prev) @ T_curr


def deskew(points: np.ndarray, t: np.ndarray, motion: np.ndarray, dt: float) -> np.ndarray:
    """Express every point in the robot frame at time 0 (the reference time).

    Args:
        points: (N, 3) points in the robot (or sensor) frame at their capture times, m.
        t: (N,) capture time of each point relative to the reference time, s.
        motion: (4, 4) motion of the same frame over `dt` seconds (new-in-old).
        dt: duration of `motion`, s (> 0).

    Returns:
        (N, 3) float64 points in the frame at the reference time, m.
    """
    points = np.asarray(points)
    if points.dtype not in (np.float32, np.float64):
        points = points.astype(np.float64)
    t = np.asarray(t)
    if t.dtype not in (np.float32, np.float64):
        t = t.astype(np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or t.shape != (len(points),):
        raise ValueError(f"deskew needs (N, 3) points and (N,) times, got {points.shape} "
                         f"and {t.shape}")
    if not dt > 0:
        raise ValueError(f"deskew needs a positive motion duration dt, got {dt}")
    if len(points) == 0:
        return points.astype(np.float64)
    rotvec = _k.rotvec_of(np.ascontiguousarray(motion[:3, :3], dtype=np.float64))
    return _k.deskew(points, t, rotvec, np.ascontiguousarray(motion[:3, 3], dtype=np.float64), float(dt))
