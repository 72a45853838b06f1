"""Estimation windows along the drive (paper section IV-C): where each window's ground lies,
which cells its cost counts, and the cropped, simulation-ready data of one window."""

from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from scipy import ndimage
from scipy.spatial import cKDTree

from torchsoil.grid import Grid
from torchsoil.pipeline.visit_tracker import visit_gap
from torchsoil.robot import Robot
from torchsoil.settings import EstimatorConfig, SimConfig
from torchsoil.sim import WheelGeometry, wheel_geometry
from torchsoil.sim.geometry import resample_poses, wheel_positions
from torchsoil.sim.sinkage import reference_height


class PathIndex(NamedTuple):
    """Every cell's place relative to the drive; (X, Y) arrays, inf/NaN far from the path.

    s: arc length of the nearest base_link path point, m. offset: distance to the base_link
    path, m. wheel_dist: distance to the nearest wheel path, m. arc: (N,) arc length at each
    pose, m. order: flat indices of the cells with a finite s, sorted by s, and s_sorted their
    s (so that a window finds its ground without a pass over the whole grid).
    """

    s: np.ndarray
    offset: np.ndarray
    wheel_dist: np.ndarray
    arc: np.ndarray
    order: np.ndarray
    s_sorted: np.ndarray

    def ground(self, s0: float, s1: float, corridor: float) -> np.ndarray:
        """(G, 2) cells (i, j), in row-major order, whose s lies in [s0, s1) [m] and that lie
        within corridor / 2 [m] of the base_link path."""
        a, b = np.searchsorted(self.s_sorted, [s0, s1])
        flat = np.sort(self.order[a:b])
        flat = flat[self.offset.ravel()[flat] <= corridor / 2]
        return np.stack(np.unravel_index(flat, self.s.shape), 1)


def path_arc(poses: np.ndarray) -> np.ndarray:
    """(N,) cumulative base_link path length at each (N, 7) pose, m."""
    step = np.linalg.norm(np.diff(poses[:, 1:3], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(step)])


def path_index(grid: Grid, poses: np.ndarray, robot: Robot, reach: float, touch: float | None = None) -> PathIndex:
    """Arc length and distances for the cells within `reach` [m] of the path; a cell the path
    passes more than once takes the arc length of the last pass whose wheels came within
    `touch` [m] of it (default: one wheel width, the footprint and the berm beside it; the
    estimator passes the simulator's reach, half a wheel width plus the relaxation margin:
    the last pass that could change the cell, before which a front lidar keeping its newest
    view saw it), or, where no wheel did, of the last pass about as near as the nearest."""
    arc = path_arc(poses)
    planar = poses[:, [0, 1, 2, 6]]
    dense = resample_poses(planar, robot.wheels[:, :2], grid.dx / 2)
    dense_arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense[:, 1:3], axis=0), axis=1))])
    xs, ys = grid.centers()
    cells = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
    tree = cKDTree(dense[:, 1:3])
    d, i = tree.query(cells, distance_upper_bound=reach)
    hit = np.flatnonzero(np.isfinite(d))
    # ground the robot drove over twice belongs to its last pass (a terrain pair shows the
    # surface before and after the last pass): the last pass whose wheels went over it (a
    # later pass shifted sideways, a lane change or a crossing, may dig ground nearer an
    # earlier pass's base_link and pass beside ground it leaves as it was); where no wheel
    # did, the latest path point about as near as the nearest
    again = hit[_revisited(dense[:, 1:3], dense_arc, reach)[i[hit]]]
    wheels = wheel_positions(dense, robot.wheels[:, :2])                          # (K, N, 2)
    if len(again):
        touch = robot.wheel_width if touch is None else touch
        span = 2 * (np.abs(robot.wheels[:, 0]).max() + touch)
        last = _last_wheel_pass(cells[again], dense[:, 1:3], wheels, dense_arc, touch, span, i[again])
        i[again[last >= 0]] = last[last >= 0]
        rest = again[last < 0]
        if len(rest):
            i[rest] = _latest_hit(cells[rest], dense[None, :, 1:3], d[rest] + 2 * grid.dx)
    s = np.full(len(cells), np.nan)
    s[hit] = dense_arc[i[hit]]
    wd, _ = cKDTree(wheels.reshape(-1, 2)).query(cells, distance_upper_bound=reach)
    order = np.flatnonzero(np.isfinite(s))
    order = order[np.argsort(s[order], kind="stable")]
    if len(cells) < 2**31:                    # flat indices: int32 halves the index's largest array
        order = order.astype(np.int32)
    return PathIndex(s.reshape(grid.shape), d.reshape(grid.shape), wd.reshape(grid.shape), arc, order, s[order])


