"""Confusion-table studies of the diagnosis on drives with known truth.

- `run_study`: seeded synthetic drives (the cases: `study_cases.STUDY_CASES`, or the
  randomized `study_cases.randomized_cases` with measurement nuisances and null drives);
- `run_foreign`: terrain pairs from another simulator (`NAME.npz`, `NAME_truth.json`,
  `NAME_surfaces.npz` and `robot.yaml` in one directory, /work/shared/foreign/README.md),
  with the estimator's model error against the noise-free surfaces.

Both append one JSON line per drive to OUT/cases.jsonl (drives already there are skipped:
an interrupted study resumes) and write OUT/confusion.md. With an `engine`
(torchsoil.engines.make_engine: a local process pool or a Ray cluster) each drive is one task,
its line appended as it finishes; a drive whose task fails is reported and left for the next
run. The table lists the drives in the order of the cases, however they finished.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
import zlib
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from torchsoil.diagnosis.catalogue import CATALOGUE, signs
from torchsoil.diagnosis.fit import section_of, with_section
from torchsoil.diagnosis.phases import accept_in_order, by_gain, diagnose
from torchsoil.diagnosis.report import mean_sinkage
from torchsoil.diagnosis.stats import SAME, by_fold, fold_choice, folds, gain_material, term_test
from torchsoil.io.terrain_pair import TerrainPair
from torchsoil.settings import DiagnosisConfig, Settings
from torchsoil.synth import effects as fx
from torchsoil.synth.scenario import make_terrain_pair

CHANGED = 1e-3  # m: a cell's ground changed where the noise-free |H_b - H_f| exceeds this (model error zone)


def _resume(out: Path) -> dict[str, dict]:
    out.mkdir(parents=True, exist_ok=True)
    log = out / "cases.jsonl"
    return {json.loads(line)["case"]: json.loads(line) for line in log.read_text().splitlines()} if log.exists() else {}


def _append(out: Path, rec: dict) -> None:
    with (out / "cases.jsonl").open("a") as f:
        f.write(json.dumps(rec) + "\n")


def _record(name: str, diag, want_verdict: str, want_id: str | None, seconds: float,
            want_learned: dict | None = None, **extra) -> dict:
    """One line of cases.jsonl: the diagnosis' verdict against the truth, with each candidate's
    held-out test (`held_out_tests`) and the numbers behind it (`held_out_series`).

    For a law outside the catalogue that a learned modifier describes (want_id "learned",
    want_learned its parameter, covariate and direction: `wanted_term`) the record also keeps
    the diagnosis' `learned` section and `learned_match` (`learned_match` of its `named_terms`),
    and it is `correct` where the verdict is right and a named term agrees in all three (a
    catalogue id counts where its term is the wanted one: slip_sinkage for d following traction
    upwards); otherwise `correct` wants the verdict and the id."""
    s = diag.summary
    learned = getattr(diag, "learned", None)
    match = learned_match(want_learned, named_terms(s, learned)) if want_learned is not None else None
    right_id = match["right"] if match is not None else s["missing_physics"] == want_id
    return {"case": name, "want": want_verdict, "want_id": want_id, "verdict": s["verdict"],
            "id": s["missing_physics"], "where": s["where"], "parameters": s["extension_parameters"],
            "cost_before": s["cost_before"], "cost_after": s["cost_after"], "noise_floor": s.get("noise_floor"),
            "correct": s["verdict"] == want_verdict and right_id, "seconds": seconds,
            "want_learned": want_learned, "learned": learned, "learned_match": match,
            "tests": held_out_tests(diag), "series": held_out_series(diag), "revisits": revisit_test(diag), **extra}


# a catalogue term named is a learned modifier of these (parameter, covariate), its direction
# the sign of its fitted coefficient (as learned.CATALOGUE_MATCH pairs them)
CATALOGUE_TERMS: dict[str, tuple[str, tuple[tuple[str, str], ...]]] = {
    "speed_dependent_sinkage": ("k_speed", (("d", "speed"),)),
    "slip_sinkage": ("k_slip", (("d", "traction"), ("d", "accel"))),
    "lateral_load_transfer": ("k_lateral", (("d_side", "lateral_load"), ("d_side", "roll"))),
    "multi_pass_hardening": ("k_pass", (("d", "passes"),)),
}
TERM_KEYS = ("parameter", "covariate", "direction")


def wanted_term(expected: dict | None) -> dict | None:
    """{parameter, covariate, direction} a truth's `expected` (effects.expected, a foreign
    truth's) wants a learned modifier to name; None unless its missing_physics is "learned"."""
    if not expected or expected.get("missing_physics") != "learned":
        return None
    return {k: expected.get(k) for k in TERM_KEYS}


