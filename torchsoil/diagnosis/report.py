"""Diagnosis outputs: DIR/diagnosis.json (exactly docs/formats.md section 4), a plain-language
report.md, figures and TensorBoard scalars."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.image import imread

from torchsoil.diagnosis.learned import WORDS
from torchsoil.plotting import coarse, coarse_extent

KEYS = ("verdict", "missing_physics", "where", "explanation", "cost_before", "cost_after", "noise_floor",
        "extension_parameters", "candidates")
VERDICTS = ("adequate", "missing_physics", "unexplained")
CROSS = ("rut_floor", "rut_wall", "berm", "outside", "mixed")


def _mm(x: float) -> str:
    return f"{1e3 * x:.2f} mm" if math.isfinite(x) else "n/a"


def explain(diag) -> str:
    """One paragraph, plain language, from a Diagnosis; ends with what was removed from the
    maps as measurement nuisance (offset, tilt) before anything was fitted, and the tyre
    section and dig order the base model was given."""
    removed = diag.evidence.get("map_nuisance_text")
    note = (f" Removed from H_b before fitting, as measurement rather than physics: {removed}."
            if removed else " No map offset was removed (estimator.nuisance.offset is off).")
    sec = diag.evidence.get("tyre_section")
    if sec is not None:
        (f, e), (f0, e0) = sec["fitted"], sec["declared"]
        note += (f" Tyre section fitted as a nuisance: taper flat to {f:.2f} of the radius, exponent {e:.2f}"
                 + (f" (the robot description: {f0:.2f}, {e0:.2f})." if (f, e) != (f0, e0)
                    else ", as the robot description says."))
    best = diag.best
    if best is not None and best.sections:
        k = min(best.sections, key=lambda q: abs(q - best.k))
        if best.sections[k] != best.sections[0.0]:
            f, e = best.sections[k]
            note += (f" With {best.ext.id} the tyre section that fits is another: taper flat to {f:.2f} of the "
                     f"radius, exponent {e:.2f}.")
    blur = diag.evidence.get("raster_blur")
    if blur is not None and blur["fitted"] > 0:
        note += (f" The simulated change is compared with H_b through a Gaussian blur of {blur['fitted']:g} cells "
                 "(fitted as a nuisance: the lidar map spreads a rut's walls).")
    dig = diag.evidence.get("dig_order")
    if dig is not None and dig["fitted"] != dig["declared"]:
        note += (" The wheels dig in turn (sim.dig_order: wheel): each trailing wheel digs again from the rut "
                 "the wheels ahead of it left; this fits the drive better than every wheel digging from the "
                 "surface before the robot, so d is the sinkage of each wheel, not of the robot, and a "
                 "hardening term counts every wheel's pass (a rear wheel in its front wheel's rut runs the "
                 "second).")
    named = diag.summary["verdict"] == "missing_physics"        # by a candidate, or on the ground driven again
    return _explain(diag) + ("" if named else _nearest(diag)) + learned_note(getattr(diag, "learned", None)) + note


def learned_text(learned: dict, s: dict, span: str) -> str:
    """The verdict's paragraph where the learned modifier is named (diagnosis.learned)."""
    t = learned["terms"][0]
    name = (f"the law of {t['catalogue_match']}" if t["catalogue_match"] else
            "a law no catalogue term has (missing_physics: learned)")
    if t["shape"] == "per_pass":
        v = next(v for v in learned["visits"] if v["parameter"] == t["parameter"])
        return (f"The base model leaves out {name}. {t['sentence']} Each visit of the ground driven again was "
                f"fitted on its own maps: the factor per pass is tested across the windows paired visit by visit "
                f"(z = {v['z']:.1f} against {v['z_level']:.1f}, {v['n_eff']:.0f} effective windows). It matters "
                f"at {span}. Noise floor {_mm(s['noise_floor'])}.")
    return (f"The base model leaves out {name}. {t['sentence']} A learned modifier (the parameter times exp of a "
            f"curve of the covariate, fitted through the simulator on each fold's windows and scored on the "
            f"other fold's) lowers the cost of predicting held-out ground from {_mm(s['cost_before']['prediction'])} "
            f"to {_mm(s['cost_after']['prediction'])} (paired over windows: {_mm(learned['improvement'])} +- "
            f"{_mm(learned['se'])}, z = {learned['held_z']:.1f}"
            + (f"; {learned['z']:.1f} with the windows' own fits" if learned["own_z"] is not None else "")
            + f", against {learned['z_needed']:.1f} allowed by noise). It matters most at {span}. "
            f"Noise floor {_mm(s['noise_floor'])}.")


