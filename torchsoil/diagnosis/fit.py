"""Fitting a catalogue extension and comparing held-out prediction costs pairwise.

A pass runs the sliding-window estimator over the whole drive with the extension's
coefficient held fixed (the per-window base parameters are fitted as usual) and records each
window's residual and its prediction cost on the next window's ground. The coefficient is
chosen by two-fold cross-validation over blocks of windows: each block is scored with the
coefficient that predicted best on the other fold (0, the base model, is always a choice),
so the extra parameter pays for itself only if it predicts ground it was not chosen on.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import time
from dataclasses import dataclass

import numpy as np
import torch
from scipy import stats

from torchsoil.diagnosis.catalogue import Extension, ExtensionModel, PassCounts, effect_size
from torchsoil.diagnosis.checkpoint import PassCache, kept, portable
from torchsoil.diagnosis.covariates import DriveSignals
from torchsoil.diagnosis.locate import Profiles
from torchsoil.diagnosis.stats import by_fold, finite_mean, fold_choice, folds, paired_z, term_test
from torchsoil.estimate.estimator import Estimator, Stitcher
from torchsoil.estimate.windows import WindowData, WindowStore
from torchsoil.memory import release
from torchsoil.settings import EstimatorConfig, SimConfig
from torchsoil.sim.geometry import footprint


@dataclass
class Pass:
    """One estimator pass: rows (params.csv rows), residual and prediction (W,) costs [m],
    floor (W,) noise floor [m], profiles (or None), k the coefficient (0: base model).

    prediction: cost of each window's fit on the next window's ground (the estimator's);
    backward: (W, O) its cost on the ground of the windows `offsets` strides back (also not
    used to fit it); held_out: (W,) mean of all of them, the per-window held-out cost. Far
    offsets carry a fit across changes of a covariate, where a missing term shows. index: the
    windows.PathIndex the pass used (shared by the passes of one diagnosis); nuisance: the map
    offset it removed from H_b (nuisance.MapNuisance or None; shared likewise); view: what
    H_f holds on revisited ground (Estimator.view; shared likewise); store: the prepared
    windows (windows.WindowStore; shared likewise). h_sim: (X, Y) simulated H_b over the
    drive, each cell from the window whose centre is nearest (estimator.Stitcher), m, when
    the pass was asked to stitch it."""

    k: float
    rows: list[dict]
    residual: np.ndarray
    prediction: np.ndarray
    floor: np.ndarray
    profiles: Profiles | None = None
    backward: np.ndarray | None = None
    index: object = None
    nuisance: object = None
    view: str | None = None
    store: object = None
    surfaces: object = None
    h_sim: np.ndarray | None = None

    @property
    def held_out(self) -> np.ndarray:
        if self.backward is None:
            return self.prediction
        both = np.vstack([self.prediction[None], self.backward.T])
        n = np.isfinite(both).sum(0)
        total = np.where(np.isfinite(both), both, 0.0).sum(0)
        return np.where(n > 0, total / np.maximum(n, 1), np.nan)


def shared_of(done) -> dict:
    """run_pass's keywords for later passes over the same pair (index, nuisance, view, store,
    surfaces), from an Estimator or a Pass."""
    return {"index": done.index, "nuisance": done.nuisance, "view": done.view, "store": done.store,
            "surfaces": done.surfaces}


def run_pass(pair, est: EstimatorConfig, sim: SimConfig, model: ExtensionModel | None = None,
             profiles: bool = False,
             theta0: torch.Tensor | None = None, on_window=None, offsets: tuple[int, ...] = (2, 4, 6),
             index=None, nuisance=None, view: str | None = None, store: WindowStore | None = None,
             stitch: bool = False, cache: PassCache | None = None, surfaces=None) -> Pass:
    """Run the estimator once over the drive; collect costs (and profiles when asked).

    on_window: optional callable(k, WindowOutput, estimator) called after every window.
    offsets: windows back (in strides) on whose ground each fit is also scored; use
    multiples of window / stride so that the ground does not overlap the fit's. index: the
    pair's PathIndex from an earlier pass with the same config (Pass.index), to skip
    recomputing it; nuisance, view, store and surfaces likewise (Pass.nuisance, Pass.view,
    Pass.store, Pass.surfaces; a new store when None). stitch: also keep the simulated H_b
    over the drive (Pass.h_sim). cache: where finished passes are kept (checkpoint.PassCache):
    a pass found there is read back (on_window is then not called), a new one is saved, and a
    pass in progress is kept as it goes (`Partial`) and resumed from its last kept window."""
    estimator = Estimator(pair, est, sim, modifiers=model.modifiers if model is not None else None, index=index,
                          nuisance=nuisance, view=view, store=store if store is not None else WindowStore(),
                          surfaces=surfaces)
    shared = shared_of(estimator)
    label = "base" if model is None else model.ext.id
    what = (None if model is None else model.k, section_of(pair), sim.dig_order, tuple(offsets), profiles, stitch,
            None if theta0 is None else tuple(np.asarray(theta0.cpu(), np.float64).round(12).tolist()))
    done = cache.load(label, what) if cache is not None else None
    if done is not None:
        return dataclasses.replace(done, **shared)
    stitcher = Stitcher(pair.h_front.shape, estimator.index.s) if stitch else None
    prof = None
    if profiles:
        r = pair.robot.wheel_width / 2
        prof = Profiles.empty(r, pair.dx, est.weight_width * pair.robot.wheel_width, floor=model is None)
    stride = est.stride
    rows, floor, backward = [], [], []
    wheels_y = pair.robot.wheels[:, 1]
    recent: dict[int, object] = {}
    part = Partial(cache, label, what)
    start, thetas = 0, theta0
    if part.state is not None:        # an interrupted pass: on from its last finished window
        start, thetas, rows, floor, backward, prof, sim_state, recent = part.restore(estimator, theta0)
        if stitcher is not None:
            stitcher.h_sim, stitcher.best = sim_state
    for k, o in enumerate(estimator.run(start=start, theta=thetas), start=len(rows)):
        rows.append(o.row)
        floor.append(o.reference["floor"])
        recent[k] = o.data
        recent.pop(k - max(offsets, default=0) - 1, None)
        costs = []
        for off in offsets:
            back = recent.get(k - off)
            ok = o.fit is not None and back is not None and "few_valid" not in back.flags
            costs.append(estimator.predict(o.fit.theta, back)[1] if ok else np.nan)
        backward.append(costs)
        if stitcher is not None and o.h_sim is not None:
            stitcher.add(o.data, o.h_sim)
        if prof is not None and o.h_sim is not None:
            i0, i1, j0, j1 = o.data.crop
            c = o.row["s"]
            idx = estimator.index
            prof.add(o.data, o.h_sim, idx.s[i0:i1, j0:j1], c - stride / 2, c + stride / 2, wheels_y,
                     (idx.offset[i0:i1, j0:j1], idx.wheel_dist[i0:i1, j0:j1]))
        if on_window is not None:
            on_window(k, o, estimator)
        part.fitted(o)
        if o.final:
            part.window_done(rows, floor, backward, prof, stitcher, recent)
    res = np.array([r["residual"] for r in rows], np.float64)
    pred = np.array([r["prediction"] for r in rows], np.float64)
    out = Pass(model.k if model is not None else 0.0, rows, res, pred, np.array(floor, np.float64), prof,
               np.array(backward, np.float64).reshape(len(rows), len(offsets)),
               h_sim=stitcher.h_sim if stitcher is not None else None, **shared)
    if cache is not None:
        cache.save(label, what, portable(out))
        part.drop()
    release()
    return out


class Partial:
    """The state of a pass in progress, kept in its PassCache every `PassCache.every` seconds (at
    the end of a window; 0: after every window) and read back by the same pass run again, so
    that an interrupted pass loses at most the windows fitted since: the next window's index and
    each visit's warm start, the rows, costs, profiles and stitched H_b so far, and which windows
    the held-out scores still need (prepared again)."""

    def __init__(self, cache: PassCache | None, label: str, what: tuple):
        self.cache, self.label, self.what = cache, f"{label}-partial", what
        self.state = cache.load(self.label, what) if cache is not None else None
        self.saved = time.monotonic()
        self.next = 0                 # the window the pass fits next
        self.thetas: dict = {}        # visit -> its last fit's free parameters (the next warm start)

    def restore(self, estimator, theta0):
        """(start window, warm starts {visit or None (any other): (P_free,)}, rows, floor,
        backward, profiles, (h_sim, best) or None, recent {output: WindowData}) of the kept state."""
        st = self.state
        self.next, self.thetas = st["start"], dict(st["thetas"])
        recent = {k: None if at is None else (estimator.visit_data(at[0]).get(at[1]) if estimator.per_visit
                                              else estimator.data(at[0])) for k, at in st["recent"].items()}
        return (self.next, {None: theta0, **self.thetas}, st["rows"], st["floor"], st["backward"], st["prof"],
                st["stitch"], recent)

    def window_done(self, rows, floor, backward, prof, stitcher, recent) -> None:
        """After each window's last visit."""
        self.next += 1
        if self.cache is None or time.monotonic() - self.saved < self.cache.every:
            return
        self.cache.save(self.label, self.what, {
            "start": self.next, "thetas": self.thetas, "rows": rows, "floor": floor, "backward": backward,
            "prof": prof, "stitch": None if stitcher is None else (stitcher.h_sim, stitcher.best),
            "recent": {k: None if wd is None else (wd.spec.index, rows[k].get("visit", 0))
                       for k, wd in recent.items()}})
        self.saved = time.monotonic()

    def fitted(self, o) -> None:
        """After each output: its fit is its visit's next warm start."""
        if o.fit is not None:
            self.thetas[o.row.get("visit", 0)] = o.fit.theta

    def drop(self) -> None:
        if self.cache is not None:
            self.cache.drop(self.label, self.what)


