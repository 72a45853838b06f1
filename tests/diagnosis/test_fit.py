"""Coefficient search and the acceptance rule."""

import math

import numpy as np
import pytest
from scipy import stats

from torchsoil.diagnosis.catalogue import CATALOGUE
from torchsoil.diagnosis.fit import CandidateFit, accept, refine
from torchsoil.diagnosis.stats import by_fold, fold_choice, folds, term_test


def test_refine_finds_the_vertex_of_a_parabola():
    ks = [-1.0, 0.0, 0.5, 2.0]
    cost = [(k - 0.7) ** 2 + 3 for k in ks]
    assert abs(refine(ks, cost, (-5, 5)) - 0.7) < 0.35
    ks3 = [0.0, 0.5, 1.0]
    assert abs(refine(ks3, [(k - 0.7) ** 2 for k in ks3], (-5, 5)) - 0.7) < 1e-9


def test_refine_steps_beyond_an_edge_minimum_within_bounds():
    assert refine([0.0, 1.0, 2.0], [3.0, 2.0, 1.0], (-5, 5)) == 3.0
    assert refine([0.0, 1.0, 2.0], [3.0, 2.0, 1.0], (-5, 2.5)) is None


def test_folds_alternate_blocks():
    assert folds(10, 3).tolist() == [0, 0, 0, 1, 1, 1, 0, 0, 0, 1]


def fit_with(z, k_fold, gain=1e-4, own_z=0.0):
    n = np.zeros(3)
    return CandidateFit(CATALOGUE["slip_sinkage"], 1.0, k_fold, n, n, gain, 1.0, z, {}, own_z=own_z)


def test_accept_needs_significance_material_gain_and_agreeing_folds():
    assert accept(fit_with(3.0, (2.0, 4.0)), 2.1)
    assert not accept(fit_with(1.5, (2.0, 4.0)), 2.1)        # within the noise
    assert not accept(fit_with(3.0, (0.0, 4.0)), 2.1)        # one fold preferred the base model
    assert not accept(fit_with(3.0, (-2.0, 4.0)), 2.1)       # folds disagree on the sign
    # steady but immaterial: 0.001 mm gained where 0.006 mm is asked
    assert not accept(fit_with(3.0, (2.0, 4.0), gain=1e-6), 2.1, material=6e-6)
    assert accept(fit_with(3.0, (2.0, 4.0), gain=1e-5), 2.1, material=6e-6)
    # held-out ground predicted better, own windows fitted worse: the term stands in for
    # something else that changes along the drive (checked only when asked)
    assert not accept(fit_with(3.0, (2.0, 4.0), own_z=-1.4), 2.1, own_z=0.0)
    assert accept(fit_with(3.0, (2.0, 4.0), own_z=0.3), 2.1, own_z=0.0)
    assert accept(fit_with(3.0, (2.0, 4.0), own_z=-1.4), 2.1)
    # a change to the physics too small to be that cause: checked at both folds' coefficients
    small = fit_with(3.0, (2.0, 4.0))
    small.effects = {0.0: 0.0, 2.0: 0.03, 4.0: 0.2}
    assert small.effect == 0.03
    assert not accept(small, 2.1, effect=0.05) and accept(small, 2.1, effect=0.02)
    assert accept(fit_with(3.0, (2.0, 4.0)), 2.1, effect=0.05)        # no effect sizes: not checked


def test_shape_terms_are_tested_where_their_zones_show_a_material_residual():
    """Cohesive walls under a flat or rounded tyre leave their mark on the berms: the slumped
    soil that a steeper wall keeps in place is missing beside the rut. A shape term is fitted
    when any of floor, wall or berm shows a residual beyond z_locate and materiality, and the
    held-out test (not this gate) decides."""
    from torchsoil.diagnosis.phases import evidence_for
    from torchsoil.settings import DiagnosisConfig

    def zones(berm_z, berm_mean):
        quiet = {"z": 0.5, "mean": 1e-5}
        return {"rut_floor": quiet, "rut_wall": quiet, "outside": quiet, "berm": {"z": berm_z, "mean": berm_mean}}

    rows = [{"d1": 0.03, "d2": 0.03}] * 8
    args = (2, DiagnosisConfig(), np.zeros(8), 2)
    walls = CATALOGUE["cohesive_walls"]
    berm = evidence_for(walls, rows, {}, zones(-6.0, -4e-4), *args, z_locate=3.1, material=3e-4)
    assert berm["testable"] and berm["p"] == pytest.approx(6 * stats.norm.sf(6.0))
    assert not evidence_for(walls, rows, {}, zones(2.0, -4e-4), *args, z_locate=3.1, material=3e-4)["testable"]
    assert not evidence_for(walls, rows, {}, zones(-6.0, -1e-4), *args, z_locate=3.1, material=3e-4)["testable"]