def _latest_hit(cells: np.ndarray, points: np.ndarray, radius) -> np.ndarray:
    """(C,) latest index n whose (K, N, 2) points[:, n] came within `radius` [m] (a scalar or one
    per cell, (C,)) of each (C, 2) cell, -1 where none did. The path is walked backwards over
    the cells binned near each point (a compiled loop, `_path_numba.latest_within`), and a cell
    leaves the search at its first hit: the work grows with the drive's length, not with its
    square."""
    from torchsoil.estimate._path_numba import latest_within

    cells = np.ascontiguousarray(cells, dtype=np.float64).reshape(-1, 2)
    radius = np.ascontiguousarray(np.broadcast_to(np.asarray(radius, dtype=np.float64), (len(cells),)))
    if len(cells) == 0:
        return np.full(0, -1, np.int64)
    span = float(np.ptp(cells, axis=0).max())
    h = max(float(radius.max()), span / 1000.0, 1e-6)       # at most ~10^6 bins
    return latest_within(cells, np.ascontiguousarray(points, dtype=np.float64), radius, h)


def _last_wheel_pass(cells: np.ndarray, xy: np.ndarray, wheels: np.ndarray, arc: np.ndarray, touch: float,
                     span: float, nearest: np.ndarray) -> np.ndarray:
    """(C,) index of the path point nearest each (C, 2) cell among the (N, 2) points of the
    last pass whose (K, N, 2) wheel positions came within `touch` [m] of it: the points up
    to `span` m of arc before the last one with a wheel that near; -1 where no wheel was.
    `nearest` (C,) is each cell's nearest point on the whole path: where it lies in that
    pass it is the answer, and only the other cells are searched."""
    from torchsoil.estimate._path_numba import nearest_between

    last = _latest_hit(cells, wheels, touch)
    out = np.full(len(cells), -1)
    sel = np.flatnonzero(last >= 0)
    lo = np.searchsorted(arc, arc[last[sel]] - span)
    inside = (nearest[sel] >= lo) & (nearest[sel] <= last[sel])
    out[sel[inside]] = nearest[sel[inside]]
    sel, lo = sel[~inside], lo[~inside]
    if len(sel) == 0:
        return out
    out[sel] = nearest_between(np.ascontiguousarray(cells[sel]), np.ascontiguousarray(xy), lo, last[sel])
    return out


def _revisited(xy: np.ndarray, arc: np.ndarray, reach: float, step: float = 0.1) -> np.ndarray:
    """(N,) bool: path points within 2 reach [m] of a part of the path more than 2 reach
    (+ 2 steps) of arc length away, which a straight drive never is: where a cell may lie
    under two passes."""
    k = max(1, int(np.searchsorted(arc, step)))
    sub = np.arange(0, len(xy), k)
    pairs = cKDTree(xy[sub]).query_pairs(2 * reach, output_type="ndarray")
    out = np.zeros(len(xy), dtype=bool)
    if len(pairs):
        far = np.abs(arc[sub[pairs[:, 0]]] - arc[sub[pairs[:, 1]]]) > 2 * reach + 2 * step
        flagged = np.zeros(len(sub), dtype=bool)
        flagged[pairs[far].ravel()] = True
        out = np.repeat(flagged, k)[: len(xy)]
    return out


@dataclass(frozen=True)
class WindowSpec:
    """Window `index` covers the ground whose nearest path point lies at arc length [s0, s1), m."""

    index: int
    s0: float
    s1: float

    @property
    def centre(self) -> float:
        return 0.5 * (self.s0 + self.s1)


def plan_windows(length: float, window: float, stride: float, start: float = 0.0) -> list[WindowSpec]:
    """Full windows of `window` m every `stride` m along a path of `length` m."""
    if window <= 0 or stride <= 0:
        raise ValueError(f"window ({window}) and stride ({stride}) must be positive lengths in metres")
    n = int(np.floor((length - start - window) / stride + 1e-9)) + 1
    return [WindowSpec(k, start + k * stride, start + k * stride + window) for k in range(max(n, 0))]


