"""The studies' parts: randomized cases, error rates, the foreign layout and the model error
(the studies themselves are long: `torchsoil study`, not run here)."""

import json
import math

import numpy as np
import pytest

from torchsoil.diagnosis import study_cases as sc
from torchsoil.diagnosis.study import confusion, error_rates, model_error, redraw_noise, run_foreign, truth_coefficients
from torchsoil.io.terrain_pair import TerrainPair
from torchsoil.robot import paper_platform
from torchsoil.settings import Settings
from torchsoil.synth import effects as fx
from torchsoil.synth.scenario import load_scenario
from torchsoil.synth.terrain import Relief
from torchsoil.synth.trajectory import build_trajectory


def test_randomized_cases_have_the_nulls_and_every_id():
    cases = sc.randomized_cases(14, 20, seed=3)
    assert len(cases) == 34 and len({c[0] for c in cases}) == 34
    nulls = [c for c in cases if c[3] == "adequate"]
    assert len(nulls) == 20 and all(c[4] is None and "effects" not in c[1] for c in nulls)
    named = {c[4] for c in cases if c[3] == "missing_physics"}
    assert named == set(fx.CATALOGUE)
    assert any(c[3] == "unexplained" and "tread" in c[1]["effects"] for c in cases)
    assert {c[0].split()[3] for c in nulls} > {"plain"}                # nulls on every kind of drive
    for name, doc, *_ in cases:
        scn = load_scenario(doc)
        assert scn.measurement.offset > 0 and scn.measurement.noise_dof is not None, name
        assert len(scn.tyre.sections) == 4, name
    again = sc.randomized_cases(14, 20, seed=3)
    assert [json.dumps(c[1], sort_keys=True) for c in again] == [json.dumps(c[1], sort_keys=True) for c in cases]
    assert sc.randomized_cases(3, 2, seed=3) == [cases[i] for i in (0, 1, 2, 14, 15)]   # longer extends shorter


@pytest.mark.parametrize("eid", sorted(sc.LAWS))
def test_random_laws_have_the_drawn_effect_at_the_typical_covariate(eid):
    x0, (lo, hi) = sc.LAWS[eid]
    forms = set()
    for seed in range(40):
        law = sc.random_law(np.random.default_rng(seed), eid)
        forms.add(law["form"])
        k_lin = law["k"] * fx.phi(x0, law["form"], law["p"], law["x_s"]) / x0
        assert lo - 1e-9 <= k_lin <= hi + 1e-9
        fx.resolve({eid: law})                                           # a valid law
    assert forms == set(fx.FORMS)


@pytest.mark.parametrize("kind", sc.REVISITS)
def test_hardening_drives_come_back_over_their_ruts(kind):
    """Every revisit shape takes the wheels back over the first leg: some pose of the later
    part of the drive lies within 0.15 m of the first leg's line (y = 0, 0 <= x <= 5)."""
    seed = next(s for s in range(200) if sc.random_case(s, "multi_pass_hardening")[0].endswith(kind))
    doc = sc.random_case(seed, "multi_pass_hardening")[1]
    traj = build_trajectory(load_scenario(doc).trajectory, Relief(0.0, 0.0, *[np.zeros(0)] * 4), paper_platform())
    x, y = traj.poses[:, 1], traj.poses[:, 2]
    later = traj.arc > 8.0 + 3.0
    back = later & (np.abs(y) < 0.15) & (x > 0.0) & (x < 5.0)
    assert back.sum() > 30      # 0.3 m at least


def test_revisit_cases_keep_the_drives_over_their_own_ruts_only():
    cases = sc.randomized_cases(21, 20, seed=0)
    kept = sc.revisit_cases(cases)
    hardening = [c for c in cases if c[4] == "multi_pass_hardening"]
    assert hardening and all(c in kept for c in hardening)
    assert any(c[3] == "adequate" for c in kept)                   # null drives of those shapes too
    assert all(c[0].split()[-1] in sc.REVISITS for c in kept)
    assert all(c in kept for c in cases if c[0].split()[-1] in sc.REVISITS)