def named_terms(summary: dict, learned: dict | None = None) -> list[dict]:
    """The learned terms a diagnosis (its summary, diagnosis.json, and its learned modifier,
    learned.json) names: the learned modifier's `terms` ({parameter, covariate, direction, ...})
    where it was named, and, where its verdict names a catalogue id of
    CATALOGUE_TERMS with a fitted coefficient, that term's (parameter, covariate) pairs with the
    coefficient's sign as direction (`from`: the id)."""
    terms = [dict(t) for t in (learned or {}).get("terms") or []] if (learned or {}).get("named") else []
    eid = summary.get("missing_physics")
    if summary.get("verdict") == "missing_physics" and eid in CATALOGUE_TERMS:
        name, pairs = CATALOGUE_TERMS[eid]
        k = (summary.get("extension_parameters") or {}).get(name)
        if k is not None:
            terms += [{"parameter": p, "covariate": c, "direction": "-" if k < 0 else "+", "from": eid}
                      for p, c in pairs]
    return terms


def learned_match(want: dict, terms: list[dict]) -> dict:
    """How the named terms agree with the wanted {parameter, covariate, direction}: of the term
    that agrees most (covariate first, then direction, then parameter) whether its covariate
    agrees, its direction (counted only on the right covariate), its parameter, `right` all
    three, and the `term` itself (None, and all False, where no term was named)."""
    def score(t):
        cov = t.get("covariate") == want["covariate"]
        return cov, cov and t.get("direction") == want["direction"], t.get("parameter") == want["parameter"]

    best = max(terms, key=score, default=None)
    cov, dirn, par = score(best) if best is not None else (False, False, False)
    return {"covariate": cov, "direction": dirn, "parameter": par, "right": cov and dirn and par, "term": best}


def revisit_test(diag) -> dict | None:
    """The hardening test on the ground driven again (`revisits.hardening_across_visits`) in
    brief: accepted, the later visits it simulated (windows), its z against its level, the
    per-pass g on all later visits and by fold, the g of the fit pass by pass where it ran
    (g_per_pass), the reason it could not run; None on a drive without visit layers."""
    rev = diag.evidence.get("revisits")
    if rev is None:
        return None
    keys = ("accepted", "windows", "z", "z_visible", "z_level", "g", "g_folds", "reason")
    out = {k: rev[k] for k in keys if k in rev}
    if "g" in (rev.get("per_pass") or {}):
        out["g_per_pass"] = rev["per_pass"]["g"]
    return out


def held_out_tests(diag) -> list[dict]:
    """Each fitted candidate's test: coefficient (all windows and per fold), its z (held-out
    and own-fit evidence together, `stats.combined_z`) and the z it needed, the held-out
    paired z and mean gain [mm], the paired z of its windows' own residuals and its location
    evidence p (a study compares these across settings more finely than verdicts)."""
    need, ev = diag.evidence["z_accept"], diag.evidence["candidates"]
    return [{"id": f.ext.id, "k": round(f.k, 4), "k_fold": [round(k, 4) for k in f.k_fold],
             "z": round(f.z, 3), "z_needed": round(need[f.ext.id], 3), "gain_mm": round(1e3 * f.improvement, 5),
             "held_z": round(f.held_z, 3), "own_z": round(f.own_z, 3), "effect": round(f.effect, 5),
             "effects": {f"{k:.6g}": round(e, 6) for k, e in sorted((f.effects or {}).items())},
             "p_location": ev[f.ext.id]["p"], "accepted": bool(f.accepted)} for f in diag.fits]


