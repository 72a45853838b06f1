"""Hardening named on the same ground: pass-count laws tested across the visits of one window.

On a terrain pair with visit layers (docs/formats.md, visits v1.1) the estimator fits each
visit of a window's ground on that visit's own maps (docs/visits.md): the same cells, the
same soil, only the wheel passes before the visit differ. Soil that hardens under traffic
sinks less at each later visit; soil that does not keeps its sinkage. The windows' sinkage
ratios d_v / d_0 against the passes between the visits test that, paired window by window
(soil that changes along the drive cancels), with an effective sample size for the
neighbouring windows' shared ground (`stats.effective_n`).

Laws of the sinkage d_n after n earlier wheel passes, relative to the first visit's d_0:

| shape | law | coefficient |
| --- | --- | --- |
| geometric | d_n = d_0 g^n | g: each pass sinks g times the one before |
| hyperbolic | d_n = d_0 / (1 + a n) | a |
| power | d_n = d_0 (1 + n)^b (the catalogue's, b = log2(1 + k_pass)) | b |

The geometric law is the one whose ratio between two visits does not depend on how the
passes are grouped into visits (a visit of m passes scales by g^m wherever it starts), so it
is the one a per-visit fit measures directly; with two pass counts only, every law fits the
ratios exactly and the shape is not told apart.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import interpolate, optimize, stats

from torchsoil.diagnosis.stats import effective_n, paired_improvement, spaced_z
from torchsoil.sim.simulate import Modifiers

LAWS = ("geometric", "hyperbolic", "power")
PARAMETER = {"geometric": "g_pass", "hyperbolic": "a_pass", "power": "b_pass"}   # diagnosis.json names
BOUNDS = {"geometric": (1e-3, 2.0), "hyperbolic": (-0.5, 50.0), "power": (-8.0, 2.0)}


def law_factor(shape: str, c: float, n) -> np.ndarray:
    """d_n / d_0 under law `shape` with coefficient c after n earlier passes (c and n: floats or
    arrays that broadcast together)."""
    n = np.asarray(n, np.float64)
    if shape == "geometric":
        return c ** n
    if shape == "hyperbolic":
        return 1.0 / np.maximum(1.0 + c * n, 1e-6)
    if shape == "power":
        return (1.0 + n) ** c
    raise ValueError(f"unknown pass law {shape!r}; known: {LAWS}")


@dataclass(frozen=True)
class Revisit:
    """One window whose ground was fitted at V >= 2 visits.

    s: window centre, m. passes: (V,) wheel passes before each visit. d: (V,) fitted sinkage
    (mean over tracks), m. rut: (V,) measured rut depth of each visit, m (NaN: not measured).
    rut_sim: {factor: (V,) rut depth simulated with the first visit's parameters, d scaled by
    factor} for the factors tried (`Estimator`-side; empty when not simulated), m."""

    s: float
    passes: np.ndarray
    d: np.ndarray
    rut: np.ndarray
    rut_sim: dict | None = None


def visit_groups(rows: list[dict]) -> list[tuple[float, list[dict]]]:
    """(s [m], its rows in visit order) of every window whose ground was fitted at two visits or
    more from its first (per-visit params.csv rows; flagged or unfitted visits left out), in
    window order."""
    by: dict[float, list[dict]] = {}
    for r in rows:
        if np.isfinite(float(r["residual"])) and not r.get("flags"):
            by.setdefault(round(float(r["s"]), 6), []).append(r)
    out = []
    for s, rs in sorted(by.items()):
        rs = sorted(rs, key=lambda r: int(r["visit"]))
        if len(rs) >= 2 and int(rs[0]["visit"]) == 0:
            out.append((s, rs))
    return out


def revisits(rows: list[dict], n_tracks: int) -> list[Revisit]:
    """The windows of per-visit params.csv rows (keys s, visit, passes_before, d1..dT,
    rut_depth, residual, flags) fitted at two visits or more, with more passes at each later
    visit and a positive first sinkage; flagged or unfitted visits left out."""
    out = []
    for s, rs in visit_groups(rows):
        n = np.array([float(r["passes_before"]) for r in rs])
        d = np.array([np.mean([float(r[f"d{t + 1}"]) for t in range(n_tracks)]) for r in rs])
        if d[0] <= 0 or np.any(np.diff(n) <= 0):
            continue
        out.append(Revisit(s, n, d, np.array([float(r["rut_depth"]) for r in rs])))
    return out


def _log_ratios(wins: list[Revisit], floor: float) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) over all later visits: passes since the first visit, log(d_v / d_0) with d_v
    floored at `floor` m (a visit fitted at d 0 reads as that much)."""
    x = np.concatenate([w.passes[1:] - w.passes[0] for w in wins])
    y = np.concatenate([np.log(np.maximum(w.d[1:], floor) / w.d[0]) for w in wins])
    return x, y


