"""The study's out-of-catalogue laws a learned modifier names: the cases (fixed and randomized)
and the scoring of a learned verdict on hand-written diagnoses and records."""

import json
from types import SimpleNamespace

import numpy as np
import pytest

from torchsoil.diagnosis import study_cases as sc
from torchsoil.diagnosis.study import _record, confusion, error_rates, learned_match, named_terms, wanted_term
from torchsoil.synth import effects as fx
from torchsoil.synth.scenario import load_scenario

CHI_SPEED_UP = {"parameter": "chi", "covariate": "speed", "direction": "+"}


def summary(verdict="missing_physics", eid="learned", terms=(), params=None):
    """A diagnosis summary (diagnosis.json) with its learned modifier's terms under `learned`
    (`fake_diag` moves them where a Diagnosis holds them)."""
    return {"verdict": verdict, "missing_physics": eid, "where": {"cross_track": None, "along_track": [],
                                                                  "covariate": None},
            "extension_parameters": params or {}, "cost_before": {"prediction": 0.004},
            "cost_after": {"prediction": 0.003}, "noise_floor": 0.003,
            "learned": {"terms": [dict(t) for t in terms], "catalogue_match": None} if terms else None}


def fake_diag(s):
    """The least of a Diagnosis `_record` reads: its summary (diagnosis.json: `learned` taken
    out), its learned modifier (learned.json, named with a missing_physics verdict), no
    catalogue fits, no windows."""
    s = dict(s)
    learned = s.pop("learned", None)
    if learned is not None:
        learned = {**learned, "named": s["verdict"] == "missing_physics"}
    return SimpleNamespace(summary=s, learned=learned, evidence={"z_accept": {}, "candidates": {}}, fits=[],
                           windows={"s": []}, base=SimpleNamespace(held_out=[], residual=[]))


def term(parameter, covariate, direction, gain=0.1):
    return {"parameter": parameter, "covariate": covariate, "direction": direction, "shape": "linear",
            "held_out_gain": gain}


def rec(name, s, want="missing_physics", want_id="learned", want_learned=CHI_SPEED_UP):
    return _record(name, fake_diag(s), want, want_id, 5.0, want_learned if want_id == "learned" else None)


def test_a_learned_verdict_is_right_on_the_covariate_direction_and_parameter():
    right = rec("right", summary(terms=[term("d", "turn_rate", "+"), term("chi", "speed", "+", 0.2)]))
    assert right["correct"] and right["learned_match"] == {"covariate": True, "direction": True, "parameter": True,
                                                           "right": True, "term": term("chi", "speed", "+", 0.2)}
    assert right["want_learned"] == CHI_SPEED_UP and right["learned"]["terms"][0]["covariate"] == "turn_rate"
    json.dumps(right)                                                   # a cases.jsonl line
    wrong_dir = rec("wrong direction", summary(terms=[term("chi", "speed", "-")]))
    assert not wrong_dir["correct"]
    assert wrong_dir["learned_match"] == {"covariate": True, "direction": False, "parameter": True, "right": False,
                                          "term": term("chi", "speed", "-")}
    wrong_par = rec("wrong parameter", summary(terms=[term("d", "speed", "+")]))
    assert not wrong_par["correct"] and wrong_par["learned_match"]["direction"]
    wrong_cov = rec("wrong covariate", summary(terms=[term("chi", "accel", "+")]))
    m = wrong_cov["learned_match"]
    assert not wrong_cov["correct"] and (m["covariate"], m["direction"], m["parameter"]) == (False, False, True)
    # the right term, but the verdict is not missing_physics: not right
    told = rec("adequate", summary("adequate", None, terms=[term("chi", "speed", "+")]))
    assert not told["correct"]
    nothing = rec("nothing", summary("unexplained", None))
    assert not nothing["correct"] and nothing["learned_match"]["term"] is None


def test_a_catalogue_id_whose_term_is_the_wanted_one_is_right():
    want = {"parameter": "d", "covariate": "traction", "direction": "+"}   # a convex slip law
    slip = summary(eid="slip_sinkage", params={"k_slip": 5.0})
    assert named_terms(slip) == [{"parameter": "d", "covariate": "traction", "direction": "+", "from": "slip_sinkage"},
                                 {"parameter": "d", "covariate": "accel", "direction": "+", "from": "slip_sinkage"}]
    assert rec("slip", slip, want_learned=want)["correct"]
    harder = summary(eid="multi_pass_hardening", params={"k_pass": -0.4})
    assert learned_match({"parameter": "d", "covariate": "passes", "direction": "-"}, named_terms(harder))["right"]
    assert not learned_match({"parameter": "beta", "covariate": "passes", "direction": "-"},
                             named_terms(harder))["right"]            # hardening is no loosening
    assert not rec("speed", summary(eid="speed_dependent_sinkage", params={"k_speed": 0.5}))["correct"]  # d, not chi
    # a catalogue drive keeps its own rule: the id
    cat = rec("cat", summary(eid="slip_sinkage", params={"k_slip": 5.0}), want_id="slip_sinkage")
    assert cat["correct"] and cat["learned_match"] is None and cat["want_learned"] is None