def learned_markdown(learned: dict) -> str:
    """report.md's section on the learned modifier: each fold's screen and choice, the kept
    term's curve and the held-out test."""
    lines = ["| fold | steepest terms (gradient) | trial fits (objective, base 1) | chosen |",
             "| --- | --- | --- | --- |"]
    for i, f in enumerate(learned["folds"]):
        top = sorted(f["gradients"].items(), key=lambda kv: -kv[1])[:3]
        lines.append(f"| {i} | {', '.join(f'{k} {v:.3g}' for k, v in top) or '-'} | "
                     f"{', '.join(f'{k} {v:.3f}' for k, v in f['trials'].items()) or '-'} | {f['term'] or 'none'} |")
    for t in learned["terms"]:
        lines += ["", f"- {t['sentence']} Shape: {t['shape']}; knots {[round(k, 3) for k in t['knots']]} "
                  f"{t['unit']}, factors {[round(math.exp(v), 3) for v in t['log_factor']]}."]
    if learned["terms"] and not learned["tested"]:
        lines += ["", "The law of the catalogue term named: tested as that term, not again."]
    elif learned["terms"]:
        lines += ["", f"Held-out gain {_mm(learned['improvement'])} +- {_mm(learned['se'])}, z = "
                  f"{learned['held_z']:.2f} held-out, "
                  + (f"{learned['own_z']:.2f} own fit, {learned['z']:.2f} both " if learned["own_z"] is not None
                     else "no own-fit test (one factor per visit) ")
                  + f"(needed {learned['z_needed']:.2f}); effect {100 * learned['effect']:.0f} %; "
                  + ("named." if learned.get("named") else "accepted, not named." if learned["accepted"]
                     else "not accepted.")]
    else:
        lines += ["", "The folds chose no term in common: nothing learned."]
    return "\n".join(lines)


def learned_note(learned: dict | None) -> str:
    """A sentence on a learned modifier that was fitted but not named (short of its level, or a
    catalogue term predicted as well), else ''."""
    if not learned or learned.get("named"):
        return ""
    visits = [v for v in learned.get("visits") or [] if v.get("z", 0.0) > 1.0]
    seen = ""
    if visits:
        v = max(visits, key=lambda v: v["z"])
        cost = ""
        if v.get("cost_z") is not None and np.isfinite(v["cost_z"]):
            cost = (f"; with that law the first visit's soil predicts the later visits by "
                    f"{1e3 * v['cost_gain']:+.3f} mm, z = {v['cost_z']:.2f}")
        seen = (f" On the ground driven again, {WORDS[v['parameter']]} {'rises' if v['g'] > 1 else 'falls'} "
                f"by x{v['g']:.2f} per wheel pass between the visits (z = {v['z']:.2f} against {v['z_level']:.2f} "
                f"needed, {v['windows']} windows{cost}): not named.")
    if not learned.get("terms"):
        return seen
    t = learned["terms"][0]
    why = ("the catalogue's term predicts the held-out ground as well" if learned["accepted"] else
           "the law of the term named, tested as that term" if not learned["tested"] else
           f"z = {learned['z']:.2f} against {learned['z_needed']:.2f} needed")
    return (f" A learned modifier found: {t['sentence'][0].lower() + t['sentence'][1:-1]}; not named ({why})."
            + seen)



def _nearest(diag) -> str:
    """For a drive with no term accepted: the fitted candidate nearest its level (largest z
    minus the z it needed), when it gained at all, and what more data would give it. When
    both folds chose the same sign, also how much more of the same driving would reach the
    level at the gain measured: a paired z grows as the square root of the windows, so
    (z needed / z)^2 times the drive's length. A misfit of other physics that follows the
    covariate grows with the drive as well (docs/notes.md, Diagnosis)."""
    if diag.best is not None or not diag.fits:
        return ""
    need = diag.evidence["z_accept"]
    f = max(diag.fits, key=lambda f: f.z - need[f.ext.id])
    if not f.z > 0:
        return ""
    more = (f"more changes of its covariate ({f.ext.covariate.replace('_', ' ')}) along the drive"
            if f.ext.covariate is not None else "a longer drive")
    a, b = f.k_fold
    head = (f" Nearest to acceptance: {f.ext.id} ({f.ext.parameter} = {f.k:.3g}, folds {a:.3g} and "
            f"{b:.3g}), z = {f.z:.2f} against {need[f.ext.id]:.2f} needed")
    material = diag.evidence.get("gain_material", 0.0)
    if f.z > need[f.ext.id] and f.improvement < material:
        return (f"{head}, but its held-out gain, {1e3 * f.improvement:.2g} mm, is under the {1e3 * material:.2g} mm "
                f"a term must bring (diagnosis.gain_materiality): a steady but immaterial difference.")
    effect = diag.evidence.get("effect_material", 0.0)
    if f.z > need[f.ext.id] and getattr(f, "effect", math.inf) < effect:
        return (f"{head}, but at that coefficient it changes the model by {100 * f.effect:.2g} %, under the "
                f"{100 * effect:.2g} % a named cause must (diagnosis.effect_materiality): a steady difference too "
                f"small to be that physics.")
    own_min = diag.evidence.get("own_z_min", -math.inf)
    if f.z > need[f.ext.id] and f.own_z < own_min:
        where = (f" where the {f.ext.covariate.replace('_', ' ')} changes" if f.ext.covariate is not None
                 else " along the drive")
        return (f"{head}, but its windows fit their own ground worse with it (paired z of their residuals "
                f"{f.own_z:.2f}): it predicts the neighbouring ground better while it fits its own worse, as a term "
                f"standing in for soil that changes{where} does; not named.")
    if a != 0 and b != 0 and (a > 0) == (b > 0):
        more += (f" (at the gain measured here, about {(need[f.ext.id] / f.z) ** 2:.1f} x this drive's length of "
                 f"the same driving, if nothing else the model misses follows the same covariate)")
    return f"{head}; {more} would give it more evidence."


