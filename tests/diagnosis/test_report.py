"""The plain-language explanation on hand-made diagnoses."""

from types import SimpleNamespace

from torchsoil.diagnosis import catalogue
from torchsoil.diagnosis.report import basis_text, effect_text, explain, per_pass_text, revisit_markdown, runner_up_text


def _adequate(fits, z_accept):
    zones = {zn: {"mean": 0.0, "z": 0.1} for zn in ("rut_floor", "rut_wall", "berm", "outside")}
    summary = {"verdict": "adequate", "missing_physics": None, "cost_before": {"prediction": 0.003, "residual": 0.003},
               "cost_after": {"prediction": 0.003, "residual": 0.003}, "noise_floor": 0.0034,
               "where": {"cross_track": "mixed", "along_track": [], "covariate": None},
               "candidates": [{"id": f.ext.id} for f in fits]}
    evidence = {"zones": zones, "z_locate": 3.09, "z_accept": z_accept, "map_nuisance_text": None,
                "tyre_section": None, "dig_order": None}
    return SimpleNamespace(summary=summary, evidence=evidence, best=None, fits=fits)


def _fit(ext_id, k, z, folds):
    return SimpleNamespace(ext=catalogue.get(ext_id), k=k, z=z, k_fold=folds, sections=None)


def test_an_adequate_drive_names_the_candidate_nearest_its_level_and_what_would_help():
    """Nearest by z minus its level (hardening 1.80 of 1.88), not by z (slip 2.0 of 2.47)."""
    fits = [_fit("slip_sinkage", 6.0, 2.0, (4.0, 8.0)), _fit("multi_pass_hardening", -0.45, 1.80, (-0.45, -0.6))]
    text = explain(_adequate(fits, {"slip_sinkage": 2.47, "multi_pass_hardening": 1.88}))
    assert "Nearest to acceptance: multi_pass_hardening (k_pass = -0.45, folds -0.45 and -0.6)" in text
    assert "z = 1.80 against 1.88 needed" in text and "more changes of its covariate (passes)" in text
    assert "about 1.1 x this drive's length" in text                     # (1.88 / 1.80)^2 = 1.09
    shape = explain(_adequate([_fit("footprint_width", 0.3, 1.2, (0.3, 0.15))], {"footprint_width": 2.17}))
    assert "footprint_width" in shape and "a longer drive" in shape
    assert "about 3.3 x this drive's length" in shape                   # (2.17 / 1.2)^2 = 3.27


def test_no_length_is_promised_when_the_folds_disagree():
    fits = [_fit("lateral_load_transfer", 0.8, 1.5, (0.8, 0.0)), _fit("slip_sinkage", 4.0, 1.0, (4.0, -4.0))]
    text = explain(_adequate(fits, {"lateral_load_transfer": 1.88, "slip_sinkage": 2.33}))
    assert "Nearest to acceptance: lateral_load_transfer" in text and "this drive's length" not in text


def test_no_nearest_candidate_is_named_when_none_gained():
    fits = [_fit("speed_dependent_sinkage", 0.0, 0.0, (0.0, 0.0)), _fit("slip_sinkage", -4.0, -0.7, (-4.0, 4.0))]
    text = explain(_adequate(fits, {"speed_dependent_sinkage": 1.88, "slip_sinkage": 2.33}))
    assert "Nearest to acceptance" not in text


def test_a_steady_but_immaterial_gain_is_named_as_such():
    """z above its level, gain 0.0014 mm against the 0.0062 mm a term must bring."""
    f = SimpleNamespace(**vars(_fit("speed_dependent_sinkage", 0.07, 2.64, (0.07, 0.07))), improvement=1.4e-6)
    diag = _adequate([f], {"speed_dependent_sinkage": 2.33})
    diag.evidence["gain_material"] = 6.2e-6
    text = explain(diag)
    assert "z = 2.64 against 2.33 needed" in text
    assert "held-out gain, 0.0014 mm, is under the 0.0062 mm a term must bring" in text
    assert "this drive's length" not in text


def test_a_steady_gain_from_a_negligible_coefficient_is_named_as_such():
    """z above its level and a material gain, but k_speed 0.028 changes the sinkage by 0.9 %."""
    f = SimpleNamespace(**vars(_fit("speed_dependent_sinkage", 0.028, 2.46, (0.028, 0.028))), improvement=6e-6,
                        effect=0.009, own_z=1.5)
    diag = _adequate([f], {"speed_dependent_sinkage": 1.95})
    diag.evidence.update(gain_material=5.7e-6, effect_material=0.05)
    text = explain(diag)
    assert "z = 2.46 against 1.95 needed" in text
    assert "it changes the model by 0.9 %, under the 5 % a named cause must" in text
    assert "this drive's length" not in text


def test_a_term_that_fits_its_own_windows_worse_is_named_as_a_stand_in():
    """z above its level and a material gain, but the windows' own residuals worse with it."""
    f = SimpleNamespace(**vars(_fit("speed_dependent_sinkage", 1.2, 3.15, (1.2, 1.2))), improvement=7e-5,
                        own_z=-1.44)
    diag = _adequate([f], {"speed_dependent_sinkage": 2.48})
    diag.evidence.update(gain_material=6e-6, own_z_min=0.0)
    text = explain(diag)
    assert "z = 3.15 against 2.48 needed" in text
    assert "paired z of their residuals -1.44" in text and "soil that changes where the speed changes" in text
    assert "this drive's length" not in text


