"""A minimal analytic scene for testing and timing the pipeline without the full recorder.

Ground z = g(x, y) (smooth relief, optionally a rut band lowered behind the robot), vertical
poles and a wall; two 32-beam spinning lidars on a robot moving at constant velocity and
yaw rate, with per-point capture times (motion-distorted sweeps). Everything is exact
ray casting, so the true surfaces and poses are known.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from torchsoil.io.extrinsics import xyzrpy_matrix


@dataclass
class ToyScene:
    """speed: m/s along base x; yaw_rate: rad/s; relief: ground amplitude, m; poles: (P, 4)
    x, y, radius, height [m]; walls: (W, 4) x0, y0, x1, y1 vertical segments [m], 3 m tall;
    noise: range noise 1 sigma, m; columns: azimuth samples per sweep; period: sweep, s;
    pitch_amp: body pitch oscillation amplitude, rad; rut_depth: the back lidar sees the
    ground lowered by this much within 0.1 m of y = +/-0.5 (in the world, for x < robot x);
    stop: (t0, t1) the robot stands still between these times, s; flip: time at which the yaw
    rate changes sign (a steering step, as into a keyhole turn), s; silent: {sensor: (t0, t1)}
    the sensor publishes nothing between these times, s; imu_rate: an exact IMU (body rates and
    specific force, frame imu_link turned 90 deg about z) on /imu/data at this rate, Hz (0: none);
    crab: angle of the direction of travel to the heading, rad (four-wheel crab steering)."""

    speed: float = 1.0
    yaw_rate: float = 0.0
    relief: float = 0.03
    poles: np.ndarray = field(default_factory=lambda: np.array(
        [[x, s * 4.0, 0.15, 3.0] for x in np.arange(-6.0, 40.0, 5.0) for s in (-1, 1)]))
    walls: np.ndarray = field(default_factory=lambda: np.array([[-8.0, -8.0, -8.0, 8.0]]))
    noise: float = 0.0
    columns: int = 512
    period: float = 0.1
    pitch_amp: float = 0.0
    rut_depth: float = 0.0
    stop: tuple[float, float] | None = None
    flip: float | None = None
    silent: dict = field(default_factory=dict)
    imu_rate: float = 0.0
    crab: float = 0.0
    seed: int = 0

    extrinsics: dict = field(default_factory=lambda: {
        "lidar_front": xyzrpy_matrix([0.9, 0.0, 0.8, 0.0, 0.35, 0.0]),
        "lidar_back": xyzrpy_matrix([-0.9, 0.0, 0.8, 0.0, 0.35, np.pi]),
        "imu_link": xyzrpy_matrix([0.1, 0.0, 0.3, 0.0, 0.0, np.pi / 2]),
    })

    def ground(self, x, y):
        """True undeformed ground height at world (x, y), m."""
        return self.relief * (np.sin(0.9 * x + 0.3) * np.cos(0.7 * y) + 0.5 * np.sin(2.3 * y + 0.4 * x))

    def pose(self, t) -> np.ndarray:
        """(..., 4, 4) base_link in world at times t [s]."""
        t = np.asarray(t, dtype=np.float64)
        if self.stop is not None:  # time spent standing still does not advance the robot
            t = t - np.clip(t - self.stop[0], 0.0, self.stop[1] - self.stop[0])
        yaw = self.yaw_rate * t
        if self.yaw_rate:
            r = self.speed / self.yaw_rate
            x, y = r * np.sin(yaw), r * (1 - np.cos(yaw))
        else:
            x, y = self.speed * t, np.zeros_like(t)
        if self.flip is not None and self.yaw_rate:   # on the other circle after the step
            tf = self.flip
            yf = self.yaw_rate * tf
            xf, yyf = r * np.sin(yf), r * (1 - np.cos(yf))
            after = t > tf
            ya = yf - self.yaw_rate * (t - tf)
            yaw = np.where(after, ya, yaw)
            x = np.where(after, xf - r * (np.sin(ya) - np.sin(yf)), x)
            y = np.where(after, yyf + r * (np.cos(ya) - np.cos(yf)), y)
        if self.crab:   # the path turned by the crab angle about the start; the heading is not
            c, s = np.cos(self.crab), np.sin(self.crab)
            x, y = c * x - s * y, s * x + c * y
        pitch = self.pitch_amp * np.sin(2 * np.pi * 0.5 * t)
        T = np.zeros((*t.shape, 4, 4))
        T[..., :3, :3] = Rotation.from_euler("xyz", np.stack(
            [np.zeros_like(t), pitch, yaw], -1).reshape(-1, 3)).as_matrix().reshape(*t.shape, 3, 3)
        T[..., 0, 3], T[..., 1, 3] = x, y
        T[..., 2, 3] = self.ground(x, y) + 0.0
        T[..., 3, 3] = 1.0
        return T

    def surface(self, x, y, after: bool = False, robot_x=None):
        z = self.ground(x, y)
        if after and self.rut_depth:
            in_rut = (np.abs(np.abs(y) - 0.5) < 0.1) & (x < (np.inf if robot_x is None else robot_x))
            z = z - self.rut_depth * in_rut
        return z

    def sweep(self, sensor: str, stamp: float, rng: np.random.Generator):
        """Points (N, 3) float32 in the sensor frame and times (N,) uint32 ns after stamp."""
        beams = np.deg2rad(np.linspace(-22.5, 22.5, 32))
        az = np.linspace(-np.pi, np.pi, self.columns, endpoint=False)
        tcol = np.arange(self.columns) * self.period / self.columns
        el, a = np.meshgrid(beams, az, indexing="ij")
        tt = np.broadcast_to(tcol, el.shape)
        d_s = np.stack([np.cos(el) * np.cos(a), np.cos(el) * np.sin(a), np.sin(el)], -1)
        W = self.pose(stamp + tt) @ self.extrinsics[sensor]  # (32, C, 4, 4)
        o = W[..., :3, 3]
        d = np.einsum("...ij,...j->...i", W[..., :3, :3], d_s)
        with np.errstate(invalid="ignore", over="ignore"):
            r = self._cast(o, d, back=(sensor == "lidar_back"), robot_x=o[..., 0])
        ok = np.isfinite(r) & (r > 0.5) & (r < 60)
        if self.noise:
            r = r + rng.normal(0, self.noise, r.shape)
        p = d_s * np.where(ok, r, np.nan)[..., None]
        tns = (tt * 1e9).astype(np.uint32)
        return p.reshape(-1, 3).astype(np.float32), tns.reshape(-1)

    def _cast(self, o, d, back: bool, robot_x):
        """Range along unit rays d (..., 3) from origins o (..., 3) to the first hit, m."""
        best = np.full(o.shape[:-1], np.inf)
        down = d[..., 2] < -1e-3
        dz = np.where(down, d[..., 2], -1.0)
        r = np.where(down, (self.ground(o[..., 0], o[..., 1]) - o[..., 2]) / dz, np.inf)
        for _ in range(6):
            h = o + r[..., None] * d
            z = self.surface(h[..., 0], h[..., 1], after=back, robot_x=robot_x)
            r = np.where(down, (z - o[..., 2]) / dz, np.inf)
        best = np.minimum(best, np.where(r > 0, r, np.inf))
        for x, y, rad, height in self.poles:
            dx, dy = o[..., 0] - x, o[..., 1] - y
            a = d[..., 0] ** 2 + d[..., 1] ** 2
            b = 2 * (dx * d[..., 0] + dy * d[..., 1])
            c = dx**2 + dy**2 - rad**2
            disc = b * b - 4 * a * c
            with np.errstate(invalid="ignore"):
                rr = (-b - np.sqrt(disc)) / (2 * np.maximum(a, 1e-12))
            zz = o[..., 2] + rr * d[..., 2]
            hit = (disc > 0) & (rr > 0) & (zz < height) & (zz > -1)
            best = np.where(hit, np.minimum(best, rr), best)
        for x0, y0, x1, y1 in self.walls:
            e = np.array([x1 - x0, y1 - y0])
            nrm = np.array([-e[1], e[0]]) / np.linalg.norm(e)
            den = d[..., 0] * nrm[0] + d[..., 1] * nrm[1]
            with np.errstate(divide="ignore", invalid="ignore"):
                rr = ((x0 - o[..., 0]) * nrm[0] + (y0 - o[..., 1]) * nrm[1]) / den
            hx, hy = o[..., 0] + rr * d[..., 0], o[..., 1] + rr * d[..., 1]
            s = ((hx - x0) * e[0] + (hy - y0) * e[1]) / (e @ e)
            zz = o[..., 2] + rr * d[..., 2]
            hit = (rr > 0) & (s >= 0) & (s <= 1) & (zz < 3.0) & (zz > -1)
            best = np.where(hit, np.minimum(best, rr), best)
        return best

    def messages(self, duration: float, start: float = 100.0, back_offset: float = 0.05):
        """(topic, PointCloud2) list for a bag: both lidars at 1 / period Hz."""
        from torchsoil.io.write import encode

        rng = np.random.default_rng(self.seed)
        out = []
        for k in range(int(round(duration / self.period))):
            for sensor, off in (("lidar_front", 0.0), ("lidar_back", back_offset)):
                stamp = start + k * self.period + off
                t0, t1 = self.silent.get(sensor, (np.inf, -np.inf))
                if t0 <= stamp - start <= t1:
                    continue
                xyz, tns = self.sweep(sensor, stamp - start, rng)
                out.append((f"/{sensor}/points", encode(xyz, tns, stamp, sensor, height=32)))
        if self.imu_rate > 0:
            out += self.imu_messages(duration, start)
            out.sort(key=lambda m: m[1].header.stamp.sec + 1e-9 * m[1].header.stamp.nanosec)
        return out

    def imu_messages(self, duration: float, start: float = 100.0, h: float = 1e-4):
        """(topic, sensor_msgs/Imu) list: exact body rates and specific force in imu_link."""
        from torchsoil.synth.bagwriter import imu_message

        R_bi = self.extrinsics["imu_link"][:3, :3]
        out = []
        for t in np.arange(0.0, duration, 1.0 / self.imu_rate):
            P = self.pose(np.array([t - h, t, t + h]))
            w = Rotation.from_matrix(P[1, :3, :3].T @ P[2, :3, :3]).as_rotvec() / h            # body rates
            a = (P[2, :3, 3] - 2 * P[1, :3, 3] + P[0, :3, 3]) / h**2
            f = P[1, :3, :3].T @ (a + [0.0, 0.0, 9.81])
            out.append(("/imu/data", imu_message("imu_link", int(round((start + t) * 1e9)), R_bi.T @ f, R_bi.T @ w,
                                                 1e-4, 1e-6)))
        return out

    def write(self, path, duration: float, start: float = 100.0):
        """Write a ROS 2 bag of `duration` s (sweeps stamped from `start` s) with /tf_static."""
        from torchsoil.io.write import write_bag

        return write_bag(path, self.messages(duration, start), self.extrinsics)