def test_error_rates_by_hand():
    def rec(want, want_id, verdict, eid):
        return {"case": f"{want}{want_id}{verdict}{eid}", "want": want, "want_id": want_id, "verdict": verdict,
                "id": eid, "parameters": {}, "cost_before": {"prediction": 0.003}, "cost_after": {"prediction": 0.003},
                "correct": (want, want_id) == (verdict, eid), "seconds": 10.0}

    records = [rec("adequate", None, "adequate", None), rec("adequate", None, "unexplained", None),
               rec("adequate", None, "missing_physics", "slip_sinkage"), rec("adequate", None, "adequate", None),
               rec("missing_physics", "speed_dependent_sinkage", "missing_physics", "slip_sinkage"),
               rec("missing_physics", "speed_dependent_sinkage", "missing_physics", "speed_dependent_sinkage"),
               rec("unexplained", None, "missing_physics", "cohesive_walls")]
    e = error_rates(records)        # the null drive named slip is a false alarm, not a wrong id
    assert (e["nulls"], e["false_alarms"], e["wrong_id"]) == (4, 2, 2)
    table = confusion(records)
    assert "false alarms on null drives: 2/4 (rate 0.50)" in table and "wrong id named: 2" in table
    assert "right: 3/7" in table


def test_case_table_shows_each_drive_s_margin_to_acceptance():
    """The true term's z against its level; on a null drive the candidate nearest acceptance
    (largest z - level), not the largest z."""
    def rec(name, want, want_id, tests):
        return {"case": name, "want": want, "want_id": want_id, "verdict": "adequate", "id": None,
                "parameters": {}, "cost_before": {"prediction": 0.003}, "cost_after": {"prediction": 0.003},
                "correct": False, "seconds": 1.0, "tests": tests}

    t = [{"id": "slip_sinkage", "z": 2.0, "z_needed": 2.33}, {"id": "speed_dependent_sinkage", "z": 1.8,
                                                             "z_needed": 1.88}]
    rows = confusion([rec("a", "missing_physics", "speed_dependent_sinkage", t),
                      rec("b", "missing_physics", "cohesive_walls", t), rec("c", "adequate", None, t),
                      rec("d", "adequate", None, [])]).splitlines()
    assert next(r for r in rows if r.startswith("| a |")).endswith("| 1.80 (1.88) |")
    assert next(r for r in rows if r.startswith("| b |")).endswith("| not fitted |")
    assert next(r for r in rows if r.startswith("| c |")).endswith("| speed_dependent_sinkage 1.80 (1.88) |")
    assert next(r for r in rows if r.startswith("| d |")).endswith("| none fitted |")


def test_model_error_by_hand():
    cf = np.zeros((4, 5), np.float32)
    cb = cf.copy()
    cb[1:3, 1:4] = -0.02                                                 # 6 cells changed
    clean = TerrainPair(0.02, (0.0, 0.0), cf, cb, np.array([[0.0, 0, 0, 0, 0, 0, 0]]),
                        paper_platform().wheels, 0.14)
    h_sim = cb.astype(np.float64) + 0.002
    h_sim[1, 1] = cb[1, 1] - 0.008                                      # one cell 8 mm off
    h_sim[0, 0] = 5.0                                                   # unchanged ground: not counted
    h_sim[2, 3] = np.nan                                                # not simulated: not counted
    assert model_error(h_sim, clean) == pytest.approx((0.008 + 4 * 0.002) / 5)


def _noisy_pair(corridor, noise_f, noise_b):
    """A pair on a sloping noise-free ground (float32 maps, as TerrainPair keeps them)
    with the given noise fields, NaN outside `corridor`."""
    X, Y = corridor.shape
    clean_f = np.add.outer(0.01 * np.arange(X), 0.003 * np.arange(Y))
    clean_b = clean_f - 0.02 * (np.arange(Y) % 3 == 0)[None]
    mk = lambda f, b: TerrainPair(0.02, (0.0, 0.0), f, b, np.array([[0.0, 0, 0, 0, 0, 0, 0]]),  # noqa: E731
                                  paper_platform().wheels, 0.14)
    measured = mk(np.where(corridor, clean_f + noise_f, np.nan), np.where(corridor, clean_b + noise_b, np.nan))
    return measured, mk(clean_f, clean_b)