def shape_text(runs) -> str:
    """Profiles.shape runs [(from, to, mean residual), ...] [m] as plain language: where across
    the rut, outward from the wheel centre line, the recording lies above or below the model
    (residual = model - recording); "" when there are none."""
    parts = []
    for a, b, m in runs:
        span = (f"{1e3 * a:.0f} mm out" if a > 0 or b > 0 else "at the centre line") if abs(b - a) < 1e-9 \
            else f"{1e3 * a:.0f}-{1e3 * b:.0f} mm out"
        parts.append(f"{'above' if m < 0 else 'below'} {'the model' if not parts else 'it'} {span} (by {_mm(abs(m))})")
    return ", ".join(parts)


WHAT_CHANGES = {"multi_pass_hardening": "sinkage of a second pass over the same ground",
                "footprint_width": "footprint radius", "cohesive_walls": "slope (tangent) intact ground stands at"}


def effect_text(f) -> str:
    """How much an accepted term changes the model at its coefficient (CandidateFit.effects,
    catalogue.effect_size), as a sentence; empty without effect sizes."""
    e = (getattr(f, "effects", None) or {}).get(float(f.k))
    if e is None or not math.isfinite(e):
        return ""
    if f.ext.id in WHAT_CHANGES:
        return f" At that coefficient the term changes the {WHAT_CHANGES[f.ext.id]} by {100 * e:.0f} %."
    return f" At that coefficient the term changes the sinkage by {100 * e:.0f} % or more on a twentieth of the drive."


LAW_TEXT = {"geometric": "d_n = d_0 g^n", "hyperbolic": "d_n = d_0 / (1 + a n)", "power": "d_n = d_0 (1 + n)^b"}


def revisit_text(rev: dict, s: dict, span: str) -> str:
    """The explanation of hardening named on the same ground (revisits.hardening_across_visits)."""
    shape = rev["shape"] or "geometric"
    how = (f"a {shape} law fits best ({LAW_TEXT[shape]}, {rev['parameter']} = {rev['coefficient']:.3g})"
           if rev["shape"] else f"{LAW_TEXT['geometric']} with g = {rev['g']:.3g} per wheel pass (the drive does "
           f"not tell the laws' shapes apart: "
           + ", ".join(f"{k} {v['coefficient']:.3g}" for k, v in rev["laws"].items()) + ")")
    rut = rev["rut"]
    return (f"The base model leaves out: each later pass over the same ground sinks less than the first "
            f"(multi_pass_hardening), named on the ground driven more than once. {len(rev['s'])} windows were "
            f"fitted visit by visit; the first visit's soil predicts the later visits' ground at "
            f"{_mm(rev['cost_before'])} against their noise floor {_mm(rev['noise_floor'])}, and sinking less by "
            f"{how} brings it to {_mm(rev['cost_after'])} (g chosen on the other fold of blocks: "
            f"{rev['g_folds'][0]:.3g}, {rev['g_folds'][1]:.3g}; the gain over windows that share no ground: "
            f"z = {rev['z']:.1f} against {rev['z_level']:.1f}). Each pass sinks {100 * rev['effect']:.0f} % less "
            f"than the one before. The later visits dug ruts of {_mm(rut['measured'])}; the first visit's soil "
            f"would dig {_mm(rut['simulated_without_law'])}, with the law {_mm(rut['simulated_with_law'])}. The "
            f"mismatch lies on the rut floor and follows the passes; it matters at {span}."
            + per_pass_text(rev.get("per_pass")))