TyreSection = tuple[float, float]   # a tyre section: flat fraction f, taper exponent e (sim.sinkage.taper)


def section_of(pair) -> TyreSection:
    """The pair's tyre section (flat fraction f, taper exponent e) (sim.sinkage.taper)."""
    return float(pair.wheel_flat_fraction), float(pair.wheel_section_exponent)


def with_section(pair, section: TyreSection):
    """A copy of the pair whose robot has the tyre section (f, e)."""
    return dataclasses.replace(pair, wheel_flat_fraction=section[0], wheel_section_exponent=section[1])


def fit_section(pair, est: EstimatorConfig, sim: SimConfig, sections, every: int = 3, progress=None,
                model: ExtensionModel | None = None, shared: dict | None = None, cache: PassCache | None = None,
                z: float = 1.96) -> tuple[TyreSection, dict[TyreSection, float], dict, dict[TyreSection, np.ndarray]]:
    """The tyre section as a nuisance: the footprint taper (flat fraction f, exponent e;
    sim.sinkage.taper) that fits the drive best.

    A robot description rarely knows its tyre's section (rounded, crowned, flat tread) or
    how it flattens on a given soil; a wrong one leaves a systematic residual on the rut
    floor and shoulders that a shape term (footprint_width) would otherwise be fitted to, or
    that reads as unexplained structure. The estimator runs on every `every`-th window (with
    the default 0.8 m window and 0.4 m stride, every 3rd: ground that does not overlap) once
    per candidate (f, e), the robot's own and `sections`; two numbers for the whole drive
    against hundreds of cells per window, so the windows' own residual (m) decides. The
    robot's own section stays unless another fits those windows better at a paired z of
    `z` (`stats.paired_z`): on noisy maps sections that fit alike are told apart by the noise
    alone, and a section taken on noise moves d (a crowned tyre for the flat one of a
    recording made elsewhere fitted its first-pass d 4 mm deep). model: an
    extension with a fixed coefficient to fit the section under (a wider footprint and a
    fuller section both widen the rut: a footprint term must beat the base model at its
    best section, with the section it needs itself). shared: run_pass's index, nuisance and
    view (and store), when already known. cache: where each section's score is kept and read
    back (checkpoint.PassCache). Returns (best (f, e), {(f, e): mean residual, m},
    {index, nuisance, view, store}: run_pass's keywords for later passes, {(f, e): the
    windows' residuals (W,), m})."""
    own = section_of(pair)
    candidates = section_candidates(pair, sections)
    costs: dict[TyreSection, float] = {}
    shared = dict(shared or {})
    shared.setdefault("store", WindowStore())
    windows = {}
    for sec in candidates:
        costs[sec], found, windows[sec] = section_cost(pair, est, sim, sec, every, model, shared, cache)
        shared = {**found, "store": shared["store"]}
        if progress is not None:
            progress.set_postfix_str(f"tyre section f={sec[0]:.2f} e={sec[1]:.2f}")
    best = plainest_choice(own, costs, windows, z)
    if progress is not None:
        progress.update(1)
    return best, costs, shared, windows