def held_out_series(diag) -> dict:
    """The per-window numbers behind the held-out tests, so that a study can be re-scored
    offline under another test statistic: window centres s [m], each window's covariates, the
    base pass's held-out cost and every other candidate pass's, by coefficient, and the same
    for the windows' own residuals (`base_residual`, `residuals`) [mm]."""
    def mm(x):  # to 1e-7 mm: blocks a term left alone (to SAME) stay recognisable offline
        return [None if not np.isfinite(v) else round(1e3 * float(v), 7) for v in x]

    return {"s": [round(float(v), 3) for v in diag.windows["s"]],
            "covariates": {n: [round(float(v), 6) for v in x] for n, x in diag.windows.items() if n != "s"},
            "base": mm(diag.base.held_out),
            "passes": {f.ext.id: {f"{k:.6g}": mm(p.held_out) for k, p in sorted(f.passes.items()) if k != 0.0}
                       for f in diag.fits},
            "base_residual": mm(diag.base.residual),
            "residuals": {f.ext.id: {f"{k:.6g}": mm(p.residual) for k, p in sorted(f.passes.items()) if k != 0.0}
                          for f in diag.fits}}


_DIAG = DiagnosisConfig()


def retest(rec: dict, block_m: float = _DIAG.block_m, stride: float = 0.4, alpha: float = _DIAG.alpha_accept,
           lead_share: float = _DIAG.lead_share, gain_materiality: float = _DIAG.gain_materiality,
           own_fit_z: float = _DIAG.own_fit_z, effect_materiality: float = _DIAG.effect_materiality
           ) -> tuple[list[dict], str | None]:
    """A case record's held-out tests redone from its `series` (held_out_series), as the
    diagnosis does them: each candidate's coefficient chosen per fold (`stats.fold_choice`,
    folds of block_m [m] at the estimator's stride [m]), the paired z of the held-out costs and
    of the windows' own residuals against the base pass and their combined z
    (`stats.combined_z`; records without residual series: the held-out z alone), and
    acceptance in order of location evidence (`phases.accept_in_order`), a term's mean gain
    at least gain_materiality times the base's mean held-out cost and its windows' own fit
    no worse than -own_fit_z (records without residual series skip this check), and its
    effect size at both folds' coefficients at least effect_materiality (records without
    `effects` skip this check). Change any of these
    (or patch the statistic) to re-score a study without running the estimator again.
    Returns (the tests with k_fold and z recomputed, the id the diagnosis would name or None)."""
    def arr(x):
        return np.array([np.nan if v is None else v for v in x], np.float64)

    ser = rec["series"]                                      # in mm
    same = 1e3 * SAME
    base = arr(ser["base"])
    lab = folds(len(base), int(round(block_m / stride)))
    out = []
    for t in sorted(rec.get("tests", []), key=lambda t: t["p_location"]):
        held = {float(k): arr(v) for k, v in ser["passes"][t["id"]].items()}
        held[0.0] = base
        k_fold = fold_choice(held, lab)
        base_res = own = None
        if "residuals" in ser:
            res = {float(k): arr(v) for k, v in ser["residuals"][t["id"]].items()}
            base_res = res[0.0] = arr(ser["base_residual"])
            own = by_fold(res, k_fold, lab)
        gain, _, held_z, own_z, z = term_test(base, by_fold(held, k_fold, lab), base_res, own, same=same)
        effects = {float(k): e for k, e in t.get("effects", {}).items()}
        effect = min(effects.get(k, math.inf) for k in k_fold) if effects else math.inf
        out.append({**t, "k_fold": list(k_fold), "z": z, "held_z": held_z, "gain_mm": gain, "own_z": own_z,
                    "effect": effect})
    fits = [SimpleNamespace(z=t["z"], k_fold=t["k_fold"], improvement=t["gain_mm"], own_z=t["own_z"],
                            effect=t["effect"], accepted=False, ext=CATALOGUE[t["id"]]) for t in out]
    material = gain_material(gain_materiality, base)
    levels = accept_in_order(fits, [t["p_location"] for t in out], alpha, lead_share, material, -own_fit_z,
                             [signs(CATALOGUE[t["id"]]) for t in out], effect_materiality)
    for t, f, level in zip(out, fits, levels, strict=True):
        t.update(z_needed=level, accepted=f.accepted)
    named = by_gain(fits, material, -own_fit_z, effect_materiality)
    return out, next(t["id"] for t, f in zip(out, fits, strict=True) if f is named[0]) if named else None


