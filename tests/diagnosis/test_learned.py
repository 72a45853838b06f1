"""The learned modifier: its curves, its hooks into the simulator, its words, by hand."""

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from torchsoil.diagnosis import learned as L
from torchsoil.diagnosis.covariates import DriveSignals
from torchsoil.grid import Grid
from torchsoil.robot import paper_platform
from torchsoil.sim import Modifiers
from torchsoil.sim.geometry import wheel_geometry
from torchsoil.sim.simulate import simulate

ROBOT = paper_platform()


def ramp_poses(v0=0.5, v1=1.5, n=301, length=6.0):
    """(n, 7) poses straight along x, the speed rising linearly from v0 to v1 m/s over `length` m."""
    x = np.linspace(0.0, length, n)
    v = v0 + (v1 - v0) * x / length
    t = np.concatenate([[0.0], np.cumsum(np.diff(x) / (0.5 * (v[1:] + v[:-1])))])
    p = np.zeros((n, 7))
    p[:, 0], p[:, 1] = t, x
    return p


def test_a_curve_interpolates_its_knot_values_is_zero_at_its_anchor_and_flat_beyond():
    b = L.Basis(np.array([0.0, 1.0, 3.0]), anchor=1)
    w = np.array([-0.4, 0.6])                           # values at knots 0 and 3; 0 at knot 1
    assert b.values(w).tolist() == [-0.4, 0.0, 0.6]
    f = b.curve(w, [-2.0, 0.0, 0.5, 1.0, 2.0, 3.0, 7.0])
    assert f == pytest.approx([-0.4, -0.4, -0.2, 0.0, 0.3, 0.6, 0.6])
    assert b.matrix([0.25, 2.5]).sum(1) == pytest.approx([0.75, 0.75])   # the anchor's share left out


def test_knots_follow_the_ground_driven_and_a_steady_covariate_has_none():
    drive = DriveSignals.from_poses(ramp_poses(), ROBOT)
    speed = L.make_basis(L.Term("d", "speed"), drive, ROBOT)
    assert speed.knots[0] == pytest.approx(0.52, abs=0.02) and speed.knots[-1] == pytest.approx(1.48, abs=0.02)
    assert speed.knots[speed.anchor] == pytest.approx(1.0, abs=0.03)     # the median speed over the ground
    passes = L.make_basis(L.Term("beta", "passes"), drive, ROBOT)
    assert passes.knots.tolist() == [0.0, 1.0, 2.0, 4.0] and passes.anchor == 0
    steady = DriveSignals.from_poses(ramp_poses(1.0, 1.0), ROBOT)
    assert L.make_basis(L.Term("d", "speed"), steady, ROBOT, min_spread={"speed": 0.05}) is None
    assert L.make_basis(L.Term("d", "turn_rate"), drive, ROBOT) is None   # a straight drive never turns


def test_terms_read_as_the_same_signal_are_kept_once():
    p = ramp_poses(1.0, 1.0, n=401, length=8.0)
    p[:, 6] = 0.3 * np.sin(p[:, 1])                     # weaving at a steady speed
    drive = DriveSignals.from_poses(p, ROBOT)
    bases = {t: b for t in (L.Term("d", "turn_rate"), L.Term("d", "lateral_accel"), L.Term("chi", "lateral_accel"))
             if (b := L.make_basis(t, drive, ROBOT)) is not None}
    kept = L.distinct(drive, bases)
    assert L.Term("d", "turn_rate") in kept and L.Term("d", "lateral_accel") not in kept
    assert L.Term("chi", "lateral_accel") in kept        # another parameter: a term of its own


def grid_and_geometry(poses):
    grid = Grid(0.02, (-0.5, -1.0), (int(7.0 / 0.02), int(2.0 / 0.02)))
    return grid, wheel_geometry(grid, poses, ROBOT, dtype=torch.float64)