def _main_groups(pp: dict) -> list[dict]:
    """The per-pass fit's largest group of windows at each visit (revisits.per_pass_fit)."""
    best: dict[int, dict] = {}
    for grp in pp["visits"]:
        if grp["visit"] not in best or grp["windows"] > best[grp["visit"]]["windows"]:
            best[grp["visit"]] = grp
    return [best[v] for v in sorted(best)]


def per_pass_text(pp: dict | None) -> str:
    """One sentence on the sinkage pass by pass (revisits.per_pass_fit), or "" without it."""
    if not pp or "g" not in pp:
        return ""
    groups = _main_groups(pp)
    sinks = ", ".join(f"{1000 * q['sinkage']:.1f}" for grp in groups for q in grp["passes"])
    return (f" Fitted pass by pass (each wheel digging in turn from the rut the passes before it left, sinking "
            f"d g^n after n passes), every visit fits the same first-pass sinkage at g = {pp['g']:.3g} ("
            + ", ".join(f"{_mm(grp['d_first_pass'])} at visit {grp['visit']}" for grp in groups)
            + f"): the wheel passes sink {sinks} mm in turn" + _rut_text(pp.get("rut")) + ".")


def _rut_text(rut: dict | None) -> str:
    if not rut or not np.isfinite([rut["measured"], rut["simulated"]]).all():
        return ""
    return (f", and the later visits' ruts are {_mm(rut['simulated'])} simulated under the law, "
            f"{_mm(rut['measured'])} measured")


def basis_text(basis: dict | None) -> str:
    """What a named term's held-out gain rests on (stats.evidence_basis), or ""."""
    if not basis or not basis["blocks"]:
        return ""
    spans = ", ".join(f"{a:.1f}-{b:.1f} m" for a, b in basis["carriers"])
    half = (f"; half of it comes from {basis['carrier_blocks']} of them ({spans})" if basis["carriers"] else "")
    return (f" The gain rests on {basis['windows']} windows in {basis['blocks']} blocks of neighbours, as much "
            f"evidence as {basis['n_eff']:.1f} independent blocks{half}.")


def _across(zone: str) -> str:
    """Where across the rut a mismatch lies, in words (a zone, or `mixed`)."""
    return "across the rut (floor, walls and berms)" if zone == "mixed" else f"on the {zone.replace('_', ' ')}"


def _accepted_cell(f, diag) -> str:
    """The candidates table's `accepted` entry: whether the term passed its own test, and for a
    shape term named without (`run.by_gain`) that it was named as the better shape term."""
    if not f.accepted and getattr(diag, "best", None) is f:
        return "False; named: the better of the shape terms"
    return str(f.accepted)


def runner_up_text(pairwise: dict | None) -> str:
    """A sentence on the runner-up, where there is one (the evidence's `pairwise`: the named
    term's held-out gain over it [m], its se and z, and which of the two passed its own test:
    a shape term may be named short of its level once another shape term passed, `run.by_gain`)."""
    if not pairwise:
        return ""
    by = f"by {_mm(pairwise['improvement'])} +- {_mm(pairwise['se'])} (z = {pairwise['z']:.1f})"
    if not pairwise.get("named_passed", True):
        return (f" {pairwise['runner_up']} passed its test, so the rut's shape needs a term; of the shape terms the "
                f"named one predicts the held-out ground better, {by}, and it meets every condition but its own "
                f"level.")
    if not pairwise.get("runner_up_passed", True):
        return (f" {pairwise['runner_up']} also predicts the held-out ground better than the base model, short of "
                f"its own level; the named term does better, {by}.")
    return f" {pairwise['runner_up']} passed its test too; the named term predicts the held-out ground better {by}."