def test_redrawn_noise_moves_the_noise_and_keeps_the_corridor():
    X, Y = 60, 8
    corridor = np.zeros((X, Y), bool)
    corridor[:, 1:7] = True                                        # the same under a mirror across
    noise_f = 1e-4 * np.arange(X * Y, dtype=np.float64).reshape(X, Y)  # every value its own
    noise_f[[5, 30, 31], [2, 4, 4]] = np.nan                       # dropouts
    noise_b = 0.005 + 1e-5 * np.arange(X * Y, dtype=np.float64).reshape(X, Y)[::-1]   # a 5 mm map offset
    pair, clean = _noisy_pair(corridor, noise_f, noise_b)
    rng = np.random.default_rng(4)
    for _ in range(5):
        new = redraw_noise(pair, clean, rng, offset=0.002)
        nf, nb = new.h_front - clean.h_front, new.h_back - clean.h_back
        assert np.isnan(nf[~corridor]).all() and np.isnan(nb[~corridor]).all()
        # the corridor's own values, moved: the same dropouts and values, elsewhere
        before = np.sort(noise_f[corridor & np.isfinite(noise_f)])
        assert np.isnan(nf[corridor]).sum() == 3 and np.isnan(new.h_front).sum() == np.isnan(pair.h_front).sum()
        assert np.allclose(np.sort(nf[corridor & np.isfinite(nf)]), before, atol=1e-6)
        assert not np.allclose(np.nan_to_num(nf[corridor]), np.nan_to_num(noise_f[corridor]))
        # the after map keeps its spread, with an offset of at most 2 mm instead of 5
        spread = noise_b[corridor] - np.median(noise_b[corridor])
        assert abs(np.median(nb[corridor])) <= 0.002 + 1e-6
        assert np.allclose(np.sort(nb[corridor] - np.median(nb[corridor])), np.sort(spread), atol=1e-6)