def fit_law(wins: list[Revisit], shape: str, floor: float = 1e-4) -> tuple[float, float]:
    """Coefficient of law `shape` fitted to the windows' sinkage ratios d_v / d_0 (least
    squares in log ratio, each visit's passes n_v against the first visit's n_0), and the
    RMS log-ratio misfit."""
    n0 = np.concatenate([np.full(len(w.passes) - 1, w.passes[0]) for w in wins])
    nv = np.concatenate([w.passes[1:] for w in wins])
    _, y = _log_ratios(wins, floor)

    def sse(c):
        pred = np.log(law_factor(shape, c, nv) / law_factor(shape, c, n0))
        return float(np.mean((y - pred) ** 2))

    lo, hi = BOUNDS[shape]
    res = optimize.minimize_scalar(sse, bounds=(lo, hi), method="bounded", options={"xatol": 1e-6})
    return float(res.x), math.sqrt(sse(res.x))


def per_pass(wins: list[Revisit], floor: float = 1e-4) -> np.ndarray:
    """(W,) each window's log sinkage factor per wheel pass (the geometric law's log g fitted
    to that window alone), in window order."""
    out = []
    for w in wins:
        x = w.passes[1:] - w.passes[0]
        y = np.log(np.maximum(w.d[1:], floor) / w.d[0])
        out.append(float((x * y).sum() / (x * x).sum()))
    return np.array(out)


def ratio_test(wins: list[Revisit], alpha: float, materiality: float) -> dict:
    """Is the sinkage at later visits of the same ground lower than at the first?

    Per window, the log factor per pass (`per_pass`); their mean is tested against 0 with a
    t test on the effective number of windows (neighbouring windows share ground), one-sided
    at `alpha` (hardening only lowers sinkage). The effect is 1 - g, g = exp(mean): the share
    by which each pass sinks less than the one before; it must reach `materiality`.

    Returns {windows, n_eff, g, effect, z, z_level, p, significant, material, accepted,
    laws: {shape: {coefficient, rms}}, shape (best-fitting law, or None when the drive has
    fewer than three pass counts to tell them apart), pass_counts}."""
    out: dict = {"windows": len(wins), "accepted": False}
    if len(wins) < 4:
        return {**out, "reason": f"{len(wins)} windows fitted at two visits or more (need 4)"}
    lg = per_pass(wins)
    n_eff = effective_n(len(lg), lg)
    sd = float(np.std(lg, ddof=1))
    dof = max(n_eff - 1.0, 1.0)
    t = float(np.mean(lg)) / max(sd / math.sqrt(n_eff), 1e-12)
    p = float(stats.t.cdf(t, dof))
    z = float(stats.norm.ppf(p))                                  # the normal z of the same one-sided p
    level = float(stats.norm.isf(alpha))
    g = math.exp(float(np.mean(lg)))
    counts = sorted({float(n) for w in wins for n in w.passes})
    laws = {}
    for shape in LAWS:
        c, rms = fit_law(wins, shape)
        laws[shape] = {"coefficient": c, "rms": rms}
    best = min(LAWS, key=lambda k: laws[k]["rms"]) if len(counts) >= 3 else None
    significant, material = z < -level, 1.0 - g >= materiality
    return {**out, "n_eff": n_eff, "g": g, "effect": 1.0 - g, "z": z, "z_level": -level, "p": p,
            "significant": bool(significant), "material": bool(material),
            "accepted": bool(significant and material), "laws": laws, "shape": best, "pass_counts": counts}


FACTORS = tuple(np.round(np.linspace(1.0, 0.0, 21), 3))   # sinkage factors a later visit is simulated at
# factors on the deposit share and the angle of repose a later visit is simulated at (x0.5 to x2, 1 among them)
SHARE_FACTORS = tuple(np.round(np.exp(np.linspace(math.log(0.5), math.log(2.0), 13)), 4))


