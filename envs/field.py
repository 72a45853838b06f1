"""The field: an initial heightmap and maps of the soil parameters that vary in space.

Layers follow the simulator's theta: d_1..d_T sinkage per track [m], chi [-], beta [rad],
stored as one (T + 2, X, Y) stack. A field comes from its settings (`env.field`, a
`torchsoil.settings.FieldConfig`: uniform soil with wet patches of deep sinkage and packed
lanes of shallow sinkage) or from an estimator run's `params.csv` along a recorded path
(nearest estimate to each cell).
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import gaussian_filter
from scipy.spatial import cKDTree

from torchsoil.grid import Grid
from torchsoil.settings import FieldConfig, SettingsError, SoilValues, merge, validate
from torchsoil.sim.params import BETA_BOUNDS, CHI_BOUNDS, D_BOUNDS


@dataclass(frozen=True)
class SoilField:
    """Initial surface and soil-parameter maps on one grid.

    Attributes:
        grid: the field grid (cell [i, j] at origin + (i, j) * dx).
        h0: (X, Y) float32 initial surface, m.
        soil: (T + 2, X, Y) float32 d_1..d_T [m], chi [-], beta [rad].
        names: T + 2 layer names ("d1", ..., "chi", "beta").
    """

    grid: Grid
    h0: torch.Tensor
    soil: torch.Tensor
    names: tuple[str, ...]

    def __post_init__(self):
        X, Y = self.grid.shape
        if tuple(self.h0.shape) != (X, Y):
            raise ValueError(f"h0 must be (X, Y) = ({X}, {Y}), got {tuple(self.h0.shape)}")
        if self.soil.ndim != 3 or tuple(self.soil.shape[1:]) != (X, Y) or self.soil.shape[0] < 3:
            raise ValueError(f"soil must be (T + 2, {X}, {Y}) with T >= 1, got {tuple(self.soil.shape)}")
        if len(self.names) != self.soil.shape[0]:
            raise ValueError(f"{len(self.names)} layer names for {self.soil.shape[0]} soil layers")
        if not (torch.isfinite(self.h0).all() and torch.isfinite(self.soil).all()):
            raise ValueError("field heights and soil parameters must be finite everywhere")
        T = self.n_tracks
        _check_range("d", self.soil[:T], D_BOUNDS)
        _check_range("chi", self.soil[T], CHI_BOUNDS)
        _check_range("beta", self.soil[T + 1], BETA_BOUNDS)

    @property
    def n_tracks(self) -> int:
        return self.soil.shape[0] - 2

    def to(self, device) -> SoilField:
        return SoilField(self.grid, self.h0.to(device), self.soil.to(device), self.names)


def _check_range(name, t, bounds):
    lo, hi = float(t.min()), float(t.max())
    if lo < bounds[0] - 1e-6 or hi > bounds[1] + 1e-6:
        raise ValueError(f"soil layer {name} spans [{lo:.4g}, {hi:.4g}], outside its bounds {bounds}")


def field_config(config: FieldConfig | dict | None = None) -> FieldConfig:
    """A `torchsoil.settings.FieldConfig` from itself, None (the defaults) or a dict merged onto
    the defaults (mappings merge, lists replace); unknown keys are refused with the key named."""
    if isinstance(config, FieldConfig):
        return config
    if config is not None and not isinstance(config, dict):
        raise SettingsError(f"field config must be a mapping, got {type(config).__name__}")
    return validate(FieldConfig, merge(FieldConfig().model_dump(), config or {}), "field config",
                    prefix="field.")


def _layer_values(spec: SoilValues, n_tracks: int, where: str, base: np.ndarray | None = None
                  ) -> np.ndarray:
    """(T + 2,) d_1..d_T, chi, beta [rad] from soil values d, chi, beta_deg (None: from base)."""
    out = np.array(base, dtype=np.float64) if base is not None else np.full(n_tracks + 2, np.nan)
    if spec.d is not None:
        d = np.atleast_1d(np.asarray(spec.d, dtype=np.float64))
        if d.size not in (1, n_tracks):
            raise ValueError(f"{where}: d needs 1 or {n_tracks} values, got {d.size}")
        out[:n_tracks] = d
    if spec.chi is not None:
        out[n_tracks] = float(spec.chi)
    if spec.beta_deg is not None:
        out[n_tracks + 1] = math.radians(float(spec.beta_deg))
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{where}: needs d, chi and beta_deg")
    return out


def layer_names(n_tracks: int) -> tuple[str, ...]:
    return tuple(f"d{k + 1}" for k in range(n_tracks)) + ("chi", "beta")


def make_field(config: FieldConfig | dict | None = None, n_tracks: int = 2) -> SoilField:
    """Build a field from its config (`torchsoil.settings.FieldConfig`, or a dict of it):
    rough initial surface, background soil, wet patches (blended in over `edge` metres) and
    packed lanes, with one sinkage layer per wheel track. Same config, same field."""
    cfg = field_config(config)
    if cfg.dx <= 0 or min(cfg.size) < 4 * cfg.dx:
        raise ValueError(f"field size {cfg.size} m must span several cells of dx = {cfg.dx} m")
    grid = Grid.covering(0.0, 0.0, cfg.size[0], cfg.size[1], cfg.dx)
    T = int(n_tracks)
    if T < 1:
        raise ValueError(f"a field needs at least one sinkage track, got n_tracks = {n_tracks}")
    rng = np.random.default_rng(cfg.seed)
    noise = rng.standard_normal(grid.shape)
    if cfg.roughness > 0:
        noise = gaussian_filter(noise, cfg.roughness_length / cfg.dx, mode="wrap")
        noise *= cfg.roughness / max(noise.std(), 1e-12)
    h0 = noise * (cfg.roughness > 0)
    base = _layer_values(cfg.soil, T, "field.soil")
    soil = np.broadcast_to(base[:, None, None], (T + 2, *grid.shape)).copy()
    xs, ys = grid.centers()
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    for n, lane in enumerate(cfg.lanes):
        y0, y1 = (float(v) for v in lane.y)
        vals = _layer_values(lane, T, f"field.lanes[{n}]", base)
        w = ((gy >= y0) & (gy <= y1)).astype(np.float64)
        soil = soil * (1 - w) + vals[:, None, None] * w
    for n, patch in enumerate(cfg.patches):
        vals = _layer_values(patch, T, f"field.patches[{n}]", base)
        r = np.hypot(gx - float(patch.center[0]), gy - float(patch.center[1]))
        w = np.clip((float(patch.radius) + cfg.edge / 2 - r) / max(cfg.edge, 1e-9), 0.0, 1.0)
        soil = soil * (1 - w) + vals[:, None, None] * w
    return SoilField(grid, torch.as_tensor(h0, dtype=torch.float32),
                     torch.as_tensor(soil, dtype=torch.float32), layer_names(T))


def read_params_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray, tuple[str, ...]]:
    """An estimator run's params.csv -> path points (M, 2) x, y [m], parameters (M, T + 2)
    d_1..d_T [m], chi, beta [rad], and the layer names. Rows with non-finite values are dropped,
    and so are the rows of later visits of ground driven more than once (`visit` > 0): the
    field is the soil before the robot."""
    path = Path(path)
    try:
        with path.open(newline="") as f:
            rows = list(csv.DictReader(f))
    except FileNotFoundError:
        raise FileNotFoundError(f"params.csv not found: {path}") from None
    rows = [r for r in rows if r.get("visit") in (None, "", "0", "0.0")]
    if not rows:
        raise ValueError(f"{path}: no estimates")
    cols = rows[0].keys()
    ds = sorted((c for c in cols if c.startswith("d") and c[1:].isdigit()), key=lambda c: int(c[1:]))
    beta_col = next((c for c in cols if c.startswith("beta")), None)
    missing = [c for c in ("x", "y", "chi") if c not in cols] + ([] if ds else ["d1"]) \
        + ([] if beta_col else ["beta[deg]"])
    if missing:
        raise ValueError(f"{path}: missing columns {missing}; have {list(cols)}")
    try:
        xy = np.array([[float(r["x"]), float(r["y"])] for r in rows])
        vals = np.array([[float(r[c]) for c in ds] + [float(r["chi"]), math.radians(float(r[beta_col]))]
                         for r in rows])
    except (TypeError, ValueError) as e:
        raise ValueError(f"{path}: non-numeric value ({e})") from None
    ok = np.isfinite(xy).all(1) & np.isfinite(vals).all(1)
    if not ok.any():
        raise ValueError(f"{path}: no row with finite x, y and parameters")
    return xy[ok], vals[ok], layer_names(len(ds))


def field_from_params_csv(path: str | Path, config: FieldConfig | dict | None = None,
                          reach: float = 1.5) -> SoilField:
    """A field whose soil near a recorded path is the estimate nearest to each cell.

    Cells within `reach` metres of an estimate take its d_1..d_T, chi and beta; farther ones
    keep the config's soil (patches and lanes). The field's tracks follow the csv's d columns.
    """
    xy, vals, names = read_params_csv(path)
    base = make_field(config, len(names) - 2)
    xs, ys = base.grid.centers()
    cells = np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)
    d, i = cKDTree(xy).query(cells, distance_upper_bound=reach)
    hit = np.isfinite(d)
    soil = base.soil.numpy().reshape(len(names), -1).copy()
    lo = np.array([D_BOUNDS[0]] * (len(names) - 2) + [CHI_BOUNDS[0], BETA_BOUNDS[0]])
    hi = np.array([D_BOUNDS[1]] * (len(names) - 2) + [CHI_BOUNDS[1], BETA_BOUNDS[1]])
    soil[:, hit] = np.clip(vals[i[hit]], lo, hi).T
    return SoilField(base.grid, base.h0, torch.as_tensor(soil.reshape(base.soil.shape),
                                                         dtype=torch.float32), names)