def study_case(case: tuple, settings: Settings) -> dict:
    """The record of one (name, scenario, seed, verdict, id) case: its drive made (with visit
    layers where it drives over its own ruts, as a pipeline keeping every visit writes them)
    and diagnosed (`_record`; for id "learned" the term wanted is the law's, effects.expected),
    with the world's effect law, the tyre and measurement draws and the drive's length [m]."""
    name, scn, seed, want_verdict, want_id = case
    law = scn.get("effects", {}) if isinstance(scn, dict) else scn.effects
    want_learned = wanted_term(fx.expected(fx.resolve(law))) if want_id == "learned" else None
    t0 = time.perf_counter()
    data = make_terrain_pair(scn, seed=seed, visits=True)
    pair = TerrainPair.from_mapping(data)
    diag = diagnose(pair, settings.diagnosis, settings.estimator, settings.sim)
    xy = pair.poses[:, 1:3]
    return _record(name, diag, want_verdict, want_id, time.perf_counter() - t0, want_learned, seed=seed,
                   law=scn.get("effects", {}) if isinstance(scn, dict) else {},
                   nuisances=json.loads(str(data["nuisances"])),
                   length_m=float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum()))


def _each(fn, calls: list[tuple], engine, desc: str) -> Iterator[dict]:
    """fn(*call) for every call, in order in this process (engine None) or as tasks of
    `engine` as they finish; a failed task is printed and skipped."""
    from tqdm import tqdm

    if engine is None:
        for c in tqdm(calls, desc=desc, unit="case"):
            yield fn(*c)
        return
    for k, (i, o) in enumerate(engine.imap(fn, calls)):
        if o.ok:
            print(f"[{k + 1}/{len(calls)}] {o.value['case']}: {o.seconds:.0f} s", flush=True)
            yield o.value
        else:
            print(f"[{k + 1}/{len(calls)}] case {i} failed (run again to retry): {o.error}", file=sys.stderr,
                  flush=True)


def _in_order(done: dict[str, dict], names: list[str]) -> list[dict]:
    """The records of `names` in that order, then any others the results file holds."""
    return [done[n] for n in names if n in done] + [r for n, r in done.items() if n not in set(names)]


def run_study(cases, out: Path, settings: Settings | None = None, engine=None) -> str:
    """Diagnose every (name, scenario, seed, verdict, id) case (`study_case`), in this process
    or as tasks of `engine` (torchsoil.jobs.fleet); append results to out/cases.jsonl (cases already
    there are skipped) and return the confusion table (markdown)."""
    out = Path(out)
    done = _resume(out)
    settings = settings or Settings()
    calls = [(tuple(c), settings) for c in cases if c[0] not in done]
    for rec in _each(study_case, calls, engine, "study"):
        done[rec["case"]] = rec
        _append(out, rec)
    table = confusion(_in_order(done, [c[0] for c in cases]))
    (out / "confusion.md").write_text(table)
    return table


def _label(verdict, eid):
    return eid if verdict == "missing_physics" else verdict


def _term_label(t: dict) -> str:
    return f"learned {t.get('parameter')}~{t.get('covariate')}{t.get('direction')}"


def _truth_label(r: dict) -> str:
    return _term_label(r["want_learned"]) if r.get("want_learned") else _label(r["want"], r["want_id"])


def _verdict_label(r: dict) -> str:
    """The verdict's column: the truth's own where a learned term was right; a learned verdict
    by its (best-matching, else first) term; otherwise the id or the verdict."""
    m = r.get("learned_match")
    if m is not None and m["right"]:
        return _truth_label(r)
    if r["verdict"] == "missing_physics" and r["id"] == "learned":
        t = (m or {}).get("term") or next(iter((r.get("learned") or {}).get("terms") or []), None)
        return _term_label(t) if t else "learned"
    return _label(r["verdict"], r["id"])


def _named_right(r: dict) -> bool:
    m = r.get("learned_match")
    return m["right"] if m is not None else r["id"] == r["want_id"]