def test_the_sinkage_factor_at_each_entry_is_exp_of_the_curve_at_its_pose():
    poses = ramp_poses()
    drive = DriveSignals.from_poses(poses, ROBOT)
    _, geom = grid_and_geometry(poses)
    term = L.Term("d", "speed")
    basis = L.Basis(np.array([0.5, 1.0, 1.5]), anchor=1)
    model = L.LearnedModel({term: basis}, drive, ROBOT, w={term: np.array([math.log(0.5), math.log(2.0)])})
    wd = SimpleNamespace(spec=SimpleNamespace(s0=0.0, s1=6.0), crop=(0, 1, 0, 1), geom=geom)
    mods = model.modifiers(wd, torch.zeros(3, 4, dtype=torch.float64))
    assert mods.chi_scale is None and mods.beta_scale is None
    got = mods.depth_scale.numpy()
    assert got.shape == (3, len(geom.cell))
    t = geom.poses[:, 0].numpy()[geom.pose.numpy()]
    v = np.interp(t, drive.signals["t"], drive.signals["speed"])
    want = np.exp(np.interp(v, [0.5, 1.0, 1.5], [math.log(0.5), 0.0, math.log(2.0)]))
    assert got[1] == pytest.approx(want, rel=1e-9)
    assert want.min() < 0.6 and want.max() > 1.8       # the ramp spans the curve
    # a window's fit scaled back to the reference: the anchor is f at its own ground
    model.anchor = model.own_mean(wd)
    back = model.modifiers(wd, torch.zeros(1, 4, dtype=torch.float64)).depth_scale[0].numpy()
    assert np.log(back).mean() == pytest.approx(0.0, abs=1e-12)


def test_a_visit_without_entries_or_with_unknown_covariates_gets_no_factor():
    """An earlier visit none of whose wheels meets the window's cells (a window's ground at a
    neighbouring row, say), and entries whose covariate is unknown, get f = 0: a factor of 1,
    not the NaN of a mean over nothing that the simulator refuses."""
    poses = ramp_poses()
    drive = DriveSignals.from_poses(poses, ROBOT)
    d, chi = L.Term("d", "speed"), L.Term("chi", "speed")
    basis = L.Basis(np.array([0.5, 1.0, 1.5]), anchor=1)
    w = {d: np.array([math.log(0.5), math.log(2.0)]), chi: np.array([math.log(0.5), math.log(2.0)])}
    model = L.LearnedModel({d: basis, chi: basis}, drive, ROBOT, w=w)
    far = wheel_geometry(Grid(0.02, (40.0, 40.0), (20, 20)), poses, ROBOT, dtype=torch.float64)
    assert len(far.cell) == 0
    wd = SimpleNamespace(spec=SimpleNamespace(s0=0.0, s1=6.0), crop=(0, 1, 0, 1), geom=far)
    anchor = model.own_mean(wd)
    assert {p: float(v) for p, v in anchor.items()} == {"d": 0.0, "chi": 0.0}
    mods = model.modifiers(wd, torch.zeros(1, 4, dtype=torch.float64))
    assert mods.depth_scale.shape == (1, 0) and float(mods.chi_scale[0]) == 1.0
    # speed unknown over the second half of the drive: those entries keep their d
    _, geom = grid_and_geometry(poses)
    half = drive.signals["t"] > drive.signals["t"][-1] / 2
    drive.signals["speed"] = np.where(half, np.nan, drive.signals["speed"])
    model = L.LearnedModel({d: basis}, drive, ROBOT, w={d: w[d]})
    wd = SimpleNamespace(spec=SimpleNamespace(s0=0.0, s1=6.0), crop=(0, 1, 0, 1), geom=geom)
    got = model.modifiers(wd, torch.zeros(1, 4, dtype=torch.float64)).depth_scale[0].numpy()
    t = geom.poses[:, 0].numpy()[geom.pose.numpy()]
    late = t > drive.signals["t"][np.argmax(half)]
    assert np.isfinite(got).all() and late.any() and (got[late] == 1.0).all()
    assert (got[~late] < 0.99).any()                     # the known half keeps its curve (speed below 1 m/s)


