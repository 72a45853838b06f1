"""Online soil-parameter estimation along a drive (paper section IV-C).

`Estimator(pair, settings.estimator, settings.sim)` cuts the drive into windows, fits (d_1..d_T, chi, beta) in each one
from the measured H_f (never from an earlier window's simulation), warm-started from the
previous window, and scores the fit on the window itself (residual) and one window length
ahead, on ground it did not see (prediction).
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from typing import NamedTuple

import numpy as np
import torch
from scipy import ndimage

from torchsoil.estimate.cost import raster_blur, weighted_l1
from torchsoil.estimate.nuisance import MapNuisance, fit_map_nuisance
from torchsoil.estimate.optimizer import FitResult, fit
from torchsoil.estimate.visits import (
    passes_before,
    rut_depth,
    track_heading,
    visit_counts,
    visit_poses,
    visit_stretches,
    wheel_passes,
)
from torchsoil.estimate.windows import (
    WindowData,
    WindowSpec,
    WindowStore,
    drive_windows,
    front_view,
    path_index,
    prepare_window,
    sim_reach,
    smooth_along,
    smooth_heightmap,
    window_cells,
)
from torchsoil.memory import release
from torchsoil.settings import EstimatorConfig, SimConfig
from torchsoil.sim import ParamSpec, simulate
from torchsoil.sim.sinkage import revisit_reference


def pick_device(name: str = "auto") -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def kind(name: str) -> str:
    """The kind of a parameter for per-kind settings: "d" for the sinkages d1..dT, else its name."""
    return "d" if name[:1] == "d" and name[1:].isdigit() else name


class WindowOutput(NamedTuple):
    """row: the params.csv row (metres, beta in degrees); reference: deformation signal and
    noise floor of the window, m; data: the window; h_sim: (X, Y) simulated H_b on the crop at
    the fitted parameters (None when the window was skipped); fit: optimizer result; final:
    the window's last visit (its only one unless fitted per visit)."""

    row: dict
    reference: dict
    data: WindowData | None
    h_sim: torch.Tensor | None
    fit: FitResult | None
    final: bool = True