def _explain(diag) -> str:
    s, ev = diag.summary, diag.evidence
    before, after = s["cost_before"], s["cost_after"]
    where = s["where"]
    span = ", ".join(f"{a:.1f}-{b:.1f} m" for a, b in where["along_track"]) or "no particular stretch"
    rev = getattr(diag, "revisits", None)
    learned = getattr(diag, "learned", None) or {}
    if s["verdict"] == "missing_physics" and learned.get("named"):
        return learned_text(learned, s, span)
    if s["verdict"] == "missing_physics" and diag.best is None and rev is not None:
        return revisit_text(rev, s, span)
    if s["verdict"] == "missing_physics":
        f = diag.best
        par = s["extension_parameters"]
        k, v = f.ext.parameter, f"{par[f.ext.parameter]:.3g}"
        if "beta_intact_deg" in par:
            v += (f" (intact ground stands up to {par['beta_intact_deg']:.0f} deg, moved soil settles at "
                  f"{par['beta_loose_deg']:.0f} deg)")
        return (f"The base model leaves out: {f.ext.description} ({f.ext.id}). Adding it with {k} = {v} "
                f"lowers the cost of predicting the next window from {_mm(before['prediction'])} to "
                f"{_mm(after['prediction'])} (paired over windows: {_mm(f.improvement)} +- {_mm(f.se)}, "
                f"z = {f.held_z:.1f}; {f.z:.1f} with the windows' own fits, "
                + (f"against {ev['z_accept'][f.ext.id]:.1f} allowed by noise" if f.accepted else
                   f"short of its own level of {ev['z_accept'][f.ext.id]:.1f}")
                + "; coefficient chosen on other "
                f"windows than those it is scored on).{effect_text(f)}{basis_text(ev.get('basis'))}"
                f"{runner_up_text(ev.get('pairwise'))} The mismatch "
                f"lies {_across(where['cross_track'])}"
                f" and follows {where['covariate'] or 'the shape of the rut'}; it matters most at {span}. "
                f"Noise floor {_mm(s['noise_floor'])}.")
    if s["verdict"] == "unexplained":
        line = ev["spectral_line"]
        what = (f"a periodic pattern of wavelength {line['wavelength']:.3f} m and amplitude "
                f"{_mm(line['amplitude'])} along the rut floor ({line.get('ruts', 'both')} ruts; "
                f"{line['ratio']:.0f} x the spectral background)"
                if line["p"] < 1 and where["covariate"] == "arc_length" else
                f"a systematic residual on the {where['cross_track'].replace('_', ' ')}")
        tried = ", ".join(f"{c['id']}" for c in s["candidates"]) or "none testable"
        shape = shape_text(ev.get("rut_shape", []))
        shape = f"Across the rut, outward from the wheel centre line, the recording lies {shape}." if shape else ""
        return (f"Simulation and recording disagree in structure: {what}, at {span}"
                f"{', following ' + where['covariate'] if where['covariate'] else ''}. No catalogue term "
                f"explains it (tried: {tried}; none predicted held-out windows better than noise allows), so "
                f"no cause is named.{' ' + shape if shape else ''} Prediction cost {_mm(before['prediction'])}, "
                f"noise floor {_mm(s['noise_floor'])}.")
    z = ev["zones"]
    return (f"No significant structured mismatch: rut-floor, rut-wall and outside residuals average "
            f"{_mm(z['rut_floor']['mean'])} (z = {z['rut_floor']['z']:.1f}), {_mm(z['rut_wall']['mean'])} "
            f"(z = {z['rut_wall']['z']:.1f}) and {_mm(z['outside']['mean'])} (z = {z['outside']['z']:.1f}) "
            f"against |z| {ev['z_locate']:.1f} allowed, no periodic pattern, and no "
            f"catalogue term predicted held-out windows better than noise allows. Soil that varies along the "
            f"path is followed by the per-window parameters. Prediction cost {_mm(before['prediction'])}, "
            f"noise floor {_mm(s['noise_floor'])}.")


def validate_summary(d: dict) -> dict:
    """Check a diagnosis dict against docs/formats.md section 4; raises ValueError naming the key."""
    if set(d) != set(KEYS):
        raise ValueError(f"diagnosis.json keys {sorted(d)} differ from docs/formats.md section 4 {sorted(KEYS)}")
    if d["verdict"] not in VERDICTS:
        raise ValueError(f"verdict {d['verdict']!r} not in {VERDICTS}")
    if (d["verdict"] == "missing_physics") != (d["missing_physics"] is not None):
        raise ValueError("missing_physics must name an id exactly when the verdict is missing_physics")
    w = d["where"]
    if set(w) != {"cross_track", "along_track", "covariate"} or w["cross_track"] not in CROSS:
        raise ValueError(f"where {w} does not follow docs/formats.md section 4")
    for key in ("cost_before", "cost_after"):
        if set(d[key]) != {"residual", "prediction"}:
            raise ValueError(f"{key} must hold residual and prediction")
    for c in d["candidates"]:
        if set(c) != {"id", "prediction", "accepted"}:
            raise ValueError(f"candidate {c} must hold id, prediction, accepted")
    return d


def write_json(summary: dict, path: Path) -> Path:
    path.write_text(json.dumps(validate_summary(summary), indent=2))
    return path