def test_redrawn_noise_fills_what_a_moved_corridor_leaves_bare():
    X, Y = 50, 10
    rows = np.arange(X)[:, None]
    corridor = np.abs(np.arange(Y)[None] - (2 + rows * 6 // X)) <= 1   # a band drifting across
    noise = 1e-4 * np.arange(X * Y, dtype=np.float64).reshape(X, Y)
    pair, clean = _noisy_pair(corridor, noise, noise)
    new = redraw_noise(pair, clean, np.random.default_rng(0))
    nf = new.h_front - clean.h_front
    assert np.isfinite(nf[corridor]).all() and np.isnan(nf[~corridor]).all()   # no dropout, nothing lost
    values = noise[corridor]
    assert np.abs(nf[corridor][:, None] - values[None]).min(1).max() < 1e-6  # every value one of the map's own
    with pytest.raises(ValueError, match="too short"):
        redraw_noise(*_noisy_pair(corridor[:30], noise[:30], noise[:30]), np.random.default_rng(0))


def test_truth_coefficients_by_hand():
    v = np.array([0.5, 1.0, 1.5, 0.5, 1.5])
    windows = [{"d1": 0.02 * (1 + 0.6 * (s - 1.0)), "d2": 0.02 * (1 + 0.6 * (s - 1.0)), "speed": s,
                "curvature": 0.0, "roll_deg": 0.0, "beta_deg": 30.0} for s in v]
    speed = {"expected": {"missing_physics": "speed_dependent_sinkage"}, "windows": windows}
    assert truth_coefficients(speed)["k_speed"] == pytest.approx(0.6)             # mean speed 1.0
    lat = [{"d1": 0.02 * (1 - 1.5 * L), "d2": 0.02 * (1 + 1.5 * L), "speed": 1.0, "curvature": 0.0,
            "roll_deg": math.degrees(math.asin(L))} for L in (0.02, -0.05, 0.1)]
    out = truth_coefficients({"expected": {"missing_physics": "lateral_load_transfer"}, "windows": lat})
    assert out["k_lateral"] == pytest.approx(1.5)
    walls = [{"d1": 0.02, "d2": 0.02, "beta_deg": 45.0, "beta_loose_deg": 30.0}]
    out = truth_coefficients({"expected": {"missing_physics": "cohesive_walls"}, "windows": walls})
    assert out["k_wall"] == pytest.approx(1.0 / math.tan(math.radians(30)) - 1.0)
    passes = [{"d1": 0.02, "d2": 0.02, "g": 0.6}]
    assert truth_coefficients({"expected": {"missing_physics": "multi_pass_hardening"},
                               "windows": passes})["k_pass"] == pytest.approx(-0.4)
    assert truth_coefficients({"expected": {"missing_physics": None}, "windows": windows}) == {}


def test_foreign_study_runs_on_a_pair_in_the_foreign_layout(tmp_path):
    """A 4 m synthetic drive written as NAME.npz, NAME_truth.json, NAME_surfaces.npz and
    robot.yaml (with the pair's own wheels deliberately wrong: robot.yaml must win)."""
    from torchsoil.synth.scenario import build_truth, terrain_pair_from_truth

    doc = {"name": "tiny", "trajectory": {"segments": [{"straight": 4.0, "speed": 1.0}]},
           "terrain": {"margin": 0.5}, "landmarks": {"poles": 0, "trunks": 0, "shed": False, "fence": False},
           "measurement": {"offset": 0.002}}
    truth = build_truth(doc, seed=1)
    pair = terrain_pair_from_truth(truth, seed=1)
    w = truth.world
    clean_f = np.take_along_axis(w.states, np.maximum(w.n_visits - 1, 0)[None], 0)[0]
    pair_bad_robot = {**{k: pair[k] for k in ("dx", "origin", "h_front", "h_back", "poses")},
                      "wheels": pair["wheels"] * [1, 2, 1], "wheel_width": np.float64(0.3)}
    np.savez(tmp_path / "tiny.npz", **pair_bad_robot)
    np.savez(tmp_path / "tiny_surfaces.npz", h_front_clean=clean_f, h_back_clean=w.h_after)
    (tmp_path / "tiny_truth.json").write_text(json.dumps({"expected": {"verdict": "adequate",
                                                                       "missing_physics": None}, "windows": []}))
    import yaml

    (tmp_path / "robot.yaml").write_text(yaml.safe_dump(paper_platform().to_dict()))
    settings = Settings().replace(diagnosis={"n_fit": 0})
    table = run_foreign(tmp_path, tmp_path / "out", settings, redraws=1)
    rec = json.loads((tmp_path / "out" / "cases.jsonl").read_text())
    assert rec["case"] == "tiny" and rec["want"] == "adequate"
    assert "| tiny |" in table and "false alarms on null drives" in table and "model error" in table
    # fitted to its own noise-free surfaces, the base model (the world's physics) is within
    # a fraction of the 3 mm noise; the noisy pair cannot do better
    assert 0 < rec["model_error_clean_mm"] < 1.0
    assert rec["model_error_mm"] > rec["model_error_clean_mm"]
    # another draw of the pair's noise: as far from the noise-free fit, not a copy of the pair's
    (other,) = rec["model_error_redraws_mm"]
    assert rec["model_error_clean_mm"] < other < 3 * rec["model_error_mm"] and other != rec["model_error_mm"]
    assert f"| {other - rec['model_error_clean_mm']:+.2f} / " in table and "(1) |" in table
    assert 0 < rec["model_error_fitted_clean_mm"] < 1.0 and rec["d_mm"] > 5    # the world digs a rut
    assert "diagnosis' section and dig order" in table
    # the per-window series a study is re-scored from offline: one held-out cost per window [mm]
    ser = rec["series"]
    assert len(ser["base"]) == len(ser["s"]) == len(ser["covariates"]["speed"]) >= 6 and ser["passes"] == {}
    assert all(c is None or 0 < c < 20 for c in ser["base"]) and sum(c is not None for c in ser["base"]) >= 4
    assert (tmp_path / "out" / "confusion.md").read_text() == table
    assert run_foreign(tmp_path, tmp_path / "out", settings) == table               # resumed: nothing redone


def test_a_record_re_scores_a_term_that_left_ground_alone_as_the_diagnosis_did():
    """A pass-count term leaves the costs of windows off revisited ground as they were, up to
    the simulator's rounding (here 2e-8 m, above locate.SAME, so the diagnosis keeps those
    blocks): the record keeps enough digits for the offline test to keep them too."""
    from types import SimpleNamespace

    from torchsoil.diagnosis.stats import by_fold, combined_z, fold_choice, folds, gain_correlation, paired_improvement
    from torchsoil.diagnosis.study import held_out_series, retest

    rng = np.random.default_rng(3)
    W = 48
    touched = np.arange(W) % 16 < 8                           # revisited ground: 2 blocks in every 4
    base, res0 = 3e-3 + 3e-4 * rng.standard_normal(W), 2.5e-3 + 3e-4 * rng.standard_normal(W)

    def ext(x, gain):
        return x - np.where(touched, gain + 5e-5 * rng.standard_normal(W), 2e-8 * rng.standard_normal(W))

    held = {0.0: base, -0.5: ext(base, 1e-4), 0.3: ext(base, -1e-4)}
    res = {0.0: res0, -0.5: ext(res0, 5e-5), 0.3: ext(res0, -5e-5)}
    passes = {k: SimpleNamespace(held_out=held[k], residual=res[k]) for k in held}
    diag = SimpleNamespace(windows={"s": 0.4 * np.arange(W)}, base=passes[0.0],
                           fits=[SimpleNamespace(ext=SimpleNamespace(id="multi_pass_hardening"), passes=passes)])
    rec = json.loads(json.dumps({"series": held_out_series(diag), "tests": [
        {"id": "multi_pass_hardening", "p_location": 0.01}]}))
    (t,), _ = retest(rec)

    lab = folds(W, 6)                                          # as the diagnosis scores it, in metres
    k_fold = fold_choice(held, lab)
    e, o = by_fold(held, k_fold, lab), by_fold(res, k_fold, lab)
    z_held = paired_improvement(base, e)[2]
    z = combined_z(z_held, paired_improvement(res0, o)[2], gain_correlation(base, e, res0, o))
    assert t["k_fold"] == list(k_fold) and t["held_z"] == pytest.approx(z_held, abs=1e-3)
    assert t["z"] == pytest.approx(z, abs=1e-3)
    assert abs(paired_improvement(base, e, same=1e-7)[2] - z_held) > 0.05   # the untouched blocks count


def test_a_study_record_keeps_the_hardening_test_in_brief():
    from types import SimpleNamespace

    from torchsoil.diagnosis.study import revisit_test

    rev = {"accepted": True, "windows": 11, "z": 2.8, "z_visible": 2.5, "z_level": 1.96, "g": 0.62,
           "g_folds": [0.6, 0.64], "laws": {}, "s": [1.0, 1.4], "per_pass": {"g": 0.54, "visits": []}}
    brief = revisit_test(SimpleNamespace(evidence={"revisits": rev}))
    assert brief == {"accepted": True, "windows": 11, "z": 2.8, "z_visible": 2.5, "z_level": 1.96, "g": 0.62,
                     "g_folds": [0.6, 0.64], "g_per_pass": 0.54}
    assert "g_per_pass" not in revisit_test(SimpleNamespace(evidence={"revisits": {**rev, "per_pass": None}}))
    assert revisit_test(SimpleNamespace(evidence={"revisits": None})) is None