def test_fallback_levels_spend_alpha_once_and_carry_after_acceptance_or_nothing_to_test():
    from types import SimpleNamespace

    from torchsoil.diagnosis.phases import accept_in_order
    from torchsoil.diagnosis.stats import level_z, thresholds

    levels = thresholds([1e-5, 1e-3, 0.01, 0.2], 0.05, 0.6)
    assert sum(levels) == pytest.approx(0.05) and levels[0] == pytest.approx(0.03)
    assert thresholds([0.3], 0.05, 0.6) == [0.05]
    tied = thresholds([1e-30, 1e-30, 0.01], 0.05, 0.6)       # two shape terms, same profile evidence
    assert tied == pytest.approx([0.015, 0.015, 0.02])

    def fit(z):
        return SimpleNamespace(z=z, k_fold=(-0.3, -0.3), improvement=1e-4, own_z=0.0, accepted=None)

    # the leading candidate needs less than a Bonferroni split would ask (z 1.87 vs 2.24) ...
    fits = [fit(2.0), fit(2.4), fit(0.0)]
    p = [1e-4, 1e-3, 1e-2]
    used = accept_in_order(fits, p, 0.05, 0.6)
    assert [f.accepted for f in fits] == [True, True, False]
    assert used[0] == pytest.approx(level_z(0.03))
    # ... a later one more, unless the ones before it were accepted and passed their level on
    assert used[1] == pytest.approx(level_z(0.03 + 0.01))
    fits = [fit(1.0), fit(2.3), fit(0.0)]
    used = accept_in_order(fits, p, 0.05, 0.6)
    assert [f.accepted for f in fits] == [False, False, False]
    assert used[1] == pytest.approx(level_z(0.01))
    # a two-signed coefficient is held to its own level: 2.0 is enough with one sign, not two
    fits = [fit(2.0), fit(0.0), fit(0.0)]
    used = accept_in_order(fits, p, 0.05, 0.6, signs=[2, 1, 1])
    assert not fits[0].accepted and used[0] == pytest.approx(level_z(0.03, 2)) and used[0] > 2.0
    # a candidate left at 0 on both folds is the base model: it has nothing to test and passes
    # its level on; one at 0 on a single fold was tested (and not accepted), and does not
    zero = fit(1.0)
    zero.k_fold = (0.0, 0.0)
    half = fit(1.0)
    half.k_fold = (0.0, -0.3)
    fits = [zero, fit(1.8), fit(0.0)]
    used = accept_in_order(fits, p, 0.05, 0.6)
    assert [f.accepted for f in fits] == [False, True, False]
    assert used[1] == pytest.approx(level_z(0.03 + 0.01))
    fits = [half, fit(1.8), fit(0.0)]
    used = accept_in_order(fits, p, 0.05, 0.6)
    assert [f.accepted for f in fits] == [False, False, False]
    assert used[1] == pytest.approx(level_z(0.01))


def test_of_two_accepted_terms_the_larger_held_out_gain_is_named_not_the_steadier():
    from types import SimpleNamespace

    from torchsoil.diagnosis.phases import by_gain

    # a wider footprint (gain 0.67 mm at z 3.4) and walls (0.45 mm at z 3.7) both accepted on
    # one rut: the footprint accounts for more of the mismatch; a refused term is never listed
    walls = SimpleNamespace(z=3.7, improvement=0.45e-3, accepted=True)
    width = SimpleNamespace(z=3.4, improvement=0.67e-3, accepted=True)
    speed = SimpleNamespace(z=1.0, improvement=0.9e-3, accepted=False)
    assert by_gain([walls, speed, width]) == [width, walls]
    assert by_gain([speed]) == []


