"""Trajectories as FORMATS rows (t, x, y, z, roll, pitch, yaw) and as pose matrices."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def poses_to_rows(stamps: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """(S,) times and (S, 4, 4) poses -> (S, 7) FORMATS rows t, x, y, z, roll, pitch, yaw."""
    rpy = Rotation.from_matrix(poses[:, :3, :3]).as_euler("xyz")
    return np.column_stack([stamps, poses[:, :3, 3], rpy])


def rows_to_poses(rows: np.ndarray) -> np.ndarray:
    """(S, 7) FORMATS rows -> (S, 4, 4) pose matrices."""
    P = np.zeros((len(rows), 4, 4))
    P[:, :3, :3] = Rotation.from_euler("xyz", rows[:, 4:]).as_matrix()
    P[:, :3, 3] = rows[:, 1:4]
    P[:, 3, 3] = 1.0
    return P
