"""Tying a run's map frame to the field (docs/export.md): UTM from RTK GNSS, an anchor, or a
local engineering frame that says so.

The map frame (metres, z up, REP 103) goes to the UTM zone's grid coordinates by a rigid
motion scaled by the projection's point scale factor k at the field (UTM is conformal, so a
ground metre is k grid metres there):

    (E, N) = (east, north) + k R(yaw) (x, y),    ellipsoidal height = up + z

`fit_gnss` finds yaw, east, north and up from the fixes: the antenna's place in the map at
each fix time (the trajectory interpolated, the antenna's offset from /tf_static applied)
against the fix projected to UTM, weighted by the fixes' covariance, non-RTK fixes and
outliers left out. Pure functions on numpy arrays; pyproj for the projection.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from torchsoil.io.gnss import STATUS_FIX, STATUS_GBAS_FIX, Fixes

RTK_SIGMA = 0.05       # m: a fix whose horizontal standard deviation is larger is not RTK-fixed
MIN_SPREAD = 2.0       # m: fixes spread less than this along the drive cannot give its heading
OUTLIER_SIGMAS = 4.0   # a fix further than this many standard deviations from the fit is an outlier
MAP_SIGMA = 0.01       # m: the trajectory's own error, added to each fix's in that test
TRIES = 200            # random pairs of fixes tried for the consensus
MIN_TURN_DEG = 30.0    # the heading change over the fixes that lets an unknown antenna offset be fitted


class GeorefError(ValueError):
    """The fixes cannot tie the map to the field; the message says why."""


@dataclass
class Georef:
    """Map frame -> projected CRS (module docstring).

    kind: "gnss" (fitted to fixes), "anchor" (the first pose placed by hand) or "local" (no
    CRS: map coordinates as they are); epsg: the UTM zone's EPSG code (None when local);
    yaw: rad, counterclockwise from grid east to the map's x axis; east, north: grid
    coordinates of the map origin, m; scale: k; up: ellipsoidal height of map z = 0, m;
    note: one sentence on where it came from; fit: the fit's figures (fixes used, rejected,
    residual RMS and max [m], yaw standard deviation [deg]).
    """

    kind: str
    epsg: int | None = None
    yaw: float = 0.0
    east: float = 0.0
    north: float = 0.0
    scale: float = 1.0
    up: float = 0.0
    note: str = ""
    fit: dict = field(default_factory=dict)

    @classmethod
    def local(cls, why: str = "") -> Georef:
        return cls("local", note="local engineering frame: the run's map frame in metres, not tied to the Earth"
                   + (f" ({why})" if why else ""))

    @property
    def crs(self) -> str | None:
        """"EPSG:326NN" or None for the local frame."""
        return None if self.epsg is None else f"EPSG:{self.epsg}"

    def rotation(self) -> np.ndarray:
        """(2, 2) k R(yaw)."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return self.scale * np.array([[c, -s], [s, c]])

    def to_crs(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) map x, y [m] -> (..., 2) easting, northing [m] (map x, y when local)."""
        xy = np.asarray(xy, dtype=np.float64)
        return xy @ self.rotation().T + np.array([self.east, self.north])

    def affine(self, x0: float, y_top: float, dx: float) -> tuple[float, ...]:
        """GDAL geotransform coefficients (a, b, c, d, e, f) of a raster whose column c runs
        along map x from the corner x0 and whose row r runs along -y from the corner y_top [m],
        cells dx [m]: E = a c + b r + c0, N = d c + e r + f0 (as rasterio's Affine(a, b, c, d, e, f))."""
        (r00, r01), (r10, r11) = self.rotation()
        e0, n0 = self.to_crs(np.array([x0, y_top]))
        return (r00 * dx, -r01 * dx, float(e0), r10 * dx, -r11 * dx, float(n0))

    def save(self, path: str | Path) -> Path:
        Path(path).write_text(json.dumps(asdict(self), indent=1))
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> Georef:
        return cls(**json.loads(Path(path).read_text()))


def utm_epsg(lat: float, lon: float) -> int:
    """EPSG code of the WGS 84 UTM zone holding (lat, lon) [deg], with the grid's exceptions
    (zone 32V over south-west Norway, zones 31X-37X over Svalbard), which PROJ's database of
    areas does not draw."""
    if not (-80.0 <= lat <= 84.0 and -180.0 <= lon <= 180.0):
        raise GeorefError(f"latitude {lat:.6f}, longitude {lon:.6f} lies outside UTM (80 S to 84 N)")
    zone = min(int((lon + 180.0) // 6) + 1, 60)
    if 56.0 <= lat < 64.0 and 3.0 <= lon < 12.0:
        zone = 32
    elif 72.0 <= lat and 0.0 <= lon < 42.0:
        zone = 31 if lon < 9.0 else 33 if lon < 21.0 else 35 if lon < 33.0 else 37
    return (32600 if lat >= 0 else 32700) + zone


def project(epsg: int, lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    """(N,) lat, lon [deg] -> (N, 2) easting, northing [m] in EPSG `epsg`."""
    from pyproj import Transformer

    tr = Transformer.from_crs("EPSG:4326", f"EPSG:{epsg}", always_xy=True)
    e, n = tr.transform(np.asarray(lon, dtype=np.float64), np.asarray(lat, dtype=np.float64))
    return np.column_stack([e, n])


def unproject(epsg: int, en: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) easting, northing [m] in EPSG `epsg` -> lat, lon (N,) [deg]."""
    from pyproj import Transformer

    tr = Transformer.from_crs(f"EPSG:{epsg}", "EPSG:4326", always_xy=True)
    lon, lat = tr.transform(en[:, 0], en[:, 1])
    return np.asarray(lat), np.asarray(lon)


def scale_factor(epsg: int, lat: float, lon: float) -> float:
    """The projection's point scale factor k at (lat, lon) [deg]."""
    from pyproj import Proj

    return float(Proj(f"EPSG:{epsg}").get_factors(lon, lat).meridional_scale)


def grid_bearing_of_north(epsg: int, lat: float, lon: float) -> float:
    """The grid bearing of true north at (lat, lon), rad clockwise from grid north (the
    meridian convergence, measured on the projection itself)."""
    en = project(epsg, np.array([lat, lat + 1e-4]), np.array([lon, lon]))
    d = en[1] - en[0]
    return math.atan2(d[0], d[1])


def from_anchor(lat: float, lon: float, heading_deg: float, first_pose: np.ndarray) -> Georef:
    """The map placed by hand: base_link's first pose (7,) (t, x, y, z, roll, pitch, yaw) at
    (lat, lon) [deg], its x axis at compass heading `heading_deg` (clockwise from true north)."""
    if not (-90 <= lat <= 90 and -180 <= lon <= 180 and math.isfinite(heading_deg)):
        raise GeorefError(f"--anchor {lat},{lon},{heading_deg}: latitude must lie in [-90, 90], longitude in "
                          "[-180, 180] degrees and the heading be a number of degrees")
    epsg = utm_epsg(lat, lon)
    k = scale_factor(epsg, lat, lon)
    bearing = math.radians(heading_deg) + grid_bearing_of_north(epsg, lat, lon)
    yaw = math.atan2(math.cos(bearing), math.sin(bearing)) - float(first_pose[6])   # grid east -> map x
    g = Georef("anchor", epsg, _wrap(yaw), scale=k,
               note=f"anchored by hand: the first pose at {lat:.7f}, {lon:.7f}, heading {heading_deg:.1f} deg")
    e0 = project(epsg, np.array([lat]), np.array([lon]))[0]
    g.east, g.north = (e0 - g.rotation() @ np.asarray(first_pose[1:3], dtype=np.float64))
    g.east, g.north = float(g.east), float(g.north)
    return g


def antenna_track(stamps: np.ndarray, rows: np.ndarray, antenna: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(M, 3) the antenna in the map at times t (M,) [s]: base_link's poses (S, 7) rows (t, x,
    y, z, roll, pitch, yaw) at stamps (S,) interpolated (position linearly, attitude by slerp),
    the antenna's offset (3,) from base_link [m] applied. t must lie within the stamps."""
    pos = np.column_stack([np.interp(t, stamps, rows[:, k]) for k in (1, 2, 3)])
    rot = Slerp(stamps, Rotation.from_euler("xyz", rows[:, 4:7]))(t)
    return pos + rot.apply(np.asarray(antenna, dtype=np.float64))


def rtk_mask(fixes: Fixes, rtk_sigma: float = RTK_SIGMA) -> np.ndarray:
    """(N,) the RTK-fixed fixes: a fix, finite, and horizontal sigma <= rtk_sigma [m] where the
    covariance is known, or GBAS status where it is not."""
    finite = np.isfinite(fixes.lat) & np.isfinite(fixes.lon) & np.isfinite(fixes.alt)
    sig = fixes.sigma_h()
    known = np.isfinite(sig)
    precise = np.where(known, np.nan_to_num(sig, nan=np.inf) <= rtk_sigma, fixes.status >= STATUS_GBAS_FIX)
    return finite & (fixes.status >= STATUS_FIX) & precise


def fit_gnss(stamps: np.ndarray, rows: np.ndarray, fixes: Fixes, rtk_sigma: float = RTK_SIGMA) -> Georef:
    """The map frame tied to UTM by the fixes (module docstring); GeorefError when they
    cannot (no fix in the drive's time, no RTK fix, too few or too close together).

    stamps: (S,) pose times [s], the fixes' clock; rows: (S, 7) base_link poses in the map.
    """
    n_all = len(fixes)
    if n_all == 0:
        raise GeorefError(f"{fixes.topic}: no fixes")
    span = (fixes.t >= stamps[0]) & (fixes.t <= stamps[-1])
    if not span.any():
        raise GeorefError(f"{fixes.topic}: none of its {n_all} fixes ({fixes.t[0]:.1f}-{fixes.t[-1]:.1f} s) falls "
                          f"within the trajectory's time ({stamps[0]:.1f}-{stamps[-1]:.1f} s)")
    rtk = span & rtk_mask(fixes, rtk_sigma)
    if rtk.sum() < 3:
        kinds = _status_counts(fixes, span)
        raise GeorefError(f"{fixes.topic}: {int(rtk.sum())} RTK-fixed fixes (horizontal sigma <= {100 * rtk_sigma:.0f} "
                          f"cm) among the {int(span.sum())} in the drive ({kinds}); at least 3 are needed")
    lat0, lon0 = float(np.median(fixes.lat[rtk])), float(np.median(fixes.lon[rtk]))
    epsg = utm_epsg(lat0, lon0)
    k = scale_factor(epsg, lat0, lon0)
    u = project(epsg, fixes.lat[rtk], fixes.lon[rtk])
    a = antenna_track(stamps, rows, fixes.antenna, fixes.t[rtk])
    sig = fixes.sigma_h()[rtk]
    sig = np.where(np.isfinite(sig) & (sig > 0), sig, 0.02)   # GBAS status without covariance: an RTK's 2 cm
    spread = _spread(a[:, :2])
    if spread < MIN_SPREAD:
        raise GeorefError(f"{fixes.topic}: the RTK fixes spread over {spread:.2f} m of the drive, less than "
                          f"{MIN_SPREAD:.0f} m: the map's heading cannot be told from them (a robot standing still?)")
    thr = OUTLIER_SIGMAS * np.hypot(sig, MAP_SIGMA if fixes.antenna_known else MAP_SIGMA + 1.0)
    keep = _consensus(a[:, :2], u, k, thr)
    yaw, t, r, keep = _robust_fit(a, u, sig, k, thr, keep)
    antenna, lever = np.asarray(fixes.antenna, dtype=np.float64), ""
    if not fixes.antenna_known:
        heading = np.interp(fixes.t[rtk], stamps, np.unwrap(rows[:, 6]))
        turned = float(np.degrees(np.ptp(heading[keep])))
        if turned >= MIN_TURN_DEG:
            base = antenna_track(stamps, rows, np.zeros(3), fixes.t[rtk])
            for _ in range(3):   # the offset for the fixes kept, then the fixes kept for the offset
                yaw, antenna[:2], t = _lever_arm(base[keep, :2], heading[keep], u[keep], 1.0 / sig[keep] ** 2, k,
                                                 yaw, t)
                a = antenna_track(stamps, rows, antenna, fixes.t[rtk])
                yaw, t, r, keep = _robust_fit(a, u, sig, k, OUTLIER_SIGMAS * np.hypot(sig, MAP_SIGMA), keep)
            lever = f"; the antenna's offset, missing from TF, fitted at ({antenna[0]:.3f}, {antenna[1]:.3f}) m"
        else:
            lever = (f"; the antenna's offset is missing from TF and the drive turned {turned:.0f} deg, too little "
                     "to fit it: the antenna taken at base_link")
    w = 1.0 / sig[keep] ** 2
    up = float(np.sum(w * (fixes.alt[rtk][keep] - a[keep, 2])) / np.sum(w))
    rms = float(np.sqrt(np.mean(r[keep] ** 2)))
    yaw_sd = float(np.sqrt(1.0 / np.sum(w * np.sum((k * (a[keep, :2] - a[keep, :2].mean(0))) ** 2, 1))))
    fit = {"fixes": n_all, "in_drive": int(span.sum()), "rtk": int(rtk.sum()), "used": int(keep.sum()),
           "outliers": int((~keep).sum()), "residual_rms_m": rms, "residual_max_m": float(r[keep].max()),
           "yaw_sd_deg": math.degrees(yaw_sd), "spread_m": spread, "antenna_m": [float(v) for v in antenna],
           "antenna_from_tf": bool(fixes.antenna_known), "topic": fixes.topic}
    note = (f"fitted to {int(keep.sum())} RTK fixes on {fixes.topic} (of {n_all}; {int((~keep).sum())} outliers and "
            f"{int(span.sum() - rtk.sum())} non-RTK fixes left out): residual RMS {100 * rms:.1f} cm, "
            f"yaw sd {math.degrees(yaw_sd):.3f} deg{lever}")
    return Georef("gnss", epsg, _wrap(yaw), float(t[0]), float(t[1]), k, up, note, fit)


def _robust_fit(a, u, sig, k, thr, keep):
    """Weighted fits, each leaving out the fixes beyond thr of the last, until the set holds."""
    for _ in range(20):
        yaw, t = _procrustes(a[keep, :2], u[keep], 1.0 / sig[keep] ** 2, k)
        r = np.linalg.norm(u - (a[:, :2] @ _rot(yaw, k).T + t), axis=1)
        new = r <= thr
        if new.sum() < 3 or np.array_equal(new, keep):
            break
        keep = new
    return yaw, t, r, keep


def _lever_arm(base: np.ndarray, heading: np.ndarray, u: np.ndarray, w: np.ndarray, k: float, yaw: float,
               t: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """yaw, the antenna's (x, y) in base_link [m] and t, by weighted Gauss-Newton from (yaw, 0, t):
    u = k R(yaw) (base + R(heading) a) + t, base (M, 2) base_link in the map, heading (M,) rad."""
    c, s = np.cos(heading), np.sin(heading)
    rb = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)             # (M, 2, 2)
    x = np.array([yaw, 0.0, 0.0, t[0], t[1]])
    sw = np.sqrt(w)[:, None]
    for _ in range(10):
        R, dR = _rot(x[0], k), _rot(x[0] + math.pi / 2, k)                      # dR/dyaw = R(yaw + 90 deg)
        q = base + np.einsum("mij,j->mi", rb, x[1:3])
        f = q @ R.T + x[3:] - u
        J = np.concatenate([(q @ dR.T)[:, :, None], np.einsum("ij,mjk->mik", R, rb),
                            np.broadcast_to(np.eye(2), (len(u), 2, 2))], 2)      # (M, 2, 5)
        step, *_ = np.linalg.lstsq((J * sw[:, :, None]).reshape(-1, 5), -(f * sw).reshape(-1), rcond=None)
        x += step
        if np.abs(step).max() < 1e-6:
            break
    return float(x[0]), x[1:3], x[3:]


def _consensus(a: np.ndarray, u: np.ndarray, k: float, thr: np.ndarray) -> np.ndarray:
    """(M,) the fixes that agree with the best of TRIES two-fix fits (a RANSAC start, so that
    a stretch of jumped fixes cannot pull the first fit); all where none is better."""
    rng = np.random.default_rng(0)
    best = np.ones(len(a), dtype=bool)
    n_best = 0
    for _ in range(TRIES):
        i, j = rng.choice(len(a), 2, replace=False)
        if np.linalg.norm(a[i] - a[j]) < MIN_SPREAD / 2:
            continue
        yaw, t = _procrustes(a[[i, j]], u[[i, j]], np.ones(2), k)
        inl = np.linalg.norm(u - (a @ _rot(yaw, k).T + t), axis=1) <= thr
        if inl.sum() > n_best:
            best, n_best = inl, int(inl.sum())
    return best if n_best >= 3 else np.ones(len(a), dtype=bool)


def _status_counts(fixes: Fixes, mask: np.ndarray) -> str:
    names = {-1: "no fix", 0: "fix", 1: "SBAS", 2: "GBAS/RTK"}
    vals, counts = np.unique(fixes.status[mask], return_counts=True)
    sig = fixes.sigma_h()[mask]
    parts = [f"{c} {names.get(int(v), f'status {int(v)}')}" for v, c in zip(vals, counts, strict=True)]
    if np.isfinite(sig).any():
        parts.append(f"median sigma {100 * float(np.nanmedian(sig)):.0f} cm")
    return ", ".join(parts)


def _rot(yaw: float, k: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return k * np.array([[c, -s], [s, c]])


def _procrustes(a: np.ndarray, u: np.ndarray, w: np.ndarray, k: float) -> tuple[float, np.ndarray]:
    """Weighted least squares yaw and t of u = k R(yaw) a + t; a, u (M, 2), w (M,)."""
    w = w / w.sum()
    am, um = w @ a, w @ u
    h = ((a - am) * w[:, None]).T @ (u - um)
    yaw = math.atan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
    return yaw, um - _rot(yaw, k) @ am


def _spread(xy: np.ndarray) -> float:
    """The extent of points along their main direction (4 standard deviations), m."""
    if len(xy) < 2:
        return 0.0
    return float(4.0 * np.sqrt(np.linalg.eigvalsh(np.cov(xy.T))[-1]))


def _wrap(a: float) -> float:
    return float((a + math.pi) % (2 * math.pi) - math.pi)