def test_an_unexplained_rut_says_where_across_the_rut_the_recording_differs():
    d = _adequate([], {})
    d.summary.update(verdict="unexplained", where={"cross_track": "rut_wall", "along_track": [[0.0, 20.0]],
                                                    "covariate": None})
    d.evidence.update(spectral_line={"p": 0.5}, rut_shape=[(0.0, 0.02, -1.0e-3), (0.04, 0.04, 1.2e-3)])
    text = explain(d)
    assert "a systematic residual on the rut wall" in text
    assert ("the recording lies above the model 0-20 mm out (by 1.00 mm), below it 40 mm out (by 1.20 mm)."
            in text)
    d.evidence["rut_shape"] = [(0.0, 0.0, -1.0e-3)]
    assert "the recording lies above the model at the centre line (by 1.00 mm)." in explain(d)
    d.evidence["rut_shape"] = []
    assert "Across the rut" not in explain(d)


def test_an_accepted_term_says_how_much_it_changes_the_model():
    speed = SimpleNamespace(ext=catalogue.get("speed_dependent_sinkage"), k=-0.4, effects={0.0: 0.0, -0.4: 0.234})
    assert effect_text(speed) == " At that coefficient the term changes the sinkage by 23 % or more on a " \
                                 "twentieth of the drive."
    hard = SimpleNamespace(ext=catalogue.get("multi_pass_hardening"), k=-0.45, effects={-0.45: 0.45})
    assert "sinkage of a second pass over the same ground by 45 %" in effect_text(hard)
    assert effect_text(SimpleNamespace(ext=speed.ext, k=0.2, effects=None)) == ""


def _per_pass():
    """A fit pass by pass (revisits.per_pass_fit) by hand: g 0.5, first-pass d 30 mm at both
    visits of a robot with two wheels per track; one window came back over a single pass."""
    def group(visit, n, windows):
        return {"visit": visit, "passes_before": n, "windows": windows, "d_first_pass": 0.03, "d_sd": 0.002,
                "passes": [{"pass": n + j, "sinkage": 0.03 * 0.5 ** (n + j), "sd": 0.001} for j in (0, 1)]}
    return {"g": 0.5, "g_tried": [[0.667, -0.2], [0.5, 0.0]], "windows": 20,
            "visits": [group(0, 0, 20), group(1, 1, 1), group(1, 2, 19)]}


def test_the_sinkage_pass_by_pass_reads_each_pass_in_turn():
    text = per_pass_text(_per_pass())
    assert "g = 0.5" in text and "30.00 mm at visit 0, 30.00 mm at visit 1" in text
    assert "30.0, 15.0, 7.5, 3.8 mm in turn" in text          # the largest group of each visit
    assert per_pass_text(None) == "" and per_pass_text({"reason": "3 windows"}) == ""


def test_the_revisit_section_tables_the_sinkage_of_every_pass():
    rev = {"z": 2.9, "z_visible": 2.6, "z_level": 1.96, "windows": 20, "cost_before": 0.0046, "noise_floor": 0.0035,
           "g": 0.667, "g_folds": [0.68, 0.66], "gain": 0.001, "cost_after": 0.0035, "accepted": True,
           "rut": {"measured": 0.0036, "simulated_without_law": 0.0093, "simulated_with_law": 0.0033},
           "laws": {"geometric": {"coefficient": 0.667, "cost": 0.0035}}, "shape": None, "per_pass": _per_pass()}
    md = revisit_markdown(rev)
    assert "| 1 | 2 | 19 | 30.0 ± 2.0 | 7.5 ± 1.0, 3.8 ± 1.0 |" in md
    assert "| 0 | 0 | 20 | 30.0 ± 2.0 | 30.0 ± 1.0, 15.0 ± 1.0 |" in md
    assert "tried: 0.667, 0.5" in md
    assert "not fitted (3 windows" in revisit_markdown({**rev, "per_pass": {"reason": "3 windows"}})


def test_a_named_term_says_what_its_gain_rests_on():
    basis = {"windows": 48, "blocks": 12, "n_eff": 2.5, "carrier_blocks": 2, "carriers": [[3.2, 6.0]]}
    text = basis_text(basis)
    assert "48 windows in 12 blocks" in text and "2.5 independent blocks" in text
    assert "half of it comes from 2 of them (3.2-6.0 m)" in text
    assert basis_text(None) == "" and basis_text({**basis, "blocks": 0}) == ""


def test_the_runner_up_sentence_says_which_term_passed_its_own_test():
    both = {"runner_up": "cohesive_walls", "improvement": 2.8e-4, "se": 1.5e-4, "z": 1.87}
    assert "cohesive_walls passed its test too" in runner_up_text(both)
    assert "by 0.28 mm +- 0.15 mm (z = 1.9)" in runner_up_text(both)
    joined = {**both, "named_passed": False, "runner_up_passed": True}
    text = runner_up_text(joined)
    assert "cohesive_walls passed its test, so the rut's shape needs a term" in text
    assert "meets every condition but its own level" in text
    short = {**both, "named_passed": True, "runner_up_passed": False}
    assert "short of its own level; the named term does better" in runner_up_text(short)
    assert runner_up_text(None) == ""