def test_once_a_shape_term_passes_the_other_shape_terms_are_told_apart_by_their_gain():
    from types import SimpleNamespace

    from torchsoil.diagnosis import catalogue
    from torchsoil.diagnosis.phases import by_gain

    def term(ext_id, z, gain, k_fold, accepted, own_z=1.7, effect=0.3):
        return SimpleNamespace(ext=catalogue.get(ext_id), z=z, improvement=gain, k_fold=k_fold, own_z=own_z,
                               effect=effect, accepted=accepted)

    # walls pass (z 2.5, 0.18 mm); a wider footprint falls short of its level (z 2.0) but gains
    # 0.46 mm with one sign on both folds: the rut's shape needs a term, and it is the footprint
    walls = term("cohesive_walls", 2.5, 0.18e-3, (1.4, 1.0), True)
    width = term("footprint_width", 2.0, 0.46e-3, (0.3, 0.3), False)
    assert by_gain([walls, width], effect=0.05) == [width, walls]
    # a footprint that fails any other condition stays out: folds of two signs, no gain, a
    # negligible effect, its own windows fitted worse
    for bad in (term("footprint_width", 2.0, 0.46e-3, (0.3, -0.2), False),
                term("footprint_width", -0.5, 0.46e-3, (0.3, 0.3), False),
                term("footprint_width", 2.0, 0.46e-3, (0.3, 0.3), False, effect=0.01),
                term("footprint_width", 2.0, 0.46e-3, (0.3, 0.3), False, own_z=-0.5)):
        assert by_gain([walls, bad], effect=0.05, own_z=0.0) == [walls]
    # no shape term passed: nothing joins, whatever its gain (a covariate term's pass is no
    # evidence about the rut's shape)
    slip = term("slip_sinkage", 2.4, 0.1e-3, (8.0, 8.0), True)
    assert by_gain([slip, width], effect=0.05) == [slip]
    assert by_gain([term("cohesive_walls", 1.0, 0.18e-3, (1.4, 1.0), False), width], effect=0.05) == []


def test_level_z_by_hand():
    # two signs: Q (1 - Q) = 0.025, Q = (1 - sqrt(0.9)) / 2 = 0.025658, z = 1.9488; one sign:
    # Q = (1 - sqrt(0.8)) / 2 = 0.052786, z = 1.6184 (normal table)
    from torchsoil.diagnosis.stats import level_z

    assert level_z(0.05, 2) == pytest.approx(1.9488, abs=2e-4)
    assert level_z(0.05, 1) == pytest.approx(1.6184, abs=2e-4)
    assert level_z(1e-6, 2) > level_z(1e-6, 1) > 4.7


@pytest.mark.parametrize("signs, trials", [(2, (-1.0, 1.0)), (1, (0.5, 1.0))])
def test_the_fold_procedure_holds_its_level_on_noise(signs, trials):
    """Drives with no effect, by simulation of the procedure itself (not of the formula): a
    term whose per-window gain is k times noise, its coefficient chosen per fold on the other
    fold's held-out costs (`fold_choice`), scored by the paired test (`term_test`) and
    accepted (`accept`) at `level_z`: the false alarms stay at the level; at the normal
    quantile a two-signed term's nearly double."""
    from torchsoil.diagnosis.catalogue import get
    from torchsoil.diagnosis.stats import level_z

    rng = np.random.default_rng(7)
    lab = folds(48, 6)
    alpha, n, hits, nominal = 0.05, 3000, 0, 0
    for _ in range(n):
        base = 3e-3 + 1e-4 * rng.standard_normal(48)
        noise = 1e-4 * rng.standard_normal(48)
        held = {0.0: base, **{k: base - k * noise for k in trials}}
        k_fold = fold_choice(held, lab)
        gain, se, _, _, z = term_test(base, by_fold(held, k_fold, lab))
        fit = CandidateFit(get("slip_sinkage"), 1.0, k_fold, base, base, gain, se, z, {})
        hits += accept(fit, level_z(alpha, signs))
        nominal += accept(fit, stats.norm.isf(alpha))
    sd = np.sqrt(alpha * (1 - alpha) / n)
    assert hits / n < alpha + 3 * sd
    if signs == 2:
        assert nominal / n > alpha + 5 * sd


def _straight_pair(section):
    from torchsoil.io.terrain_pair import TerrainPair
    from torchsoil.synth.scenario import make_terrain_pair

    scn = {"trajectory": {"segments": [{"straight": 5.0, "speed": 1.0}]},
           "soil": {"base": {"d": 0.035, "chi": 0.2, "beta_deg": 30.0}},
           "tyre": {"sections": [section]}, "world": {"chunk": 0.1}}
    return TerrainPair.from_mapping(make_terrain_pair(scn, seed=3))