def test_deposit_share_and_repose_scales_act_as_the_scaled_parameters():
    poses = ramp_poses(1.0, 1.0)
    _, geom = grid_and_geometry(poses)
    rng = np.random.default_rng(3)
    h = torch.as_tensor(rng.normal(0, 0.002, geom.shape), dtype=torch.float64)
    theta = torch.tensor([[0.03, 0.03, 0.6, math.radians(30.0)]], dtype=torch.float64)
    scaled = simulate(h, geom, theta, modifiers=Modifiers(chi_scale=torch.tensor([0.5], dtype=torch.float64),
                                                          beta_scale=torch.tensor([0.5], dtype=torch.float64)))
    plain = simulate(h, geom, torch.tensor([[0.03, 0.03, 0.3, math.radians(15.0)]], dtype=torch.float64))
    assert torch.equal(scaled.h, plain.h)
    assert float(scaled.deposited[0]) == pytest.approx(0.5 * float(simulate(h, geom, theta).deposited[0]), rel=1e-9)
    # chi x scale beyond 1 is clipped to 1: every removed cell's soil laid beside the rut
    over = simulate(h, geom, theta, modifiers=Modifiers(chi_scale=torch.tensor([3.0], dtype=torch.float64)))
    full = simulate(h, geom, torch.tensor([[0.03, 0.03, 1.0, math.radians(30.0)]], dtype=torch.float64))
    assert torch.equal(over.h, full.h)


def test_gradients_reach_the_chi_and_beta_scales_as_finite_differences_say():
    poses = ramp_poses(1.0, 1.0, n=101, length=2.0)
    _, geom = grid_and_geometry(poses)
    h = torch.zeros(geom.shape, dtype=torch.float64)
    target = simulate(h, geom, torch.tensor([[0.03, 0.03, 0.5, math.radians(25.0)]], dtype=torch.float64)).h
    theta = torch.tensor([[0.03, 0.03, 0.6, math.radians(30.0)]], dtype=torch.float64)

    def cost(c, b):
        m = Modifiers(chi_scale=c.reshape(1), beta_scale=b.reshape(1))
        return ((simulate(h, geom, theta, modifiers=m).h - target) ** 2).sum()

    c, b = torch.tensor(0.9, dtype=torch.float64, requires_grad=True), torch.tensor(0.9, dtype=torch.float64,
                                                                                      requires_grad=True)
    cost(c, b).backward()
    eps = 1e-6
    with torch.no_grad():
        fd_c = (cost(c + eps, b) - cost(c - eps, b)) / (2 * eps)
        fd_b = (cost(c, b + eps) - cost(c, b - eps)) / (2 * eps)
    assert float(c.grad) == pytest.approx(float(fd_c), rel=1e-4) and abs(float(fd_c)) > 0
    assert float(b.grad) == pytest.approx(float(fd_b), rel=1e-3, abs=1e-12)


def test_curve_shapes_and_the_catalogue_laws_they_are():
    x = np.linspace(0.0, 1.0, 41)
    assert L.shape(x, 1 + x) == "linear" and L.shape(x, 2 - x) == "linear"
    assert L.shape(x, 1 + x ** 2) == "convex" and L.shape(x, 2 - x ** 2) == "concave"
    assert L.shape(x, 1 + np.sqrt(x)) == "concave"
    assert L.shape(x, 1 + (x - 0.5) ** 2) == "u_shaped" and L.shape(x, 2 - (x - 0.5) ** 2) == "peaked"
    assert L.catalogue_match(L.Term("d", "speed"), "-") == "speed_dependent_sinkage"
    assert L.catalogue_match(L.Term("d", "traction"), "+") == "slip_sinkage"
    assert L.catalogue_match(L.Term("d", "traction"), "-") is None        # the catalogue's slip deepens ruts
    assert L.catalogue_match(L.Term("d", "passes"), "-") == "multi_pass_hardening"
    assert L.catalogue_match(L.Term("d", "passes"), "+") is None          # loosening is no hardening
    assert L.catalogue_match(L.Term("chi", "speed"), "+") is None
    assert L.catalogue_match(L.Term("d", "turn_rate"), "+") is None


def fold(term, basis, values):
    m = L.LearnedModel({term: basis}, None, ROBOT, w={term: np.asarray(values)})
    return L.FoldChoice({term.name: 1.0}, {term.name: 0.9}, term, m)


