"""The synthetic field: large-scale relief, tilled micro-topography, soil fields and landmarks.

Everything is a deterministic function of the scenario and a seed. Heights in metres,
world frame (REP 103: x forward along the field, y left, z up).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter

from torchsoil.grid import Grid
from torchsoil.settings import LandmarkConfig, WorldSoil, validate


@dataclass(frozen=True)
class Relief:
    """Gentle large-scale relief: a plane (slopes) plus a few long sinusoids.

    h(x, y) = slope_x * x + slope_y * y + sum_k a_k sin(kx_k x + ky_k y + phi_k)   [m]
    """

    slope_x: float
    slope_y: float
    amp: np.ndarray     # (M,) m
    kx: np.ndarray      # (M,) rad/m
    ky: np.ndarray      # (M,) rad/m
    phase: np.ndarray   # (M,) rad

    @classmethod
    def random(cls, rng: np.random.Generator, amplitude: float = 0.05,
               wavelength: float = 25.0, slope_x: float = 0.0, slope_y: float = 0.0,
               n: int = 3) -> Relief:
        """Relief with n sinusoids of total amplitude ~`amplitude` [m] and wavelengths
        around `wavelength` [m]; slope_x, slope_y [m/m] (a side slope is slope_y)."""
        lam = wavelength * rng.uniform(0.7, 1.4, n)
        ang = rng.uniform(0, math.pi, n)
        k = 2 * math.pi / lam
        return cls(float(slope_x), float(slope_y), amplitude / math.sqrt(n) * rng.uniform(0.6, 1.2, n),
                   k * np.cos(ang), k * np.sin(ang), rng.uniform(0, 2 * math.pi, n))

    def height(self, x, y) -> np.ndarray:
        """Relief height at world points (broadcastable arrays), m."""
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        h = self.slope_x * x + self.slope_y * y
        for a, kx, ky, ph in zip(self.amp, self.kx, self.ky, self.phase, strict=True):
            h = h + a * np.sin(kx * x + ky * y + ph)
        return h

    def gradient(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """dh/dx, dh/dy at world points, m/m."""
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        gx = np.full(np.broadcast(x, y).shape, self.slope_x)
        gy = np.full(np.broadcast(x, y).shape, self.slope_y)
        for a, kx, ky, ph in zip(self.amp, self.kx, self.ky, self.phase, strict=True):
            c = a * np.cos(kx * x + ky * y + ph)
            gx = gx + kx * c
            gy = gy + ky * c
        return gx, gy


def micro_topography(grid: Grid, rng: np.random.Generator, rms: float = 0.007,
                     corr_length: float = 0.07) -> np.ndarray:
    """Tilled-soil roughness: band-limited Gaussian noise of standard deviation `rms` [m] and
    correlation length ~`corr_length` [m] (Gaussian kernel sigma = corr_length / 2).

    Returns (X, Y) float64 heights, m, zero mean.
    """
    if rms < 0 or corr_length <= 0:
        raise ValueError(f"micro-topography needs rms >= 0 and corr_length > 0, got {rms}, {corr_length}")
    white = rng.standard_normal(grid.shape)
    if rms == 0:
        return np.zeros(grid.shape)
    sigma = max(corr_length / 2 / grid.dx, 0.5)
    f = gaussian_filter(white, sigma, mode="wrap")
    f -= f.mean()
    return f * (rms / max(f.std(), 1e-12))


# --------------------------------------------------------------------------- soil fields

SOIL_KEYS = ("d", "chi", "beta_deg", "moisture")


PATCH_KEYS = {"band_x": ({"center", "sigma"}, set()), "disc": ({"center", "sigma"}, set()),
              "lane": ({"x0", "x1"}, {"y0", "y1", "edge"})}   # kind: (required, optional) keys


def check_patch(p) -> None:
    """Refuse a soil patch with an unknown kind, missing or unknown keys, or unknown or
    non-numeric delta keys (ValueError naming them); see `_patch_weight` for the kinds."""
    if not isinstance(p, dict):
        raise ValueError(f"a soil patch is a mapping {{kind, ..., delta}}, got {p!r}")
    kind = p.get("kind")
    if kind not in PATCH_KEYS:
        raise ValueError(f"`kind` must be one of {', '.join(PATCH_KEYS)}, got {kind!r}")
    required, optional = PATCH_KEYS[kind]
    missing = required - set(p)
    unknown = set(p) - required - optional - {"kind", "delta"}
    if missing or unknown:
        raise ValueError(f"a {kind} patch needs {sorted(required)}"
                         + (f" and may have {sorted(optional)}" if optional else "")
                         + (f"; missing {sorted(missing)}" if missing else "")
                         + (f"; unknown {sorted(unknown)}" if unknown else ""))
    delta = p.get("delta") or {}
    if not isinstance(delta, dict):
        raise ValueError(f"`delta` must be a mapping of {SOIL_KEYS}, got {delta!r}")
    for k, v in delta.items():
        if k not in SOIL_KEYS:
            raise ValueError(f"delta: unknown key {k!r}; known: {SOIL_KEYS}")
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ValueError(f"delta.{k} must be a number, got {v!r}")
    center = p.get("center")
    if kind == "disc" and not (isinstance(center, (list, tuple)) and len(center) == 2):
        raise ValueError(f"a disc patch's `center` is [x, y], got {center!r}")
    for k in set(p) - {"kind", "delta"} - ({"center"} if kind == "disc" else set()):
        if isinstance(p[k], bool) or not isinstance(p[k], (int, float)):
            raise ValueError(f"`{k}` must be a number, got {p[k]!r}")


def _patch_weight(p: dict, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Smooth 0..1 weight of one soil patch at world points.

    kinds: `band_x` (Gaussian in x: center, sigma), `disc` (Gaussian: center [x, y], sigma),
    `lane` (rectangle x0..x1 by y0..y1 with smooth edges of width `edge`).
    """
    kind = p.get("kind")
    if kind == "band_x":
        return np.exp(-0.5 * ((x - p["center"]) / p["sigma"]) ** 2)
    if kind == "disc":
        cx, cy = p["center"]
        return np.exp(-0.5 * ((x - cx) ** 2 + (y - cy) ** 2) / p["sigma"] ** 2)
    if kind == "lane":
        e = float(p.get("edge", 0.5))

        def step(u):
            return 0.5 * (1 + np.tanh(u / max(e, 1e-6) * 2))

        return (step(x - p["x0"]) * step(p["x1"] - x)
                * step(y - p.get("y0", -1e9)) * step(p.get("y1", 1e9) - y))
    raise ValueError(f"soil patch kind must be band_x, disc or lane, got {kind!r} in {p}")