def drive_windows(length: float, window: float, stride: float, arc0: float = 0.0) -> list[WindowSpec]:
    """The windows of a stretch `length` m long whose first pose lies at arc length arc0 [m]
    along a longer drive: placed where the whole drive's windows are (every `stride` m from its
    start), s0/s1 relative to the stretch."""
    start = (math.ceil(arc0 / stride - 1e-9) * stride - arc0) if arc0 > 0 else 0.0
    return plan_windows(length, window, stride, start)


class WindowData(NamedTuple):
    """One window cropped from the terrain pair, ready to simulate (tensors on one device).

    crop: (i0, i1, j0, j1) cells of the full grid. grid: the crop's Grid. geom: wheel geometry
    of the poses that pass over the crop. h_front: (1, X, Y) surface the simulation starts from
    (measured H_f, smoothed, gaps filled from the nearest measured cell), m. h_ref: (1, X, Y)
    reference height. h_back: (X, Y) measured surface after the wheels (0 where unmeasured),
    m. h_measured: (X, Y) measured H_f as recorded (0 where unmeasured), for the reference
    costs. weight: (X, Y) cost weight
    (window ground, measured before and after, near a wheel path). floor: (X, Y) bool cells
    beside the rut for the noise floor. ground: (X, Y) bool window ground. t, x, y: time [s]
    and position [m] at the window centre. flags: reasons to distrust the window. earlier:
    wheel geometry of each earlier visit over the window's ground, in time order, when H_f
    shows the ground before the first visit (`front_view`); the simulation drives them first.
    """

    spec: WindowSpec
    crop: tuple[int, int, int, int]
    grid: Grid
    geom: WheelGeometry
    h_front: torch.Tensor
    h_ref: torch.Tensor
    h_back: torch.Tensor
    h_measured: torch.Tensor
    weight: torch.Tensor
    floor: torch.Tensor
    ground: torch.Tensor
    t: float
    x: float
    y: float
    flags: tuple[str, ...]
    earlier: tuple[WheelGeometry, ...] = ()


class WindowStore:
    """Prepared windows (WindowData) kept across estimator runs over one terrain pair.

    A diagnosis runs the estimator over the same drive some thirty times, and preparing a
    window (crop, masks, wheel geometry) is about a quarter of a run. Share a store, like the
    PathIndex, only among estimators over the same pair and map nuisance; the key holds what
    may differ between them (tyre section, settings, view, device, the window's span). Windows
    are kept in memory while their tensors take at most `max_bytes` (0.2 to 0.5 MB a window
    with the default corridor and 2 cm cells: a 20 m drive's windows of one tyre section take
    about 20 MB); beyond that they are written to a temporary directory under `spill_dir`
    (None: the system's; removed with the store) and read back from there, so that memory
    does not grow with the drive and a long drive is not prepared anew on every pass.
    spill=False: beyond `max_bytes`, windows are prepared anew each time."""

    def __init__(self, max_bytes: int = 16 << 20, spill: bool = True, spill_dir: str | None = None):
        self.max_bytes, self.spill, self.spill_dir = max_bytes, spill, spill_dir
        self.nbytes = 0
        self.spilled_bytes = 0
        self._kept: dict[tuple, WindowData | None] = {}
        self._files: dict[tuple, str] = {}
        self._tmp = None

    def __len__(self) -> int:
        return len(self._kept) + len(self._files)

    def get(self, key: tuple, prepare) -> WindowData | None:
        """The window under `key`, from `prepare()` the first time (None: not preparable)."""
        if key in self._kept:
            return self._kept[key]
        if key in self._files:
            return torch.load(self._files[key], weights_only=False)
        wd = prepare()
        size = _nbytes(wd)
        if self.nbytes + size <= self.max_bytes:
            self._kept[key] = wd
            self.nbytes += size
        elif self.spill:
            if self._tmp is None:
                self._tmp = tempfile.TemporaryDirectory(prefix="torchsoil-windows-", dir=self.spill_dir)
            path = f"{self._tmp.name}/{len(self._files)}.pt"
            torch.save(wd, path)
            self._files[key] = path
            self.spilled_bytes += size
        return wd