# ------------------------------------------------------------------ figures
def fig_residual_map(diag, pair, path: Path) -> Path:
    r, f = coarse(diag.residual_map)
    fig = Figure(figsize=(10, 3.5))
    ax = fig.subplots()
    extent = coarse_extent(pair.origin, pair.dx, diag.residual_map.shape, f)
    lim = 3 * np.nanstd(r) if np.isfinite(r).any() else 1e-3
    im = ax.imshow(r.T * 1e3, origin="lower", extent=extent, cmap="RdBu_r", vmin=-1e3 * lim, vmax=1e3 * lim,
                   interpolation="nearest")
    fig.colorbar(im, ax=ax, label="simulated - measured H_b [mm]")
    sidx = coarse(diag.s_index)[0]
    xs = extent[0] + (np.arange(r.shape[0]) + 0.5) * f * pair.dx
    ys = extent[2] + (np.arange(r.shape[1]) + 0.5) * f * pair.dx
    located = np.zeros(sidx.shape, bool)                  # one outline for all spans: a contour each would
    for a, b in diag.summary["where"]["along_track"]:     # keep a grid each, as many as the drive has spans
        located |= np.isfinite(sidx) & (sidx >= a) & (sidx < b)
    if located.any():
        ax.contour(xs, ys, located.T.astype(np.float32), levels=[0.5], colors="k", linewidths=1.2)
    ax.plot(pair.poses[:, 1], pair.poses[:, 2], "k--", lw=0.5)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"base-model residual; located region outlined ({diag.summary['verdict']})")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def mean_sinkage(rows: list[dict]) -> np.ndarray:
    """(W,) mean of d1..dT per params row, m."""
    return np.array([np.mean([r[k] for k in r if k.startswith("d") and k[1:].isdigit()]) for r in rows])