def error_rates(records: list[dict]) -> dict:
    """false_alarms / nulls: drives without missing physics (expected `adequate`) given
    another verdict (a learned term named included); wrong_id: drives with an effect where an
    id was named that is not the true one (out-of-catalogue effects included; for a learned
    law, a name whose term is not the wanted one, `learned_match`; a null drive named is a false
    alarm, counted there); learned: drives with a learned law, learned_right those named right
    and learned_covariate, learned_direction, learned_parameter those whose best-matching term
    (`learned_match`) had that right (on a missing_physics verdict); seconds_per_case: mean wall
    time."""
    nulls = [r for r in records if r["want"] == "adequate"]
    learned = [r for r in records if r.get("want_learned")]

    def got(r, key):
        return r["verdict"] == "missing_physics" and bool((r.get("learned_match") or {}).get(key))

    return {"nulls": len(nulls), "false_alarms": sum(r["verdict"] != "adequate" for r in nulls),
            "wrong_id": sum(r["verdict"] == "missing_physics" and not _named_right(r)
                            for r in records if r["want"] != "adequate"),
            "learned": len(learned), "learned_right": sum(bool(r["correct"]) for r in learned),
            **{f"learned_{k}": sum(got(r, k) for r in learned) for k in TERM_KEYS},
            "seconds_per_case": float(np.mean([r["seconds"] for r in records])) if records else math.nan}


def confusion(records: list[dict]) -> str:
    """Markdown: per expected answer, how often each verdict came out; the false-alarm rate on
    null drives and the count of wrong ids named; and the case list."""
    counts: dict[str, Counter] = {}
    for r in records:
        counts.setdefault(_truth_label(r), Counter())[_verdict_label(r)] += 1
    cols = sorted({c for v in counts.values() for c in v})
    lines = ["| truth \\ verdict | " + " | ".join(cols) + " | right |", "|" + " --- |" * (len(cols) + 2)]
    for t, c in sorted(counts.items()):
        lines.append(f"| {t} | " + " | ".join(str(c.get(k, 0)) for k in cols) + f" | {c.get(t, 0)}/{sum(c.values())} |")
    right = sum(r["correct"] for r in records)
    e = error_rates(records)
    rate = f"{e['false_alarms'] / e['nulls']:.2f}" if e["nulls"] else "n/a"
    lines += ["", f"right: {right}/{len(records)}",
              f"false alarms on null drives: {e['false_alarms']}/{e['nulls']} (rate {rate})",
              f"wrong id named: {e['wrong_id']}"]
    if e["learned"]:
        n = e["learned"]
        lines.append(f"learned laws named right: {e['learned_right']}/{n} (covariate {e['learned_covariate']}/{n}, "
                     f"direction {e['learned_direction']}/{n}, parameter {e['learned_parameter']}/{n})")
    lines += [f"time per case: {e['seconds_per_case']:.0f} s", "",
              "| case | verdict | parameters | prediction before -> after [mm] | z (needed) |",
              "| --- | --- | --- | --- | --- |"]
    for r in records:
        lines.append(f"| {r['case']} | {_verdict_label(r)} | {r['parameters']} | "
                     f"{1e3 * r['cost_before']['prediction']:.3f} -> {1e3 * r['cost_after']['prediction']:.3f} | "
                     f"{_margin(r)} |")
    return "\n".join(lines) + "\n"


def _margin(r: dict) -> str:
    """The z of the true term against the z it needed (of the nearest to acceptance
    when the drive has no catalogue effect), '-' for records without tests; for a learned law
    the best-matching term named and its held-out gain."""
    if r.get("want_learned"):
        t = (r.get("learned_match") or {}).get("term")
        gain = (t or {}).get("held_out_gain")
        return "no term named" if t is None else _term_label(t) + ("" if gain is None else f" gain {gain:.3g}")
    tests = r.get("tests")
    if tests is None:
        return "-"
    if r["want_id"] is not None:
        t = next((t for t in tests if t["id"] == r["want_id"]), None)
        return "not fitted" if t is None else f"{t['z']:.2f} ({t['z_needed']:.2f})"
    if not tests:
        return "none fitted"
    t = max(tests, key=lambda t: t["z"] - t["z_needed"])
    return f"{t['id']} {t['z']:.2f} ({t['z_needed']:.2f})"


# ---------------------------------------------------------------------------- foreign pairs
def foreign_names(directory: Path) -> list[str]:
    """Drive names in a directory of foreign pairs: each NAME.npz with NAME_truth.json."""
    directory = Path(directory)
    if not directory.is_dir():
        raise FileNotFoundError(f"foreign pairs directory not found: {directory}")
    names = sorted(p.stem for p in directory.glob("*.npz")
                   if not p.stem.endswith("_surfaces") and (directory / f"{p.stem}_truth.json").is_file())
    if not names:
        raise FileNotFoundError(f"{directory}: no NAME.npz with NAME_truth.json")
    return names