@dataclass
class VisitPass:
    """The per-visit estimator pass of a pair with visit layers (`run_visits`).

    rows: params.csv rows, one per visit of each window. later: {(s, visit): {"factor": (F,),
    "cost": (F,) cost of the visit's maps simulated from its own start with the window's
    first-visit parameters, d scaled by each factor, m; "rut": (F,) the rut depth that
    simulation digs, m; "rut_measured": m; "floor": the visit's noise floor, m; "share_factor":
    (S,) SHARE_FACTORS; "cost_chi", "cost_beta": (S,) the visit's cost with the first visit's
    parameters, chi or beta scaled by each of them (within their bounds), m}}."""

    rows: list
    later: dict


def window_floor(plain, wd) -> float:
    """The noise floor [m] of the window of per-visit data wd on the drive's first view and
    last (`plain`: an Estimator of the same pair without per_visit): the lidars' noise, measured
    on the window's untouched ground, where a visit's own maps hold none (a producer whose visit
    layers cover the wheels' reach alone, not the corridor of docs/formats.md section 3)."""
    from torchsoil.estimate.cost import weighted_l1

    k = wd.spec.index
    if k >= len(plain.windows) or abs(plain.windows[k].centre - wd.spec.centre) > 1e-9:
        return math.nan
    plain.forget_before(k)                    # the later visits come window after window
    pd = plain.data(k)
    if pd is None or not bool(pd.floor.any()):
        return math.nan
    return float(weighted_l1(pd.h_measured, pd.h_back, pd.floor.to(pd.h_back.dtype)))


def run_visits(pair, est, sim, nuisance=None, index=None, factors=FACTORS) -> VisitPass:
    """Fit each visit of each window on its own maps (Estimator per_visit) and simulate every
    later visit with the first visit's parameters at sinkage factors `factors` (what the
    first visit's soil predicts for it, hardened by each factor). est, sim: settings sections."""
    import torch

    from torchsoil.estimate.cost import weighted_l1
    from torchsoil.estimate.estimator import Estimator, kind

    e = Estimator(pair, est, sim, per_visit=True, nuisance=nuisance, index=index)
    dmask = torch.tensor([kind(n) == "d" for n in e.free_names], device=e.theta0.device)
    f = torch.tensor(factors, dtype=e.theta0.dtype, device=e.theta0.device)
    fs = torch.tensor(SHARE_FACTORS, dtype=e.theta0.dtype, device=e.theta0.device)
    masks = {p: torch.tensor([n == p for n in e.free_names], device=e.theta0.device) for p in ("chi", "beta")}
    rows, later, first, n0, plain = [], {}, None, 0.0, None
    for o in e.run():
        rows.append(o.row)
        v = int(o.row["visit"])
        if v == 0:
            first = o.fit.theta if o.fit is not None else None
            n0 = float(o.row["passes_before"])
            continue
        wd, ruts = o.data, e._ruts(o.data)
        if first is None or wd is None or ruts is None or o.fit is None:
            continue
        free = torch.where(dmask[None], first[None] * f[:, None], first[None])
        shares = {}
        with torch.no_grad():
            h = e.simulate(free, wd).h
            for p, m in masks.items():
                scaled = torch.where(m[None], first[None] * fs[:, None], first[None])
                scaled = torch.minimum(torch.maximum(scaled, e.lower), e.upper)
                shares[f"cost_{p}"] = weighted_l1(e.simulate(scaled, wd).h, wd.h_back, wd.weight).cpu().numpy()
        cost = weighted_l1(h, wd.h_back, wd.weight).cpu().numpy()
        start = wd.h_measured.cpu().numpy()
        rut = np.array([float(np.mean((start - hb)[ruts])) for hb in h.cpu().numpy()])
        floor = float(o.reference["floor"])
        if not math.isfinite(floor):
            plain = plain or Estimator(pair, est, sim, nuisance=e.nuisance, index=e.index)
            floor = window_floor(plain, wd)
        later[(round(float(o.row["s"]), 6), v)] = {"factor": np.array(factors), "cost": cost, "rut": rut,
                                                   "rut_measured": float(o.row["rut_depth"]),
                                                   "passes": float(o.row["passes_before"]) - n0,
                                                   "floor": floor, "share_factor": np.array(SHARE_FACTORS),
                                                   **shares}
    return VisitPass(rows, later)


def cross_costs(later: dict, g: float, shape: str = "geometric") -> np.ndarray:
    """(L,) cost of each later visit simulated from the first visit's soil hardened by law
    `shape` with coefficient g over the passes since the first visit (the cost curve of
    `VisitPass.later` interpolated at the law's factor), m, in the order of `later`."""
    return np.array([at_factor(v, "cost", float(law_factor(shape, g, v["passes"]))) for v in later.values()])