def test_the_description_says_what_the_curve_follows_by_how_much():
    term = L.Term("d", "turn_rate")
    basis = L.Basis(np.array([0.0, 0.2, 0.4]), anchor=0)
    a = fold(term, basis, [math.log(1.3), math.log(2.0)])
    b = fold(term, basis, [math.log(1.5), math.log(2.0)])
    fit = L.LearnedFit((a, b), [term], z=3.0, improvement=2e-4, se=5e-5, held_z=2.5, own_z=1.0, effect=0.9,
                       accepted=True)
    out = L.describe(fit, 1.95)
    t = out["terms"][0]
    assert (t["parameter"], t["covariate"], t["direction"], t["catalogue_match"]) == ("d", "turn_rate", "+", None)
    mean = np.log([1.0, math.sqrt(1.3 * 1.5), 2.0])
    assert t["log_factor"] == pytest.approx(mean.tolist())
    assert t["band"][0] == pytest.approx(np.log([1.0, 1.3, 2.0]).tolist())
    x_lo, x_hi = 0.02, 0.38                              # 5 and 95 % of the knots' span
    want = math.exp(np.interp(x_hi, basis.knots, mean) - np.interp(x_lo, basis.knots, mean))
    # factors 1, 1.40, 2 at 0, 0.2, 0.4 rad/s: below the chord (1.5 half way), a convex rise
    assert t["factor"] == pytest.approx(want) and t["shape"] == "convex"
    assert t["sentence"].startswith("Sinkage rises convexly with turn rate (x") and "no catalogue term" in t["sentence"]


def visit_rows(beta_per_pass, n_windows=10, seed=0):
    """Per-visit rows of windows each driven twice (2 wheel passes before the second visit),
    beta [deg] times beta_per_pass per pass at the second, with 1 % noise."""
    rng = np.random.default_rng(seed)
    rows = []
    for k in range(n_windows):
        b0 = 30.0 * (1 + 0.01 * rng.normal())
        for visit, n in ((0, 0), (1, 2)):
            beta = b0 * beta_per_pass ** n * (1 + 0.01 * rng.normal())
            rows.append({"s": 0.4 * k, "visit": visit, "passes_before": n, "beta": beta, "chi": 0.5,
                         "residual": 1e-3, "flags": ""})
    return rows


def test_a_parameter_falling_with_the_passes_on_the_same_ground_is_found_and_a_steady_one_is_not():
    falling = L.visit_test(visit_rows(0.9), "beta", alpha=0.0125, materiality=0.05)
    assert falling["accepted"] and falling["direction"] == "-"
    assert falling["g"] == pytest.approx(0.9, abs=0.01) and falling["windows"] == 10
    steady = L.visit_test(visit_rows(1.0), "beta", alpha=0.0125, materiality=0.05)
    assert not steady["accepted"] and abs(steady["g"] - 1) < 0.01
    small = L.visit_test(visit_rows(0.98), "beta", alpha=0.0125, materiality=0.05)
    assert not small["accepted"]                        # 2 % per pass: under the materiality
    few = L.visit_test(visit_rows(0.9, n_windows=3), "beta", alpha=0.0125, materiality=0.05)
    assert not few["accepted"] and few["windows"] == 3
    desc = L.describe_visits(falling)
    assert desc["parameter"] == "beta" and desc["direction"] == "-" and desc["catalogue_match"] is None
    assert desc["sentence"].startswith("The angle of repose falls with the passes")


def visit_costs(minimum_at, n_windows=24, seed=1):
    """Per-visit pass `later` entries of visit_rows' windows: each later visit's cost [m] over
    the angle-of-repose factors, a parabola in the log factor with its least at `minimum_at`
    (None: flat, the angle the maps do not pin down), with 0.005 mm noise."""
    from torchsoil.diagnosis.revisits import SHARE_FACTORS

    rng = np.random.default_rng(seed)
    x = np.log(np.array(SHARE_FACTORS))
    later = {}
    for k in range(n_windows):
        bowl = 0.0 if minimum_at is None else 2e-3 * (x - math.log(minimum_at)) ** 2
        later[(0.4 * k, 1)] = {"passes": 2.0, "share_factor": np.array(SHARE_FACTORS),
                               "cost_beta": 2e-3 + bowl + rng.normal(0, 5e-6, len(x))}
    return later