def load_foreign(directory: Path, name: str) -> tuple[TerrainPair, TerrainPair | None, dict]:
    """The pair NAME.npz with the robot of directory/robot.yaml (when present), the same pair
    on the noise-free surfaces of NAME_surfaces.npz (None without it), and NAME_truth.json."""
    from torchsoil.robot import Robot

    directory = Path(directory)
    pair = TerrainPair.load(directory / f"{name}.npz")
    if (directory / "robot.yaml").is_file():
        robot = Robot.from_yaml(directory / "robot.yaml")
        pair.wheels, pair.wheel_width, pair.wheel_flat_fraction = robot.wheels, robot.wheel_width, \
            robot.wheel_flat_fraction
    truth = json.loads((directory / f"{name}_truth.json").read_text())
    clean = None
    surfaces = directory / f"{name}_surfaces.npz"
    if surfaces.is_file():
        with np.load(surfaces) as f:
            hf, hb = f["h_front_clean"], f["h_back_clean"]
        if hf.shape != pair.h_front.shape or hb.shape != pair.h_front.shape:
            raise ValueError(f"{surfaces}: surfaces of shape {hf.shape}, {hb.shape}; the pair's is "
                             f"{pair.h_front.shape}")
        clean = TerrainPair(pair.dx, pair.origin, hf.astype(np.float32), hb.astype(np.float32), pair.poses,
                            pair.wheels, pair.wheel_width, pair.wheel_flat_fraction)
    return pair, clean, truth


def simulated_back(pair: TerrainPair, settings: Settings) -> np.ndarray:
    """(X, Y) the estimator's simulated H_b over the drive [m]: every window fitted in turn,
    each cell from the window whose centre is nearest (NaN off the windows' ground)."""
    from torchsoil.estimate.estimator import Estimator, Stitcher

    est = Estimator(pair, settings.estimator, settings.sim)
    stitch = Stitcher(pair.h_front.shape, est.index.s)
    for o in est.run():
        if o.h_sim is not None:
            stitch.add(o.data, o.h_sim)
    return stitch.h_sim.astype(np.float64)


def model_error(h_sim: np.ndarray, clean: TerrainPair, changed: float = CHANGED) -> float:
    """Mean |h_sim - noise-free H_b| [m] over cells whose noise-free ground changed
    (|H_b - H_f| > `changed` m) and that h_sim covers (NaN when there are none)."""
    cf, cb = clean.h_front.astype(np.float64), clean.h_back.astype(np.float64)
    zone = (np.abs(cb - cf) > changed) & np.isfinite(h_sim) & np.isfinite(cb)
    return float(np.mean(np.abs(h_sim[zone] - cb[zone]))) if zone.any() else math.nan


def redraw_noise(pair: TerrainPair, clean: TerrainPair, rng: np.random.Generator, offset: float = 0.002
                 ) -> TerrainPair:
    """The pair with another draw of its measurement noise, for a model error that does not
    rest on one draw (recordings of the same world with other seeds).

    Each map's noise field (measured minus noise-free [m], its dropouts and occlusion streaks
    NaN) moves along the grid's first axis by a random number of rows (wrapping; at least 20,
    beyond the noise's own correlation) and is mirrored across at random. The measured
    corridor (cells either map measured) keeps its place: the moved dropouts and streaks
    that land in it stay NaN, and its cells that the moved field's own corridor does not
    reach draw a value from the map's noise. The after-map's median offset to the noise-free
    ground is replaced by one drawn uniformly within +-offset [m]."""
    corridor = np.isfinite(pair.h_front) | np.isfinite(pair.h_back)
    X = corridor.shape[0]
    if X < 41:
        raise ValueError(f"a grid of {X} rows is too short to move the noise by 20 rows or more")
    maps = []
    for measured, truth in ((pair.h_front, clean.h_front), (pair.h_back, clean.h_back)):
        noise = measured.astype(np.float64) - truth.astype(np.float64)
        values = noise[np.isfinite(noise) & corridor]
        if values.size == 0:
            raise ValueError("a map has no measured cell: no noise to redraw")
        shift, mirror = int(rng.integers(20, X - 19)), bool(rng.random() < 0.5)
        moved, reach = np.roll(noise, shift, 0), np.roll(corridor, shift, 0)
        if mirror:
            moved, reach = moved[:, ::-1], reach[:, ::-1]
        fill = ~reach & corridor
        moved[fill] = rng.choice(values, int(fill.sum()))
        moved[~corridor] = np.nan
        maps.append((truth, moved, values))
    (tf, nf, _), (tb, nb, vb) = maps
    nb = nb - float(np.median(vb)) + float(rng.uniform(-offset, offset))
    return dataclasses.replace(pair, h_front=(tf + nf).astype(pair.h_front.dtype),
                               h_back=(tb + nb).astype(pair.h_back.dtype))