def _curve(visit: dict, key: str):
    """A later visit's `key` curve over its sinkage factors: (cubic spline, lowest factor,
    highest factor)."""
    order = np.argsort(visit["factor"])
    x = np.asarray(visit["factor"], np.float64)[order]
    return interpolate.CubicSpline(x, np.asarray(visit[key], np.float64)[order]), x[0], x[-1]


def at_factor(visit: dict, key: str, f: float) -> float:
    """A later visit's `key` curve ("cost" or "rut", over its sinkage factors) at factor f
    (cubic spline: a minimum may lie between two factors; f clipped to the factors simulated)."""
    spline, lo, hi = _curve(visit, key)
    return float(spline(np.clip(f, lo, hi)))


def fit_cost_law(later: dict, shape: str = "geometric") -> float:
    """The law's coefficient at which the first visits' soil predicts the later visits best
    (least mean cross-visit cost, `cross_costs`, over a grid of 401 coefficients); g in
    (0, 1] for the geometric law."""
    if not later:
        return 1.0
    lo, hi = {"geometric": (0.05, 1.0), "hyperbolic": (0.0, 20.0), "power": (-4.0, 0.0)}[shape]
    grid = np.linspace(lo, hi, 401)
    n = np.array([v["passes"] for v in later.values()], np.float64)
    f = law_factor(shape, grid[:, None], n[None])                         # (G, L)
    cost = np.empty_like(f)
    for i, v in enumerate(later.values()):          # one spline per visit, at every coefficient
        spline, a, b = _curve(v, "cost")
        cost[:, i] = spline(np.clip(f[:, i], a, b))
    return float(grid[int(np.nanargmin(np.nanmean(cost, 1)))])


def _shapes(later: dict, level: float, min_windows: int = 4) -> tuple[dict, str | None]:
    """Each law's coefficient fitted on the cross-visit costs and its mean cost, m; the
    best-fitting shape, or None when the shapes are not told apart: fewer than two pass
    distances (passes since the first visit) with `min_windows` windows each (with one, every
    law fits exactly), or the best law's per-window costs not lower than each other law's at
    z `level` (`stats.paired_improvement`)."""
    laws, costs = {}, {}
    for shape in LAWS:
        c = fit_cost_law(later, shape)
        costs[shape] = cross_costs(later, c, shape)
        laws[shape] = {"coefficient": c, "cost": float(np.nanmean(costs[shape]))}
    dn = np.array([v["passes"] for v in later.values()])
    levels = [n for n in np.unique(dn) if (dn == n).sum() >= min_windows]
    best = min(LAWS, key=lambda k: laws[k]["cost"])
    apart = all(paired_improvement(costs[k], costs[best])[2] > level for k in LAWS if k != best)
    return laws, (best if len(levels) >= 2 and apart else None)


