"""A simulated MEMS IMU on the robot: specific force and angular rate along the true trajectory.

The accelerometer reads f = R_world_imu^T (a - g), g = (0, 0, -9.80665) m/s^2 (so a unit at
rest reads +9.8 m/s^2 up), a the acceleration of the IMU's own point (including the lever
arm's turn); the gyro reads the body rate. Both carry a constant bias per axis, drawn once,
and white noise given as a noise density (sigma per sample = density * sqrt(rate)). The
defaults are those of a calibrated industrial MEMS unit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from torchsoil.synth.lidar import rpy_matrix

G = 9.80665  # m/s^2


@dataclass(frozen=True)
class ImuSpec:
    """name: frame (imu_link); xyz: (3,) position in base_link, m; rpy: (3,) mount roll,
    pitch, yaw in base_link, rad; rate_hz: samples per second; acc_bias: 1 sigma of each
    axis' constant bias, m/s^2 (1 mg); acc_noise: white-noise density, m/s^2/sqrt(Hz)
    (100 ug/sqrt(Hz)); gyro_bias: rad/s (0.05 deg/s); gyro_noise: rad/s/sqrt(Hz)
    (0.005 deg/s/sqrt(Hz))."""

    name: str = "imu_link"
    xyz: tuple[float, float, float] = (0.2, 0.05, 0.35)
    rpy: tuple[float, float, float] = (0.0, 0.0, math.pi / 2)
    rate_hz: float = 100.0
    acc_bias: float = 1e-3 * G
    acc_noise: float = 100e-6 * G
    gyro_bias: float = math.radians(0.05)
    gyro_noise: float = math.radians(0.005)

    def transform(self) -> np.ndarray:
        """(4, 4) base_link <- imu_link."""
        T = np.eye(4)
        T[:3, :3] = rpy_matrix(*self.rpy)
        T[:3, 3] = self.xyz
        return T


def imu_samples(traj_poses: np.ndarray, spec: ImuSpec, rng: np.random.Generator, end: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IMU readings from trajectory time 0 to `end` s.

    traj_poses: (N, 7) true base_link rows t, x, y, z, roll, pitch, yaw (docs/formats.md section 3).
    Returns t (M,) [s], acc (M, 3) specific force [m/s^2] and gyro (M, 3) rate [rad/s], both
    in the IMU frame, with bias and noise.
    """
    dt = 1.0 / spec.rate_hz
    t = np.arange(0.0, end + 1e-9, dt)
    # fine samples around each reading: differentiate twice there (the trajectory is smooth
    # between its 100 Hz rows, interpolated linearly in position and angles)
    tt = traj_poses[:, 0]
    h = 0.01
    tq = (t[:, None] + np.array([-h, 0.0, h])).reshape(-1)
    rows = np.stack([np.interp(tq, tt, traj_poses[:, c]) for c in range(1, 7)], -1)
    R_wb = rpy_matrix(rows[:, 3], rows[:, 4], rows[:, 5])
    T = spec.transform()
    p = (rows[:, :3] + R_wb @ T[:3, 3]).reshape(len(t), 3, 3)
    acc_w = (p[:, 2] - 2 * p[:, 1] + p[:, 0]) / h**2
    R = R_wb.reshape(len(t), 3, 3, 3)
    R_wi = R[:, 1] @ T[:3, :3]
    f = np.einsum("nji,nj->ni", R_wi, acc_w - np.array([0.0, 0.0, -G]))
    w_body = Rotation.from_matrix(np.swapaxes(R[:, 0], 1, 2) @ R[:, 2]).as_rotvec() / (2 * h)
    gyro = w_body @ T[:3, :3]  # rate in the IMU frame: R_bi^T w
    sd = math.sqrt(spec.rate_hz)
    acc = f + rng.normal(0, spec.acc_bias, 3) + rng.normal(0, spec.acc_noise * sd, f.shape)
    gyro = gyro + rng.normal(0, spec.gyro_bias, 3) + rng.normal(0, spec.gyro_noise * sd, gyro.shape)
    return t, acc, gyro