@pytest.mark.parametrize(("section", "want"), [("flat", (0.85, 1.0)), ("taper", (0.0, 1.0)),
                                             ("rounded", (0.0, 0.25))])
def test_tyre_section_is_fitted_as_a_nuisance(section, want):
    # the world's flat tread (flat to |q| = 0.9) and elliptic section sqrt(1 - q^2)
    # (synth.world.section_profile) against a robot described with a cosine taper (f = 0,
    # e = 1); a taper world keeps the robot's section
    from torchsoil.diagnosis.fit import fit_section
    from torchsoil.settings import EstimatorConfig, SimConfig

    pair = _straight_pair(section)
    assert (pair.wheel_flat_fraction, pair.wheel_section_exponent) == (0.0, 1.0)
    tried = ((0.0, 1.0), (0.4, 1.0), (0.85, 1.0), (0.0, 0.25))
    best, costs, shared, _ = fit_section(pair, EstimatorConfig(), SimConfig(), tried)
    assert best == want and set(costs) == set(tried)
    assert costs[want] < min(c for k, c in costs.items() if k != want)
    assert set(shared) == {"index", "nuisance", "view", "store", "surfaces"}
    assert pair.wheel_flat_fraction == 0.0                                   # not changed in place


def test_paired_z_by_hand():
    """base 3 mm on four windows, other 0.1, 0, 0.2, 0.1 mm lower: mean 0.1, sd
    sqrt(0.02 / 3) = 0.08165, z = 0.1 / (0.08165 / 2) = 2.449; fewer than 3 windows (or
    scores of different lengths) leave it to the means."""
    from torchsoil.diagnosis.stats import paired_z

    base = np.array([3.0, 3.0, 3.0, 3.0])
    assert paired_z(base, base - [0.1, 0.0, 0.2, 0.1]) == pytest.approx(2.449, abs=1e-3)
    assert paired_z(base, base + [0.1, 0.0, 0.2, 0.1]) == pytest.approx(-2.449, abs=1e-3)
    assert paired_z(base[:2], base[:2] - 0.1) == math.inf
    assert paired_z(np.array([3.0]), base + 0.1) == -math.inf


def test_the_robots_own_section_stays_unless_another_fits_clearly_better(monkeypatch):
    """Window residuals [mm] given by hand: a section lower on average but only by the
XX
    taken."""
    from torchsoil.diagnosis import fit as fit_mod

    own, noisy, clear = (0.0, 1.0), (0.3, 0.5), (0.85, 1.0)
    res = {own: [3.0, 3.1, 2.9, 3.0, 3.05], noisy: [2.9, 3.2, 2.8, 3.1, 2.98],
           clear: [2.8, 2.95, 2.7, 2.78, 2.86]}

    def fake_cost(pair, est, sim, sec, *args, **kwargs):
        r = np.array(res[sec])
        return float(r.mean()), {"index": None}, r

    monkeypatch.setattr(fit_mod, "section_cost", fake_cost)
    pair = _straight_pair("taper")
    assert fit_mod.fit_section(pair, None, None, [noisy])[0] == own
    assert fit_mod.fit_section(pair, None, None, [noisy, clear])[0] == clear


def test_the_robots_own_section_under_another_dig_order_is_kept_when_it_fits_as_well():
    """Window residuals [mm] by hand: under "robot" a crowned section fits best on average,
    standing in for the other order; under "wheel" the robot's own section fits within the
XX with the robot's section. Where the
    robot's section under "wheel" is worse on every window (z 15.5), the best pair stays."""
    from torchsoil.diagnosis.phases import plainest

    own, crowned = (0.5, 1.0), (0.0, 0.5)
    best = np.array([2.90, 3.00, 2.80, 2.95, 2.85])
    fits = {("robot", crowned): best, ("robot", own): best + 0.05,
            ("wheel", own): best + [0.1, -0.08, 0.05, -0.05, 0.02]}
    assert plainest(fits, ("robot", crowned), own) == "wheel"
    fits[("wheel", own)] = best + [0.06, 0.05, 0.07, 0.05, 0.06]
    assert plainest(fits, ("robot", crowned), own) == "robot"
    assert plainest(fits, ("robot", own), own) == "robot"


