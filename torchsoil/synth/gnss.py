"""A simulated RTK GNSS receiver on the robot: NavSatFix fixes of the antenna along the true
trajectory, and the datum that ties the synthetic world to the Earth.

The world frame (metres) sits in the UTM zone of `Datum` by (E, N) = (E0, N0) + k R(yaw) (x, y)
and ellipsoidal height = up + z (k the projection's scale factor at the datum, as a
surveyed field's local frame is placed): the truth of every cell's UTM position. Fixes carry
white noise of an RTK fixed solution (1 cm horizontal, 2 cm vertical, 1 sigma) and say so in
their covariance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from torchsoil.geo.georef import Georef, antenna_track, project, scale_factor, unproject, utm_epsg


@dataclass(frozen=True)
class Datum:
    """lat, lon: the world origin, deg (WGS 84; a field near Zurich by default); up: its
    ellipsoidal height, m; yaw: grid east -> world x, rad counterclockwise."""

    lat: float = 47.3986
    lon: float = 8.5491
    up: float = 452.0
    yaw: float = 0.35

    def georef(self) -> Georef:
        """The world -> UTM map (torchsoil.geo.georef.Georef, kind "truth")."""
        epsg = utm_epsg(self.lat, self.lon)
        e0, n0 = project(epsg, np.array([self.lat]), np.array([self.lon]))[0]
        return Georef("truth", epsg, self.yaw, float(e0), float(n0), scale_factor(epsg, self.lat, self.lon),
                      self.up, "the synthetic world's datum")


@dataclass(frozen=True)
class GnssSpec:
    """name: the antenna's frame; xyz: (3,) its place in base_link, m; rate_hz: fixes per
    second; sigma_h, sigma_v: 1 sigma of the horizontal and vertical noise, m."""

    name: str = "gnss_link"
    xyz: tuple[float, float, float] = (-0.25, 0.1, 0.9)
    rate_hz: float = 10.0
    sigma_h: float = 0.01
    sigma_v: float = 0.02


def gnss_fixes(poses: np.ndarray, spec: GnssSpec, datum: Datum, rng: np.random.Generator, end: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Fixes from trajectory time 0 to `end` s along the true poses (N, 7) (t, x, y, z, roll,
    pitch, yaw in the world): times t (M,) [s], lat, lon (M,) [deg], alt (M,) [m]."""
    t = np.arange(0.0, min(end, float(poses[-1, 0])) + 1e-9, 1.0 / spec.rate_hz)
    a = antenna_track(poses[:, 0], poses, np.asarray(spec.xyz), t)
    g = datum.georef()
    en = g.to_crs(a[:, :2] + rng.normal(0.0, spec.sigma_h, (len(t), 2)) / g.scale)
    lat, lon = unproject(g.epsg, en)
    return t, lat, lon, g.up + a[:, 2] + rng.normal(0.0, spec.sigma_v, len(t))