class Estimator:
    """Sliding-window estimator over one terrain pair (an object with grid, robot, poses,
    h_front, h_back, dx; see torchsoil.io.terrain_pair.TerrainPair).

    Args:
        pair: the terrain pair.
        est: estimator settings (settings section `estimator`).
        sim: simulator settings (section `sim`).
        device: torch device (default: est.device).
        modifiers: optional callable (WindowData, theta (B, P), geometry) -> sim.Modifiers: a
            model extension with fixed parameters (e.g. a sinkage factor per pose from the
            window's speed), applied in every simulation of that window, fit and prediction
            alike; geometry is the visit simulated (the window's own, or an earlier one).
        index: the pair's windows.PathIndex for these settings, when already computed (it
            depends on the poses, robot and corridor only; repeated runs over one pair share it).
        nuisance: the pair's fitted map offset (`nuisance.MapNuisance`), when already computed
            (default: fitted here when est.nuisance.offset).
        arc0: arc length [m] of the pair's first pose along a longer drive (a stretch cut out of
            it): windows sit where the whole drive's would, and rows report the drive's arc length.
        view: what H_f holds on revisited ground ("last_visit" or "first_view"), when already
            told (default: est.front_view, "auto" told from the maps by `windows.front_view`).
        store: a `windows.WindowStore` that keeps prepared windows for later runs over the same
            pair and map nuisance (a diagnosis's passes share one); None: prepared per run.
        surfaces: (h_start, h_back) (X, Y) float64 [m] of an earlier estimator over the same pair,
            map nuisance and settings (`self.surfaces`), so that the passes of a diagnosis share
            them rather than each holding its own (default: made here).
        per_visit: on a pair with visit layers (docs/formats.md v1.1), fit each visit of a window's
            ground on its own before and after maps (`visit_front[v]` -> `visit_back[v]`) with
            the wheels of that visit, one row per visit (`visit`, `passes_before`); without
            visit layers, or False: one fit per window over everything that happened to it.

    H_b is used net of the map offset and tilt (`self.nuisance`, fitted on untouched ground;
    `self.h_back`); each row reports the offset removed on the window's ground (`map_offset`, m).

    The optimizer's variables are named (`free_names`): the simulator's parameters
    (`spec.names`, d1..dT, chi, beta), or with `est.merged_sinkage` one sinkage `d` shared
    by all tracks. Settings given per kind of parameter (scale, lr, fd_step, init) are looked
    up by `kind(name)`.
    """

    def __init__(self, pair, est: EstimatorConfig | None = None, sim: SimConfig | None = None, device=None,
                 dtype=torch.float64, modifiers=None, index=None, nuisance: MapNuisance | None = None,
                 arc0: float = 0.0, view: str | None = None, store: WindowStore | None = None,
                 surfaces: tuple[np.ndarray, np.ndarray] | None = None,
                 per_visit: bool = False):
        self.pair = pair
        self.modifiers = modifiers
        self.est = est = est or EstimatorConfig()
        self.sim = sim or SimConfig()
        self.device = torch.device(device) if device is not None else pick_device(est.device)
        self.dtype = dtype
        robot = pair.robot
        self.spec = ParamSpec.base(robot.n_tracks)
        reach = max(est.corridor / 2, est.floor_outer * robot.wheel_width + np.abs(
            robot.wheels[:, 1]).max()) + robot.wheel_width
        # revisited ground belongs to the last pass that could change it: whose wheels came within
        # the simulator's reach (the footprint and the relaxation margin beside it)
        touch = sim_reach(robot, self.sim)
        self.index = path_index(pair.grid, pair.poses, robot, reach, touch) if index is None else index
        self.nuisance = nuisance if nuisance is not None else fit_map_nuisance(
            np.asarray(pair.h_front), np.asarray(pair.h_back), pair.grid, self.index, robot.wheel_width,
            est.floor_inner, est.corridor, est.nuisance)
        self.per_visit = per_visit and getattr(pair, "visit_front", None) is not None
        view = "last_visit" if self.per_visit else view or est.front_view   # per visit: each from its own H_f
        self.view, self.view_info = (front_view(pair, self.index) if view == "auto" else (view, {}))
        if surfaces is None:
            h_back = np.asarray(pair.h_back, np.float64)
            h_start = smooth_heightmap(np.asarray(pair.h_front, np.float64), float(est.front_smoothing))
            surfaces = (h_start, h_back - np.asarray(self.nuisance.field) if self.nuisance is not None else h_back)
            release()                  # the whole-grid temporaries of the index, nuisance and smoothing
        self.surfaces = surfaces
        self.h_start, self.h_back = surfaces
        self.arc0 = arc0
        self.store = store
        # what a prepared window depends on besides its span, the pair and the map nuisance (not the
        # blur the simulated change is seen through)
        self._context = (getattr(pair, "wheel_flat_fraction", None), getattr(pair, "wheel_section_exponent", None),
                         est.model_dump_json(exclude={"after_blur"}), self.sim.model_dump_json(), self.view,
                         str(self.device), str(dtype),
                         arc0)
        self.windows: list[WindowSpec] = drive_windows(float(self.index.arc[-1]), est.window, est.stride, arc0)
        ratio = est.window / est.stride
        self.ahead = int(round(ratio)) if abs(ratio - round(ratio)) < 1e-6 else None
        self.names = self.spec.names
        self.free_names = tuple(dict.fromkeys(self._free_name(n) for n in self.names))
        # column of each simulator parameter among the optimizer's variables
        self.expand = [self.free_names.index(self._free_name(n)) for n in self.names]
        self._expand = (None if self.expand == list(range(len(self.names)))
                        else torch.tensor(self.expand, device=self.device))
        kw = dict(device=self.device, dtype=dtype)
        lo, hi = self.spec.bounds(torch.zeros(1, **kw))
        first = [self.expand.index(i) for i in range(len(self.free_names))]  # a parameter per variable
        self.lower, self.upper = lo[first], hi[first]
        kinds = [kind(n) for n in self.free_names]
        self.scale = torch.tensor([getattr(est.scale, k) for k in kinds], **kw)
        self.lr = torch.tensor([getattr(est.lr, k) for k in kinds], **kw)
        self.fd_step = torch.tensor([getattr(est.fd_step, k) for k in kinds], **kw)
        init = {"d": est.init.d, "chi": est.init.chi, "beta": math.radians(est.init.beta_deg)}
        self.theta0 = torch.tensor([init[k] for k in kinds], **kw)
        self._cache: dict[int, WindowData | None] = {}
        if self.per_visit:
            self._visit_setup()

    def _visit_setup(self) -> None:
        """Per-visit maps over the whole grid: the surfaces each visit starts from and ends on
        (net of the map offset), visits and wheel passes before each visit per cell. A visit
        starts from its H_f smoothed (estimator.front_smoothing) on fresh ground. Within a wheel
        width of the cells earlier wheel passes went over, where H_f shows the ground the visit
        before left, that ground is the mean of its two views (H_f of the visit and H_b of the
        one before, net of the map offset), smoothed as much but only along the track that dug
        it (`smooth_along`, the heading of base_link when it last passed the cell): round
        smoothing would fill the ruts the robot made (a relief of the wheel's own width, with
        the walls and berms beside it) and raise the ground the wheels dig from, and left
        noisy, the start biases the fit (a wheel's cut replaces noise by its own floor, so
        digging deeper always looks closer to the next map). Nor do the ruts enter the
        smoothing of the ground beyond."""
        pair, sigma = self.pair, float(self.est.front_smoothing)
        off = 0.0 if self.nuisance is None else np.asarray(self.nuisance.field)
        self.visits_per_cell = visit_counts(pair.visit_time)
        self.passes = wheel_passes(pair.poses, pair.wheels, pair.wheel_width, pair.grid, pair.visit_time)
        self.passes_before = passes_before(self.passes)
        prior = pair.extras.get("passes_prior")        # a field's earlier sessions (torchsoil.field)
        if prior is not None:
            self.passes_before = self.passes_before + np.asarray(prior, np.int64)[None]
        self.visit_start = []
        r = int(math.ceil(pair.wheel_width / pair.dx))
        near = np.hypot(*np.mgrid[-r:r + 1, -r:r + 1]) <= r
        yaw = np.unwrap(pair.poses[:, 6])
        for v, (dug, h) in enumerate(zip(self.passes_before > 0, pair.visit_front, strict=True)):
            h = np.asarray(h, np.float64)
            dug = ndimage.binary_dilation(dug, near) if dug.any() else dug
            start = np.where(dug, h, smooth_heightmap(np.where(dug, np.nan, h), sigma))
            if dug.any():
                seen = h
                if v > 0:       # the ground between the visits, seen again as the last one ended
                    before = np.asarray(pair.visit_back[v - 1], np.float64) - off
                    seen = np.where(np.isfinite(h) & np.isfinite(before), (h + before) / 2, np.fmax(h, before))
                heading = track_heading(pair.visit_time[:v], pair.poses[:, 0], yaw)
                along = smooth_along(np.where(dug, seen, np.nan), heading, sigma)
                start = np.where(dug, along, start)
            self.visit_start.append(start)
        self.visit_back = [np.asarray(h, np.float64) - off for h in pair.visit_back]
        self._visit_cache: dict[int, dict[int, WindowData | None]] = {}

    def _free_name(self, name: str) -> str:
        return "d" if self.est.merged_sinkage and kind(name) == "d" else name

    # ------------------------------------------------------------------ helpers
    def window_of(self, s: float) -> int:
        """Index of the window centred at arc length s [m] (a params.csv row's s)."""
        return int(np.argmin([abs(w.centre + self.arc0 - float(s)) for w in self.windows]))

    def full_theta(self, free: torch.Tensor) -> torch.Tensor:
        """(B, P_free) optimizer variables -> (B, P) simulator parameters."""
        return free if self._expand is None else free.index_select(1, self._expand)

    def forget_before(self, k: int) -> None:
        """Let go of the prepared data of the windows before window k (`data`, `visit_data`):
        windows are taken in order, and a long drive's would not fit in memory."""
        cache = self._visit_cache if self.per_visit else self._cache
        for old in [i for i in cache if i < k]:
            del cache[old]

    def data(self, k: int) -> WindowData | None:
        if k not in self._cache:
            spec = self.windows[k]
            self._cache[k] = self._prepare(spec)
        return self._cache[k]

    def simulate(self, free: torch.Tensor, wd: WindowData):
        """Simulate window wd for optimizer variables free (B, P_free): its earlier visits in
        turn (`WindowData.earlier`), each settled and digging from the surface it finds (as
        the recorder's world does), then its own; the result is that of its own visit, its change
        from H_f seen through the raster's blur (estimator.after_blur, `cost.raster_blur`)."""
        theta = self.full_theta(free)
        h, h_ref, again = wd.h_front, wd.h_ref, None
        for g in wd.earlier:
            h = simulate(h, g, theta, self.sim, self.spec, modifiers=self._modifiers(wd, theta, g), h_ref=h_ref).h
            again = g.domain if again is None else again | g.domain
            h_ref = revisit_reference(h, wd.h_ref, again, self.sim.revisit_ref, self.sim.ref_radius, g.radius, g.dx)
        r = simulate(h, wd.geom, theta, self.sim, self.spec, modifiers=self._modifiers(wd, theta, wd.geom),
                     h_ref=h_ref)
        blur = float(self.est.after_blur)
        return r if blur <= 0 else r._replace(h=wd.h_front + raster_blur(r.h - wd.h_front, blur))

    def _modifiers(self, wd: WindowData, theta: torch.Tensor, geom):
        return self.modifiers(wd, theta, geom) if self.modifiers is not None else None

    def objective(self, wd: WindowData):
        def cost(free: torch.Tensor) -> torch.Tensor:
            return weighted_l1(self.simulate(free, wd).h, wd.h_back, wd.weight)

        return cost

    def fit_window(self, wd: WindowData, theta0: torch.Tensor) -> FitResult:
        e = self.est
        return fit(self.objective(wd), theta0, self.lower, self.upper, scale=self.scale, rule=e.optimizer,
                   step=e.step, lr=self.lr, max_iter=e.max_iter, step_tol=e.step_tol,
                   grad=e.grad, fd_step=self.fd_step)

    def predict(self, free: torch.Tensor, wd: WindowData) -> tuple[torch.Tensor, float]:
        """Simulated H_b (X, Y) and cost of parameters `free` on window data wd."""
        with torch.no_grad():
            r = self.simulate(free[None], wd)
            return r.h[0], float(weighted_l1(r.h, wd.h_back, wd.weight)[0])

    # --------------------------------------------------------------------- run
    def run(self, start: int = 0, theta: torch.Tensor | dict | None = None, stop: int | None = None,
            skip: set | None = None) -> Iterator[WindowOutput]:
        """Fit windows start, start+1, ... (up to stop, excluded) in order, yielding each as soon
        as it is done; per visit, each visit of a window in turn (visit 0 first).

        theta: warm start (P_free,) (default: config estimator.init), or one per visit
        {visit: (P_free,)} (each visit's fits warm-start from the same visit's previous window;
        key None: the warm start of the visits without one, default config estimator.init).
        skip: (s, visit) keys (s rounded to 1e-6 m) of rows not to fit again (a resumed run).
        """
        thetas = dict(theta) if isinstance(theta, dict) else {None: theta}
        first = thetas.pop(None, None)
        theta0 = self.theta0.clone() if first is None else first.to(self.theta0)
        thetas = {v: t.to(self.theta0) for v, t in thetas.items()}
        skip = skip or set()
        for k in range(start, len(self.windows) if stop is None else min(stop, len(self.windows))):
            t0 = time.perf_counter()       # a window's seconds include preparing its data
            spec = self.windows[k]
            self.forget_before(k)
            if self.per_visit:
                visits = self.visit_data(k)
                ahead = self.visit_data(k + self.ahead) if self.ahead and k + self.ahead < len(self.windows) else {}
            else:
                visits = {0: self.data(k)}
                ahead = {0: self._ahead_data(k)}
            for v, wd in (visits or {0: None}).items():
                if (round(spec.centre + self.arc0, 6), v) in skip:
                    continue
                o = self._fit_one(spec, wd, ahead.get(v), thetas.get(v, theta0), v, t0)
                if o.fit is not None:
                    thetas[v] = o.fit.theta
                yield o._replace(final=v == max(visits or {0: None}))
                t0 = time.perf_counter()

    def _fit_one(self, spec: WindowSpec, wd: WindowData | None, ahead: WindowData | None, theta: torch.Tensor,
                 visit: int, t0: float) -> WindowOutput:
        """Fit one visit of a window (its only one without visit layers), warm-started at theta;
        t0: perf_counter time at which its work began."""
        reference = {"signal": math.nan, "floor": math.nan}
        if wd is None or "few_valid" in wd.flags:
            flags = (self._no_ground(spec),) if wd is None else wd.flags
            return WindowOutput(self._row(spec, wd, None, math.nan, math.nan, 0, time.perf_counter() - t0,
                                          flags, visit), reference, wd, None, None)
        res = self.fit_window(wd, theta)
        theta = res.theta
        h_sim, residual = self.predict(theta, wd)
        prediction = math.nan
        if ahead is not None and "few_valid" not in ahead.flags:
            prediction = self.predict(theta, ahead)[1]
        with torch.no_grad():
            reference["signal"] = float(weighted_l1(wd.h_measured, wd.h_back, wd.weight))
            reference["floor"] = float(weighted_l1(wd.h_measured, wd.h_back, wd.floor.to(self.dtype)))
        flags = list(wd.flags) + ([] if res.converged else ["not_converged"])
        row = self._row(spec, wd, theta, residual, prediction, res.iterations, time.perf_counter() - t0,
                        tuple(flags), visit)
        return WindowOutput(row, reference, wd, h_sim, res)

    def _no_ground(self, spec: WindowSpec) -> str:
        """Why window `spec` holds no ground: "driven_again" where the cells under its stretch
        of the path belong to a later stretch (the drive came back over them: their window
        there fits every visit of that ground, on a pair with visit layers this window's as
        its visit 0), else "empty"."""
        arc = self.index.arc
        on = (arc >= spec.s0) & (arc < spec.s1)
        ij = self.pair.grid.index(self.pair.poses[on, 1:3]) if on.any() else np.zeros((0, 2), np.int64)
        X, Y = self.index.s.shape
        ij = ij[(ij[:, 0] >= 0) & (ij[:, 0] < X) & (ij[:, 1] >= 0) & (ij[:, 1] < Y)]
        later = self.index.s[ij[:, 0], ij[:, 1]] >= spec.s1
        return "driven_again" if later.any() else "empty"

    # ------------------------------------------------------------------ visits
    def visit_data(self, k: int) -> dict[int, WindowData | None]:
        """The visits of window k's ground, visit -> its WindowData (per_visit only).

        A window's visits are those of its cells driven most often, each visit the stretch of
        the drive that passed most of them (`visits.visit_stretches`): cells with another number
        of visits, or whose v-th visit was another stretch (ground at the edge of a neighbouring
        row's reach, visited by it but no wheel of it), stay out of its costs, so that visit v
        means one stretch of the drive for every cell counted. The visit nearest the window's
        own time uses the window's poses, as without visits; each other visit uses the poses of
        its stretch of the drive, told by the cells' `visit_time`. Empty when the window holds
        no ground."""
        if k in self._visit_cache:
            return self._visit_cache[k]
        spec, pair = self.windows[k], self.pair
        _, cells = window_cells(self.index, spec, self.est, self.sim, pair.robot)
        out: dict[int, WindowData | None] = {}
        if len(cells):
            n = self.visits_per_cell[cells[:, 0], cells[:, 1]]
            m = int(np.argmax(np.bincount(n, minlength=2)[1:])) + 1 if (n > 0).any() else 1
            reach = np.abs(pair.robot.wheels[:, 0]).max() + pair.wheel_width / 2 + 0.1
            mine = cells[n == m] if (n == m).any() else cells
            (i0, j0), (i1, j1) = cells.min(0), cells.max(0) + 1          # the costs count cells of the window only
            arc = np.interp(pair.visit_time[:m, i0:i1, j0:j1], pair.poses[:, 0], self.index.arc)   # m, NaN: none
            spans = visit_stretches(arc[:, mine[:, 0] - i0, mine[:, 1] - j0], reach)[:, :, None, None]
            keep = np.zeros(self.visits_per_cell.shape, bool)
            keep[i0:i1, j0:j1] = (self.visits_per_cell[i0:i1, j0:j1] == m) & np.all(
                (arc >= spans[:, 0]) & (arc <= spans[:, 1]), 0)
            mine = mine[keep[mine[:, 0], mine[:, 1]]]
            times = pair.visit_time[:, mine[:, 0], mine[:, 1]]                         # (V, G)
            t_own = float(np.interp(spec.centre, self.index.arc, pair.poses[:, 0]))
            t_med = [float(np.nanmedian(times[v])) if np.isfinite(times[v]).any() else math.inf for v in range(m)]
            own = int(np.argmin([abs(t - t_own) for t in t_med]))
            for v in range(m):
                if not math.isfinite(t_med[v]):
                    continue
                poses = None if v == own else visit_poses(pair.poses, self.index.arc,
                                                          times[v][np.isfinite(times[v])], reach)
                wd = prepare_window(pair, self.index, spec, self.est, self.sim, self.device, self.dtype,
                                    extra_flags=self._registration_flags(spec), h_start=self.visit_start[v],
                                    h_back=self.visit_back[v], h_measured=pair.visit_front[v], poses=poses,
                                    keep=keep)
                if wd is not None:
                    wd = self._dug_reference(wd, v)
                out[v] = wd if wd is None or v == own else wd._replace(t=t_med[v])
        self._visit_cache[k] = out
        return out

    def _dug_reference(self, wd: WindowData, visit: int) -> WindowData:
        """wd with its reference height on the cells earlier wheel passes went over before visit
        `visit` (`passes_before`) taken as a wheel coming back finds it (sim.revisit_ref)."""
        i0, i1, j0, j1 = wd.crop
        dug = torch.as_tensor(self.passes_before[visit, i0:i1, j0:j1] > 0, device=wd.h_ref.device)
        if not bool(dug.any()):
            return wd
        ref = revisit_reference(wd.h_front, wd.h_ref, dug, self.sim.revisit_ref, self.sim.ref_radius,
                                wd.geom.radius, wd.geom.dx)
        return wd._replace(h_ref=ref)

    def _passes_before(self, wd: WindowData | None, visit: int) -> float:
        """Wheel passes the window's ruts (its ground within a quarter wheel width of a wheel
        path, with that visit) had had before visit `visit`: their median (0 without visit
        layers or ruts)."""
        if not self.per_visit or wd is None:
            return 0
        i0, i1, j0, j1 = wd.crop
        ruts = (wd.ground.cpu().numpy() & (self.index.wheel_dist[i0:i1, j0:j1] <= self.pair.wheel_width / 4)
                & np.isfinite(self.pair.visit_time[visit, i0:i1, j0:j1]))
        return float(np.median(self.passes_before[visit, i0:i1, j0:j1][ruts])) if ruts.any() else 0

    def _ruts(self, wd: WindowData | None) -> np.ndarray | None:
        """(X, Y) bool rut centres of the window's crop (counted cells within a quarter wheel
        width of a wheel path), None when there are none."""
        if wd is None:
            return None
        i0, i1, j0, j1 = wd.crop
        ruts = (wd.weight.cpu().numpy() > 0) & (self.index.wheel_dist[i0:i1, j0:j1] <= self.pair.wheel_width / 4)
        return ruts if ruts.any() else None

    def _ahead_data(self, k: int) -> WindowData | None:
        if self.ahead is not None:
            return self.data(k + self.ahead) if k + self.ahead < len(self.windows) else None
        spec = self.windows[k]
        if spec.s1 + self.est.window > self.index.arc[-1]:
            return None
        return self._prepare(WindowSpec(-1, spec.s1, spec.s1 + self.est.window))

    def _prepare(self, spec: WindowSpec) -> WindowData | None:
        def prepare():
            return prepare_window(self.pair, self.index, spec, self.est, self.sim, self.device, self.dtype,
                                  h_start=self.h_start, h_back=self.h_back,
                                  extra_flags=self._registration_flags(spec), view=self.view)

        if self.store is None:
            return prepare()
        return self.store.get((self._context, spec.s0, spec.s1), prepare)

    def _registration_flags(self, spec: WindowSpec) -> tuple[str, ...]:
        """("registration",) when a sweep the lidar pipeline flagged was taken while the robot
        was over this window (extras scan_stamps, scan_flags of a pipeline terrain pair)."""
        extras = getattr(self.pair, "extras", {})
        if "scan_flags" not in extras or "scan_stamps" not in extras:
            return ()
        reach = np.abs(self.pair.wheels[:, 0]).max() + self.pair.wheel_width
        t0, t1 = np.interp([spec.s0 - reach, spec.s1 + reach], self.index.arc, self.pair.poses[:, 0])
        stamps, flags = extras["scan_stamps"], extras["scan_flags"]
        from torchsoil.pipeline.mapping import PROBLEMS

        bad = (np.asarray(flags, np.int64) & PROBLEMS) != 0
        return ("registration",) if np.any(bad & (stamps >= t0) & (stamps <= t1)) else ()

    def _row(self, spec, wd, free, residual, prediction, iterations, seconds, flags, visit: int = 0) -> dict:
        row = {"s": spec.centre + self.arc0, "visit": visit, "passes_before": self._passes_before(wd, visit),
               "t": wd.t if wd else math.nan, "x": wd.x if wd else math.nan, "y": wd.y if wd else math.nan}
        full = self.full_theta(free[None])[0].tolist() if free is not None else [math.nan] * len(self.names)
        for name, unit, value in zip(self.names, self.spec.units, full, strict=True):
            row[name] = math.degrees(value) if unit == "rad" else value
        row["map_offset"] = self._offset_on(wd)
        ruts = self._ruts(wd)
        row["rut_depth"] = math.nan if ruts is None else rut_depth(wd.h_measured.cpu().numpy(),
                                                                    wd.h_back.cpu().numpy(), ruts)
        row.update(residual=residual, prediction=prediction, iterations=iterations, seconds=seconds,
                   flags="|".join(flags))
        return row

    def _offset_on(self, wd: WindowData | None) -> float:
        """Mean map offset removed from H_b on the window's weighted cells, m (0: none fitted)."""
        if self.nuisance is None:
            return 0.0
        if wd is None:
            return math.nan
        i0, i1, j0, j1 = wd.crop
        w = wd.weight.cpu().numpy() > 0
        return float(self.nuisance.field[i0:i1, j0:j1][w].mean()) if w.any() else math.nan

    def free_from_row(self, row: dict) -> torch.Tensor | None:
        """Warm start from a params.csv row (None when the row holds no fit)."""
        full = [float(row[n]) for n in self.names]
        if any(math.isnan(v) for v in full):
            return None
        full = [math.radians(v) if unit == "rad" else v for v, unit in zip(full, self.spec.units, strict=True)]
        return torch.tensor([full[self.expand.index(i)] for i in range(len(self.free_names))],
                            device=self.device, dtype=self.dtype)


class Stitcher:
    """Simulated H_b over the whole grid: each cell from the window whose centre is nearest."""

    def __init__(self, shape, s_index: np.ndarray, h_sim: np.ndarray | None = None):
        self.h_sim = np.full(shape, np.nan, np.float32) if h_sim is None else h_sim.astype(np.float32)
        self.best = np.full(shape, np.inf)
        if h_sim is not None:
            self.best[np.isfinite(h_sim)] = 0.0  # cells restored from a previous run stay
        self.s = s_index

    def add(self, wd: WindowData, h_sim: torch.Tensor) -> None:
        i0, i1, j0, j1 = wd.crop
        dist = np.abs(self.s[i0:i1, j0:j1] - wd.spec.centre)
        take = wd.ground.cpu().numpy() & (dist < self.best[i0:i1, j0:j1])
        self.best[i0:i1, j0:j1][take] = dist[take]
        self.h_sim[i0:i1, j0:j1][take] = h_sim.detach().cpu().numpy()[take]