def plainest_choice(own, costs: dict, windows: dict, z: float = 1.96):
    """The candidate of least mean cost among `costs` ({candidate: mean window residual, m}), unless
    it fits its windows (`windows`: {candidate: (W,) residuals, m}) no better than `own` at a
    paired z of `z` (`stats.paired_z`): then `own`, the setting as declared."""
    best = min(costs, key=lambda c: (costs[c], c != own))
    return own if best != own and paired_z(windows[own], windows[best]) < z else best


def fit_blur(pair, est: EstimatorConfig, sim: SimConfig, blurs, cache: PassCache | None = None, pool=None,
             z: float = 1.96) -> tuple[EstimatorConfig, dict | None, dict]:
    """The raster's blur as a nuisance: the Gaussian (sigma in cells, estimator.after_blur) that
    the simulated change is seen through before it is compared with H_b (`cost.raster_blur`).

    A lidar heightmap spreads a rut's walls over a cell or two (the sweeps' pose errors, the
    beams' spots, the de-skew, the cells' own averaging); the simulator digs them sharp. Left
    alone, the spread reads as a lower angle of repose, or as a wider footprint and a cohesive
    soil's walls, on ground that follows the model (a null drive's bag named footprint_width).
    Scored as the tyre section is (`section_cost`: every third window, the base model, the
    pair's own section, sim's dig order), for est's own blur and each of `blurs`; the own blur
    stays unless another fits those windows better at a paired z of `z`. pool: a
    parallel.PassPool that scores the other blurs as tasks (it is given the pair first).
    Returns (est with the chosen blur, the evidence {declared, fitted, residual: [[sigma,
    mean residual m]]} or None when none was tried, run_pass's keywords for later passes)."""
    own = float(est.after_blur)
    candidates = list(dict.fromkeys([own, *(float(b) for b in blurs)]))
    if len(candidates) < 2:
        return est, None, {}
    sec, ests = section_of(pair), {b: est.replace(after_blur=b) for b in candidates}
    costs, res = {}, {}
    costs[own], shared, res[own] = section_cost(pair, est, sim, sec, 3, None, None, cache)
    if pool is not None:
        pool.share(pair, shared)
        pool.run("section", [(ests[b], sim, sec, 3, None) for b in candidates[1:]])
    for b in candidates[1:]:
        costs[b], _, res[b] = section_cost(pair, ests[b], sim, sec, 3, None, shared, cache)
    best = plainest_choice(own, costs, res, z)
    return ests[best], {"declared": own, "fitted": best, "residual": [[b, costs[b]] for b in candidates]}, shared