def _nbytes(x) -> int:
    """Bytes held by the tensors in x (a tensor or nested tuples and NamedTuples of them)."""
    if isinstance(x, torch.Tensor):
        return x.numel() * x.element_size()
    return sum(_nbytes(v) for v in x) if isinstance(x, tuple) else 0


def smooth_heightmap(h: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing of an (X, Y) heightmap [m] with sigma in cells, ignoring NaN cells
    (normalised convolution); NaN stays NaN. sigma = 0 returns h unchanged."""
    if sigma <= 0:
        return h
    valid = np.isfinite(h)
    num = ndimage.gaussian_filter(np.where(valid, h, 0.0).astype(np.float64), sigma, mode="nearest")
    den = ndimage.gaussian_filter(valid.astype(np.float64), sigma, mode="nearest")
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(valid, num / den, np.nan)


def smooth_along(h: np.ndarray, yaw: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing of an (X, Y) heightmap [m] along a direction per cell only: yaw
    (X, Y) [rad, world frame; i runs along x, j along y], sigma in cells, NaN cells ignored
    (normalised) and kept NaN; cells with a NaN yaw are left as they are. Relief that runs
    along the direction (a rut along the track that dug it) keeps its cross-section while the
    noise averages out. sigma = 0 returns h unchanged."""
    if sigma <= 0:
        return h
    valid = np.isfinite(h)
    vals, w = np.where(valid, h, 0.0).astype(np.float64), valid.astype(np.float64)
    ii, jj = np.indices(h.shape, dtype=np.float64)
    c, s = np.cos(np.nan_to_num(yaw)), np.sin(np.nan_to_num(yaw))
    num = np.zeros(h.shape)
    den = np.zeros(h.shape)
    for k in range(-int(math.ceil(3 * sigma)), int(math.ceil(3 * sigma)) + 1):
        g = math.exp(-0.5 * (k / sigma) ** 2)
        at = [ii + k * c, jj + k * s]
        num += g * ndimage.map_coordinates(vals, at, order=1, mode="nearest")
        den += g * ndimage.map_coordinates(w, at, order=1, mode="nearest")
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(valid & (den > 0), num / den, np.nan)
    return np.where(np.isfinite(yaw), out, h)


def _stopped(poses: np.ndarray, speed: float, duration: float) -> bool:
    """The robot moved slower than `speed` [m/s] for more than `duration` [s] in these poses."""
    if len(poses) < 2:
        return False
    dt = np.diff(poses[:, 0])
    v = np.linalg.norm(np.diff(poses[:, 1:3], axis=0), axis=1) / np.maximum(dt, 1e-9)
    slow = np.where(v < speed, dt, 0.0)
    run = best = 0.0
    for d in slow:
        run = run + d if d > 0 else 0.0
        best = max(best, run)
    return best > duration


def sim_reach(robot: Robot, sim: SimConfig) -> float:
    """How far from a wheel's centre line the simulator changes the ground, m: half a wheel
    width (the footprint) plus the relaxation margin (0.35 m on the paper's platform)."""
    return robot.wheel_width * (0.5 + sim.relax_margin)


def _wheel_samples(poses: np.ndarray, robot: Robot, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """(M, 2) wheel centres along the drive every `spacing` m or less, and (M,) base_link arc
    length there, m."""
    dense = resample_poses(poses[:, [0, 1, 2, 6]], robot.wheels[:, :2], spacing)
    arc = np.interp(dense[:, 0], poses[:, 0], path_arc(poses))
    w = wheel_positions(dense, robot.wheels[:, :2])
    return w.reshape(-1, 2), np.tile(arc, len(w))


def front_view(pair, index: PathIndex, min_cells: int = 50) -> tuple[str, dict]:
    """What H_f holds on ground the wheels crossed more than once, told from the maps.

    A pipeline that keeps the newest view of each cell shows the ruts of the earlier visits in
    H_f ("last_visit", as docs/formats.md terrain pairs from torchsoil); one that keeps the first
    view shows untouched ground there ("first_view"). On the rut centres of revisited ground
    (within a quarter wheel width of an earlier visit's wheel and of the last one's), the
    ratio of H_f's rut depth to H_b's (each height less its Gaussian mean over a wheel width)
    tells them apart: about 0 on a first view, well above it when H_f shows the earlier ruts.
    Returns (view, {"ratio", "cells"}); too few revisited cells, or ruts too shallow to
    measure (< 1 mm), give "last_visit" (the two agree where nothing was revisited)."""
    robot, dx = pair.robot, pair.dx
    w, gap = robot.wheel_width, visit_gap(robot)
    rut = np.isfinite(index.s) & (index.wheel_dist <= w / 4)
    cells = np.argwhere(rut)
    info = {"ratio": float("nan"), "cells": 0}
    if len(cells) < min_cells:
        return "last_visit", info
    pts, arc = _wheel_samples(np.asarray(pair.poses, np.float64), robot, dx / 2)
    xs, ys = pair.grid.centers()
    xy = np.stack([xs[cells[:, 0]], ys[cells[:, 1]]], 1)
    s_last = index.s[cells[:, 0], cells[:, 1]]
    hits = cKDTree(pts).query_ball_point(xy, w / 4)
    before = np.fromiter((len(h) > 0 and arc[h].min() < s - gap for h, s in zip(hits, s_last, strict=True)),
                         bool, len(cells))
    info["cells"] = int(before.sum())
    if before.sum() < min_cells:
        return "last_visit", info
    i, j = cells[before].T
    dev = {}
    for name, h in (("front", pair.h_front), ("back", pair.h_back)):
        h = np.asarray(h, np.float64)
        d = (h - smooth_heightmap(h, w / dx))[i, j]
        dev[name] = float(np.nanmedian(d)) if np.isfinite(d).any() else float("nan")
    if not (dev["back"] < -1e-3):
        return "last_visit", info
    info["ratio"] = dev["front"] / dev["back"]
    return ("first_view" if info["ratio"] < 0.25 else "last_visit"), info


def visit_span(pair, index: PathIndex, ground_xy: np.ndarray, s0: float, s1: float, touch: float
               ) -> tuple[float, float]:
    """base_link arc range [m] over which the visit that owns some ground brings a wheel
    within `touch` [m] of it: (G, 2) points [m] owned by arcs in [s0, s1) (PathIndex.s).

    Ground driven again belongs to its last wheel pass, a rear wheel's, whose front wheel went
    over it a wheelbase of travel earlier; on the inside of a tight turn the passes of one
    visit lie farther apart still. Wheels within `visit_gap` of travel of every owner (arcs
    s1 - gap to s0 + gap) are of the owning visit. (inf, -inf) when none came near."""
    gap = visit_gap(pair.robot)
    near = np.flatnonzero((index.arc >= s1 - gap) & (index.arc <= s0 + gap))
    if len(near) == 0 or len(ground_xy) == 0:
        return math.inf, -math.inf
    lo, hi = max(near[0] - 1, 0), min(near[-1] + 2, len(index.arc))
    pts, arc = _wheel_samples(np.asarray(pair.poses[lo:hi], np.float64), pair.robot, pair.dx)
    a = arc[_within(pts, ground_xy, pair.grid, touch)] + index.arc[lo]
    return (float(a.min()), float(a.max())) if len(a) else (math.inf, -math.inf)


def _within(pts: np.ndarray, ground_xy: np.ndarray, grid, reach: float) -> np.ndarray:
    """(M,) bool: the (M, 2) points lie within `reach` [m] of a ground cell ((G, 2) centres of
    cells of `grid`), reach >= one cell.

    The nearest ground cell of a point whose own cell is not ground has a 4-neighbour that is
    not ground either (one step from any other cell towards the point would come closer), so
    only those edge cells are searched; a point on a ground cell is within a cell of it."""
    ij = grid.index(ground_xy)
    lo = ij.min(0) - 1
    mask = np.zeros(tuple(ij.max(0) - lo + 2), bool)
    mask[ij[:, 0] - lo[0], ij[:, 1] - lo[1]] = True
    i, j = (ij - lo).T
    edge = ~(mask[i - 1, j] & mask[i + 1, j] & mask[i, j - 1] & mask[i, j + 1])
    own = grid.index(pts) - lo
    inside = np.all((own >= 0) & (own < mask.shape), axis=1)
    on = np.zeros(len(pts), bool)
    on[inside] = mask[own[inside, 0], own[inside, 1]]
    dist, _ = cKDTree(ground_xy[edge]).query(pts[~on], distance_upper_bound=reach)
    on[~on] = np.isfinite(dist)
    return on


def earlier_poses(pair, before: int, ground_xy: np.ndarray, reach: float) -> list[np.ndarray]:
    """The earlier visits over some ground: runs of the poses before pose `before` that bring
    a wheel within `reach` [m] of any of the (G, 2) ground points, each as its (n, 7) poses
    (one more on each side), in time order."""
    if before <= 0 or len(ground_xy) == 0:
        return []
    poses = np.asarray(pair.poses[:before], np.float64)
    margin = np.hypot(*np.abs(pair.robot.wheels[:, :2]).max(0)) + reach       # base_link to a wheel's reach
    box = np.all((poses[:, 1:3] >= ground_xy.min(0) - margin) & (poses[:, 1:3] <= ground_xy.max(0) + margin), 1)
    near = np.flatnonzero(box)                                                 # only these can reach the ground
    if len(near) == 0:
        return []
    wheels = wheel_positions(poses[near][:, [0, 1, 2, 6]], pair.robot.wheels[:, :2])  # (K, n, 2)
    dist, _ = cKDTree(ground_xy).query(wheels.reshape(-1, 2), distance_upper_bound=reach)
    idx = near[np.isfinite(dist).reshape(wheels.shape[:2]).any(0)]
    if len(idx) == 0:
        return []
    breaks = np.flatnonzero(np.diff(idx) > 1)
    starts, ends = np.r_[idx[0], idx[breaks + 1]], np.r_[idx[breaks], idx[-1]]
    return [np.asarray(pair.poses[max(a - 1, 0):min(b + 2, before + 1)], np.float64)
            for a, b in zip(starts, ends, strict=True)]


def window_cells(index: PathIndex, spec: WindowSpec, est: EstimatorConfig, sim: SimConfig, robot: Robot
                 ) -> tuple[np.ndarray, np.ndarray]:
    """A window's ground, (G, 2) cells (i, j), and those of it near a wheel path (within the
    cost's weight width or the simulator's reach), (C, 2)."""
    on_ground = index.ground(spec.s0, spec.s1, est.corridor)
    near = index.wheel_dist[on_ground[:, 0], on_ground[:, 1]] <= max(est.weight_width * robot.wheel_width,
                                                                     sim_reach(robot, sim))
    return on_ground, on_ground[near]


def prepare_window(pair, index: PathIndex, spec: WindowSpec, est: EstimatorConfig, sim: SimConfig,
                   device=None, dtype=torch.float64, extra_flags: tuple[str, ...] = (),
                   h_start: np.ndarray | None = None, h_back: np.ndarray | None = None,
                   view: str = "last_visit", h_measured: np.ndarray | None = None,
                   poses: np.ndarray | None = None, keep: np.ndarray | None = None) -> WindowData | None:
    """Crop, fill and index one window. Returns None when the window holds no ground at all.

    h_start: (X, Y) surface the simulation starts from (default: pair.h_front). h_back: (X, Y)
    measured surface after the wheels (default: pair.h_back; the estimator passes it net of
    the map offset). view: what H_f holds on revisited ground (`front_view`); with
    "first_view" the earlier visits over the window's ground are part of the window
    (`WindowData.earlier`). h_measured: (X, Y) measured surface before the wheels, as
    recorded (default: pair.h_front). poses: (n, 7) the poses whose wheels the window
    simulates (default: those that pass over the window's ground at its own arc length; an
    earlier visit of the ground passes them). keep: (X, Y) bool cells the costs may count
    (default: all)."""
    robot = pair.robot
    w = robot.wheel_width
    on_ground, cells = window_cells(index, spec, est, sim, robot)               # (G, 2) cells
    if len(cells) == 0:
        return None
    margin = int(np.ceil(0.1 / pair.dx))
    X, Y = index.s.shape
    i0, j0 = np.maximum(cells.min(0) - margin, 0)
    i1, j1 = np.minimum(cells.max(0) + margin + 1, (X, Y))
    crop = (int(i0), int(i1), int(j0), int(j1))
    sl = (slice(i0, i1), slice(j0, j1))
    inside = on_ground[np.all((on_ground >= (i0, j0)) & (on_ground < (i1, j1)), axis=1)]
    ground = np.zeros((i1 - i0, j1 - j0), dtype=bool)
    ground[inside[:, 0] - i0, inside[:, 1] - j0] = True
    grid = pair.grid.crop(*crop)

    reach = np.abs(robot.wheels[:, 0]).max() + w / 2 + 0.1
    xs, ys = pair.grid.centers()
    ground_xy = np.stack([xs[cells[:, 0]], ys[cells[:, 1]]], 1)
    if poses is None:
        a0, a1 = visit_span(pair, index, ground_xy, spec.s0, spec.s1, sim_reach(robot, sim))
        sel = np.flatnonzero((index.arc >= min(spec.s0 - reach, a0)) & (index.arc <= max(spec.s1 + reach, a1)))
        if len(sel) == 0:   # poses sparser than the window (sweeps dropped): the nearest on either side
            k = int(np.searchsorted(index.arc, spec.s0))
            sel = np.array([max(k - 1, 0), min(k, len(index.arc) - 1)])
        first, last = sel[[0, -1]]
        poses = pair.poses[max(first - 1, 0):last + 2]
    else:
        first = int(np.searchsorted(pair.poses[:, 0], poses[0, 0]))
    gkw = dict(pose_spacing=sim.pose_spacing, band_width=sim.band_width, relax_margin=sim.relax_margin,
               device=device, dtype=dtype)
    geom = wheel_geometry(grid, poses, robot, **gkw)
    earlier: tuple[WheelGeometry, ...] = ()
    if view == "first_view":
        runs = earlier_poses(pair, max(first - 1, 0), ground_xy, sim_reach(robot, sim))
        earlier = tuple(wheel_geometry(grid, p, robot, **gkw) for p in runs if len(p) >= 2)

    hf = np.asarray((pair.h_front if h_start is None else h_start)[sl], dtype=np.float64)
    raw = np.asarray((pair.h_front if h_measured is None else h_measured)[sl], dtype=np.float64)
    hb = np.asarray((pair.h_back if h_back is None else h_back)[sl], dtype=np.float64)
    measured_f = np.isfinite(hf)
    flags = list(extra_flags)
    if not measured_f.any():
        return None
    if not measured_f.all():  # gaps: nearest measured value (kept out of the cost)
        idx = ndimage.distance_transform_edt(~measured_f, return_distances=False, return_indices=True)
        hf = hf[tuple(idx)]
    zone = ground & (index.wheel_dist[sl] <= est.weight_width * w)
    measured = np.isfinite(raw) & np.isfinite(hb) & (True if keep is None else keep[sl])
    weight = zone & measured
    floor = (ground & measured & (index.wheel_dist[sl] >= est.floor_inner * w)
             & (index.wheel_dist[sl] <= est.floor_outer * w))
    foot = zone & (index.wheel_dist[sl] <= w / 2)       # the ruts themselves, which d is fitted to
    if (weight.sum() < est.min_valid_fraction * max(zone.sum(), 1)
            or (weight & foot).sum() < est.min_valid_fraction * max(foot.sum(), 1)):
        flags.append("few_valid")
    in_window = pair.poses[(index.arc >= spec.s0) & (index.arc <= spec.s1)]
    if _stopped(in_window, est.stop_speed, est.stop_time):
        flags.append("stopped")
    c = spec.centre
    kw = dict(device=device, dtype=dtype)
    h_front = torch.as_tensor(hf, **kw)[None]
    return WindowData(
        spec=spec, crop=crop, grid=grid, geom=geom, h_front=h_front,
        h_ref=reference_height(h_front, sim.ref_radius * w / 2, pair.dx),
        h_back=torch.as_tensor(np.where(np.isfinite(hb), hb, 0.0), **kw),
        h_measured=torch.as_tensor(np.where(np.isfinite(raw), raw, 0.0), **kw),
        weight=torch.as_tensor(weight, **kw), floor=torch.as_tensor(floor, device=device),
        ground=torch.as_tensor(ground, device=device),
        t=float(np.interp(c, index.arc, pair.poses[:, 0])),
        x=float(np.interp(c, index.arc, pair.poses[:, 1])),
        y=float(np.interp(c, index.arc, pair.poses[:, 2])),
        flags=tuple(flags),
        earlier=earlier,
    )