def hardening_across_visits(vp: VisitPass, alpha: float, materiality: float, block_m: float,
                            n_tracks: int, stride: float = 0.4, apart: int = 2) -> dict:
    """Does the soil of a window's first visit predict its later visits, or does it sink less
    there (multi_pass_hardening, named on the same ground)?

    1. Law: each later visit is simulated from its own start with the first visit's soil
       (`run_visits`) at sinkage factors 1 down to 0; the geometric law's g is chosen on the
       cost, two-fold over `block_m` blocks along the drive: both folds must find the physical
       sign (g < 1).
    2. Gain: the windows scored at the other fold's g must predict their later visits better
       than the first visit's soil as it is, at one-sided level `alpha`, counting windows that
       share no ground (`stats.spaced_z`, `apart` strides of `stride` [m]). Soil that does not harden
       predicts its later visits best at g 1, and there is nothing to gain.
    3. Material: 1 - g, the share by which each pass sinks less than the one before, at least
       `materiality`.

    The cost of the later visits without the law is also set against their noise floor
    (z_visible, `stats.paired_improvement`; reported, not tested: the floor of two noisy maps
    lies above what an adequate model reaches, by 0.4-0.8 mm on the nulls, so a hardening
    whose rut is shallow hides below it).

    Returns a dict (diagnosis.json `pass_law`): accepted, windows, z (the gain's) and z_level,
    z_visible, g and g_folds, effect, gain (m), cost_before / cost_after (mean cross-visit cost
    without and with the law, m), noise_floor (m), rut (measured, simulated without the law and
    with it, mean over the later visits, m), laws {shape: {coefficient, cost}}, shape
    (best-fitting law, or None), and the per-visit fits' sinkage ratios (`ratio_test`, for
    reference)."""
    later = {k: v for k, v in vp.later.items() if np.all(np.isfinite(v["cost"])) and np.isfinite(v["floor"])}
    out: dict = {"accepted": False, "windows": len(later)}
    if len(later) < 6:
        return {**out, "reason": f"{len(later)} later visits simulated (need 6)"}
    keys = list(later)
    base = cross_costs(later, 1.0)
    floor = np.array([later[k]["floor"] for k in keys])
    _, _, z_vis = paired_improvement(base, floor)
    fold = np.array([int(math.floor(s / block_m)) % 2 for s, _ in keys])
    ext, g_folds = np.full(len(keys), np.nan), []
    for f in (0, 1):
        g = fit_cost_law({k: later[k] for k, m in zip(keys, fold, strict=True) if m != f})
        g_folds.append(g)
        ext[fold == f] = cross_costs({k: later[k] for k, m in zip(keys, fold, strict=True) if m == f}, g)
    g = fit_cost_law(later)
    after = cross_costs(later, g)
    level = float(stats.norm.isf(alpha))
    gain = float(np.nanmean(base - ext))
    rut_at = [at_factor(v, "rut", float(law_factor("geometric", g, v["passes"]))) for v in later.values()]
    laws, shape = _shapes(later, level)
    named = shape or "geometric"          # the geometric law is the one a visit's ratio measures directly
    z = spaced_z([k[0] for k in keys], base - ext, stride, apart)
    accepted = bool(z > level and all(x < 1.0 for x in g_folds) and gain > 0 and 1.0 - g >= materiality)
    return {**out, "accepted": accepted, "z": z, "z_visible": float(z_vis), "z_level": level, "g": g,
            "g_folds": g_folds, "effect": 1.0 - g, "gain": gain,
            "cost_before": float(np.mean(base)), "cost_after": float(np.mean(after)),
            "noise_floor": float(np.mean(floor)),
            "rut": {"measured": float(np.nanmean([v["rut_measured"] for v in later.values()])),
                    "simulated_without_law": float(np.mean([at_factor(v, "rut", 1.0) for v in later.values()])),
                    "simulated_with_law": float(np.mean(rut_at))},
            "laws": laws, "shape": shape, "parameter": PARAMETER[named],
            "coefficient": g if named == "geometric" else laws[named]["coefficient"],
            "s": [float(s) for s, _ in keys],
            "sinkage_ratios": ratio_test(revisits(vp.rows, n_tracks), alpha, materiality)}


class PassLaw:
    """sim.Modifiers of a per-pass law, for the Estimator's `modifiers`: every wheel sinks
    d x law_factor(shape, c, n), n the wheel passes over the cell before that wheel's own (a
    rear wheel in its front wheel's rut runs the cell's second pass; `catalogue.entry_passes`
    with before and by_wheel). d is then the soil's first-pass sinkage, m, at every visit.
    drive: `covariates.DriveSignals` of the pair; counts: a `catalogue.PassCounts` shared by
    the laws of one drive (the counts do not depend on c)."""

    def __init__(self, shape: str, c: float, drive, counts=None):
        from torchsoil.diagnosis.catalogue import PassCounts

        law_factor(shape, c, 0)                    # an unknown shape fails here, not window by window
        self.shape, self.c, self.drive = shape, float(c), drive
        self.counts = PassCounts() if counts is None else counts

    def __call__(self, wd, theta, geom) -> Modifiers:
        import torch

        n = self.counts.of(self.drive, wd, geom, True, True)
        f = torch.as_tensor(law_factor(self.shape, self.c, n), dtype=theta.dtype, device=theta.device)
        return Modifiers(depth_scale=f[None].expand(theta.shape[0], -1))