def section_candidates(pair, sections) -> list[TyreSection]:
    """The sections `fit_section` tries: the pair's own first, then `sections`, each once."""
    return list(dict.fromkeys([section_of(pair), *((float(f), float(e)) for f, e in sections)]))


class AnySection:
    """Prepared windows (windows.WindowStore's `get`) for estimators over one pair, map nuisance
    and settings that differ only in the tyre section and the dig order (`section_cost`'s): a
    prepared window does not depend on the dig order, and on the section only through its wheel
    geometries' taper (flat fraction, exponent) and the nominal footprint made from them, so
    each window is prepared once and given the asked section's taper and footprint
    (`with_taper`), the same as one prepared under that section. Kept in `store` (default: a
    WindowStore's, in memory up to 16 MB and spilled to disk beyond, so that a long drive's
    section scores do not hold its every third window in memory)."""

    def __init__(self, index, surfaces, store: WindowStore | None = None):
        self.index, self.surfaces = index, surfaces
        self.store = WindowStore() if store is None else store

    def get(self, key: tuple, prepare) -> WindowData | None:
        (f, e, est_json, sim_json, *rest), s0, s1 = key
        wd = self.store.get(((est_json, _without_order(sim_json), *rest), s0, s1), prepare)
        return None if wd is None else with_taper(wd, f, e)


