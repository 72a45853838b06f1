"""A learned modifier: the law the catalogue leaves out, fitted through the simulator.

Each model parameter p (the sinkage d, the deposit share chi, the angle of repose beta) is
multiplied by exp(f_p(x)), f_p an additive model of the driving covariates x, each a
piecewise-linear curve through a few knots (`Basis`), 0 at the covariate's reference
value. The per-window parameters (d1..dT, chi, beta) are still fitted per window, so f only
has to say how a parameter changes with the covariate, not its level.

| term | acts on | covariates |
| --- | --- | --- |
| d | every wheel's sinkage, pose by pose (passes: cell by cell) | COMMON: speed, accel, traction, pitch, |
| | | turn_rate, lateral_accel, passes |
| d_side | a wheel's sinkage by side (x signed: -x left, +x right) | roll, lateral_load |
| chi, beta | deposit share, angle of repose (at the covariate's mean over the visit simulated) | COMMON |

turn_rate and lateral_accel are magnitudes (|yaw rate| [rad/s], |a_lat| [m/s^2]): a tyre
scrubs in a turn either way; the signed load shift is d_side's. The arc length is left out:
a parameter that changes along the path is the soil changing, which is what the per-window
parameters are for.

The modifier is fitted like a catalogue term, by two-fold block cross-validation
(`learn`). On each fold's windows, each window's base fit, scaled back to the covariate's
reference (its parameters over exp(f) at its own ground), predicts its own ground and the
ground 2, 4 and 6 strides back under exp(f) there (`objective`: the mean cost over the base
model's). The terms of the steepest gradient of that objective at f = 0 (`gradient_screen`,
autograd through the simulator) are fitted on a few windows, and the one that lowers it most
is the fold's (`choose_term`). Where both folds chose the same term, each fold's curve is
fitted on more of its windows with a penalty on its second differences (`fit_term`,
`fit_weights`), the estimator runs over the drive with each fold's modifier, and the other
fold's windows are scored on ground they were not fitted on, as for a catalogue term. The
term is kept only where both folds' curves run in one direction.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np
import torch

from torchsoil.diagnosis.catalogue import PassCounts, ground_times, visit_key
from torchsoil.diagnosis.checkpoint import kept
from torchsoil.diagnosis.covariates import DriveSignals
from torchsoil.diagnosis.fit import run_pass, section_of, shared_of
from torchsoil.diagnosis.revisits import visit_groups
from torchsoil.diagnosis.stats import effective_n, folds, paired_improvement, t_z, term_test, z_two_sided
from torchsoil.estimate.cost import weighted_l1
from torchsoil.estimate.estimator import Estimator
from torchsoil.robot import Robot
from torchsoil.sim import Modifiers

COMMON = ("speed", "accel", "traction", "pitch", "turn_rate", "lateral_accel", "passes")
SIDED = ("roll", "lateral_load")
PARAMETERS = ("d", "d_side", "chi", "beta")
SIGNAL_OF = {"turn_rate": "yaw_rate"}           # a covariate read from another signal (its magnitude)
MAGNITUDES = ("turn_rate", "lateral_accel")
UNITS = {"speed": "m/s", "accel": "m/s^2", "traction": "-", "pitch": "rad", "turn_rate": "rad/s",
         "lateral_accel": "m/s^2", "passes": "passes", "roll": "rad", "lateral_load": "-"}
# a learned curve of one of these shapes is that catalogue term (its direction as the term's bounds allow)
CATALOGUE_MATCH = {("d", "speed"): ("speed_dependent_sinkage", "+-"), ("d", "traction"): ("slip_sinkage", "+"),
                   ("d", "accel"): ("slip_sinkage", "+"), ("d_side", "lateral_load"): ("lateral_load_transfer", "+"),
                   ("d_side", "roll"): ("lateral_load_transfer", "+"), ("d", "passes"): ("multi_pass_hardening", "-")}
MAX_LOG = math.log(10.0)                        # factors within [0.1, 10]


@dataclass(frozen=True)
class Term:
    """One curve of the additive model: `parameter` (PARAMETERS) following `covariate`."""

    parameter: str
    covariate: str

    @property
    def name(self) -> str:
        return f"{self.parameter}~{self.covariate}"


def all_terms() -> list[Term]:
    """Every term the modifier may use (module table)."""
    return ([Term(p, c) for p in ("d", "chi", "beta") for c in COMMON]
            + [Term("d_side", c) for c in SIDED])


def signal(drive: DriveSignals, covariate: str, t) -> np.ndarray:
    """A pose covariate at times t [s] (turn_rate, lateral_accel: magnitudes)."""
    x = drive.at(SIGNAL_OF.get(covariate, covariate), t)
    return np.abs(x) if covariate in MAGNITUDES else x


@dataclass(frozen=True)
class Basis:
    """Piecewise-linear curve through `knots` (J,) of a covariate, flat beyond the end knots,
    0 at knots[anchor] (the reference): f(x) = matrix(x) @ w, w (J - 1,) the values at the
    other knots."""

    knots: np.ndarray
    anchor: int

    def matrix(self, x) -> np.ndarray:
        """(n, J - 1) hat-function weights of x (n,)."""
        k = self.knots
        x = np.clip(np.asarray(x, np.float64).ravel(), k[0], k[-1])
        i = np.clip(np.searchsorted(k, x, side="right") - 1, 0, len(k) - 2)
        u = (x - k[i]) / (k[i + 1] - k[i])
        h = np.zeros((len(x), len(k)))
        h[np.arange(len(x)), i] = 1.0 - u
        h[np.arange(len(x)), i + 1] += u
        return np.delete(h, self.anchor, axis=1)

    def curve(self, w: np.ndarray, x) -> np.ndarray:
        """f(x) (n,) for values w (J - 1,) at the knots but the anchor."""
        return self.matrix(x) @ np.asarray(w, np.float64)

    def values(self, w) -> np.ndarray:
        """(J,) f at every knot, 0 at the anchor."""
        return np.insert(np.asarray(w, np.float64), self.anchor, 0.0)


def make_basis(term: Term, drive: DriveSignals, robot: Robot, n_knots: int = 5,
               min_spread: dict[str, float] | None = None) -> Basis | None:
    """The knots of a term's curve over the ground driven (`catalogue.ground_times`): the
    2, 27, 50, 73 and 98 % quantiles (n_knots of them), those closer than a tenth of the
    range merged; anchored at the median, at 0 for a sided covariate (no load shift) and for
    passes (first pass; knots at 0, 1, 2 and 4 passes). None where the covariate barely varies
    (its 2-98 % range under `min_spread` [its unit], or fewer than two knots)."""
    min_spread = min_spread or {}
    if term.covariate == "passes":
        return Basis(np.array([0.0, 1.0, 2.0, 4.0]), 0)
    x = signal(drive, term.covariate, ground_times(drive))
    if term.parameter == "d_side":
        x = np.concatenate([x, -x])
    q = np.quantile(x, np.linspace(0.02, 0.98, n_knots))
    spread = float(q[-1] - q[0])
    if not spread > min_spread.get(term.covariate, 1e-9):
        return None
    anchor_at = 0.0 if term.parameter == "d_side" else float(np.median(x))
    knots = [q[0]]
    for v in q[1:]:
        if v - knots[-1] >= 0.1 * spread:
            knots.append(float(v))
    knots = np.unique(np.concatenate([knots, [anchor_at]]))
    if len(knots) < 2:
        return None
    return Basis(knots, int(np.argmin(np.abs(knots - anchor_at))))


class LearnedModel:
    """The modifier exp(f_p(x)) for the terms `bases` {Term: Basis} at knot values `w`
    {Term: (J - 1,) tensor}, applied to the windows of one drive (the Estimator's
    `modifiers` hook: (WindowData, theta (B, P), geometry) -> sim.Modifiers).

    view, dig_order: as catalogue.ExtensionModel's (which passes count). anchor: {parameter:
    () tensor} subtracted from f (`fit_weights`: a base fit scaled back to the reference);
    empty in a pass. `ext` and `k` name it for fit.run_pass (label and cache key)."""

    def __init__(self, bases: dict[Term, Basis], drive: DriveSignals, robot: Robot, w: dict | None = None,
                 view: str = "last_visit", dig_order: str = "robot", label: str = "learned"):
        self.bases, self.drive, self.robot = dict(bases), drive, robot
        self.w = {t: torch.as_tensor(np.zeros(len(b.knots) - 1) if w is None or t not in w else w[t],
                                     dtype=torch.float64) for t, b in self.bases.items()}
        self.before, self.by_wheel = view == "first_view", dig_order == "wheel"
        self.anchor: dict[str, torch.Tensor] = {}
        self.counts = PassCounts()
        self._rows: dict[tuple, dict] = {}
        self.ext = SimpleNamespace(id=label)

    @property
    def k(self) -> tuple:
        return tuple((t.name, tuple(np.round(self.w[t].detach().numpy(), 9).tolist())) for t in self.bases)

    def _entry_x(self, wd, geom, term: Term) -> np.ndarray:
        """(E,) the covariate at each entry of geom (a cell near a wheel, at its nearest pose)."""
        if term.covariate == "passes":
            return np.asarray(self.counts.of(self.drive, wd, geom, self.before, self.by_wheel), np.float64)
        t = geom.poses[:, 0].detach().cpu().numpy()[geom.pose.cpu().numpy()]
        x = signal(self.drive, term.covariate, t)
        if term.parameter == "d_side":
            x = x * -np.sign(self.robot.wheels[geom.wheel.cpu().numpy(), 1])   # left -1, right +1
        return x

    def rows(self, wd, geom) -> dict[Term, torch.Tensor]:
        """{term: basis rows}: (E, J - 1) per entry for d terms, (J - 1,) at the visit's mean for
        chi and beta; kept per visit (the last 64). An entry whose covariate is not known (NaN),
        or a visit without entries, gets rows of 0: no factor, f = 0 before the anchor."""
        key = visit_key(wd, geom)
        if key not in self._rows:
            out = {}
            for term, basis in self.bases.items():
                x = np.asarray(self._entry_x(wd, geom, term), np.float64)
                ok, x0 = np.isfinite(x), basis.knots[basis.anchor]       # at the anchor every row is 0
                if term.parameter in ("d", "d_side"):
                    m = basis.matrix(np.where(ok, x, x0))
                else:       # a visit no wheel of which meets the window's cells: no factor
                    m = basis.matrix([np.mean(x[ok]) if ok.any() else x0])[0]
                out[term] = torch.as_tensor(m, dtype=torch.float64)
            self._rows[key] = out
            if len(self._rows) > 64:
                self._rows.pop(next(iter(self._rows)))
        return self._rows[key]

    def log_factors(self, wd, geom) -> dict[str, torch.Tensor]:
        """{parameter: f}: (E,) for d (d and d_side terms summed), () for chi and beta, net of
        the anchor."""
        rows, out = self.rows(wd, geom), {}
        for term, m in rows.items():
            p = "d" if term.parameter == "d_side" else term.parameter
            f = m @ self.w[term]
            out[p] = out[p] + f if p in out else f
        return {p: f - self.anchor[p] if p in self.anchor else f for p, f in out.items()}

    def modifiers(self, wd, theta: torch.Tensor, geom=None) -> Modifiers:
        B = theta.shape[0]
        geom = wd.geom if geom is None else geom
        f = {p: v.to(theta.device).clamp(-MAX_LOG, MAX_LOG) for p, v in self.log_factors(wd, geom).items()}
        return Modifiers(
            depth_scale=torch.exp(f["d"])[None].expand(B, -1) if "d" in f else None,
            chi_scale=torch.exp(f["chi"]).expand(B) if "chi" in f else None,
            beta_scale=torch.exp(f["beta"]).expand(B) if "beta" in f else None)

    def own_mean(self, wd) -> dict[str, torch.Tensor]:
        """{parameter: () f at the window's own ground}: the mean over its own visit's entries for
        d, the value at the visit's mean covariate for chi and beta."""
        return {p: v.mean() if v.numel() else torch.zeros((), dtype=v.dtype)
                for p, v in self.log_factors(wd, wd.geom).items()}


def smoothness(model: LearnedModel) -> torch.Tensor:
    """Sum over terms of the squared second differences of the curve's knot values (the
    anchor's 0 among them), plus a small ridge on the values."""
    total = torch.zeros((), dtype=torch.float64)
    for term, basis in model.bases.items():
        w = model.w[term]
        v = torch.cat([w[:basis.anchor], torch.zeros(1, dtype=w.dtype), w[basis.anchor:]])
        if len(v) > 2:
            total = total + ((v[2:] - 2 * v[1:-1] + v[:-2]) ** 2).sum()
        total = total + 1e-2 * (w ** 2).sum()
    return total


def fold_pairs(estimator, fits: dict[int, torch.Tensor], offsets: tuple[int, ...] = (2, 4, 6),
               max_windows: int = 16) -> list[tuple]:
    """(own window data, its fit's free parameters (P_free,), target window data) of the
    windows `fits` {window index: fit} (at most `max_windows`, evenly spread): each fit on its
    own ground and on the ground `offsets` strides back, where there is ground."""
    keys = sorted(fits)
    if len(keys) > max_windows:
        keys = [keys[i] for i in np.linspace(0, len(keys) - 1, max_windows).round().astype(int)]
    pairs = []
    for k in keys:
        wd = estimator.data(k)
        if wd is None or "few_valid" in wd.flags:
            continue
        for o in (0, *offsets):
            tg = estimator.data(k - o) if k - o >= 0 else None
            if tg is not None and "few_valid" not in tg.flags:
                pairs.append((wd, fits[k], tg))
    return pairs


def objective(estimator, model: LearnedModel, pairs: list[tuple], base_cost: list[float] | None = None,
              backward: bool = False) -> tuple[float, list[float]]:
    """The mean over `pairs` (`fold_pairs`) of each fit's cost on its target under the model,
    the fit scaled back to the reference (`model.anchor`: f at its own ground), over the base
    model's cost there (`base_cost`; None: these costs are the base's, so 1 at w = 0).
    backward: accumulate the gradient into the model's knot values (pair by pair, so that one
    simulation's graph is held at a time). Returns (objective, the costs [m])."""
    estimator.modifiers = model.modifiers
    costs, total = [], 0.0
    for i, (wd, free, tg) in enumerate(pairs):
        with torch.set_grad_enabled(backward):
            model.anchor = {}
            model.anchor = model.own_mean(wd)
            c = weighted_l1(estimator.simulate(free[None], tg).h, tg.h_back, tg.weight)[0]
            costs.append(max(float(c.detach()), 1e-9))
            loss = c / (base_cost[i] if base_cost is not None else costs[-1]) / len(pairs)
            if backward:
                loss.backward()
        total += float(loss.detach())
    model.anchor = {}
    return total, costs


def fit_weights(estimator, model: LearnedModel, pairs: list[tuple], base_cost: list[float], steps: int = 12,
                lr: float = 0.2, penalty: float = 0.05) -> list[float]:
    """Fit the model's knot values through the simulator (in place): minimise `objective` over
    `pairs` plus `penalty` times `smoothness`, by Adam for `steps` steps at `lr` (halved twice on
    the way); the best values seen are kept. Returns the objective at every step."""
    leaves = {t: model.w[t].clone().requires_grad_(True) for t in model.bases}
    model.w = dict(leaves)
    opt = torch.optim.Adam(list(leaves.values()), lr=lr)
    sched = torch.optim.lr_scheduler.MultiStepLR(opt, [steps // 2, (3 * steps) // 4], 0.5)
    history, best = [], (math.inf, None)
    for step in range(steps + 1):
        opt.zero_grad()
        last = step == steps
        total, _ = objective(estimator, model, pairs, base_cost, backward=not last)
        reg = penalty * smoothness(model)
        total += float(reg.detach())
        history.append(total)
        if total < best[0]:
            best = (total, {t: v.detach().clone() for t, v in leaves.items()})
        if not last:
            reg.backward()
            opt.step()
            sched.step()
    model.w = best[1]
    return history


def gradient_screen(estimator, bases: dict[Term, Basis], drive: DriveSignals, robot: Robot, pairs: list[tuple],
                    base_cost: list[float], view: str, dig_order: str) -> dict[Term, float]:
    """{term: the norm of the objective's gradient in its knot values at w = 0}: how fast each
    term, alone, starts to lower the cost of the fold's fits on their neighbours' ground (one
    simulation and backward pass per pair for all terms at once)."""
    model = LearnedModel(bases, drive, robot, view=view, dig_order=dig_order)
    leaves = {t: model.w[t].clone().requires_grad_(True) for t in bases}
    model.w = dict(leaves)
    objective(estimator, model, pairs, base_cost, backward=True)
    return {t: float(v.grad.norm()) if v.grad is not None else 0.0 for t, v in leaves.items()}


@dataclass
class FoldChoice:
    """One fold's term: the terms screened {name: gradient norm}, the trial fits {name:
    relative objective (1: the base model)}, the chosen term (None: none gained) and its model."""

    gradients: dict[str, float]
    trials: dict[str, float]
    term: Term | None = None
    model: LearnedModel | None = None


@dataclass
class LearnedFit:
    """The learned modifier's cross-validated result.

    folds: each fold's `FoldChoice`; terms: the term both folds chose with one direction
    (kept, else empty); held_out, residual, prediction: (W,) each window's cost under the other
    fold's model [m] (None unless both folds chose the same term); improvement, se, held_z,
    own_z, z: `stats.term_test` against the base model; effect: the smaller of the folds'
    effect sizes (`effect_size`); passes: each fold's estimator pass; seconds."""

    folds: tuple[FoldChoice, FoldChoice]
    terms: list[Term] = field(default_factory=list)
    held_out: np.ndarray | None = None
    residual: np.ndarray | None = None
    prediction: np.ndarray | None = None
    improvement: float = 0.0
    se: float = math.inf
    held_z: float = 0.0
    own_z: float = 0.0
    z: float = -math.inf
    effect: float = 0.0
    passes: tuple = (None, None)
    accepted: bool = False
    seconds: float = 0.0


def direction(basis: Basis, w) -> str:
    """"+" where the curve ends higher than it starts over the knots, else "-"."""
    v = basis.values(np.asarray(w.detach() if isinstance(w, torch.Tensor) else w))
    return "+" if v[-1] - v[0] > 0 else "-"


def effect_size(model: LearnedModel, quantile: float = 0.95) -> float:
    """How much the model changes its parameters [-]: per term the `quantile` of |exp(f) - 1|
    over the knots' span (the covariate's 2-98 % range, 201 points), the largest of the terms."""
    out = 0.0
    for term, basis in model.bases.items():
        x = np.linspace(basis.knots[0], basis.knots[-1], 201)
        f = basis.curve(model.w[term].detach().numpy(), x)
        out = max(out, float(np.quantile(np.abs(np.exp(f) - 1.0), quantile)))
    return out


def distinct(drive: DriveSignals, bases: dict[Term, Basis], r: float = 0.98) -> dict[Term, Basis]:
    """The terms whose covariate is not, over the ground driven, the same signal as an earlier
    one's on the same parameter (|correlation| above r; the order of COMMON, SIDED): at a steady
    speed the lateral acceleration is the turn rate times a constant, on a drive that never
    speeds up the traction demand is the pitch. A term that cannot be told from another would
    split the folds' choices between them."""
    t = ground_times(drive)
    x = {c: signal(drive, c, t) for c in COMMON + SIDED if c != "passes"}
    kept: dict[Term, Basis] = {}
    for term, basis in bases.items():
        same = [k for k in kept if k.parameter == term.parameter and "passes" not in (k.covariate, term.covariate)
                and abs(np.corrcoef(x[k.covariate], x[term.covariate])[0, 1]) > r]
        if not same:
            kept[term] = basis
    return kept


def choose_term(estimator, bases: dict[Term, Basis], drive: DriveSignals, robot: Robot, fits: dict, offsets,
                view: str, dig_order: str, n_trials: int = 2, min_gain: float = 0.01) -> FoldChoice:
    """One fold's term: the `n_trials` terms of the steepest gradient (`gradient_screen`) each
    fitted on a few of the fold's windows (8, 8 steps); the one that lowers the objective most,
    by at least `min_gain` of the base model's (None: none did)."""
    small = fold_pairs(estimator, fits, offsets, max_windows=8)
    if not small:
        return FoldChoice({}, {})
    small_cost = objective(estimator, LearnedModel({}, drive, robot), small)[1]
    grads = gradient_screen(estimator, bases, drive, robot, small, small_cost, view, dig_order)
    ranked = sorted(grads, key=lambda t: -grads[t])[:n_trials]
    trials = {}
    for t in ranked:
        m = LearnedModel({t: bases[t]}, drive, robot, view=view, dig_order=dig_order)
        trials[t] = min(fit_weights(estimator, m, small, small_cost, steps=8))
    out = FoldChoice({t.name: g for t, g in grads.items()}, {t.name: v for t, v in trials.items()})
    best = min(trials, key=trials.get, default=None)
    if best is not None and trials[best] <= 1.0 - min_gain:
        out.term = best
    return out


def transported(estimator, rows: list[dict], offsets: tuple[int, ...], only: np.ndarray | None = None) -> np.ndarray:
    """(W,) each window's held-out cost [m]: the mean cost of its fit (params.csv `rows`) on the
    ground of the windows `offsets` strides away (back and ahead: a law shows where its
    covariate changes between the fit's ground and the ground predicted), under the
    estimator's modifiers; NaN without a fit or such ground. only: (W,) the windows to score."""
    out = np.full(len(rows), np.nan)
    for k, row in enumerate(rows):
        estimator.forget_before(k - max(abs(o) for o in offsets))    # windows are taken in order
        free = estimator.free_from_row(row) if only is None or only[k] else None
        if free is None:
            continue
        costs = []
        for o in offsets:
            j = k - o
            tg = estimator.data(j) if 0 <= j < len(rows) else None
            if tg is not None and "few_valid" not in tg.flags:
                costs.append(estimator.predict(free, tg)[1])
        if costs:
            out[k] = float(np.mean(costs))
    return out


def fit_term(estimator, term: Term, basis: Basis, drive: DriveSignals, robot: Robot, fits: dict, offsets,
             view: str, dig_order: str, steps: int = 20) -> LearnedModel:
    """A fold's model of one term, fitted on up to 16 of its windows for `steps` steps."""
    pairs = fold_pairs(estimator, fits, offsets, max_windows=16)
    model = LearnedModel({term: basis}, drive, robot, view=view, dig_order=dig_order)
    fit_weights(estimator, model, pairs, objective(estimator, LearnedModel({}, drive, robot), pairs)[1], steps)
    return model


def _fold_fits(estimator, base, est, block_m: float, fold: int) -> dict[int, torch.Tensor]:
    """{window: its base fit's free parameters} of one fold's windows (`stats.folds`: blocks of block_m m)."""
    lab = folds(len(base.rows), int(round(block_m / est.stride)))
    return {k: th for k in np.flatnonzero(lab == fold).tolist()
            if (th := estimator.free_from_row(base.rows[k])) is not None}


def _bases(drive: DriveSignals, robot: Robot, cfg) -> dict[Term, Basis]:
    return distinct(drive, {t: b for t in all_terms()
                            if (b := make_basis(t, drive, robot, min_spread=cfg.min_spread)) is not None})


def fold_choice(estimator, pair, est, sim, base, drive: DriveSignals, cfg, fold: int, cache=None) -> FoldChoice:
    """One fold's term (`choose_term` on its windows), kept in `cache` (label learned_choice,
    by tyre section, dig order and fold; the model left out)."""
    def compute():
        return choose_term(estimator, _bases(drive, pair.robot, cfg), drive, pair.robot,
                           _fold_fits(estimator, base, est, cfg.block_m, fold), cfg.offsets,
                           base.view or "last_visit", sim.dig_order)

    return kept(cache, "learned_choice", (section_of(pair), sim.dig_order, fold), compute)


def fold_model(estimator, pair, est, sim, base, drive: DriveSignals, cfg, fold: int, term: Term,
               cache=None) -> LearnedModel:
    """One fold's model of `term` (`fit_term` on its windows), its knot values kept in `cache`
    (label learned_model, by tyre section, dig order, fold and term)."""
    view, robot = base.view or "last_visit", pair.robot
    basis = _bases(drive, robot, cfg)[term]

    def compute():
        m = fit_term(estimator, term, basis, drive, robot, _fold_fits(estimator, base, est, cfg.block_m, fold),
                     cfg.offsets, view, sim.dig_order)
        return m.w[term].detach().numpy()

    w = kept(cache, "learned_model", (section_of(pair), sim.dig_order, fold, term.name), compute)
    return LearnedModel({term: basis}, drive, robot, {term: w}, view=view, dig_order=sim.dig_order)


def fold_task(pair, est, sim, base, cfg, fold: int, cache, stage: str = "choice") -> None:
    """One fold of the learned modifier as a task of a diagnosis's pass pool
    (parallel.PassPool), run beside the candidates' passes, its result kept in `cache` for
    `learn` to read back: stage "choice", the fold's term (`fold_choice`); stage "model",
    once both folds' choices are kept, its model of the term where both chose the same one
    (`fold_model`; nothing otherwise, as `learn`)."""
    drive = DriveSignals.from_pair(pair)
    estimator = Estimator(pair, est, sim, **shared_of(base))
    if stage == "choice":
        fold_choice(estimator, pair, est, sim, base, drive, cfg, fold, cache)
        return
    terms = [fold_choice(estimator, pair, est, sim, base, drive, cfg, f, cache).term for f in (0, 1)]
    if terms[0] is not None and terms[0] == terms[1]:
        fold_model(estimator, pair, est, sim, base, drive, cfg, fold, terms[0], cache)


def learn(pair, est, sim, base, drive: DriveSignals, cfg, cache=None, progress=None,
          named: str | None = None) -> LearnedFit:
    """The learned modifier of one drive, cross-validated (module docstring).

    base: the base model's pass (fit.Pass; its rows, costs and shared windows); cfg:
    DiagnosisConfig (block_m, offsets, min_spread). The estimator runs with a fold's model only
    where both folds chose the same term with one direction, and its law is not that of the
    catalogue term already `named` (`catalogue_match`: that term's own test stands; the curve is
    kept, `terms` set, untested). Each fold's choice and model are read from `cache` where a
    pool's `fold_task` kept them."""
    t0 = time.perf_counter()
    rows = base.rows
    lab = folds(len(rows), int(round(cfg.block_m / est.stride)))
    estimator = Estimator(pair, est, sim, **shared_of(base))
    choices = []
    for f in (0, 1):
        if progress is not None:
            progress.set_postfix_str(f"learned modifier, fold {f}")
        choices.append(fold_choice(estimator, pair, est, sim, base, drive, cfg, f, cache))
    out = LearnedFit(tuple(choices))
    term = choices[0].term
    if term is None or term != choices[1].term:
        out.seconds = time.perf_counter() - t0
        return out
    for f, c in enumerate(choices):
        c.model = fold_model(estimator, pair, est, sim, base, drive, cfg, f, term, cache)
    basis = choices[0].model.bases[term]
    if direction(basis, choices[0].model.w[term]) != direction(basis, choices[1].model.w[term]):
        out.seconds = time.perf_counter() - t0
        return out
    if named is not None and catalogue_match(term, direction(basis, choices[0].model.w[term])) == named:
        out.terms, out.seconds = [term], time.perf_counter() - t0
        return out
    passes = [run_pass(pair, est, sim, c.model, profiles=False, offsets=cfg.offsets, cache=cache, **shared_of(base))
              for c in choices]
    both = tuple(o * sign for o in cfg.offsets for sign in (1, -1))
    estimator.modifiers = None
    base_held = transported(estimator, rows, both)
    series = {}
    for name in ("held_out", "residual", "prediction"):
        v = np.full(len(rows), np.nan)
        for f in (0, 1):                        # each fold's windows under the other fold's model
            if name == "held_out":
                estimator.modifiers = choices[f].model.modifiers
                held = transported(estimator, passes[f].rows, both, lab != f)
                v[lab != f] = held[lab != f]
            else:
                v[lab != f] = getattr(passes[f], name)[lab != f]
        series[name] = v
    estimator.modifiers = None
    imp, se, held_z, own_z, z = term_test(base_held, series["held_out"], base.residual, series["residual"])
    return LearnedFit(out.folds, [term], series["held_out"], series["residual"], series["prediction"], imp, se,
                      held_z, own_z, z, min(effect_size(c.model) for c in choices), tuple(passes),
                      seconds=time.perf_counter() - t0)


WORDS = {"d": "sinkage", "d_side": "the right wheels' share of the sinkage", "chi": "the deposit share",
         "beta": "the angle of repose"}
COVARIATE_WORDS = {"speed": "travel speed", "accel": "acceleration", "traction": "traction demand",
                   "pitch": "pitch", "turn_rate": "turn rate", "lateral_accel": "lateral acceleration",
                   "passes": "the passes the ground had before", "roll": "roll", "lateral_load": "lateral load"}
ZONE_OF = {"d": "rut_floor", "d_side": "rut_floor", "chi": "berm", "beta": "rut_wall"}


def shape(x: np.ndarray, factor: np.ndarray) -> str:
    """The shape of a factor curve (n,) over x (n,) ascending: linear, convex or concave where
    it is monotone (its largest distance from the chord under a tenth of its range: linear;
    below the chord: convex, above: concave), u_shaped or peaked where it turns (by a fifth of its range)."""
    rng = float(factor.max() - factor.min())
    if rng <= 0:
        return "flat"
    lo, hi = int(np.argmin(factor)), int(np.argmax(factor))
    ends = factor[[0, -1]]
    if 0 < lo < len(x) - 1 and ends.min() - factor[lo] > 0.2 * rng:
        return "u_shaped"
    if 0 < hi < len(x) - 1 and factor[hi] - ends.max() > 0.2 * rng:
        return "peaked"
    chord = np.interp(x, x[[0, -1]], ends)
    dev = factor - chord
    if np.abs(dev).max() < 0.1 * rng:
        return "linear"
    return "convex" if dev.mean() < 0 else "concave"


def catalogue_match(term: Term, sign: str) -> str | None:
    """The catalogue term whose law a learned curve of this term and direction is (None: it is
    none of them)."""
    m = CATALOGUE_MATCH.get((term.parameter, term.covariate))
    return m[0] if m is not None and sign in m[1] else None


def describe(fit: LearnedFit, z_needed: float) -> dict:
    """learned.json (docs/diagnosis.md): per kept term its parameter, covariate, direction,
    shape, the factor over the covariate's 5-95 % span of the knots, the curve (the mean of the
    folds' knot values, a log factor) and its band (the two folds' curves), the sentence, the
    catalogue term it matches; the test (held-out gain [m], z against z_needed, own-fit z,
    effect) and each fold's screen and trials."""
    def num(x):                                      # JSON: a test not run is null
        return float(x) if math.isfinite(x) else None

    tested = fit.held_out is not None
    out = {"accepted": bool(fit.accepted), "tested": tested, "improvement": fit.improvement if tested else None,
           "se": num(fit.se) if tested else None, "z": num(fit.z), "held_z": fit.held_z if tested else None,
           "own_z": num(fit.own_z) if tested else None, "z_needed": z_needed, "effect": fit.effect,
           "seconds": round(fit.seconds, 2), "terms": [],
           "folds": [{"term": c.term.name if c.term else None, "gradients": c.gradients, "trials": c.trials}
                     for c in fit.folds]}
    for term in fit.terms:
        basis = fit.folds[0].model.bases[term]
        vals = np.stack([basis.values(c.model.w[term].detach().numpy()) for c in fit.folds])
        mean = vals.mean(0)
        x = np.linspace(basis.knots[0], basis.knots[-1], 41)
        f = np.exp(np.interp(x, basis.knots, mean))
        lo, hi = (float(v) for v in np.interp([0.05, 0.95], [0, 1], basis.knots[[0, -1]]))
        ratio = float(np.exp(np.interp(hi, basis.knots, mean) - np.interp(lo, basis.knots, mean)))
        sign = "+" if ratio > 1 else "-"
        form = shape(x, f)
        match = catalogue_match(term, sign)
        verb = "rises" if sign == "+" else "falls"
        how = {"linear": "", "convex": " convexly", "concave": " concavely"}.get(form, f" ({form.replace('_', '-')})")
        sentence = (f"{WORDS[term.parameter]} {verb}{how} with {COVARIATE_WORDS[term.covariate]} (x{ratio:.2f} from "
                    f"{lo:.3g} to {hi:.3g} {UNITS[term.covariate]})")
        sentence = sentence[0].upper() + sentence[1:]
        sentence += (f"; the law of {match}" if match else "; no catalogue term has this law")
        out["terms"].append({"parameter": term.parameter, "covariate": term.covariate, "direction": sign,
                             "shape": form, "factor": ratio, "from": lo, "to": hi, "unit": UNITS[term.covariate],
                             "knots": basis.knots.tolist(), "log_factor": mean.tolist(),
                             "band": [vals.min(0).tolist(), vals.max(0).tolist()], "catalogue_match": match,
                             "sentence": sentence + "."})
    return out


def visit_parameters(rows: list[dict], parameter: str) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """Per window fitted at two visits or more (per-visit params.csv rows: s, visit,
    passes_before, chi, beta [deg], residual, flags; flagged or unfitted visits left out):
    (s [m], (V,) wheel passes before each visit, (V,) the visit's fitted `parameter`), with more
    passes at each later visit and a positive first value."""
    out = []
    for s, rs in visit_groups(rows):
        n = np.array([float(r["passes_before"]) for r in rs])
        v = np.array([float(r[parameter]) for r in rs])
        if v[0] > 0 and np.all(np.diff(n) > 0) and np.all(np.isfinite(v)):
            out.append((s, n, v))
    return out


def visit_test(rows: list[dict], parameter: str, alpha: float, materiality: float, floor: float = 1e-3,
               later: dict | None = None) -> dict:
    """Does a parameter change with the passes on the same ground? Per window its log factor
    per wheel pass between its first visit and the later ones (least squares through 0; values
    floored at `floor`), their mean tested against 0, two-sided at `alpha`, by a t test on the
    effective number of windows (neighbouring windows share ground). The factor per pass
    g = exp(mean) must change the parameter by `materiality` at least, and, given `later` (the
    per-visit pass's `revisits.VisitPass.later`, with its cost_chi and cost_beta curves), must
    predict the later visits better than their first visit's soil unchanged does
    (`cross_visit_gain`, at the same two-sided level): a parameter the maps do not pin down (an
    angle of repose above every slope the wheels leave) wanders from visit to visit without
    changing the surface it simulates. Returns {windows, n_eff, g, z, z_level, accepted,
    direction, and with later: cost_gain (m), cost_z}."""
    wins = visit_parameters(rows, parameter)
    out = {"parameter": parameter, "covariate": "passes", "windows": len(wins), "accepted": False}
    if len(wins) < 4:
        return out
    lg = []
    for _, n, v in wins:
        x, y = n[1:] - n[0], np.log(np.maximum(v[1:], floor) / max(v[0], floor))
        lg.append(float((x * y).sum() / (x * x).sum()))
    lg = np.array(lg)
    n_eff = effective_n(len(lg), lg)
    sd = float(np.std(lg, ddof=1))
    t = abs(float(lg.mean())) / max(sd / math.sqrt(n_eff), 1e-12)
    z = t_z(t, max(n_eff - 1.0, 1.0))
    level = z_two_sided(alpha)
    g = math.exp(float(lg.mean()))
    ok = z > level and abs(g - 1.0) >= materiality
    out = {**out, "n_eff": n_eff, "g": g, "z": z, "z_level": level, "direction": "+" if g > 1 else "-"}
    if later is not None:
        gain, _, cost_z = cross_visit_gain(later, parameter, g)
        out |= {"cost_gain": gain, "cost_z": cost_z}
        ok = ok and cost_z > level
    return {**out, "accepted": bool(ok)}


def cross_visit_gain(later: dict, parameter: str, g: float) -> tuple[float, float, float]:
    """How much better the later visits of the ground driven again are simulated from their
    first visit's soil with `parameter` (chi or beta) scaled by g per wheel pass since that
    visit than unchanged: `stats.paired_improvement` of their costs (each visit's cost curve
    over the factors it was simulated at, interpolated in the log factor; factors beyond the
    curve's held at its ends). later: `revisits.VisitPass.later`. Returns (mean gain m, se, z);
    NaN without curves."""
    key = f"cost_{parameter}"
    visits = [v for v in later.values() if key in v]
    if not visits:
        return math.nan, math.nan, math.nan
    same, scaled = [], []
    for v in visits:
        x, y = np.log(np.asarray(v["share_factor"], np.float64)), np.asarray(v[key], np.float64)
        same.append(float(np.interp(0.0, x, y)))
        scaled.append(float(np.interp(v["passes"] * math.log(g), x, y)))
    return paired_improvement(np.array(same), np.array(scaled))




def describe_visits(test: dict) -> dict:
    """A learned term found on the ground driven again (`visit_test`), as `describe` gives a
    curve: the factor per wheel pass on the parameter, its direction and sentence."""
    p, g = test["parameter"], test["g"]
    verb = "rises" if g > 1 else "falls"
    sentence = (f"{WORDS[p]} {verb} with {COVARIATE_WORDS['passes']} (x{g:.2f} per wheel pass, its fits at each "
                f"visit of the same ground over {test['windows']} windows); no catalogue term has this law.")
    return {"parameter": p, "covariate": "passes", "direction": test["direction"], "shape": "per_pass",
            "factor": g, "from": 0.0, "to": 1.0, "unit": UNITS["passes"], "knots": [0.0, 1.0],
            "log_factor": [0.0, math.log(g)], "band": [[0.0, math.log(g)], [0.0, math.log(g)]],
            "catalogue_match": catalogue_match(Term(p, "passes"), test["direction"]),
            "sentence": sentence[0].upper() + sentence[1:]}