def fig_covariate(diag, path: Path) -> Path:
    fig = Figure(figsize=(5.5, 4))
    ax = fig.subplots()
    w = diag.windows
    cov = diag.summary["where"]["covariate"]
    d = mean_sinkage(diag.base.rows)
    if cov in w and cov != "arc_length":
        ax.scatter(w[cov], 1e3 * d, s=12, label="base model: fitted sinkage")
        if diag.best is not None:
            k = min(diag.best.passes, key=lambda q: abs(q - diag.best.k))
            de = mean_sinkage(diag.best.passes[k].rows)
            ax.scatter(w[cov], 1e3 * de, s=12, label=f"with {diag.best.ext.id}")
        ax.set_xlabel(cov)
        ax.set_ylabel("mean sinkage d per window [mm]")
    else:
        fs, fr = diag.base.profiles.floor_series()
        ax.plot(fs, 1e3 * fr, lw=0.6)
        ax.set_xlabel("arc length [m]")
        ax.set_ylabel("rut-floor residual [mm]")
    ax.legend(fontsize=8) if ax.get_legend_handles_labels()[0] else None
    ax.set_title(f"what the mismatch follows: {cov}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def fig_cross_sections(diag, path: Path) -> Path:
    p = diag.base.profiles
    fig = Figure(figsize=(10, 4))
    ax = fig.subplots(1, 2)
    mm = 1e3 * p.bins
    m, se, _ = p.profile("meas")
    ax[0].errorbar(mm, 1e3 * m, 1e3 * se, fmt="k.", label="measured")
    ax[0].plot(mm, 1e3 * p.profile("sim")[0], label="base model")
    r, rse, _ = p.profile("res")
    ax[1].errorbar(mm, 1e3 * r, 1e3 * rse, fmt=".-", label="base model")
    if diag.best is not None:
        k = min(diag.best.passes, key=lambda q: abs(q - diag.best.k))
        pe = diag.best.passes[k].profiles
        if pe is not None:
            ax[0].plot(mm, 1e3 * pe.profile("sim")[0], label=f"with {diag.best.ext.id}")
            re, ree, _ = pe.profile("res")
            ax[1].errorbar(mm, 1e3 * re, 1e3 * ree, fmt=".-", label=f"with {diag.best.ext.id}")
    ax[0].set_ylabel("H_b - start surface [mm]")
    ax[1].set_ylabel("simulated - measured [mm], +- s.e.")
    for a in ax:
        a.set_xlabel("lateral offset from wheel centre, outward [mm]")
        a.axhline(0, color="0.7", lw=0.5)
        a.legend(fontsize=8)
    fig.suptitle("cross-sections averaged along the drive")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def fig_learned(learned: dict, path: Path) -> Path:
    """The learned modifier's partial dependence: per kept term the factor on its parameter
    against the covariate (the mean of the folds' curves), the band between the two folds'."""
    terms = learned["terms"]
    fig = Figure(figsize=(4.5 * len(terms), 3.5))
    for ax, t in zip(np.atleast_1d(fig.subplots(1, len(terms))), terms, strict=True):
        x, lo, hi = np.asarray(t["knots"]), *(np.exp(np.asarray(b)) for b in t["band"])
        ax.fill_between(x, lo, hi, alpha=0.3, label="the two folds' fits")
        ax.plot(x, np.exp(np.asarray(t["log_factor"])), "o-", label="learned factor")
        ax.axhline(1.0, color="0.5", lw=0.8)
        ax.set_xlabel(f"{t['covariate']} [{t['unit']}]")
        ax.set_ylabel(f"factor on {t['parameter']}")
        ax.set_title(f"{t['parameter']} ~ {t['covariate']}: {t['shape']}, x{t['factor']:.2f}", fontsize=9)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def fig_costs(diag, path: Path) -> Path:
    s = diag.windows["s"]
    fig = Figure(figsize=(8, 3.5))
    ax = fig.subplots()
    ax.plot(s, 1e3 * diag.base.prediction, ".-", label="base model")
    if diag.best is not None:
        ax.plot(s, 1e3 * diag.best.prediction, ".-", label=f"with {diag.best.ext.id} (cross-validated)")
    ax.plot(s, 1e3 * diag.base.floor, ":", color="0.5", label="noise floor")
    ax.set_xlabel("window centre s [m]")
    ax.set_ylabel("prediction cost (next window) [mm]")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def revisit_markdown(rev: dict) -> str:
    """The per-visit hardening test (revisits.hardening_across_visits) as Markdown."""
    if "z" not in rev:
        return f"Not tested: {rev.get('reason', 'no later visits')}."
    rut = rev["rut"]
    lines = [f"Each later visit of {rev['windows']} windows simulated from its own start with the first visit's "
             f"soil: cost {_mm(rev['cost_before'])} against a noise floor of {_mm(rev['noise_floor'])} (z = "
             f"{rev['z_visible']:.2f}); with each pass sinking g = {rev['g']:.3g} times the one before (folds "
             f"{rev['g_folds'][0]:.3g}, {rev['g_folds'][1]:.3g}; mean gain {_mm(rev['gain'])}, z = {rev['z']:.2f} "
             f"over windows that share no ground, needed {rev['z_level']:.2f}): {_mm(rev['cost_after'])}. "
             f"Accepted: {rev['accepted']}.", "",
             f"Rut the later visits added: measured {_mm(rut['measured'])}, simulated from the first visit's soil "
             f"{_mm(rut['simulated_without_law'])}, with the law {_mm(rut['simulated_with_law'])}.", "",
             "| law | coefficient | cross-visit cost |", "| --- | --- | --- |"]
    lines += [f"| {k}: {LAW_TEXT[k]} | {v['coefficient']:.3g} | {_mm(v['cost'])} |" for k, v in rev["laws"].items()]
    lines += ["", f"Shape: {rev['shape'] or 'not told apart on this drive'}."]
    pp = rev.get("per_pass")
    if pp and "g" in pp:
        lines += ["", f"Sinkage pass by pass: each wheel digs in turn from the rut the passes before it left and "
                      f"sinks d g^n after n earlier wheel passes; g = {pp['g']:.3g} makes the later visits fit the "
                      f"first visit's d (tried: " + ", ".join(f"{g:.3g}" for g, _ in pp["g_tried"]) + ").", "",
                  "| visit | wheel passes before | windows | first-pass d [mm] | each pass's sinkage [mm] |",
                  "| --- | --- | --- | --- | --- |"]
        lines += [f"| {grp['visit']} | {grp['passes_before']:.0f} | {grp['windows']} | "
                  f"{1000 * grp['d_first_pass']:.1f} ± {1000 * grp['d_sd']:.1f} | "
                  + ", ".join(f"{1000 * q['sinkage']:.1f} ± {1000 * q['sd']:.1f}" for q in grp["passes"]) + " |"
                  for grp in pp["visits"]]
    elif pp:
        lines += ["", f"Sinkage pass by pass: not fitted ({pp.get('reason')})."]
    return "\n".join(lines)


def write_markdown(diag, path: Path, figures: dict[str, str], input_name: str) -> Path:
    s, ev = diag.summary, diag.evidence
    lines = [f"# Diagnosis of {input_name}", "", f"**Verdict: {s['verdict']}**"
             + (f" — `{s['missing_physics']}`" if s["missing_physics"] else ""), "", s["explanation"], "",
             "## Where", "", f"- across the track: {s['where']['cross_track']}",
             f"- along the track: {s['where']['along_track'] or 'nowhere in particular'} (m of arc length)",
             f"- follows: {s['where']['covariate']}",
             f"- across the rut, outward from the wheel centre line, the recording lies: "
             f"{shape_text(ev.get('rut_shape', [])) or 'nowhere off the model beyond noise'}",
             "", "## Evidence", "",
             "| zone | mean residual | s.e. | z |", "| --- | --- | --- | --- |"]
    for zn, v in ev["zones"].items():
        lines.append(f"| {zn} | {_mm(v['mean'])} | {_mm(v['se'])} | {v['z']:.1f} |")
    a, ln = ev["asymmetry"], ev["spectral_line"]
    lines += ["", f"Left-right rut-floor asymmetry {_mm(a['mean'])}, z = {a['z']:.1f}; strongest along-track line "
              f"{ln['ratio']:.1f} x background at {ln['wavelength']:.2f} m (p = {ln['p']:.2g}). Location tests "
              f"need |z| > {ev['z_locate']:.2f}; berms are not tested (their height follows the soil parameters).",
              "", "## Candidates", "",
              "| id | location evidence | fitted | held-out prediction | z: held-out, own fit -> both (needed) "
              "| accepted |",
              "| --- | --- | --- | --- | --- | --- |"]
    fitted = {f.ext.id: f for f in diag.fits}
    for i, e in ev["candidates"].items():
        f = fitted.get(i)
        lines.append(f"| {i} | {e['statistic']} (p = {e['p']:.2g}) | "
                     + (f"{f.ext.parameter} = {f.k:.3g} (folds {f.k_fold[0]:.3g}, {f.k_fold[1]:.3g}) | "
                        f"{_mm(float(np.nanmean(f.prediction)))} | {f.held_z:.2f}, {f.own_z:.2f} -> {f.z:.2f} "
                        f"({ev['z_accept'][i]:.2f}) | "
                        f"{_accepted_cell(f, diag)} |" if f else
                        "not fitted | | | |"))
    lines += ["", "Acceptance: the paired per-window improvement of the held-out costs (each window's fit "
              "scored on its neighbours' ground) and of the windows' own fits, combined as Stouffer's z with "
              "their correlation along the drive, above the level in brackets; the windows' own fit not worse; "
              "the same coefficient sign chosen on both folds. The levels spend a family-wise 5 % over the fitted "
              "candidates in their order by location evidence, most on the leading one (fallback procedure); "
              "an accepted candidate's level passes to the next, and so does that of a candidate left at 0 "
              "on both folds (the base model itself: nothing to test). A coefficient free to take either sign "
              "(speed, footprint width) is held to a higher z at the same level: each fold takes the sign its "
              "neighbours favoured, so on noise the folds agree twice as often as a one-signed term's. Once a "
              "shape term (walls, footprint) is accepted, the other joins the choice by held-out gain when it "
              "meets every condition but its level: the rut's shape needs a term, and the two share that evidence.",
              "", "## Costs", "",
              f"- before: residual {_mm(s['cost_before']['residual'])}, "
              f"prediction {_mm(s['cost_before']['prediction'])}",
              f"- after: residual {_mm(s['cost_after']['residual'])}, "
              f"prediction {_mm(s['cost_after']['prediction'])}",
              f"- noise floor: {_mm(s['noise_floor'])}", ""]
    rev = getattr(diag, "revisits", None)
    if rev is not None:
        lines += ["## Ground driven more than once", "", revisit_markdown(rev), ""]
    if getattr(diag, "learned", None) is not None:
        lines += ["## Learned modifier", "", learned_markdown(diag.learned), ""]
    lines += ["## Figures", ""]
    lines += [f"![{k}]({v})" for k, v in figures.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


def tensorboard(diag, log_dir: Path, figures: dict[str, Path]) -> None:
    """Per-window prediction costs before/after and the figures, for TensorBoard."""
    from torch.utils.tensorboard import SummaryWriter

    w = SummaryWriter(str(log_dir))
    try:
        for k, s in enumerate(diag.windows["s"]):
            w.add_scalar("prediction/base_mm", 1e3 * diag.base.prediction[k], k)
            if diag.best is not None:
                w.add_scalar("prediction/extended_mm", 1e3 * diag.best.prediction[k], k)
            w.add_scalar("window/s_m", s, k)
        for name, p in figures.items():
            img = imread(str(p))
            w.add_image(f"diagnosis/{name}", img[..., :3], 0, dataformats="HWC")
    finally:
        w.close()


def write_all(diag, pair, out: Path, input_name: str, tb: bool = True) -> Path:
    """diagnosis.json, report.md, figures (and TensorBoard) into out."""
    out.mkdir(parents=True, exist_ok=True)
    write_json(diag.summary, out / "diagnosis.json")
    figs = {"residual_map": fig_residual_map(diag, pair, out / "residual_map.png"),
            "covariate": fig_covariate(diag, out / "residual_vs_covariate.png"),
            "cross_sections": fig_cross_sections(diag, out / "cross_sections.png"),
            "prediction_costs": fig_costs(diag, out / "prediction_costs.png")}
    if getattr(diag, "learned", None) is not None:
        (out / "learned.json").write_text(json.dumps(diag.learned, indent=2))
        if diag.learned["terms"]:
            figs["learned"] = fig_learned(diag.learned, out / "learned.png")
    write_markdown(diag, out / "report.md", {k: v.name for k, v in figs.items()}, input_name)
    if tb:
        tensorboard(diag, out / "tensorboard", figs)
    return out / "diagnosis.json"