@functools.lru_cache(maxsize=16)
def _without_order(sim_json: str) -> str:
    """SimConfig JSON without its dig_order (a prepared window does not depend on it)."""
    return json.dumps({k: v for k, v in json.loads(sim_json).items() if k != "dig_order"}, sort_keys=True)


def with_taper(wd: WindowData, f: float, e: float) -> WindowData:
    """Window wd with its wheel geometries' (its own and its earlier visits') tyre taper (flat
    fraction f, exponent e; sim.sinkage.taper) and the nominal footprint made from it, as
    windows.prepare_window makes them for a robot of that section."""
    def taper(g):
        if g.flat_fraction == f and g.section_exponent == e:
            return g
        g = g._replace(flat_fraction=f, section_exponent=e, nominal=None)
        return g._replace(nominal=footprint(g))

    return wd._replace(geom=taper(wd.geom), earlier=tuple(taper(g) for g in wd.earlier))


_ANY_SECTION: list[AnySection] = []   # this process's section scores' windows (of the last pair)


def section_windows(shared: dict) -> AnySection | None:
    """The section-free window store (`AnySection`) of the pair whose path index and surfaces
    are shared's (run_pass's keywords), made on first use; None without them."""
    index, surfaces = shared.get("index"), shared.get("surfaces")
    if index is None or surfaces is None:
        return None
    if not _ANY_SECTION or _ANY_SECTION[0].index is not index or _ANY_SECTION[0].surfaces is not surfaces:
        _ANY_SECTION[:] = [AnySection(index, surfaces)]
    return _ANY_SECTION[0]


def section_cost(pair, est: EstimatorConfig, sim: SimConfig, sec: TyreSection, every: int = 3,
                 model: ExtensionModel | None = None, shared: dict | None = None, cache: PassCache | None = None
                 ) -> tuple[float, dict, np.ndarray]:
    """One tyre section's score for `fit_section`: the mean window residual [m] of every
    `every`-th window with the section (f, e) (math.inf when none was fitted); run_pass's
    keywords (index, nuisance, view, surfaces) of its estimator; and those windows' residuals
    (W,) [m], read back from or kept in `cache` (a score kept by an older version reads back as
    its mean alone). Its windows are kept for the other sections' scores (`section_windows`),
    not in the passes' store; the windows' prediction costs are not scored."""
    shared = shared or {}
    estimator = Estimator(with_section(pair, sec), est, sim, modifiers=model.modifiers if model is not None else None,
                          **{**shared, "store": section_windows(shared)})
    what = (sec, sim.dig_order, every, None if model is None else (model.ext.id, model.k), est.after_blur)

    def score() -> list[float]:
        estimator.windows = estimator.windows[::max(1, every)]
        estimator._ahead_data = lambda k: None      # each window's residual only
        return [float(o.row["residual"]) for o in estimator.run()]

    res = np.atleast_1d(np.asarray(kept(cache, "section", what, score), np.float64))
    mean = float(np.nanmean(res)) if np.isfinite(res).any() else math.inf
    return mean, {**shared_of(estimator), "store": None}, res


