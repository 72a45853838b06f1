"""The diagnosis of one drive: locate the mismatch, rank and fit catalogue extensions,
accept one only on held-out evidence, and give the verdict (docs/formats.md section 4).

`diagnose` runs the phases in order: the tyre section and dig order as nuisances
(`fit_nuisance_model`), the base model's pass (`base_pass`), where it misses
(`locate_mismatch`), the catalogue's candidates ranked and fitted (`fit_candidates`), hardening
on the ground driven again (`_revisit`), which candidates pass (`choose_terms`), the location
tests and the verdict (`location_verdict`), the named cause and its costs (`name_cause`), and the
evidence, summary and explanation (`explain_diagnosis`)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage, stats

from torchsoil.diagnosis import catalogue, learned
from torchsoil.diagnosis.checkpoint import PassCache, kept
from torchsoil.diagnosis.covariates import SIGNALS, DriveSignals, side_arc, window_signals
from torchsoil.diagnosis.fit import (
    CandidateFit,
    Pass,
    accept,
    fit_blur,
    fit_extension,
    fit_section,
    most_trials,
    own_fit_screen,
    run_pass,
    section_candidates,
    section_cost,
    section_of,
    shared_of,
    trial_sides,
    with_section,
)
from torchsoil.diagnosis.locate import ZONES, line_zone, spectral_line, zone_segment
from torchsoil.diagnosis.revisits import hardening_across_visits, per_pass_fit, run_visits
from torchsoil.diagnosis.stats import (
    correlation,
    evidence_basis,
    gain_material,
    level_z,
    outliers,
    paired_improvement,
    paired_z,
    thresholds,
    z_two_sided,
)
from torchsoil.estimate.windows import path_arc
from torchsoil.settings import DiagnosisConfig, EstimatorConfig, SimConfig


@dataclass
class Diagnosis:
    """Everything the report needs: `summary` is the diagnosis.json dict (docs/formats.md 4);
    residual_map: (X, Y) float32 simulated - measured H_b of the base model [m]; s_index: (X, Y)
    arc length of each cell [m]."""

    summary: dict
    base: Pass
    fits: list[CandidateFit]
    best: CandidateFit | None
    evidence: dict
    windows: dict
    residual_map: np.ndarray
    s_index: np.ndarray
    revisits: dict | None = None
    learned: dict | None = None


LOCATED_ZONES = ("rut_floor", "rut_wall", "outside")   # berm heights follow chi: not a location test
N_LOCATE_TESTS = len(LOCATED_ZONES) + 2                 # + left/right asymmetry + spectral line
SHAPE_ZONES = ("rut_floor", "rut_wall", "berm")          # where a shape term (walls, footprint) may show


def accept_in_order(fits: list[CandidateFit], p: list[float], alpha: float, lead_share: float,
                    material: float = 0.0, own_z: float = -math.inf, signs: list[int] | None = None,
                    effect: float = 0.0) -> list[float]:
    """Set `accepted` on fits (in order of their location evidence p) by the fallback
    procedure, each also needing a mean held-out improvement of `material` [m], an effect
    size of `effect` (CandidateFit.effect) and its
    windows' own fit no worse than `own_z` (`fit.accept`); returns the z level each was
    tested at (`stats.level_z`, for the number of signs each coefficient may take: `signs`, default
    1 each). A candidate whose coefficient is 0 on both folds is the base model on every
    window (each fold's coefficient chosen on the other fold's windows found nothing better):
    it has no test to spend its level on, and passes it on as an accepted one does."""
    levels, carry, used = thresholds(p, alpha, lead_share), 0.0, []
    for f, a, m in zip(fits, levels, signs or [1] * len(fits), strict=True):
        z = level_z(a + carry, m)
        f.accepted = accept(f, z, material, own_z, effect)
        carry = a + carry if f.accepted or not any(f.k_fold) else 0.0
        used.append(z)
    return used


def by_gain(fits: list, material: float = 0.0, own_z: float = -math.inf, effect: float = 0.0) -> list:
    """The terms a diagnosis names from, the one that predicts the held-out ground best first
    (largest mean improvement over the base model, `CandidateFit.improvement`): terms that each
    passed their own test are told apart as cross-validation tells models apart. Two shape
    terms can both pass on one rut (a wider footprint and walls that stand both widen it at the
    rim); the steadier gain (higher z) need not be the larger one, and the cause is the term
    that accounts for more of the mismatch.

    Once a shape term (one without a covariate: cohesive_walls, footprint_width) is accepted,
    the other shape terms join the accepted ones when they meet every other condition of
    `fit.accept` (material gain and effect, both folds' coefficients of one sign, own fit no
    worse: `material`, `effect`, `own_z`) with a positive z, short of their own level: the shape
    terms share their location evidence (the rut's profile), the accepted one has shown that
    the rut's shape needs a term, and which one it needs is again a choice between models, not
    a test against the base model. Nothing joins on a drive without an accepted shape term, so
    the family-wise level of naming a term at all is that of `accept_in_order`."""
    def shape(f) -> bool:
        return getattr(f, "ext", None) is not None and f.ext.covariate is None

    established = any(f.accepted and shape(f) for f in fits)
    named = [f for f in fits if f.accepted or (established and shape(f) and accept(f, 0.0, material, own_z, effect))]
    return sorted(named, key=lambda f: -f.improvement)


def strongest_line(by_side: np.ndarray, dx: float) -> dict:
    """The most significant spectral line on the rut floors (2, S): left, right, or both
    summed (a tread marks both ruts, not necessarily in phase nor at one wavelength when the
    wheels slip differently); its p is Bonferroni-corrected for the three looks, and `ruts`
    says which."""
    looks = {"left": by_side[0], "right": by_side[1], "both": by_side}
    lines = {k: spectral_line(v, dx) for k, v in looks.items()}
    ruts, best = min(lines.items(), key=lambda kv: kv[1]["p"])
    return {**best, "p": min(1.0, len(lines) * best["p"]), "ruts": ruts}


def line_spans(by_side: np.ndarray, grid: np.ndarray, arcs: tuple, line: dict, dx: float) -> list[list[float]]:
    """Where along the drive the strongest line (`strongest_line`) stands, as base_link arc
    intervals [m]: `locate.line_zone` on the ruts that carry it ((2, S) on the own-track arc
    grid (S,) [m]; arcs as for Profiles.floor_series), over the segment its drive-wide
    strength needs (`locate.zone_segment`), gaps under half a segment bridged."""
    rows = {"left": by_side[:1], "right": by_side[1:], "both": by_side}[line.get("ruts", "both")]
    segment = zone_segment(line["ratio"], len(rows), rows.shape[1] * dx)
    on = line_zone(rows, dx, line["wavelength"], segment)
    if not on.any():
        return []
    on = ndimage.binary_closing(on, np.ones(max(1, int(segment / 2 / dx)), bool), border_value=0)
    s = np.mean([np.interp(grid, own, base) for base, own in arcs], 0)
    edges = np.flatnonzero(np.diff(np.r_[0, on.astype(np.int8), 0])).reshape(-1, 2)   # runs [a, b)
    return [[round(float(s[a]) - dx / 2, 2), round(float(s[b - 1]) + dx / 2, 2)] for a, b in edges]


def _spans(flags: np.ndarray, s0: np.ndarray, s1: np.ndarray) -> list[list[float]]:
    """Merge the [s0, s1) spans of flagged windows into intervals, m."""
    out: list[list[float]] = []
    for f, a, b in zip(flags, s0, s1, strict=True):
        if not f:
            continue
        if out and a <= out[-1][1] + 1e-9:
            out[-1][1] = max(out[-1][1], float(b))
        else:
            out.append([float(a), float(b)])
    return [[round(a, 2), round(b, 2)] for a, b in out]


def evidence_for(ext: catalogue.Extension, rows: list[dict], cov: dict[str, np.ndarray], zones: dict,
                 n_tracks: int, cfg: DiagnosisConfig, held_out: np.ndarray, ahead: int,
                 z_locate: float = 3.0, material: float = 0.0) -> dict:
    """Location evidence for one catalogue term: {testable, p, statistic}.

    Sinkage terms: Fisher's combination of two correlations over windows, each with the
    effective-sample-size correction: the fitted sinkage (mean over tracks; for lateral load
    the right-minus-left difference) against the term's covariate, and the held-out cost
    against the covariate's change to the neighbouring windows (a missing term shows where
    its covariate changes). Shape terms: the largest rut-floor / rut-wall / berm profile z
    (SHAPE_ZONES; the berm is not a location test, as its height follows chi, but steeper
    walls under a flat or rounded tyre show there first, as soil missing beside the rut);
    they are testable only when such a zone's residual is significant (|z| > z_locate, and
    its mean beyond `material`: 0 in `diagnose`, where materiality is left to the held-out
    test), since a shape term has nothing else to show in."""
    d = np.array([[r[f"d{t + 1}"] for t in range(n_tracks)] for r in rows], np.float64)
    if ext.covariate is None:
        z = max(abs(zones[zn]["z"]) if abs(zones[zn]["mean"]) > material else 0.0 for zn in SHAPE_ZONES)
        raw = max(abs(zones[zn]["z"]) for zn in SHAPE_ZONES)
        return {"testable": bool(z > z_locate), "p": float(min(1.0, 2 * len(SHAPE_ZONES) * stats.norm.sf(z))),
                "statistic": f"floor/wall/berm profile |z| = {raw:.1f}" + ("" if z > 0 else ", below materiality")}
    x = cov[ext.covariate]
    spread = float(np.nanstd(x))
    if spread < cfg.min_spread.get(ext.covariate, 0.0):
        return {"testable": False, "p": 1.0, "statistic": f"{ext.covariate} spread {spread:.3g} too small"}
    if ext.id == "lateral_load_transfer" and n_tracks >= 2:
        y = (d[:, 1] - d[:, 0]) / np.maximum(d.mean(1), 1e-4)
    else:
        y = d.mean(1)
    c = correlation(x, y)
    change = np.zeros(len(x))
    for off in (-ahead, ahead):
        shifted = np.roll(x, -off)
        valid = (np.arange(len(x)) + off >= 0) & (np.arange(len(x)) + off < len(x))
        change += np.where(valid, np.abs(shifted - x), 0.0)
    c2 = correlation(change, held_out)
    p2 = c2.p if c2.r > 0 else 1.0
    p = float(stats.chi2.sf(-2 * (math.log(max(c.p, 1e-300)) + math.log(max(p2, 1e-300))), 4))
    return {"testable": True, "p": p, "statistic": f"sinkage r = {c.r:+.2f} (n_eff {c.n_eff:.1f}), "
                                                   f"held-out cost vs change r = {c2.r:+.2f} (n_eff {c2.n_eff:.1f})"}


def plainest(fits: dict, best: tuple, declared, z: float = 1.96) -> str:
    """The dig order to keep: `best` (order, section)'s, unless the robot's own section under
    another order fits the windows as well (`stats.paired_z` of best over it below z): then
    that order, the robot's section kept. Noise tells apart pairs that fit alike, and a
    section taken to stand in for the other order moves d (a crowned tyre digging all at once
    for a flat one digging axle by axle, on a recording made elsewhere). fits: {(order,
    section): the windows' residuals (W,), m}."""
    if best[1] == declared:
        return best[0]
    for (order, sec), w in fits.items():
        if sec == declared and order != best[0] and paired_z(w, fits[best]) < z:
            return order
    return best[0]


def fit_nuisance_model(pair, cfg: DiagnosisConfig, est: EstimatorConfig, sim: SimConfig, progress=None,
                       cache: PassCache | None = None, pool=None, shared: dict | None = None):
    """The tyre section and the dig order as nuisances (`fit_section`; SimConfig.dig_order):
    the section searched over cfg.sections under sim's order, then each other order of
    cfg.dig_orders at the best few sections; the lowest mean window residual wins, unless the
    robot's own section fits as well under one order (`plainest`).

    Returns (the pair with that section, sim with that order, section evidence, dig-order
    evidence (None when only one order was tried), run_pass keywords, the sections a footprint
    or wall term may choose from). pool: a parallel.PassPool that scores the sections first (given
    the pair, unless `shared`: run_pass's keywords, already known and given to the pool)."""
    section, dig = None, None
    declared = section_of(pair)
    if not cfg.sections and not set(cfg.dig_orders) - {sim.dig_order}:
        return pair, sim, section, dig, shared or {}, ()

    def best_few(costs):
        return tuple(dict.fromkeys([*sorted(costs, key=costs.get)[:cfg.footprint_sections], declared]))

    if pool is not None:                  # the pair's own section here, the others as tasks
        if not shared:
            shared = section_cost(pair, est, sim, declared, cache=cache)[1]
            pool.share(pair, shared)
        pool.run("section", [(est, sim, sec, 3, None) for sec in section_candidates(pair, cfg.sections)[1:]])
    best, costs, shared, windows = fit_section(pair, est, sim, cfg.sections, progress=progress, cache=cache,
                                               shared=shared)
    orders, tried, by_order = {sim.dig_order: costs[best]}, best_few(costs), {sim.dig_order: costs}
    fits = {(sim.dig_order, best): windows[best], (sim.dig_order, declared): windows[declared]}
    others = list(dict.fromkeys(o for o in cfg.dig_orders if o != sim.dig_order))
    if pool is not None:
        pool.run("section", [(est, sim.replace(dig_order=o), sec, 3, None) for o in others for sec in tried])
    for order in others:
        alt = sim.replace(dig_order=order)
        b, c, shared, w = fit_section(pair, est, alt, tried, shared=shared, cache=cache)
        orders[order], by_order[order] = c[b], c
        fits.update({(order, b): w[b], (order, declared): w[declared]})
        if c[b] < costs[best]:
            sim, best, costs = alt, b, c
    order = plainest(fits, (sim.dig_order, best), declared)
    if order != sim.dig_order:
        sim, best, costs = sim.replace(dig_order=order), declared, by_order[order]
        orders[order] = costs[declared]
    if len(orders) > 1:
        dig = {"declared": next(iter(orders)), "fitted": sim.dig_order, "residual": orders}
    if cfg.sections:
        section = {"declared": list(declared), "fitted": list(best),
                   "residual": [[f, e, c] for (f, e), c in costs.items()]}
    return with_section(pair, best), sim, section, dig, shared, best_few(costs) if cfg.sections else ()


def _revisit(pair, cfg: DiagnosisConfig, est: EstimatorConfig, sim: SimConfig, base: Pass, n_tracks: int,
             progress=None, cache: PassCache | None = None) -> tuple[float, dict | None, object]:
    """Hardening on the same ground (revisits.hardening_across_visits) on a pair with visit
    layers, at half the family-wise level; where it names a law, the sinkage pass by pass under
    it (revisits.per_pass_fit, the dict's `per_pass`). Its passes kept in and read back from
    `cache`. Returns (the level left to the catalogue's candidates, the test's dict and the
    per-visit pass (revisits.VisitPass), both None without visit layers)."""
    if getattr(pair, "visit_front", None) is None:
        return cfg.alpha_accept, None, None
    vp = visit_pass(pair, est, sim, base, cache)
    rev = hardening_on_visits(pair, cfg, est, sim, base, n_tracks, cache, vp)
    if progress is not None:
        progress.update(1)
    return cfg.alpha_accept / 2, rev, vp


def hardening_on_visits(pair, cfg: DiagnosisConfig, est: EstimatorConfig, sim: SimConfig, base, n_tracks: int,
                        cache: PassCache | None = None, vp=None) -> dict:
    """`_revisit`'s test (at half cfg.alpha_accept) and its pass-by-pass fit where it names a
    law, on the base pass's map nuisance and path index (`base`: a Pass, or anything with
    them), each kept in and read back from `cache`; a parallel.PassPool runs it beside the
    candidates' passes. vp: the per-visit pass when already run (`visit_pass`). Returns the
    test's dict."""
    vp = vp if vp is not None else visit_pass(pair, est, sim, base, cache)
    rev = hardening_across_visits(vp, cfg.alpha_accept / 2, cfg.effect_materiality, cfg.block_m, n_tracks,
                                  est.stride, max(1, int(round(est.window / est.stride))))
    if rev["accepted"]:
        rev["per_pass"] = kept(cache, "per_pass", (section_of(pair), rev["g"]),
                               lambda: per_pass_fit(pair, est, sim, rev["g"], nuisance=base.nuisance,
                                                    index=base.index))
    return rev


def visit_pass(pair, est: EstimatorConfig, sim: SimConfig, base: Pass, cache: PassCache | None = None):
    """The per-visit pass of the hardening test (revisits.run_visits) on the base pass's map
    nuisance and path index, kept in and read back from `cache`; a parallel.PassPool runs it
    beside the candidates' passes."""
    return kept(cache, "visits", (section_of(pair), sim.dig_order),
                lambda: run_visits(pair, est, sim, nuisance=base.nuisance, index=base.index))


def _named_on_visits(revisit: dict | None, best) -> bool:
    """Hardening is named on the ground driven again when its test there accepted it and no
    other catalogue term was (a term accepted on the last view wins: its own evidence)."""
    return revisit is not None and revisit["accepted"] and (best is None or best.ext.id == "multi_pass_hardening")


def _visit_costs(revisit: dict, residual: float) -> tuple[dict, dict, dict]:
    """cost_before, cost_after and extension_parameters of hardening named on the same
    ground: the cost of predicting the later visits from the first visit's soil without and
    with the law [m] (the windows' mean residual [m] beside them), the law's coefficient: for
    the geometric law, g of the fit pass by pass where there is one (every wheel's pass counted,
    revisits.per_pass_fit), else the cross-visit cost's."""
    before = {"residual": residual, "prediction": revisit["cost_before"]}
    after = {"residual": residual, "prediction": revisit["cost_after"]}
    c, pp = revisit["coefficient"], revisit.get("per_pass") or {}
    if revisit["parameter"] == "g_pass" and "g" in pp:
        c = pp["g"]
    return before, after, {revisit["parameter"]: round(c, 4)}


def _screen_shapes(ev: dict, pair, cfg: DiagnosisConfig, est: EstimatorConfig, sim: SimConfig, drive: DriveSignals,
                   base: Pass, progress=None, cache: PassCache | None = None, pool=None) -> None:
    """A shape term no cross-track zone located is testable still where the windows fit their
    own ground better with it (`fit.own_fit_screen`, at alpha_locate): its location evidence
    `ev[id]` (`evidence_for`) updated in place."""
    shapes = [e for e in catalogue.CATALOGUE.values() if e.covariate is None and not ev[e.id]["testable"]]
    if shapes and progress is not None:
        progress.set_postfix_str("shape terms' own fit")
    for i, scr in own_fit_screen(pair, est, sim, shapes, drive, base, cache, pool).items():
        ev[i] = {"testable": scr["p"] < cfg.alpha_locate, "p": scr["p"],
                 "statistic": f"{ev[i]['statistic']}; {scr['statistic']}"}


@dataclass
class Located:
    """What the base pass shows of the mismatch before any term is fitted (`locate_mismatch`):
    s (W,) the window centres [m]; cov {signal: (W,)} the windows' covariates
    (covariates.window_signals); zones and asym the cross-track zone statistics and the rut
    floor's left/right asymmetry (locate.Profiles); arcs per side (left, right) ((N,) base_link
    arc, (N,) that side's track arc) [m]; fs (S,) the rut floor's base_link arc lengths [m];
    fgrid (S,) and fr (2, S) each rut along its own track [m]; line the strongest spectral line
    (`strongest_line`); z_locate and material the location tests' z level and materiality [m]."""

    s: np.ndarray
    cov: dict
    zones: dict
    asym: dict
    arcs: tuple
    fs: np.ndarray
    fgrid: np.ndarray
    fr: np.ndarray
    line: dict
    z_locate: float
    material: float


@dataclass
class Choice:
    """The candidates' acceptance (`choose_terms`): best the term a diagnosis names (the first
    of `by_gain`, None when none passed), z_crit {id: the z level it was tested at}, gain_min
    the smallest mean held-out gain a term must bring [m], pairwise the named term against the
    runner-up (None with fewer than two named)."""

    best: CandidateFit | None
    z_crit: dict
    gain_min: float
    pairwise: dict | None


@dataclass
class Verdict:
    """What the diagnosis says of the drive (`location_verdict`, `name_cause`): verdict, where
    (cross-track zone `cross`, along-track `spans` [[s0, s1], ...] [m], `covariate` or None),
    the named term's id (`named`, None when adequate or unexplained) and its fit (`best`, None
    also when hardening is named on the ground driven again), cost_before and cost_after
    ({residual, prediction} [m]) and the extension's parameters."""

    verdict: str
    cross: str
    spans: list
    covariate: str | None
    named: str | None
    best: CandidateFit | None
    before: dict
    after: dict
    params: dict


def base_pass(pair, cfg: DiagnosisConfig, est: EstimatorConfig, sim: SimConfig, shared: dict, progress=None,
              cache: PassCache | None = None) -> Pass:
    """The base model's pass over the whole drive: `fit.run_pass` with cross-track profiles,
    held-out scores at cfg.offsets and the stitched H_b, on the pair and dig order that
    `fit_nuisance_model` chose and with its run_pass keywords `shared`; read back from or kept
    in `cache` (label "base"), one progress step. Returns the Pass (costs in m); raises
    ValueError on a drive of fewer than 6 fitted windows."""
    def tell(k, o, est):
        if progress is not None and k % 5 == 0:
            progress.set_postfix_str(f"base window {k}")

    base = run_pass(pair, est, sim, profiles=True, on_window=tell, offsets=cfg.offsets, stitch=True, cache=cache,
                    **shared)
    if progress is not None:
        progress.update(1)
    rows = base.rows
    if len(rows) < 6 or np.isfinite(base.residual).sum() < 6:
        raise ValueError(f"drive too short to diagnose: {len(rows)} windows of {est.window} m "
                         f"(need at least 6 fitted windows)")
    return base


def locate_mismatch(pair, cfg: DiagnosisConfig, est: EstimatorConfig, base: Pass, drive: DriveSignals) -> Located:
    """Where the base model misses, before any term is fitted: the windows' covariates
    (DriveSignals `drive` over each window of est.window m), the cross-track zones and the rut
    floor's left/right asymmetry of the base pass's profiles, each rut along its own wheels'
    track and its strongest spectral line, and the location tests' z level (family-wise
    cfg.alpha_locate over N_LOCATE_TESTS tests) and materiality (cfg.materiality of the mean
    noise floor, m). Returns them as a `Located`."""
    robot = pair.robot
    window = est.window
    rows = base.rows
    s = np.array([r["s"] for r in rows])
    cov = window_signals(drive, [(c - window / 2, c + window / 2) for c in s], robot)
    prof = base.profiles
    zones = prof.zone_stats()
    asym = prof.asymmetry()
    base_arc = path_arc(pair.poses)
    sides = [robot.wheels[robot.wheels[:, 1] >= 0, 1], robot.wheels[robot.wheels[:, 1] < 0, 1]]
    arcs = tuple((base_arc, side_arc(pair.poses, float(y.mean()))) if len(y) else (base_arc, base_arc)
                 for y in sides)
    fs = prof.floor_series()[0]                                # base_link arc length, m
    # each rut along its own wheels' track, across the tyre's contact width (its lugs print there)
    fgrid, fr = prof.floor_series(by_side=True, arcs=arcs, band=prof.radius)
    line = strongest_line(fr, pair.dx)
    z_loc = z_two_sided(cfg.alpha_locate / N_LOCATE_TESTS)
    material = cfg.materiality * float(np.nanmean(base.floor))
    return Located(s, cov, zones, asym, arcs, fs, fgrid, fr, line, z_loc, material)


def fit_candidates(pair, cfg: DiagnosisConfig, est: EstimatorConfig, sim: SimConfig, base: Pass,
                   drive: DriveSignals, where: Located, tried: tuple, progress=None, cache: PassCache | None = None,
                   pool=None) -> tuple[dict, list[str], list[CandidateFit]]:
    """The catalogue's terms ranked by their location evidence (`evidence_for`; shape terms no
    zone located screened on their own fit, `_screen_shapes`), and the leading cfg.n_fit
    testable ones fitted (`fit.fit_extension`, footprint and wall terms choosing among the
    sections `tried`); on `pool`, every candidate's first trial passes (and the per-visit pass)
    and then the rest run as tasks first. Returns (location evidence {id: {testable, p,
    statistic}}, the ranked ids, their CandidateFits in that order)."""
    rows, n_tracks = base.rows, pair.robot.n_tracks
    ahead = max(1, int(round(est.window / est.stride)))
    ev = {e.id: evidence_for(e, rows, where.cov, where.zones, n_tracks, cfg, base.held_out, ahead, where.z_locate)
          for e in catalogue.CATALOGUE.values()}
    if pool is not None:
        pool.share(pair, shared_of(base), base)
    _screen_shapes(ev, pair, cfg, est, sim, drive, base, progress, cache, pool)
    ranked = sorted((i for i in ev if ev[i]["testable"]), key=lambda i: ev[i]["p"])[:cfg.n_fit]
    theta0 = None
    if pool is not None:
        _candidate_tasks(pool, pair, cfg, est, sim, ranked, tried)
    fits: list[CandidateFit] = []
    for ext_id in ranked:
        f = fit_extension(pair, est, sim, catalogue.get(ext_id), drive, base, cfg.block_m, cfg.refine_steps,
                          theta0, progress, cfg.offsets, tried, cache)
        fits.append(f)
    return ev, ranked, fits


def _candidate_tasks(pool, pair, cfg: DiagnosisConfig, est: EstimatorConfig, sim: SimConfig, ranked: list[str],
                     tried: tuple) -> None:
    """The candidates' passes as tasks on `pool` (parallel.PassPool), in one batch: the per-visit
    pass and the pass-by-pass fit it may ask for (on a pair with visit layers,
    `hardening_on_visits`), then per candidate its first trial passes (`trial_sides`;
    a footprint or wall term's section scores at them, `fit.fit_section` over `tried`, tasks of
    their own that its pass waits for) and the rest of its fit, which waits for them. Wall and
    footprint terms first (the longest fits), then in the order of `ranked`. A wall term's
    passes are the slowest (the two-angle relaxation) and its fit the longest chain of passes:
    the section scores of each side's second trial are tasks too (beside its first pass), which
    the rest of its fit waits for (run ahead: the fit needs them where its first trial lowers
    the cost). Last, with cfg.learned, each fold's learned term, then each fold's model of it
    (`learned.fold_task`)."""
    head = (est, sim, section_of(pair))
    tail = (cfg.offsets, tried, cfg.refine_steps, cfg.block_m)
    tasks: list[tuple[str, tuple]] = []
    after: list[tuple[int, ...]] = []
    if getattr(pair, "visit_front", None) is not None:
        tasks.append(("visits", (est, sim, cfg)))
        after.append(())
    shape = sorted(ranked, key=lambda i: catalogue.get(i).kind not in ("radius", "wall"))
    for i in shape:
        ext, firsts = catalogue.get(i), []
        for side in trial_sides(ext):
            scores = []
            if ext.kind in ("radius", "wall") and tried:
                for sec in section_candidates(pair, tried):
                    scores.append(len(tasks))
                    tasks.append(("trial_section", (*head, i, side[0], sec)))
                    after.append(())
            firsts.append(len(tasks))
            tasks.append(("pass", (*head, i, side[0], *tail)))
            after.append(tuple(scores))
            if ext.kind == "wall" and tried and len(side) > 1:
                for sec in section_candidates(pair, tried):
                    firsts.append(len(tasks))
                    tasks.append(("trial_section", (*head, i, side[1], sec)))
                    after.append(())
        tasks.append(("refine", (*head, i, None, *tail)))
        after.append(tuple(firsts))
    if cfg.learned:                       # the learned modifier's folds, filling the pool's gaps
        choices = (len(tasks), len(tasks) + 1)
        for stage, wait in (("choice", ()), ("model", choices)):
            for fold in (0, 1):
                tasks.append(("learned", (est, sim, section_of(pair), cfg, fold, stage)))
                after.append(wait)
    if tasks:
        pool.run(tasks[0][0], [], others=tasks, after=after)


def choose_terms(fits: list[CandidateFit], ranked: list[str], ev: dict, cfg: DiagnosisConfig, base: Pass,
                 alpha: float) -> Choice:
    """Which fitted candidates pass: each tested in order of its location evidence `ev` at the
    family-wise level `alpha` (what `_revisit` left to the catalogue) by the fallback procedure
    (`accept_in_order`; gains of at least cfg.gain_materiality of the base model's mean
    held-out cost, m), then the named ones ordered by their held-out gain (`by_gain`) and the
    first set against the runner-up (`stats.paired_improvement`). Returns the `Choice`."""
    gain_min = gain_material(cfg.gain_materiality, base.held_out)
    z_crit = dict(zip(ranked, accept_in_order(fits, [ev[i]["p"] for i in ranked], alpha,
                                              cfg.lead_share, gain_min, -cfg.own_fit_z,
                                              [catalogue.signs(f.ext) for f in fits], cfg.effect_materiality),
                      strict=True))
    accepted = by_gain(fits, gain_min, -cfg.own_fit_z, cfg.effect_materiality)
    best = accepted[0] if accepted else None
    pairwise = None
    if len(accepted) > 1:
        m, se, z = paired_improvement(accepted[1].held_out, best.held_out)
        pairwise = {"runner_up": accepted[1].ext.id, "improvement": m, "se": se, "z": z,
                    "named_passed": bool(best.accepted), "runner_up_passed": bool(accepted[1].accepted)}
    return Choice(best, z_crit, gain_min, pairwise)


def location_verdict(pair, cfg: DiagnosisConfig, est: EstimatorConfig, base: Pass, drive: DriveSignals,
                     where: Located, best: CandidateFit | None) -> tuple[str, str, list[list[float]], str | None]:
    """The location tests (family-wise cfg.alpha_locate over N_LOCATE_TESTS tests: the located
    zones, the rut floor's asymmetry, the spectral line) and the verdict they and the named
    term `best` give: missing_physics where a term is named (where its held-out gain stands out,
    `stats.outliers`), unexplained where only a location test is significant (where the line
    or the zone's residual stands, and the covariate that follows it, if any), else adequate.
    Returns (verdict, cross-track zone, along-track spans [[s0, s1], ...] [m], covariate or
    None)."""
    robot = pair.robot
    window, stride = est.window, est.stride
    s, zones, asym, line, fr, fgrid, arcs, fs = (where.s, where.zones, where.asym, where.line, where.fr,
                                                 where.fgrid, where.arcs, where.fs)
    z_loc, material = where.z_locate, where.material
    prof = base.profiles
    sig_zones = [zn for zn in LOCATED_ZONES
                 if abs(zones[zn]["z"]) > z_loc and abs(zones[zn]["mean"]) > material]
    sig_asym = abs(asym["z"]) > z_loc and abs(asym["mean"]) > material
    sig_line = line["p"] < cfg.alpha_locate / N_LOCATE_TESTS
    located = bool(sig_zones or sig_asym or sig_line)
    s0, s1 = s - window / 2, s + window / 2
    covariate = None
    if best is not None:
        verdict = "missing_physics"
        gain = base.held_out - best.held_out            # scored on the neighbouring windows' ground
        spans = _spans(outliers(gain), s0, s1)
        covariate = best.ext.covariate
        if sig_zones:
            cross = sig_zones[0] if len(sig_zones) == 1 else "mixed"
        else:
            cross = best.ext.zone
    elif located:
        verdict = "unexplained"
        if sig_line:
            cross = "rut_floor"
            spans = line_spans(fr, fgrid, arcs, line, pair.dx) or (
                [[round(float(fs[0]), 2), round(float(fs[-1]), 2)]] if len(fs) else [])
            covariate = "arc_length"
        else:
            if sig_zones:
                strongest = max(sig_zones, key=lambda zn: abs(zones[zn]["z"]))
                cross = strongest if len(sig_zones) == 1 else "mixed"
                series = prof.segment_zone_series(strongest)
            else:                                            # left/right asymmetry of the rut floor
                cross, series = "rut_floor", asym["series"]
            sd = np.nanstd(series)
            seg = np.array(prof.seg_s)
            far = np.abs(np.nan_to_num(series - np.nanmean(series))) > 2 * sd
            spans = _spans(far, seg - stride / 2, seg + stride / 2) if sd > 0 else []
            seg_cov = window_signals(drive, [(c - stride / 2, c + stride / 2) for c in prof.seg_s], robot)
            tests = {n: correlation(seg_cov[n], series) for n in SIGNALS}
            name, c = min(tests.items(), key=lambda kv: kv[1].p)
            covariate = name if c.p < cfg.alpha_locate / len(SIGNALS) else None
    else:
        verdict, cross, spans = "adequate", "mixed", []
    return verdict, cross, spans, covariate


def name_cause(base: Pass, best: CandidateFit | None, revisit: dict | None, window: float, verdict: str,
               cross: str, spans: list[list[float]], covariate: str | None) -> Verdict:
    """The named term, its costs and parameters: the base model's mean window residual and
    held-out prediction cost [m] before, the named term's after, and its reported parameters
    (catalogue.reported_parameters); hardening named on the ground driven again instead where
    its test there accepted it and no other term was named (`_named_on_visits`: the later
    visits' spans of `window` m, `_visit_costs`). verdict, cross, spans, covariate: those of
    `location_verdict`. Returns the `Verdict`."""
    before = {"residual": float(np.nanmean(base.residual)), "prediction": float(np.nanmean(base.prediction))}
    after = before if best is None else {"residual": float(np.nanmean(best.residual)),
                                         "prediction": float(np.nanmean(best.prediction))}
    params = ({} if best is None else
              catalogue.reported_parameters(best.ext, best.k, best.passes[best.k].rows))
    named = best.ext.id if best is not None else None
    if _named_on_visits(revisit, best):      # hardening named on the ground driven again
        verdict, cross, covariate, best, named = "missing_physics", "rut_floor", "passes", None, "multi_pass_hardening"
        spans = _spans(np.ones(len(revisit["s"]), bool), np.array(revisit["s"]) - window / 2,
                       np.array(revisit["s"]) + window / 2)
        before, after, params = _visit_costs(revisit, before["residual"])
    return Verdict(verdict, cross, spans, covariate, named, best, before, after, params)


def learned_check(pair, cfg: DiagnosisConfig, est: EstimatorConfig, sim: SimConfig, base: Pass,
                  drive: DriveSignals, choice: Choice, named: str | None = None, visits=None, progress=None,
                  cache: PassCache | None = None) -> tuple[learned.LearnedFit | None, dict | None]:
    """The learned modifier (`learned.learn`) and its test: accepted where both folds chose one
    term with one direction and, as a catalogue term must, its combined z passes the level of
    cfg.alpha_accept for a two-signed coefficient (`stats.level_z`), its gain is material
    (choice.gain_min), its effect at least cfg.effect_materiality and the windows' own fit no
    worse (cfg.own_fit_z); for chi and beta (one factor per visit simulated, which the window's
    own fit takes up) the held-out z alone, and no own-fit condition; not tested where its law is
    that of the catalogue term `named` (`learned.learn`). visits: the per-visit pass of a pair
    with visit layers (`_revisit`), whose chi and beta are tested across visits. Returns (the
    fit, its description for learned.json) or (None, None) with cfg.learned off."""
    if not cfg.learned:
        return None, None
    fit = learned.learn(pair, est, sim, base, drive, cfg, cache, progress, named)
    z_need = level_z(cfg.alpha_accept, 2)
    if fit.terms and fit.terms[0].parameter in ("chi", "beta"):
        # a factor per visit simulated: the window's own fit takes it up whole (its chi or beta
        # scaled), so its own residual carries no evidence, and the held-out test stands alone
        fit.z, fit.own_z = fit.held_z, math.inf
    fit.accepted = bool(fit.terms and fit.z > z_need and fit.improvement >= choice.gain_min
                        and fit.effect >= cfg.effect_materiality and fit.own_z >= -cfg.own_fit_z)
    described = learned.describe(fit, z_need)
    if fit.held_out is not None:
        s = np.array([r["s"] for r in base.rows])
        described["spans"] = _spans(outliers(base.held_out - fit.held_out), s - est.window / 2, s + est.window / 2)
        described["after"] = {"residual": float(np.nanmean(fit.residual)),
                              "prediction": float(np.nanmean(fit.prediction))}
    if visits is not None:                                 # the deposit and repose on ground driven again
        rows = visits.rows
        tests = [learned.visit_test(rows, p, cfg.alpha_accept / 4, cfg.effect_materiality, later=visits.later)
                 for p in ("chi", "beta")]
        described["visits"] = tests
        found = [t for t in tests if t["accepted"]]
        if found and not fit.accepted:
            t = max(found, key=lambda t: t["z"])
            described["terms"] = [learned.describe_visits(t)]
            described["accepted"] = True
            wins = learned.visit_parameters(rows, t["parameter"])
            described["spans"] = _spans(np.ones(len(wins), bool), np.array([w[0] for w in wins]) - est.window / 2,
                                        np.array([w[0] for w in wins]) + est.window / 2)
    if progress is not None:
        progress.update(1)
    return fit, described


def with_learned(told: Verdict, fit: learned.LearnedFit | None, described: dict | None) -> Verdict:
    """The verdict with the learned modifier: named where it was accepted and the catalogue named
    nothing, or named a term of another law (another parameter or covariate) whose mean
    held-out gain the learned one's exceeds (both passed their own tests: they are told apart
    as `by_gain` tells the catalogue's terms apart); a parameter that changes between the
    visits of the same ground (`learned.visit_test`) only where nothing is named. The name is
    the catalogue term whose law the curve is (`learned.catalogue_match`), else "learned"; its
    parameters the factor over the covariate's span (`<parameter>_factor`, `<covariate>_from`, `<covariate>_to`)."""
    if described is None or not described["accepted"]:
        return told
    term = described["terms"][0]
    match = term["catalogue_match"]
    if told.verdict == "missing_physics":
        if told.best is None or match == told.named or not fit.accepted:
            return told
        if not fit.improvement > told.best.improvement:
            return told
    spans, after = described["spans"], described.get("after", told.before)
    located = told.verdict == "unexplained" and told.cross != "mixed"
    cross = told.cross if located else learned.ZONE_OF[term["parameter"]]
    params = {f"{term['parameter']}_factor": round(term["factor"], 4), f"{term['covariate']}_from": term["from"],
              f"{term['covariate']}_to": term["to"]}
    described["named"] = True
    return Verdict("missing_physics", cross, spans, term["covariate"], match or "learned", None, told.before,
                   after, params)


def explain_diagnosis(cfg: DiagnosisConfig, base: Pass, where: Located, ev: dict, fits: list[CandidateFit],
                      choice: Choice, section: dict | None, dig: dict | None, revisit: dict | None,
                      told: Verdict, learned_report: dict | None = None, blur: dict | None = None) -> Diagnosis:
    """The evidence behind the verdict (zones, asymmetry, spectral line, rut shape, the tests'
    levels, every candidate's location evidence `ev`, the nuisances' fits `section`, `dig` and `blur`,
    the hardening test `revisit`, what the named gain rests on, the covariates' correlations
    with the sinkage), the diagnosis.json summary (docs/formats.md 4; costs in m) and its
    explanation in words (report.explain). Returns the `Diagnosis`."""
    zones, asym, line, s, cov, z_loc = where.zones, where.asym, where.line, where.s, where.cov, where.z_locate
    prof, rows, best = base.profiles, base.rows, told.best
    evidence = {"zones": zones, "asymmetry": {k: v for k, v in asym.items() if k != "series"},
                "spectral_line": line, "rut_shape": prof.shape(z_loc),
                "z_locate": z_loc, "z_accept": choice.z_crit, "gain_material": choice.gain_min,
                "effect_material": cfg.effect_materiality,
                "own_z_min": -cfg.own_fit_z,
                "candidates": ev,
                "pairwise": choice.pairwise,
                "map_nuisance": base.nuisance.summary() if base.nuisance is not None else None,
                "map_nuisance_text": base.nuisance.describe() if base.nuisance is not None else None,
                "tyre_section": section,
                "dig_order": dig,
                "raster_blur": blur,
                "revisits": revisit,
                "basis": evidence_basis(base.held_out, best.held_out, s) if best is not None else None,
                "covariate_tests": {n: asdict(correlation(cov[n], np.array([r["d1"] for r in rows])))
                                    for n in SIGNALS}}
    summary = {
        "verdict": told.verdict,
        "missing_physics": told.named,
        "where": {"cross_track": told.cross, "along_track": told.spans, "covariate": told.covariate},
        "explanation": "",
        "cost_before": told.before,
        "cost_after": told.after,
        "noise_floor": float(np.nanmean(base.floor)),
        "extension_parameters": told.params,
        "candidates": [{"id": f.ext.id, "prediction": float(np.nanmean(f.prediction)), "accepted": bool(f.accepted)}
                       for f in fits],
    }
    from torchsoil.diagnosis.report import explain

    h_back = base.surfaces[1]                               # as the estimator fitted it (Estimator.h_back)
    residual = base.h_sim - h_back.astype(np.float32)       # drawn only (report.fig_residual_map)
    evidence["learned"] = learned_report
    diag = Diagnosis(summary, base, fits, best, evidence, {"s": s, **cov}, residual, base.index.s, revisit,
                     learned_report)
    summary["explanation"] = explain(diag)
    return diag


def diagnose(pair, cfg: DiagnosisConfig | None = None, est: EstimatorConfig | None = None,
             sim: SimConfig | None = None, progress=None, cache: PassCache | None = None, pool=None) -> Diagnosis:
    """Diagnose one terrain pair (torchsoil.io.terrain_pair.TerrainPair) with the diagnosis,
    estimator and simulator settings (their sections; defaults when None). progress:
    optional tqdm-like bar (update(n)). cache: where the finished passes are kept
    (checkpoint.PassCache): a diagnosis run again with the same cache reads them back, so an
    interrupted one resumes where it stopped. pool: a parallel.PassPool (`parallel.pass_pool`,
    with the same cache) that runs the independent passes (sections, dig orders, candidates)
    as parallel tasks first; the results are the same."""
    cfg, est, sim = cfg or DiagnosisConfig(), est or EstimatorConfig(), sim or SimConfig()
    est, blur, shared = fit_blur(pair, est, sim, cfg.blurs, cache, pool)
    pair, sim, section, dig, shared, tried = fit_nuisance_model(pair, cfg, est, sim, progress, cache, pool, shared)
    drive = DriveSignals.from_pair(pair)
    base = base_pass(pair, cfg, est, sim, shared, progress, cache)
    where = locate_mismatch(pair, cfg, est, base, drive)
    ev, ranked, fits = fit_candidates(pair, cfg, est, sim, base, drive, where, tried, progress, cache, pool)
    alpha, revisit, visits = _revisit(pair, cfg, est, sim, base, pair.robot.n_tracks, progress, cache)
    choice = choose_terms(fits, ranked, ev, cfg, base, alpha)
    told = name_cause(base, choice.best, revisit, est.window,
                      *location_verdict(pair, cfg, est, base, drive, where, choice.best))
    fit, described = learned_check(pair, cfg, est, sim, base, drive, choice, told.named, visits, progress, cache)
    told = with_learned(told, fit, described)
    return explain_diagnosis(cfg, base, where, ev, fits, choice, section, dig, revisit, told, described, blur)


def n_steps(cfg: DiagnosisConfig | None = None) -> int:
    """Upper bound on the estimator passes of one diagnosis (for a progress bar; one per visit
    pass on a pair with visit layers)."""
    cfg = cfg or DiagnosisConfig()
    trials = max(most_trials(e) for e in catalogue.CATALOGUE.values())
    return 2 + bool(cfg.sections) + cfg.n_fit * (trials + cfg.refine_steps) + cfg.learned   # + the per-visit pass


__all__ = ["ZONES", "Diagnosis", "DiagnosisConfig", "diagnose", "n_steps"]