def truth_coefficients(truth: dict) -> dict[str, float]:
    """The catalogue coefficient (torchsoil.diagnosis.catalogue) that matches the truth's
    per-window values, where they carry it: k_speed from a line of sinkage against speed
    (reference: the mean speed), k_lateral from (d_right - d_left) / (d_right + d_left) against
    the lateral load v^2 curvature / g + sin(roll) (track 1 on the right), k_pass = g - 1 for
    sinkage d g^pass (one earlier pass), k_wall = tan(beta) / tan(beta_loose) - 1 (median; with
    both angles [deg], the truth's beta being the intact one)."""
    w = truth.get("windows") or []
    effect = (truth.get("expected") or {}).get("missing_physics")
    if not w:
        return {}
    d = np.array([(x["d1"] + x["d2"]) / 2 for x in w])
    if effect == "speed_dependent_sinkage":
        v = np.array([x["speed"] for x in w])
        b, a = np.polyfit(v, d, 1)
        return {"k_speed": float(b * v.mean() / (a + b * v.mean()))}
    if effect == "lateral_load_transfer":
        lat = np.array([x["speed"] ** 2 * x["curvature"] / 9.81 + math.sin(math.radians(x["roll_deg"])) for x in w])
        y = np.array([(x["d2"] - x["d1"]) / (x["d1"] + x["d2"]) for x in w])
        return {"k_lateral": float(np.sum(lat * y) / np.sum(lat * lat))}
    if effect == "multi_pass_hardening" and "g" in w[0]:
        return {"k_pass": float(np.median([x["g"] for x in w])) - 1.0}
    if effect == "cohesive_walls" and "beta_loose_deg" in w[0]:     # beta_deg: the intact angle
        return {"k_wall": float(np.median([math.tan(math.radians(x["beta_deg"])) / math.tan(math.radians(
            x["beta_loose_deg"])) for x in w])) - 1.0,
                "beta_loose_deg": float(np.median([x["beta_loose_deg"] for x in w])),
                "beta_intact_deg": float(np.median([x["beta_deg"] for x in w]))}
    return {}


def foreign_case(directory: Path, name: str, settings: Settings, redraws: int = 0) -> dict:
    """The record of one foreign pair: its diagnosis (scored as `_record` does, a truth whose
    `expected` says missing_physics "learned" on its parameter, covariate and direction), the
    truth's coefficients and, with
    noise-free surfaces, the model error fitted to the pair and to the surfaces [mm], and
    fitted to `redraws` other draws of the pair's noise (`redraw_noise`, seeded by the name)."""
    t0 = time.perf_counter()
    pair, clean, truth = load_foreign(directory, name)
    exp = truth["expected"]
    diag = diagnose(pair, settings.diagnosis, settings.estimator, settings.sim)
    extra = {"truth_parameters": truth_coefficients(truth), "d_mm": 1e3 * _median_d(diag.base.rows),
             "d_truth_mm": 1e3 * _median_d(truth.get("windows") or [])}
    if clean is not None:
        extra["model_error_mm"] = 1e3 * model_error(simulated_back(pair, settings), clean)
        extra["model_error_clean_mm"] = 1e3 * model_error(simulated_back(clean, settings), clean)
        rng = np.random.default_rng(zlib.crc32(name.encode()))
        extra["model_error_redraws_mm"] = [1e3 * model_error(simulated_back(redraw_noise(pair, clean, rng), settings),
                                                             clean) for _ in range(redraws)]
        # the same with the nuisance model the diagnosis fitted (tyre section, dig order)
        fitted, sec = _fitted_nuisance(diag, pair, settings)
        extra["model_error_fitted_mm"] = 1e3 * model_error(simulated_back(with_section(pair, sec), fitted), clean)
        extra["model_error_fitted_clean_mm"] = 1e3 * model_error(
            simulated_back(with_section(clean, sec), fitted), clean)
    return _record(name, diag, exp["verdict"], exp.get("missing_physics"), time.perf_counter() - t0,
                   wanted_term(exp), **extra)