def own_fit_screen(pair, est: EstimatorConfig, sim: SimConfig, exts: list[Extension], drive: DriveSignals,
                   base: Pass, cache: PassCache | None = None, pool=None) -> dict[str, dict]:
    """Whether shape terms (a cohesive soil's walls, the footprint) show at all where no
    cross-track zone is located: the per-window fit may take up a term's shape in d, chi and
    beta (steep intact walls and loose spoil fitted as one angle between the two), leaving no
    residual to locate, yet the windows fit their own ground better with it. Scored on every
    third window (`section_cost`: ground that does not overlap) under the pair's section, at
    the first trial coefficient of each side (`trial_sides`) against the base model: a
    one-sided paired t test of the windows' residuals per side, Bonferroni over the sides.
    pool: a parallel.PassPool (sharing this base pass) that scores them first. Returns {ext
    id: {p, statistic}}."""
    shared, sec = shared_of(base), section_of(pair)
    models = {(e.id, side[0]): ExtensionModel(e, side[0], drive, pair.robot, base.view or "last_visit", sim.dig_order)
              for e in exts for side in trial_sides(e)}
    if pool is not None:
        pool.run("section", [(est, sim, sec, 3, m) for m in models.values()])
    ref = section_cost(pair, est, sim, sec, 3, None, shared, cache)[2] if exts else None
    out = {}
    for ext in exts:
        sides, scored = trial_sides(ext), []
        for side in sides:
            res = section_cost(pair, est, sim, sec, 3, models[ext.id, side[0]], shared, cache)[2]
            d = (ref - res)[np.isfinite(ref) & np.isfinite(res)] if ref.shape == res.shape else np.zeros(0)
            sd = float(np.std(d, ddof=1)) if len(d) >= 3 else 0.0
            if sd > 0.0:
                t = float(d.mean() / (sd / math.sqrt(len(d))))
                scored.append((float(stats.t.sf(t, len(d) - 1)),
                               f"own fit at {ext.parameter} {side[0]:g}: t = {t:+.2f} over {len(d)} windows"))
        p, text = min(scored, default=(1.0, "own fit: none scored"))
        out[ext.id] = {"p": float(min(1.0, len(sides) * p)), "statistic": text}
    return out


@dataclass
class CandidateFit:
    """Result of fitting one extension.

    k: coefficient fitted on all windows (best mean prediction, refined). k_fold: the
    coefficient each fold was scored with (chosen on the other fold). prediction: (W,)
    cross-validated next-window cost per window [m]; held_out: the same for the mean of the
    next- and previous-window costs. improvement, se, held_z: paired per-window improvement
    of held_out over the base model. passes: every pass run, by coefficient; sections: the tyre
    section (f, e) each was run with (fit_section), by coefficient. own_z: the paired z of
    the improvement of the windows' own residuals (by fold) over the base model's: a
    term that predicts the neighbouring ground better while it fits its own windows worse is
    standing in for something else that changes along the drive, such as the soil.
    z: the two tests' evidence together (`stats.combined_z`), the statistic it is accepted
    on. effects: the term's effect size at each coefficient run (`catalogue.effect_size`, a
    fraction); effect: at the fold coefficients, the smaller of the two."""

    ext: Extension
    k: float
    k_fold: tuple[float, float]
    prediction: np.ndarray
    residual: np.ndarray
    improvement: float
    se: float
    z: float
    passes: dict[float, Pass]
    held_out: np.ndarray | None = None
    accepted: bool = False
    sections: dict[float, TyreSection] | None = None
    own_z: float = 0.0
    held_z: float = 0.0
    effects: dict[float, float] | None = None

    @property
    def effect(self) -> float:
        if self.effects is None:
            return math.inf
        return min(self.effects.get(float(k), math.inf) for k in self.k_fold)


def refine(ks: list[float], costs: list[float], bounds: tuple[float, float]) -> float | None:
    """Vertex of the parabola through the best coefficient and its neighbours (None if the
    best is at the edge of the tried ones or the parabola is not convex)."""
    order = np.argsort(ks)
    k, c = np.asarray(ks)[order], np.asarray(costs)[order]
    i = int(np.argmin(c))
    if i == 0 or i == len(k) - 1:
        edge = k[i] + (k[i] - k[1 if i == 0 else -2])
        return float(np.clip(edge, *bounds)) if bounds[0] <= edge <= bounds[1] else None
    a = np.polyfit(k[i - 1:i + 2], c[i - 1:i + 2], 2)
    if a[0] <= 0:
        return None
    return float(np.clip(-a[1] / (2 * a[0]), k[i - 1], k[i + 1]))