def test_error_rates_and_table_count_learned_verdicts():
    records = [rec("r1", summary(terms=[term("chi", "speed", "+")])),
               rec("r2", summary(terms=[term("chi", "speed", "-")])),
               rec("r3", summary(eid="slip_sinkage", params={"k_slip": 5.0})),
               rec("r4", summary("unexplained", None)),
               rec("null named", summary(terms=[term("d", "turn_rate", "+")]), "adequate", None),
               rec("null", summary("adequate", None), "adequate", None)]
    e = error_rates(records)
    assert (e["nulls"], e["false_alarms"]) == (2, 1)                   # a null drive named learned: a false alarm
    assert e["wrong_id"] == 2                                          # r2 (direction) and r3 (slip, not chi)
    assert (e["learned"], e["learned_right"], e["learned_covariate"], e["learned_direction"],
            e["learned_parameter"]) == (4, 1, 2, 1, 2)
    table = confusion(records)
    assert "learned laws named right: 1/4 (covariate 2/4, direction 1/4, parameter 2/4)" in table
    assert "| learned chi~speed+ |" in table and "right: 2/6" in table
    row = next(r for r in table.splitlines() if r.startswith("| learned chi~speed+ |"))
    assert row.endswith("| 1/4 |")
    assert "| r2 | learned chi~speed- |" in table and "| r1 | learned chi~speed+ |" in table
    assert next(r for r in table.splitlines() if r.startswith("| r4 |")).endswith("| no term named |")
    assert "false alarms on null drives: 1/2" in table


def test_a_foreign_truth_s_expected_names_the_wanted_term():
    """The shape of /work/shared/foreign/outside/*_truth.json `expected`."""
    exp = {"verdict": "missing_physics", "missing_physics": "learned", "cross_track": "rut_wall",
           "covariate": "passes", "direction": "-", "parameter": "beta", "along_track": [[18.25, 23.72]]}
    assert wanted_term(exp) == {"parameter": "beta", "covariate": "passes", "direction": "-"}
    assert wanted_term({"verdict": "missing_physics", "missing_physics": "slip_sinkage"}) is None
    assert wanted_term({"verdict": "adequate", "missing_physics": None}) is None


def test_fixed_learned_cases_want_their_law_s_term():
    want = {name: wanted_term(fx.expected(fx.resolve(doc["effects"])))
            for name, doc, _, verdict, eid in sc.STUDY_CASES if eid == "learned"}
    assert want["deposit linear"] == CHI_SPEED_UP
    assert want["deposit saturating falling"] == {**CHI_SPEED_UP, "direction": "-"}
    assert want["scrub threshold"] == {"parameter": "d", "covariate": "turn_rate", "direction": "+"}
    assert want["loosening linear"] == {"parameter": "beta", "covariate": "passes", "direction": "-"}
    assert want["loosening saturating rising"]["direction"] == "+"
    assert sc.STUDY_CASES[:21] == [c for c in sc.STUDY_CASES if c[4] != "learned"]     # appended: --quick keeps its own


def test_randomized_learned_cases_leave_the_others_alone():
    base = sc.randomized_cases(14, 20, seed=3)
    cases = sc.randomized_cases(14, 20, seed=3, n_learned=9)
    assert cases[:14] == base[:14] and cases[23:] == base[14:]
    learned = cases[14:23]
    assert [c[2] for c in learned] == [3499 - j for j in range(9)]
    assert [next(iter(c[1]["effects"])) for c in learned] == list(sc.LEARNED_KINDS) * 3
    assert all(c[3:] == ("missing_physics", "learned") for c in learned)
    assert sc.randomized_cases(3, 2, seed=3, n_learned=2) == [cases[i] for i in (0, 1, 2, 14, 15, 23, 24)]
    for _name, doc, *_ in learned:
        load_scenario(doc)
    kept = sc.revisit_cases(cases)
    assert all(c in kept for c in learned if "pass_loosening" in c[1]["effects"])
    with pytest.raises(ValueError, match="at most 500"):
        sc.randomized_cases(400, 0, n_learned=101)


@pytest.mark.parametrize("eid", sc.LEARNED_KINDS)
def test_random_learned_laws_have_the_drawn_effect_and_either_direction(eid):
    x0, (lo, hi) = sc.LEARNED_LAWS[eid]
    forms, signs = set(), set()
    for seed in range(40):
        law = sc.random_law(np.random.default_rng(seed), eid)
        forms.add(law["form"])
        signs.add(np.sign(law["k"]) * np.sign(lo))
        k_lin = abs(law["k"] * fx.phi(x0, law["form"], law["p"], law["x_s"]) / x0)
        assert abs(lo) - 1e-9 <= k_lin <= abs(hi) + 1e-9 or abs(hi) - 1e-9 <= k_lin <= abs(lo) + 1e-9
        fx.resolve({eid: law})
    assert forms == set(fx.FORMS)
    assert signs == ({1, -1} if eid in sc.EITHER_WAY else {1})


def test_random_turn_drives_turn_both_ways_on_level_ground():
    from torchsoil.robot import paper_platform
    from torchsoil.synth.terrain import Relief
    from torchsoil.synth.trajectory import build_trajectory

    seed = next(s for s in range(1000) if sc.random_case(s, "turn_scrub")[0].endswith("turns"))
    doc = sc.random_case(seed, "turn_scrub")[1]
    assert "slope_x" not in doc["terrain"]["relief"] and "slope_y" not in doc["terrain"]["relief"]
    traj = build_trajectory(load_scenario(doc).trajectory, Relief(0.0, 0.0, *[np.zeros(0)] * 4), paper_platform())
    yr = traj.yaw_rate
    assert yr.max() > 0.2 and yr.min() < -0.2 and (np.abs(yr) < 0.01).mean() > 0.2    # left, right and straight


def test_learned_drives_belong_to_the_randomized_study(tmp_path, capsys):
    from torchsoil.cli import main

    assert main(["study", "--quick", "--learned", "2", "--out", str(tmp_path / "o")]) == 2
    assert "--learned" in capsys.readouterr().err and not (tmp_path / "o").exists()