def _median_d(rows: list[dict]) -> float:
    """Median over windows of the mean sinkage of the tracks (keys d1, d2, ...), m."""
    d = mean_sinkage(rows)
    d = d[np.isfinite(d)]
    return float(np.median(d)) if len(d) else math.nan


def _fitted_nuisance(diag, pair, settings: Settings) -> tuple[Settings, tuple[float, float]]:
    """Settings with the diagnosis' fitted dig order and raster blur, and its fitted tyre section
    (f, e) (the pair's own when none was fitted)."""
    ev = diag.evidence
    sim, est = settings.sim, settings.estimator
    if ev.get("dig_order"):
        sim = sim.replace(dig_order=ev["dig_order"]["fitted"])
    if ev.get("raster_blur"):
        est = est.replace(after_blur=ev["raster_blur"]["fitted"])
    sec = tuple(ev["tyre_section"]["fitted"]) if ev.get("tyre_section") else section_of(pair)
    return settings.replace(sim=sim, estimator=est), sec


def run_foreign(directory: Path, out: Path, settings: Settings | None = None, names: list[str] | None = None,
                engine=None, redraws: int = 0) -> str:
    """Diagnose every foreign pair in `directory` (`foreign_case`, in this process or as tasks
    of `engine`) and measure the estimator's model error: the mean |simulated H_b - noise-free
    H_b| [mm] where the ground changed (CHANGED), fitted to the pair and fitted to the
    noise-free surfaces themselves, and on `redraws` other draws of each pair's noise; plus
    prediction cost over noise floor and the fitted coefficients against the truth's. Appends
    to out/cases.jsonl (drives already there are skipped), writes out/confusion.md and
    returns it."""
    out = Path(out)
    done = _resume(out)
    settings = settings or Settings()
    names = names or foreign_names(directory)
    calls = [(Path(directory), name, settings, redraws) for name in names if name not in done]
    for rec in _each(foreign_case, calls, engine, "foreign"):
        done[rec["case"]] = rec
        _append(out, rec)
    records = _in_order(done, names)
    table = confusion(records) + "\n" + model_error_table(records)
    (out / "confusion.md").write_text(table)
    return table


def model_error_table(records: list[dict]) -> str:
    """Markdown: per drive, the model error on the pair and on the noise-free surfaces [mm],
    the excess on other draws of the pair's noise (mean / max, when any were run),
    prediction cost over noise floor before and after, and fitted against true coefficients."""
    lines = [f"model error: mean |simulated H_b - noise-free H_b| where the noise-free ground changed by more "
             f"than {1e3 * CHANGED:g} mm", "",
             "| drive | model error [mm] | fitted to noise-free [mm] | excess [mm] | excess on other noise draws, "
             "mean / max (draws) [mm] | the same under the "
             "diagnosis' section and dig order [mm] | d fitted / truth [mm] | prediction / floor before -> after "
             "| fitted | truth |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in records:
        e, c = r.get("model_error_mm", math.nan), r.get("model_error_clean_mm", math.nan)
        ef, cf = r.get("model_error_fitted_mm", math.nan), r.get("model_error_fitted_clean_mm", math.nan)
        floor = r.get("noise_floor") or math.nan
        other = np.asarray(r.get("model_error_redraws_mm") or [], np.float64) - c
        redrawn = f"{other.mean():+.2f} / {other.max():+.2f} ({len(other)})" if len(other) else "-"
        lines.append(f"| {r['case']} | {e:.2f} | {c:.2f} | {e - c:+.2f} | {redrawn} | "
                     f"{ef:.2f} / {cf:.2f} ({ef - cf:+.2f}) | "
                     f"{r.get('d_mm', math.nan):.1f} / {r.get('d_truth_mm', math.nan):.1f} | "
                     f"{r['cost_before']['prediction'] / floor:.2f} -> {r['cost_after']['prediction'] / floor:.2f} | "
                     f"{r['parameters'] or '-'} | "
                     f"{ {k: round(v, 3) for k, v in r.get('truth_parameters', {}).items()} or '-'} |")
    return "\n".join(lines) + "\n"