def fit_extension(pair, est: EstimatorConfig, sim: SimConfig, ext: Extension, drive: DriveSignals, base: Pass,
                  block_m: float = 2.4, refine_steps: int = 1, theta0=None, progress=None,
                  offsets: tuple[int, ...] = (2, 4, 6), sections: tuple[TyreSection, ...] = (),
                  cache: PassCache | None = None) -> CandidateFit:
    """Fit one extension's coefficient: passes at its trial coefficients (`trial_sides`:
    outward from 0 while the cost falls; where it still falls at a side's last trial, on at
    twice that coefficient, up to the bound: a law of another shape than the term's, a convex
    one on a drive whose covariate never comes near 0, needs a coefficient beyond the
    trials), `refine_steps` parabolic refinements, then two-fold
    cross-validated held-out costs and the paired comparison with the base pass (which must
    have been scored with the same `offsets`). sections: tyre sections (f, e) (`fit_section`)
    a footprint or wall term's passes at its trial coefficients choose their own from (the
    pair's is the base model's): a wider footprint and a fuller section both widen the rut, and
    steeper walls and a rounder section trade off (a flat tread's rut relaxed at the soil's
    angle looks like a rounder tyre's standing). A refinement between coefficients tried
    keeps the section of the nearer one (not 0, the base model's, when there is another): the
    search costs as much as the pass itself; a step beyond them is a trial of its own. cache:
    where finished passes are kept and read back (checkpoint.PassCache)."""
    passes: dict[float, Pass] = {0.0: base}
    sec: dict[float, TyreSection] = {0.0: section_of(pair)}
    counts = PassCounts()

    def run(k: float, search: bool = True) -> None:
        if any(abs(k - q) < 1e-9 for q in passes):
            return
        if progress is not None:
            progress.set_postfix_str(f"{ext.id} k={k:+.3g}")
        near = None if search else sec[min(sec, key=lambda q: (q == 0.0, abs(q - k)))]
        passes[k], sec[k] = candidate_pass(pair, est, sim, ext, k, drive, base, theta0, offsets, sections, cache,
                                           counts, section=near)
        if progress is not None:
            progress.update(1)

    every = np.ones(len(base.prediction), bool)
    for side in trial_sides(ext):        # outward from 0 on each side, while the cost falls
        last, queue = finite_mean(base.held_out, every), list(side)
        while queue:
            k = queue.pop(0)
            run(k)
            cost = finite_mean(passes[k].held_out, every)
            if not cost < last:
                break
            last = cost
            if not queue and (on := onward(ext, k)) is not None:    # still falling at the last trial
                queue.append(on)
    for _ in range(refine_steps):
        ks = sorted(passes)
        new = refine(ks, [finite_mean(passes[k].held_out, every) for k in ks], ext.bounds)
        if new is not None:               # between two tried: under the section of the nearer
            k = float(np.clip(new, *ext.bounds))
            run(k, search=not min(passes) < k < max(passes))
    ks = sorted(passes)
    lab = folds(len(base.prediction), int(round(block_m / est.stride)))
    k_fold = fold_choice({k: passes[k].held_out for k in ks}, lab)
    pred, held, res = (by_fold({k: getattr(passes[k], name) for k in ks}, k_fold, lab)
                       for name in ("prediction", "held_out", "residual"))
    k_all = min(ks, key=lambda k: (finite_mean(passes[k].held_out, every), abs(k)))
    shown = min(passes, key=lambda q: abs(q - k_all))     # the report's cross-sections: this pass's profiles
    for k in ks:                                          # the others' would grow with the drive, unused
        if k != 0.0 and k != shown:
            passes[k] = dataclasses.replace(passes[k], profiles=None)
    imp, se, held_z, own_z, z = term_test(base.held_out, held, base.residual, res)
    effects = {k: effect_size(ext, k, drive, pair.robot) for k in ks}
    return CandidateFit(ext, k_all, k_fold, pred, res, imp, se, z, passes, held, sections=sec, own_z=own_z,
                        held_z=held_z, effects=effects)