@pytest.mark.parametrize("dig", ["robot", "wheel"])
def test_dig_order_told_from_the_drive(dig):
    """Pairs made by the plain numpy reference model (tests/reference_model.py), where every
    wheel digs from the surface before the robot or the axles dig in turn: the diagnosis'
    nuisance fit picks the order the pair was made with, and under "wheel" the fitted
    sinkage is each wheel's (the truth's d), where "robot" needs about twice as much."""
    from tests.reference_model import straight_drive_pair
    from torchsoil.diagnosis.fit import run_pass
    from torchsoil.diagnosis.phases import DiagnosisConfig, fit_nuisance_model
    from torchsoil.io.terrain_pair import TerrainPair
    from torchsoil.settings import EstimatorConfig, SimConfig

    data, _ = straight_drive_pair(d=(0.02, 0.02), chi=0.5, beta_deg=35.0, length=4.0, flat=0.5, dig=dig, seed=4)
    pair = TerrainPair.from_mapping(data)
    cfg = DiagnosisConfig(sections=())
    est, sim = EstimatorConfig(), SimConfig()
    _, fitted, _, evidence, shared, _ = fit_nuisance_model(pair, cfg, est, sim)
    assert evidence["fitted"] == fitted.dig_order == dig
    assert set(evidence["residual"]) == {"robot", "wheel"}
    if dig == "wheel":
        d = np.nanmedian([r["d1"] for r in run_pass(pair, est, fitted, offsets=(), **shared).rows])
        paper = np.nanmedian([r["d1"] for r in run_pass(pair, est, sim, offsets=(), **shared).rows])
        assert d == pytest.approx(0.02, rel=0.1)
        assert paper > 1.5 * d


@pytest.mark.long
def test_a_wall_term_chooses_its_own_tyre_section():
    """Steeper walls and a rounder tyre section trade off (a flat tread's box rut relaxed at
    the soil's angle looks like a rounder tyre's rut standing). In a world with a flat tread
    and cohesive walls, the wall term's passes pick the flat tread among the sections they
    may choose from, although the base pass ran at the robot's cosine taper."""
    from torchsoil.diagnosis.catalogue import CATALOGUE
    from torchsoil.diagnosis.covariates import DriveSignals
    from torchsoil.diagnosis.fit import fit_extension, run_pass
    from torchsoil.io.terrain_pair import TerrainPair
    from torchsoil.settings import EstimatorConfig, SimConfig
    from torchsoil.synth.scenario import make_terrain_pair

    scn = {"trajectory": {"segments": [{"straight": 5.0, "speed": 1.0}]},
           "soil": {"base": {"d": 0.05, "chi": 0.2, "beta_deg": 30.0, "moisture": 0.0}},
           "effects": {"cohesive_walls": {"form": "linear", "k": 1.5}},
           "tyre": {"sections": ["flat"]}, "world": {"chunk": 0.1}}
    pair = TerrainPair.from_mapping(make_terrain_pair(scn, seed=3))
    est, sim = EstimatorConfig(), SimConfig()
    base = run_pass(pair, est, sim, profiles=True)
    drive = DriveSignals.from_poses(pair.poses, pair.robot)
    tried = ((0.0, 1.0), (0.0, 0.25), (0.85, 1.0))
    fit = fit_extension(pair, est, sim, CATALOGUE["cohesive_walls"], drive, base, refine_steps=0, sections=tried)
    assert fit.sections[0.0] == (0.0, 1.0)
    assert len(fit.sections) > 2 and all(sec == (0.85, 1.0) for k, sec in fit.sections.items() if k > 0)


def test_trial_coefficients_go_outward_from_zero_on_each_side():
    from torchsoil.diagnosis.fit import trial_sides

    assert trial_sides(CATALOGUE["footprint_width"]) == [[0.15, 0.3], [-0.2]]
    assert trial_sides(CATALOGUE["cohesive_walls"]) == [[0.5, 1.5, 4.0]]
    assert trial_sides(CATALOGUE["multi_pass_hardening"]) == [[-0.3, -0.6]]