def per_pass_fit(pair, est, sim, g: float, nuisance=None, index=None, steps: int = 2) -> dict:
    """Sinkage pass by pass under the geometric law: the per-visit fits again, with every wheel
    digging in turn (sim.dig_order "wheel") from the surface the passes before it left (resting
    on it as sim.revisit_ref says: a later visit's front wheel is the cell's third pass as the
    rear wheel is its second) and sinking d g^n after n earlier wheel passes
    (`PassLaw`). Where the law holds, every visit of a window fits the same first-pass d; g is
    moved until the later visits' d agrees with the first's (`per_pass`: the windows' median
    log ratio per pass, 0 at the fixed point; `steps` steps, the first by that log ratio, then
    by secant, each no longer than the step before), starting from the cross-visit cost's g.

    Returns {g, g_tried: [[g, log ratio per pass], ...], windows, rut: {measured, simulated}
    (the later visits' mean rut, m, measured and dug at their fits under the law: where g is
    right those fits sink the first visit's d), visits: [{visit, passes_before, windows,
    d_first_pass, d_sd, passes: [{pass, sinkage, sd}]}]} (m, the
    windows' median and standard deviation: a window at a turn mixes ground of other
    histories; pass: the cell's wheel passes before it, 0 the first ever; one entry per visit
    and wheel passes before it, as the multi-pass table of summary.md), or {reason} with
    fewer than 4 windows."""
    from torchsoil.diagnosis.catalogue import PassCounts
    from torchsoil.diagnosis.covariates import DriveSignals
    from torchsoil.estimate.estimator import Estimator

    drive, counts = DriveSignals.from_pair(pair), PassCounts()
    sim = sim.replace(dig_order="wheel")
    n_tracks = pair.robot.n_tracks
    per_track = int(np.bincount(pair.robot.track).max())
    tried: list[list[float]] = []
    for step in range(steps + 1):
        e = Estimator(pair, est, sim, per_visit=True, nuisance=nuisance, index=index,
                      modifiers=PassLaw("geometric", g, drive, counts))
        outs = list(e.run())
        rows = [o.row for o in outs]
        wins = revisits(rows, n_tracks)
        if len(wins) < 4:
            return {"reason": f"{len(wins)} windows fitted at two visits or more (need 4)", "g_tried": tried}
        ruts = np.array([[o.row["rut_depth"], simulated_rut(e, o)] for o in outs if o.row["visit"] > 0])
        lg = float(np.median(per_pass(wins)))
        tried.append([g, lg])
        if step == steps or abs(lg) < 1e-3:
            break
        if len(tried) == 1:
            g_next = g * math.exp(lg)
        else:
            (g0, l0), (g1, l1) = tried[-2], tried[-1]
            slope = (l1 - l0) / (math.log(g1) - math.log(g0)) if g1 != g0 else -1.0
            g_next = g1 * math.exp(-l1 / slope) if slope < 0 else g1 * math.exp(l1)
            # no further than the step before: the windows' ratios scatter, and a flat secant jumps
            reach = abs(math.log(g1 / g0)) if g1 != g0 else abs(l1)
            g_next = float(np.clip(g_next, g1 * math.exp(-reach), g1 * math.exp(reach)))
        g = float(np.clip(g_next, 0.05, 1.0))
    groups: dict[tuple[int, float], list[float]] = {}
    for w in wins:
        for v, (n, d) in enumerate(zip(w.passes, w.d, strict=True)):
            groups.setdefault((v, float(round(n))), []).append(float(d))
    visits = []
    for (v, n), ds in sorted(groups.items()):
        d = np.array(ds)
        visits.append({"visit": v, "passes_before": n, "windows": len(d), "d_first_pass": float(np.median(d)),
                       "d_sd": float(np.std(d)),
                       "passes": [{"pass": n + j, "sinkage": float(np.median(d * g ** (n + j))),
                                   "sd": float(np.std(d * g ** (n + j)))} for j in range(per_track)]})
    rut = ruts[np.isfinite(ruts).all(1)] if len(ruts) else np.zeros((0, 2))
    return {"g": g, "g_tried": tried, "windows": len(wins), "visits": visits,
            "rut": {"measured": float(rut[:, 0].mean()) if len(rut) else math.nan,
                    "simulated": float(rut[:, 1].mean()) if len(rut) else math.nan}}


def simulated_rut(e, o) -> float:
    """The rut [m] an estimator output `o` of Estimator `e` digs at its fit: the mean of its
    start minus its simulated end over the rut cells (`Estimator._ruts`), as the measured
    `rut_depth`; NaN where it has no fit or no rut cells."""
    import torch

    wd = o.data
    ruts = e._ruts(wd) if wd is not None else None
    if ruts is None or o.fit is None:
        return math.nan
    with torch.no_grad():
        h = e.simulate(o.fit.theta[None], wd).h[0].cpu().numpy()
    return float(np.mean((wd.h_measured.cpu().numpy() - h)[ruts]))