def trial_sides(ext: Extension) -> list[list[float]]:
    """The coefficients `fit_extension` may try first (ext.trials within ext.bounds, but 0:
    the base model's pass) by sign, each side in the order it runs them: outward from 0. It
    stops a side at the first coefficient whose mean held-out cost is no lower than the one
    before (the base model's for the first): past a rise the cost of a one-coefficient term
    rises on, and the refinement only looks at the best coefficient and its neighbours."""
    ks = [k for k in dict.fromkeys(float(np.clip(k, *ext.bounds)) for k in ext.trials) if abs(k) >= 1e-9]
    return [s for s in (sorted(k for k in ks if k > 0), sorted((k for k in ks if k < 0), reverse=True)) if s]


def onward(ext: Extension, k: float) -> float | None:
    """The coefficient `fit_extension` tries after k when a side's cost still falls at its last
    trial: twice k within the bound, None when k is at the bound."""
    on = float(np.clip(2.0 * k, *ext.bounds))
    return on if abs(on) > abs(k) + 1e-9 else None


def most_trials(ext: Extension) -> int:
    """The most trial passes `fit_extension` may run for ext: every side's trial coefficients
    and the doublings past its last one up to the bound (`onward`; refinements not counted)."""
    n = 0
    for side in trial_sides(ext):
        k, n = side[-1], n + len(side)
        while (k := onward(ext, k)) is not None:
            n += 1
    return n


def candidate_pass(pair, est: EstimatorConfig, sim: SimConfig, ext: Extension, k: float, drive: DriveSignals,
                   base: Pass, theta0=None, offsets: tuple[int, ...] = (2, 4, 6),
                   sections: tuple[TyreSection, ...] = (), cache: PassCache | None = None,
                   counts: PassCounts | None = None, section: TyreSection | None = None) -> tuple[Pass, TyreSection]:
    """One pass of `fit_extension`: the extension at coefficient k (within its bounds), under
    `section` where it is given, else the pair's tyre section or, for a footprint or wall term
    given `sections`, the one of them that fits best with it (`fit_section`); read back from or
    kept in `cache`. base: the base model's pass (its shared index, nuisance, view, store and
    surfaces). counts: the hardening term's pass counts kept across a candidate's passes.
    Returns (the pass, its section (f, e))."""
    shared = shared_of(base)
    model = ExtensionModel(ext, k, drive, pair.robot, base.view or "last_visit", sim.dig_order, counts or PassCounts())
    sec = section_of(pair) if section is None else section
    if section is None and ext.kind in ("radius", "wall") and sections:
        sec = fit_section(pair, est, sim, sections, model=model, shared=shared, cache=cache)[0]
    done = run_pass(with_section(pair, sec), est, sim, model, profiles=True, theta0=theta0, offsets=offsets,
                    cache=cache, **shared)
    return done, sec


def accept(fit: CandidateFit, z_crit: float, material: float = 0.0, own_z: float = -math.inf,
           effect: float = 0.0) -> bool:
    """The extension predicts held-out windows better than the noise allows, by a material
    amount: paired z above z_crit, a mean improvement of at least `material` [m], a change
    to the physics of at least `effect` at both folds' coefficients (CandidateFit.effect), the same
    non-zero coefficient sign chosen independently on both folds, and the windows' own fit no
    worse with it than `own_z` (the paired z of their residuals, CandidateFit.own_z):
    soil that changes where a covariate changes (a wetter patch where the robot slows into
    its turns) is predicted across windows by a term that follows the covariate, but the
    term then digs a step inside each window where the covariate changes, where the soil
    changes smoothly, and those windows fit worse."""
    a, b = fit.k_fold
    big = getattr(fit, "effect", math.inf) >= effect
    return bool(fit.z > z_crit and fit.improvement >= material and big and a != 0 and b != 0
                and np.sign(a) == np.sign(b) and fit.own_z >= own_z)