def fake_fit(monkeypatch, ext_id: str, best: float, curvature: float, refine_steps: int, found=None):
    """fit_extension over fake passes whose held-out cost is a parabola in k about `best`
    (the base pass's at k 0): returns (the fit, {k run: the section it was given}, in run
    order). found(k, section): the section a pass reports (default (0, 1))."""
    from torchsoil.diagnosis import fit as fit_mod

    n, given = 12, {}
    cost = lambda k: np.full(n, 1e-3 + (k - best) ** 2 * curvature)      # noqa: E731

    def fake_pass(pair, est, sim, ext, k, *a, section=None, **kw):
        given[round(k, 5)] = section
        c = cost(k)
        return fit_mod.Pass(k, [], c, c, c), (0.0, 1.0) if found is None else found(k, section)

    monkeypatch.setattr(fit_mod, "candidate_pass", fake_pass)
    monkeypatch.setattr(fit_mod, "effect_size", lambda ext, k, *a: abs(k))     # no drive signals here
    base = fit_mod.Pass(0.0, [], cost(0.0), cost(0.0), cost(0.0))
    pair = type("P", (), {"robot": None, "wheel_flat_fraction": 0.0, "wheel_section_exponent": 1.0})()
    est = type("E", (), {"stride": 0.4})()
    return fit_mod.fit_extension(pair, est, None, CATALOGUE[ext_id], None, base, refine_steps=refine_steps), given


@pytest.mark.parametrize("best, runs, k", [
    (0.0, [0.15, -0.2], 0.0),                    # both sides rise at their first trial
    (0.2, [0.15, 0.3, -0.2, 0.2], 0.2),          # rises at 0.3: the parabola's vertex
    (0.4, [0.15, 0.3, 0.45, -0.2], 0.45),        # falls to the last trial: on, twice it clipped to the bound
    (-0.25, [0.15, -0.2, -0.4, -0.25], -0.25)])  # the other side: a step beyond, then the vertex
def test_a_side_stops_at_the_first_rise_of_the_held_out_cost(monkeypatch, best, runs, k):
    """Fake passes whose held-out cost is a parabola in k about `best`: each side runs its
    trials until the cost rises, then the refinements go to the vertex (cost in the base pass: k 0)."""
    f, given = fake_fit(monkeypatch, "footprint_width", best, 1e-3, 2)
    assert list(given) == runs
    assert f.k == pytest.approx(k)


@pytest.mark.parametrize("best, runs", [
    (19.0, [4.0, 8.0, 16.0, 20.0]),              # still falling at 8: on to 16, then the bound
    (10.0, [4.0, 8.0, 16.0]),                    # rises at 16: the side stops there
    (6.0, [4.0, 8.0])])                          # rises at the last trial: nothing beyond it
def test_a_side_still_falling_at_its_last_trial_goes_on_doubling_to_the_bound(monkeypatch, best, runs):
    """Slip's trials end at 8 in a bound of 20: a convex law on a drive that never comes near
    no traction needs a larger linear coefficient, which the side reaches by doubling."""
    from torchsoil.diagnosis.fit import most_trials

    _, given = fake_fit(monkeypatch, "slip_sinkage", best, 1e-5, 0)
    ran = list(given)
    assert ran == runs
    assert len(ran) <= most_trials(CATALOGUE["slip_sinkage"]) == 4        # 4, 8, 16, 20


@pytest.mark.parametrize("best, refined, nearest", [(0.2, 0.2, 0.15), (-0.25, -0.25, -0.2), (0.4, 0.45, None)])
def test_a_refinement_keeps_the_section_of_the_nearest_coefficient_tried(monkeypatch, best, refined, nearest):
    """Trial passes search their own tyre section (none given); a refinement between two tried
    coefficients is run under the section the nearer found (each fake search finds f = |k|),
    a step beyond them (0.45 past 0.3) searches its own."""
    from torchsoil.diagnosis import fit as fit_mod

    f, given = fake_fit(monkeypatch, "footprint_width", best, 1e-3, 2,
                        found=lambda k, section: (abs(k), 1.0) if section is None else section)
    trials = {k for side in fit_mod.trial_sides(CATALOGUE["footprint_width"]) for k in side}
    assert all(given[k] is None for k in given if k in trials)
    kept = f.sections[min(f.sections, key=lambda q: abs(q - refined))]
    if nearest is None:
        assert given[refined] is None and kept == pytest.approx((abs(refined), 1.0))
    else:
        assert given[refined] == (abs(nearest), 1.0) and kept == (abs(nearest), 1.0)