def test_a_parameter_that_changes_between_visits_must_predict_the_later_visits_better():
    """The fits' angle falls x0.9 per pass on every window; where the later visits' costs are
    least at 0.81 (two passes) the law predicts them better and is kept; where the costs do not
    change with the angle, the fits wandered on a parameter the maps do not hold, and it is not."""
    rows = visit_rows(0.9, n_windows=24)
    held = L.visit_test(rows, "beta", alpha=0.0125, materiality=0.05, later=visit_costs(0.81))
    assert held["accepted"] and held["cost_gain"] > 0 and held["cost_z"] > held["z_level"]
    loose = L.visit_test(rows, "beta", alpha=0.0125, materiality=0.05, later=visit_costs(None))
    assert loose["z"] > loose["z_level"] and not loose["accepted"]
    wrong = L.visit_test(rows, "beta", alpha=0.0125, materiality=0.05, later=visit_costs(1.2))
    assert wrong["cost_gain"] < 0 and not wrong["accepted"]
    # by hand: a visit whose cost is 3 mm at factor 1 and 2 mm at 0.81, linear in the log factor between
    one = {(0.0, 1): {"passes": 2.0, "share_factor": np.array([0.81, 1.0]), "cost_beta": np.array([2e-3, 3e-3])}}
    gain, _, _ = L.cross_visit_gain(one, "beta", 0.9)
    assert gain == pytest.approx(1e-3)


@pytest.fixture(scope="module")
def deposit_drive():
    """The study's drive whose deposit share grows with speed (chi x (1 + 0.8 (v - 1)), the
    recorder's world; the speed changes every 2 m), and the base model's pass over it."""
    from torchsoil.diagnosis.fit import run_pass
    from torchsoil.diagnosis.study_cases import scenario
    from torchsoil.io.terrain_pair import TerrainPair
    from torchsoil.settings import Settings
    from torchsoil.synth.scenario import make_terrain_pair

    sc = scenario("speed_deposit")
    sc["soil"]["base"]["chi"] = 0.5              # berms that show the deposit share over the maps' noise
    pair = TerrainPair.from_mapping(make_terrain_pair(sc, seed=1))
    s = Settings()
    return pair, s, run_pass(pair, s.estimator, s.sim, offsets=s.diagnosis.offsets)


def test_a_deposit_share_following_speed_is_learned_through_the_simulator(deposit_drive, tmp_path):
    from torchsoil.diagnosis.checkpoint import PassCache
    from torchsoil.diagnosis.stats import level_z

    pair, s, base = deposit_drive
    fit = L.learn(pair, s.estimator, s.sim, base, DriveSignals.from_pair(pair), s.diagnosis)
    # each fold run ahead as a pass pool's task, then read back: the same fit
    cache = PassCache(tmp_path, {"test": "folds ahead"})
    for stage in ("choice", "model"):
        for f in (0, 1):
            L.fold_task(pair, s.estimator, s.sim, base, s.diagnosis, f, cache, stage)
    hits = cache.hits
    ahead = L.learn(pair, s.estimator, s.sim, base, DriveSignals.from_pair(pair), s.diagnosis, cache)
    assert cache.hits - hits == 4                        # two folds' choices and models read back
    assert [c.term for c in ahead.folds] == [c.term for c in fit.folds] and ahead.held_z == fit.held_z
    for a, b in zip(ahead.folds, fit.folds, strict=True):
        assert torch.equal(a.model.w[a.term], b.model.w[b.term])
    assert [c.term for c in fit.folds] == [L.Term("chi", "speed")] * 2 and fit.terms == [L.Term("chi", "speed")]
    # a factor per window's visit: the held-out test alone (phases.learned_check)
    assert fit.held_z > level_z(s.diagnosis.alpha_accept, 2) and fit.improvement > 0
    out = L.describe(fit, 1.95)["terms"][0]
    assert out["direction"] == "+" and out["catalogue_match"] is None
    # the world's factor from the 5 % to the 95 % speed of the knots' span, against the curve's
    v_lo, v_hi = (np.interp(q, [0, 1], [out["knots"][0], out["knots"][-1]]) for q in (0.05, 0.95))
    world = (1 + 0.8 * (v_hi - 1)) / (1 + 0.8 * (v_lo - 1))
    assert 0.6 * world < out["factor"] < 1.5 * world