def as_world_soil(soil: WorldSoil | dict) -> WorldSoil:
    """A soil section as WorldSoil (a dict is validated, errors naming `soil.KEY`)."""
    return soil if isinstance(soil, WorldSoil) else validate(WorldSoil, soil, "soil", prefix="soil.")


def soil_at(soil: WorldSoil | dict, x, y) -> dict[str, np.ndarray]:
    """Soil properties at world points: base values plus weighted patch deltas.

    soil: the scenario's soil section (WorldSoil, or a dict of it): base {d [m], chi [-],
    beta_deg [deg], moisture [0..1]}, patches [{kind, ..., "delta": {key: value}}].
    Returns {d, chi, beta (rad), moisture} arrays of the broadcast shape of x, y.
    """
    soil = as_world_soil(soil)
    x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
    out = {k: np.full(x.shape, float(v)) for k, v in soil.base.items()}
    for i, p in enumerate(soil.patches):
        w = _patch_weight(p, x, y)
        for k, v in (p.get("delta") or {}).items():
            if k not in SOIL_KEYS:
                raise ValueError(f"soil.patches[{i}].delta: unknown key {k!r}; known: {SOIL_KEYS}")
            out[k] = out[k] + w * float(v)
    out["d"] = np.clip(out["d"], 0.0, 0.3)
    out["chi"] = np.clip(out["chi"], 0.0, 2.0)
    out["beta"] = np.radians(np.clip(out.pop("beta_deg"), 2.0, 89.0))
    out["moisture"] = np.clip(out["moisture"], 0.0, 1.0)
    return out