@pytest.fixture(scope="module")
def two_angle_drives():
    """Base passes over the same 8 m drive in two-angle soil (loose 22 deg, intact 31 deg; the
    study's `walls saturating`) and in one-angle soil, each with its drive signals."""
    from torchsoil.diagnosis.covariates import DriveSignals
    from torchsoil.diagnosis.fit import run_pass
    from torchsoil.diagnosis.study_cases import scenario
    from torchsoil.io.terrain_pair import TerrainPair
    from torchsoil.settings import EstimatorConfig, SimConfig
    from torchsoil.synth.scenario import make_terrain_pair

    out = {}
    for name in ("two-angle", "one-angle"):
        scn = scenario("cohesive_walls")
        scn["trajectory"] = {"segments": [{"straight": 8.0, "speed": 1.0}]}
        if name == "one-angle":
            scn.pop("effects")
        pair = TerrainPair.from_mapping(make_terrain_pair(scn, seed=1))
        est, sim = EstimatorConfig(), SimConfig()
        out[name] = (pair, est, sim, DriveSignals.from_poses(pair.poses, pair.robot), run_pass(pair, est, sim))
    return out


def test_walls_the_windows_took_up_show_in_their_own_fit(two_angle_drives):
    """Two-angle soil fitted with one angle leaves nothing across the rut to locate, but every
    window fits its own ground better with the wall term; one-angle soil does not."""
    from torchsoil.diagnosis.fit import own_fit_screen

    walls = CATALOGUE["cohesive_walls"]
    got = {name: own_fit_screen(pair, est, sim, [walls], drive, base)["cohesive_walls"]
           for name, (pair, est, sim, drive, base) in two_angle_drives.items()}
    assert got["two-angle"]["p"] < 0.01 < 0.2 < got["one-angle"]["p"]
    assert "k_wall 0.5" in got["two-angle"]["statistic"]


def _same(a, b) -> bool:
    """Two prepared windows (or parts of them) hold the same values: tensors, arrays, numbers."""
    import torch

    if isinstance(a, torch.Tensor):
        return a.dtype == b.dtype and a.shape == b.shape and bool(torch.equal(a, b))
    if isinstance(a, tuple):
        return type(a) is type(b) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, np.ndarray):
        return np.array_equal(a, b)
    return a == b


def test_a_window_prepared_under_one_section_is_the_one_prepared_under_another_once_retapered():
    """fit.AnySection's premise: a prepared window depends on the tyre section only through its
    wheel geometry's taper and the nominal footprint made from it, and not on the dig order."""
    from torchsoil.diagnosis.fit import AnySection, with_section, with_taper
    from torchsoil.estimate.estimator import Estimator
    from torchsoil.settings import EstimatorConfig, SimConfig

    pair = _straight_pair("flat")
    est, sim = EstimatorConfig(), SimConfig()
    first = Estimator(with_section(pair, (0.0, 1.0)), est, sim)
    shared = {"index": first.index, "nuisance": first.nuisance, "view": first.view, "surfaces": first.surfaces}
    other = Estimator(with_section(pair, (0.5, 0.25)), est, sim.replace(dig_order="wheel"), **shared)
    for k in (2, 6):
        a, b = first.data(k), other.data(k)
        assert not _same(a.geom.nominal, b.geom.nominal)
        assert _same(with_taper(a, 0.5, 0.25), b) and _same(with_taper(b, 0.0, 1.0), a)
    store = AnySection(first.index, first.surfaces)
    via = Estimator(with_section(pair, (0.5, 0.25)), est, sim, **shared, store=store)
    first.store = store
    assert _same(first._prepare(first.windows[3]), first.data(3))        # prepared here, kept
    assert _same(via._prepare(via.windows[3]), other.data(3)) and len(store.store) == 1   # read back, retapered


@pytest.mark.parametrize("blur", [0.0, 1.0])
def test_the_rasters_blur_is_fitted_as_a_nuisance(blur):
    """A drive whose H_b change was measured through scipy's Gaussian of 1 cell is fitted through
    the blur; a sharp one keeps the estimator's own (none)."""
    from tests.synthetic_pair import sim_pair
    from torchsoil.diagnosis.fit import fit_blur
    from torchsoil.settings import EstimatorConfig, SimConfig

    pair, _ = sim_pair(length=4.4, noise=0.001, blur=blur)
    est, evidence, shared = fit_blur(pair, EstimatorConfig(), SimConfig(), (1.0, 2.0))
    assert est.after_blur == blur and evidence["fitted"] == blur and evidence["declared"] == 0.0
    costs = dict(evidence["residual"])
    assert costs[blur] < min(c for b, c in costs.items() if b != blur)
    assert {"index", "nuisance", "view", "surfaces"} <= set(shared)
    assert fit_blur(pair, est, SimConfig(), ())[1] is None                    # none tried: none fitted