def test_the_same_drive_without_the_law_learns_nothing():
    from torchsoil.diagnosis.fit import run_pass
    from torchsoil.diagnosis.stats import level_z
    from torchsoil.diagnosis.study_cases import scenario
    from torchsoil.io.terrain_pair import TerrainPair
    from torchsoil.settings import Settings
    from torchsoil.synth.scenario import make_terrain_pair

    sc = scenario("speed_deposit")
    sc["soil"]["base"]["chi"] = 0.5
    sc["effects"] = {}
    pair = TerrainPair.from_mapping(make_terrain_pair(sc, seed=1))
    s = Settings()
    base = run_pass(pair, s.estimator, s.sim, offsets=s.diagnosis.offsets)
    fit = L.learn(pair, s.estimator, s.sim, base, DriveSignals.from_pair(pair), s.diagnosis)
    assert not (fit.terms and fit.held_z > level_z(s.diagnosis.alpha_accept, 2))


def test_the_verdict_names_the_learned_law_where_the_catalogue_names_none_or_predicts_less():
    from torchsoil.diagnosis.phases import Verdict, with_learned

    before = {"residual": 3e-3, "prediction": 4e-3}
    term = {"parameter": "chi", "covariate": "speed", "direction": "+", "factor": 1.9, "from": 0.5, "to": 1.5,
            "catalogue_match": None}
    described = {"accepted": True, "terms": [term], "spans": [[2.0, 4.0]],
                 "after": {"residual": 2.9e-3, "prediction": 3.5e-3}}
    fit = SimpleNamespace(accepted=True, improvement=2e-4)
    unexplained = Verdict("unexplained", "berm", [[1.0, 2.0]], None, None, None, before, before, {})
    told = with_learned(unexplained, fit, dict(described))
    assert (told.verdict, told.named, told.covariate, told.cross) == ("missing_physics", "learned", "speed", "berm")
    assert told.params == {"chi_factor": 1.9, "speed_from": 0.5, "speed_to": 1.5}
    assert told.after["prediction"] == 3.5e-3 and told.spans == [[2.0, 4.0]]
    adequate = Verdict("adequate", "mixed", [], None, None, None, before, before, {})
    assert with_learned(adequate, fit, dict(described)).cross == "berm"       # where chi shows
    # a catalogue term named: the learned one only where it gains more on held-out ground
    speed = SimpleNamespace(improvement=1e-4)
    named = Verdict("missing_physics", "rut_floor", [], "speed", "speed_dependent_sinkage", speed, before, before,
                    {"k_speed": 0.5})
    assert with_learned(named, fit, dict(described)).named == "learned"
    speed.improvement = 3e-4
    assert with_learned(named, fit, dict(described)).named == "speed_dependent_sinkage"
    speed.improvement = 1e-4
    same = dict(described, terms=[{**term, "parameter": "d", "catalogue_match": "speed_dependent_sinkage"}])
    assert with_learned(named, fit, same).named == "speed_dependent_sinkage"   # the catalogue's law itself
    # found on the ground driven again only (no held-out fit): named only where nothing else is
    visits_only = SimpleNamespace(accepted=False, improvement=0.0)
    assert with_learned(named, visits_only, dict(described)).named == "speed_dependent_sinkage"
    assert with_learned(unexplained, visits_only, dict(described)).named == "learned"
    assert with_learned(unexplained, fit, {**described, "accepted": False}) is unexplained


@pytest.mark.long
def test_the_diagnosis_names_the_learned_deposit_law_and_writes_its_curve(deposit_drive, tmp_path):
    import json

    from torchsoil.diagnosis import DiagnosisConfig, diagnose
    from torchsoil.diagnosis.report import validate_summary, write_all

    pair, s, _ = deposit_drive
    diag = diagnose(pair, DiagnosisConfig(n_fit=1, sections=(), dig_orders=(), refine_steps=1), s.estimator, s.sim)
    summary = validate_summary(diag.summary)
    assert (summary["verdict"], summary["missing_physics"]) == ("missing_physics", "learned")
    assert summary["where"]["covariate"] == "speed" and summary["extension_parameters"]["chi_factor"] > 1
    assert "deposit share rises" in summary["explanation"]
    write_all(diag, pair, tmp_path, "deposit", tb=False)
    out = json.loads((tmp_path / "learned.json").read_text())
    assert out["named"] and out["terms"][0]["parameter"] == "chi" and (tmp_path / "learned.png").stat().st_size > 0
    assert "## Learned modifier" in (tmp_path / "report.md").read_text()