# --------------------------------------------------------------------------- landmarks

@dataclass(frozen=True)
class Landmarks:
    """Vertical cylinders (poles, trunks) and yawed boxes (walls, fence rails), world frame.

    cylinders: (C, 5) x, y, radius, z_bottom, z_top [m].
    boxes: (N, 8) cx, cy, cz, half_length, half_width, half_height [m], yaw [rad], kind.
    """

    cylinders: np.ndarray
    boxes: np.ndarray

    @classmethod
    def empty(cls) -> Landmarks:
        return cls(np.zeros((0, 5)), np.zeros((0, 8)))


def farm_landmarks(spec: LandmarkConfig, relief: Relief, bounds: tuple[float, float, float, float],
                   rng: np.random.Generator, keep_out: np.ndarray) -> Landmarks:
    """A farm scene around the field: poles, tree trunks, a shed wall and a fence.

    spec: the scenario's landmarks section (poles: n, trunks: n, shed, fence); bounds:
    (xmin, ymin, xmax, ymax) of the field, m; keep_out: (M, 2) path points, no landmark
    within 2.5 m.
    """
    xmin, ymin, xmax, ymax = bounds
    cyl, box = [], []
    tree = None
    if len(keep_out):
        from scipy.spatial import cKDTree

        tree = cKDTree(keep_out)

    def free(x, y, clear=2.5):
        return tree is None or tree.query([x, y])[0] > clear

    def place(n, r_lo, r_hi, z_lo, z_hi):
        placed = 0
        for _ in range(50 * max(n, 1)):
            if placed >= n:
                break
            x, y = rng.uniform(xmin + 1, xmax - 1), rng.uniform(ymin + 1, ymax - 1)
            if not free(x, y):
                continue
            z0 = float(relief.height(x, y)) - 0.2
            cyl.append([x, y, rng.uniform(r_lo, r_hi), z0, z0 + 0.2 + rng.uniform(z_lo, z_hi)])
            placed += 1

    place(spec.poles, 0.04, 0.08, 1.5, 3.0)
    place(spec.trunks, 0.12, 0.3, 3.0, 6.0)
    if spec.shed:
        # a wall along the field, on the +y side, 10 m long, 3 m high
        cx, cy = 0.5 * (xmin + xmax), ymax - 1.5
        z0 = float(relief.height(cx, cy)) - 0.3
        box.append([cx, cy, z0 + 1.65, 5.0, 0.1, 1.65, 0.02, 1])
        # its side wall, 4 m, toward the field; away from it where it would reach the path
        # (on a narrow field the side wall stood across the drive)
        side = -1.0 if all(free(cx + 5.0, cy - t) for t in np.linspace(0.0, 4.0, 17)) else 1.0
        box.append([cx + 5.0, cy + 2.0 * side, z0 + 1.65, 2.0, 0.1, 1.65, math.pi / 2 + 0.02, 1])
    if spec.fence:
        # a fence along the -y side: posts every 2.5 m and two rails
        y = ymin + 1.5
        xs = np.arange(xmin + 1.0, xmax - 1.0, 2.5)
        for x in xs:
            z0 = float(relief.height(x, y)) - 0.2
            cyl.append([x, y, 0.05, z0, z0 + 1.4])
        cx = 0.5 * (xs[0] + xs[-1]) if len(xs) else 0.5 * (xmin + xmax)
        half = 0.5 * (xs[-1] - xs[0]) if len(xs) > 1 else 1.0
        zc = float(relief.height(cx, y))
        for zr in (0.5, 1.0):
            box.append([cx, y, zc + zr, half, 0.02, 0.05, 0.0, 2])
    return Landmarks(np.array(cyl, dtype=np.float64).reshape(-1, 5),
                     np.array(box, dtype=np.float64).reshape(-1, 8))
