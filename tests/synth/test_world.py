"""The world soil model: base physics, and each effect changing the truth in its own way."""

import functools
import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from torchsoil.synth import effects as fx
from torchsoil.synth.scenario import build_truth

# beta = 89 deg: relaxation leaves the ruts alone, so rut depths follow the sinkage laws
BASE_SOIL = {"base": {"d": 0.03, "chi": 0.3, "beta_deg": 89.0, "moisture": 0.0}}
SOIL_30 = {"base": {"d": 0.03, "chi": 0.3, "beta_deg": 30.0, "moisture": 0.0}}
LOOP = [{"straight": 2.5, "speed": 1.0}, {"arc": 1.4, "angle_deg": 180, "speed": 1.0},
        {"straight": 2.5, "speed": 1.0}, {"arc": 1.4, "angle_deg": 180, "speed": 1.0},
        {"straight": 3.0, "speed": 1.0}]


def scenario(segments, effects=None, soil=None, relief=None, accel_limit=0.5):
    """A clean scenario: no micro-topography, small field, no landmarks."""
    return {"name": "test", "trajectory": {"segments": segments, "accel_limit": accel_limit},
            "terrain": {"relief": relief or {"amplitude": 0.0}, "micro": {"rms": 0.0},
                        "margin": 1.0},
            "soil": soil or BASE_SOIL, "effects": effects or {},
            "landmarks": {"poles": 0, "trunks": 0, "shed": False, "fence": False}}


@functools.lru_cache(maxsize=16)
def _world(key: str, seed: int):
    return build_truth(json.loads(key), seed).world


def world(scn, seed=0):
    """The world of a scenario dict (cached: generation is deterministic)."""
    return _world(json.dumps(scn, sort_keys=True), seed)


def rut_depth(w, xs, y, half=0.03):
    """Rut depth [m]: deepest (before - after) across the rut near world y, averaged over
    x in xs = (x0, x1)."""
    gx, gy = w.grid.centers()
    i = (gx >= xs[0]) & (gx <= xs[1])
    j = np.abs(gy - y) <= half
    return float((w.h_before - w.h_after)[np.ix_(i, j)].max(1).mean())


STRAIGHT = [{"straight": 6.0, "speed": 1.0}]


def test_base_rut_depth_matches_soil_d():
    """No effects, flat ground: the rut floor sits d below the surface (the taper is 1 at the
    wheel centre) in the middle of the drive."""
    w = world(scenario(STRAIGHT))
    for y in (0.5, -0.5):
        assert rut_depth(w, (2.0, 5.0), y) == pytest.approx(0.03, abs=0.0015)
    # nothing far from the wheel paths changes
    gx, gy = w.grid.centers()
    far = np.abs(np.abs(gy) - 0.5) > 0.45
    assert np.abs(w.h_after - w.h_before)[:, far].max() < 1e-9


@pytest.mark.parametrize("chunk", [0.1, 0.4])
def test_base_conserves_volume_and_deposits_share_chi(chunk):
    """chi = 1: sinkage, deposition and relaxation together conserve soil volume; without
    relaxation (beta = 89 deg) the deposited volume is chi x the removed volume, whatever the
    chunk length (none of it is dug again by a later chunk)."""
    w = world(scenario(STRAIGHT, soil={"base": {"d": 0.03, "chi": 1.0, "beta_deg": 30.0}}))
    dh = w.h_after - w.h_before
    assert abs(dh.sum()) < 1e-9 * np.abs(dh).sum() + 1e-9
    assert (dh < -0.01).sum() > 500
    for chi in (0.0, 0.5):
        scn = scenario(STRAIGHT, soil={"base": {"d": 0.03, "chi": chi, "beta_deg": 89.0}})
        scn["world"] = {"chunk": chunk}
        dh = world(scn).h_after - world(scn).h_before
        removed, added = -dh[dh < 0].sum(), dh[dh > 0].sum()
        assert added == pytest.approx(chi * removed, rel=1e-6, abs=1e-9)


def test_disabled_effects_leave_the_base_model():
    base = world(scenario(STRAIGHT))
    off = {name: {"enabled": False} for name in fx.EFFECTS}
    w = world(scenario(STRAIGHT, effects=off))
    np.testing.assert_array_equal(w.h_after, base.h_after)


TURN = [{"straight": 1.0, "speed": 1.0}, {"arc": 2.0, "angle_deg": 90, "speed": 1.0},
        {"straight": 1.0, "speed": 1.0}]


@pytest.mark.parametrize("chunk", [0.1, 0.4])
@pytest.mark.parametrize("segments", [STRAIGHT, TURN], ids=["straight", "turn"])
def test_world_matches_the_project_simulator_on_uniform_soil(segments, chunk):
    """Effects off, uniform soil: the chunked world agrees with torchsoil.sim over the whole
    path to a fraction of a millimetre where the ground changed, whatever the chunk length
    (each chunk's digs are deposited beside the poses that dug them once the visit is over,
    as the simulator deposits after digging the whole path; on a turn the rear wheels cross
    the front ones' bands)."""
    import torch

    from torchsoil.sim import ParamSpec, simulate_path

    scn = scenario(segments, soil=SOIL_30)
    scn["world"] = {"chunk": chunk}
    truth = build_truth(scn)
    w = truth.world
    theta = ParamSpec.base(2).make(1, d1=0.03, d2=0.03, chi=0.3, beta=math.radians(30))
    sim = simulate_path(torch.as_tensor(w.h_before)[None], w.grid, truth.traj.poses, truth.robot, theta)
    changed = np.abs(w.h_after - w.h_before) > 1e-4
    diff = np.abs(sim.h[0].detach().numpy() - w.h_after)
    assert changed.sum() > 1000
    assert diff[changed].mean() < 3e-4
    assert np.abs(w.h_after - w.h_before)[changed].mean() > 20 * diff[changed].mean()


def test_cohesive_world_matches_the_project_simulator_with_two_angles():
    """cohesive_walls in the world is two-angle soil, as the simulator's Modifiers.tan_beta_intact:
    ground not moved stands to tan(beta) x factor(c0 + moisture), the deposits settle at beta."""
    import torch

    from torchsoil.sim import Modifiers, ParamSpec, simulate_path

    law = {"form": "linear", "k": 1.0, "c0": 1.5}                       # factor 2.5: 55 deg over 30
    truth = build_truth(scenario(STRAIGHT, {"cohesive_walls": law}, soil=SOIL_30))
    w = truth.world
    dh = w.h_after - w.h_before
    theta = ParamSpec.base(2).make(1, d1=0.03, d2=0.03, chi=0.3, beta=math.radians(30))
    intact = Modifiers(tan_beta_intact=torch.tensor([2.5 * math.tan(math.radians(30))], dtype=torch.float64))
    h0 = torch.as_tensor(w.h_before)[None]
    two, one = (simulate_path(h0, w.grid, truth.traj.poses, truth.robot, theta, modifiers=m).h[0].numpy()
                for m in (intact, None))
    changed = np.abs(dh) > 1e-4
    assert np.abs(two - w.h_after)[changed].mean() < 3e-4
    assert np.abs(one - w.h_after)[changed].mean() > 2 * np.abs(two - w.h_after)[changed].mean()


def test_wheels_dig_in_turn_in_the_world():
    """world.dig_order "wheel": the rear wheel digs again from the front one's rut, resting on
    it at the mean over its footprint (37 cells of r = 3.5: lateral offsets 0, +-1, +-2, +-3 in
    7, 14, 10, 6 of them; under the rounded taper s = 1, 0.81174, 0.38874, 0.04952, a mean of
    0.60943 d below the ground), so on flat ground the rut is 1.60943 d where both axles passed
    and d at the start, where only the rear one did; the chunked world agrees with
    torchsoil.sim's staged dig."""
    import torch

    from torchsoil.sim import ParamSpec, SimConfig, simulate_path

    scn = scenario(STRAIGHT)
    scn["world"] = {"dig_order": "wheel"}
    truth = build_truth(scn)
    w = truth.world
    x0 = truth.traj.poses[0, 1]
    for y in (0.5, -0.5):
        assert rut_depth(w, (2.0, 4.0), y) == pytest.approx(0.03 * 1.60943, abs=1e-5)
        assert rut_depth(w, (x0 - 0.4, x0 + 0.4), y) == pytest.approx(0.03, abs=0.0015)
    theta = ParamSpec.base(2).make(1, d1=0.03, d2=0.03, chi=0.3, beta=math.radians(89.0))
    sim = simulate_path(torch.as_tensor(w.h_before)[None], w.grid, truth.traj.poses, truth.robot, theta,
                        SimConfig(dig_order="wheel"))
    diff = np.abs(sim.h[0].detach().numpy() - w.h_after)
    assert diff.mean() < 3e-5 and np.abs(w.h_after - w.h_before).mean() > 50 * diff.mean()


def test_wheels_digging_in_turn_harden_the_rut_for_the_wheel_behind():
    """world.dig_order "wheel" with hardening (linear, k -0.5): a rear wheel in its front
    wheel's rut runs the second pass and sinks d / 2 from where it rests (0.60943 d down, as
    in the test above), so the rut is 1.10943 d where both axles passed and d at the start,
    where only the rear one did."""
    scn = scenario(STRAIGHT, effects={"multi_pass_hardening": {"form": "linear", "k": -0.5}})
    scn["world"] = {"dig_order": "wheel"}
    truth = build_truth(scn)
    x0 = truth.traj.poses[0, 1]
    for y in (0.5, -0.5):
        assert rut_depth(truth.world, (2.0, 4.0), y) == pytest.approx(0.03 * 1.10943, abs=1e-5)
        assert rut_depth(truth.world, (x0 - 0.4, x0 + 0.4), y) == pytest.approx(0.03, abs=0.0015)


@pytest.mark.parametrize("order", ["robot", "wheel"])
def test_a_revisit_is_one_more_pass_from_the_settled_surface(order):
    """The loop's last straight runs over its first one: started from the surface the first
    visit left (a terrain pair's H_f under `last_visit`), torchsoil.sim over the last
    straight's poses gives the world's final surface there, as closely as it gives the first
    visit's (the world relaxes the revisit's digs once, at the end, not as it goes). On the
    ground driven before, the wheels rest on the settled surface at the mean over their
    footprint (sim.sinkage.contact_height)."""
    import torch

    from torchsoil.estimate.windows import path_arc
    from torchsoil.sim import ParamSpec, SimConfig, simulate_path
    from torchsoil.sim.sinkage import reference_height, revisit_reference

    scn = scenario(LOOP, soil=SOIL_30)
    scn["world"] = {"dig_order": order}
    truth = build_truth(scn)
    w, poses = truth.world, truth.traj.poses
    i = int(np.searchsorted(path_arc(poses), path_arc(poses)[-1] - 3.0))   # the last straight
    before = np.take_along_axis(w.states, np.maximum(w.n_visits - 1, 0)[None], 0)[0]
    theta = ParamSpec.base(2).make(1, d1=0.03, d2=0.03, chi=0.3, beta=math.radians(30))
    r = truth.robot.wheel_width / 2
    h = torch.as_tensor(before)[None]
    ref = revisit_reference(h, reference_height(torch.as_tensor(w.h_before)[None], 0.5 * r, w.grid.dx),
                            torch.as_tensor(w.n_visits >= 2), "footprint", 0.5, r, w.grid.dx)
    sim = simulate_path(h, w.grid, poses[i:], truth.robot, theta, SimConfig(dig_order=order), h_ref=ref)
    gx, _ = w.grid.centers()
    twice = (w.n_visits == 2) & ((gx >= 0.8) & (gx <= 2.2))[:, None]
    diff = np.abs(sim.h[0].numpy() - w.h_after)[twice]
    assert twice.sum() > 1000
    assert diff.mean() < 3e-4
    assert np.abs(w.h_after - before)[twice].mean() > 5 * diff.mean()


def test_multi_pass_hardening_second_pass_sinks_less():
    plain = world(scenario(LOOP))
    hard = world(scenario(LOOP, effects={"multi_pass_hardening": {"k": -0.6}}))
    assert plain.n_visits.max() == 2
    twice = (plain.n_visits == 2) & (plain.h_after < plain.h_before - 0.01)
    np.testing.assert_allclose(hard.states[1][twice], plain.states[1][twice], atol=1e-9)
    extra_plain = (plain.states[1] - plain.states[2])[twice].mean()
    extra_hard = (hard.states[1] - hard.states[2])[twice].mean()
    assert extra_plain > 0.01
    assert extra_hard < 0.7 * extra_plain


def test_ground_the_robot_only_came_near_does_not_harden():
    """Wheels digging all at once (dig order "robot", where hardening counts the robot's
    visits): a loop whose second half-turn is 0.1 m tighter runs its last straight 0.2 m
    beside the first one, each wheel 0.2 m from the first visit's wheel, beyond its footprint
    (0.07 m) and the 0.03 m band where it deposits, but within the two wheel widths the world
    counts as a visit. The ground there was never pressed, so hardening (k -0.6) leaves those
    ruts as deep as without it; on the loop that runs over its own ruts they are shallower."""
    beside = [{"straight": 2.5, "speed": 1.0}, {"arc": 1.4, "angle_deg": 180, "speed": 1.0},
              {"straight": 2.5, "speed": 1.0}, {"arc": 1.3, "angle_deg": 180, "speed": 1.0},
              {"straight": 3.0, "speed": 1.0}]
    hard = {"multi_pass_hardening": {"form": "linear", "k": -0.6}}
    depth = {}
    for name, segs in (("beside", beside), ("over", LOOP)):
        for fx_ in ("plain", "hard"):
            scn = scenario(segs, effects=hard if fx_ == "hard" else None)
            scn["world"] = {"dig_order": "robot"}
            w = world(scn)
            y_new = 0.2 if name == "beside" else 0.0
            assert w.n_visits[np.ix_((w.grid.centers()[0] > 1.0) & (w.grid.centers()[0] < 2.0),
                                     np.abs(w.grid.centers()[1] - y_new - 0.5) < 0.02)].min() == 2
            depth[name, fx_] = np.mean([rut_depth(w, (1.0, 2.0), y_new + side, half=0.02) for side in (0.5, -0.5)])
    assert depth["beside", "hard"] == pytest.approx(depth["beside", "plain"], abs=0.0005)
    assert depth["over", "hard"] < depth["over", "plain"] - 0.005


def test_speed_dependent_sinkage_deeper_when_faster():
    segs = [{"straight": 4.0, "speed": 0.5}, {"straight": 4.0, "speed": 1.5}]
    on = world(scenario(segs, {"speed_dependent_sinkage": {"k": 0.6}}, accel_limit=2.0))
    off = world(scenario(segs, accel_limit=2.0))
    # rear wheels at x - 0.69: slow ground x in [1, 2.5], fast ground x in [6, 7]
    slow, fast = (1.0, 2.5), (6.0, 7.0)
    assert rut_depth(off, fast, 0.5) == pytest.approx(rut_depth(off, slow, 0.5), abs=1e-3)
    # law: 1 + 0.6 (v - 1): 0.7 at 0.5 m/s, 1.3 at 1.5 m/s
    assert rut_depth(on, slow, 0.5) == pytest.approx(0.03 * 0.7, abs=0.002)
    assert rut_depth(on, fast, 0.5) == pytest.approx(0.03 * 1.3, abs=0.002)


def test_slip_sinkage_deeper_while_accelerating_and_climbing():
    segs = [{"straight": 3.0, "speed": 0.5}, {"straight": 5.0, "speed": 1.5}]
    on = world(scenario(segs, {"slip_sinkage": {"k": 6.0}}, accel_limit=0.3))
    off = world(scenario(segs, accel_limit=0.3))
    accel, cruise = (3.8, 4.6), (1.0, 1.8)
    assert rut_depth(off, accel, 0.5) == pytest.approx(rut_depth(off, cruise, 0.5), abs=1e-3)
    ratio = rut_depth(on, accel, 0.5) / rut_depth(on, cruise, 0.5)
    assert ratio == pytest.approx(1 + 6.0 * 0.3 / 9.81, abs=0.05)
    climb = world(scenario(STRAIGHT, {"slip_sinkage": {"k": 6.0}},
                           relief={"amplitude": 0.0, "slope_x": 0.05}))
    assert rut_depth(climb, (2.0, 5.0), 0.5) == pytest.approx(0.03 * (1 + 6.0 * math.sin(math.atan(0.05))),
                                                             abs=0.002)


def test_lateral_load_transfer_downhill_wheels_sink_deeper():
    relief = {"amplitude": 0.0, "slope_y": 0.1}          # left side higher: right is downhill
    on = world(scenario(STRAIGHT, {"lateral_load_transfer": {"k": 1.5, "h_cg": 0.6}}, relief=relief))
    off = world(scenario(STRAIGHT, relief=relief))
    assert rut_depth(off, (2, 5), -0.5) == pytest.approx(rut_depth(off, (2, 5), 0.5), abs=1e-3)
    shift = 2 * 0.6 / 1.0 * math.sin(math.atan(0.1))
    assert rut_depth(on, (2, 5), -0.5) == pytest.approx(0.03 * (1 + 1.5 * shift), abs=0.002)
    assert rut_depth(on, (2, 5), 0.5) == pytest.approx(0.03 * (1 - 1.5 * shift), abs=0.002)


def _max_wall_slope(w):
    gx = np.diff(w.h_after, axis=0) / w.grid.dx
    gy = np.diff(w.h_after, axis=1) / w.grid.dx
    g = np.hypot(gx[:, :-1], gy[:-1, :])
    dug = (w.h_after < w.h_before - 0.005)[:-1, :-1]
    return np.percentile(g[dug], 99)


def test_cohesive_walls_stand_steeper_than_the_angle_of_repose():
    soil = {"base": {"d": 0.05, "chi": 0.3, "beta_deg": 20.0, "moisture": 0.5}}
    off = world(scenario(STRAIGHT, soil=soil))
    on = world(scenario(STRAIGHT, {"cohesive_walls": {"k": 1.0, "c0": 0.5}}, soil=soil))
    tan_b = math.tan(math.radians(20.0))
    assert _max_wall_slope(off) < tan_b + 0.02
    assert _max_wall_slope(on) > tan_b + 0.15


def _rut_width(w, y):
    gx, gy = w.grid.centers()
    i = (gx > 2) & (gx < 5)
    near = np.abs(gy - y) < 0.3
    dug = (w.h_after < w.h_before - 0.002)[np.ix_(i, near)]
    return dug.sum(1).mean() * w.grid.dx


def test_footprint_width_widens_the_rut():
    off = world(scenario(STRAIGHT))
    on = world(scenario(STRAIGHT, {"footprint_width": {"k": 0.6, "d_ref": 0.05}}))
    assert _rut_width(on, 0.5) > _rut_width(off, 0.5) * 1.2
    # deeper soil, wider patch: radius factor 1 + 0.6 * d / 0.05 at d = 0.03 is 1.36
    assert fx.radius_scale(fx.resolve({"footprint_width": {"k": 0.6}}), 0.03) == pytest.approx(1.36)


def test_tread_prints_a_periodic_pattern_on_the_rut_floor():
    def amplitude(w, wavelength=0.2):
        """Amplitude [m] of the rut-floor profile's component at 1 / wavelength."""
        gx, gy = w.grid.centers()
        i = (gx > 1) & (gx < 5.4)
        j = np.abs(gy - 0.5) <= 0.03
        prof = w.h_after[np.ix_(i, j)].min(1)
        return 2 / len(prof) * abs(np.sum((prof - prof.mean()) * np.exp(-2j * np.pi * gx[i] / wavelength)))

    on = world(scenario(STRAIGHT, {"tread": {"amp": 0.007, "wavelength": 0.2}}))
    off = world(scenario(STRAIGHT))
    assert 0.0015 < amplitude(on) < 0.0045          # law: amp / 2 = 3.5 mm
    assert amplitude(off) < 2e-4
    assert amplitude(on, 0.37) < 5e-4
    # the marks are the wheels', not the simulation's: the same whatever length of drive the
    # world digs at a time, and nothing at that length (each lug marks the cell the wheel's
    # centre passes, also behind a chunk's first pose; 0.13 m does not divide the chunks)
    tread = {"tread": {"amp": 0.007, "wavelength": 0.13}}
    a = {c: world({**scenario(STRAIGHT, tread), "world": {"chunk": c}}) for c in (0.1, 0.4)}
    assert amplitude(a[0.1], 0.13) > 0.001
    assert amplitude(a[0.1], 0.13) == pytest.approx(amplitude(a[0.4], 0.13), rel=0.05)
    assert amplitude(a[0.1], 0.1) < 2e-4 and amplitude(a[0.4], 0.4) < 2e-4


def test_effect_laws_and_errors():
    e = fx.resolve({"speed_dependent_sinkage": {"form": "power", "k": 0.5, "p": 2.0}})
    f = fx.pose_depth_factor(e, np.array([1.0, 2.0, 0.0]), np.zeros(3), np.zeros(3), np.zeros(3),
                             np.zeros(3), np.array([0.5, -0.5]), 1.0)
    np.testing.assert_allclose(f, [[1.0, 1.5, 0.5]] * 2)
    assert fx.phi(np.array([100.0]), "saturating", x_s=0.5)[0] == pytest.approx(0.5)
    with pytest.raises(ValueError, match="unknown effect 'sinkage_magic'"):
        fx.resolve({"sinkage_magic": {}})
    with pytest.raises(ValueError, match="slip_sinkage: unknown parameters"):
        fx.resolve({"slip_sinkage": {"gain": 1}})
    with pytest.raises(ValueError, match="form must be one of"):
        fx.resolve({"slip_sinkage": {"form": "cubic"}})


def test_revisit_surface_follows_visits_in_time():
    w = world(scenario(LOOP))
    twice = w.n_visits == 2
    assert twice.sum() > 1000
    t1, t2 = w.visit_time[0][twice], w.visit_time[1][twice]
    assert np.all(t2 > t1 + 3.0)
    tm = float(np.median(t1)) + 1.0
    cells = twice & (w.visit_time[0] < tm) & (w.visit_time[1] > tm)
    np.testing.assert_array_equal(w.surface_at(tm)[cells], w.states[1][cells])
    np.testing.assert_array_equal(w.surface_at(1e9), w.h_after)
    np.testing.assert_array_equal(w.surface_at(-1.0), w.h_before)


@settings(max_examples=60, deadline=None)
@given(x=st.floats(-5, 5), y=st.floats(-5, 5), form=st.sampled_from(fx.FORMS),
       p=st.floats(0.3, 3.0), x_s=st.floats(0.1, 3.0))
def test_effect_shape_functions_are_odd_and_monotone(x, y, form, p, x_s):
    f = fx.phi(np.array([x, -x, y]), form, p, x_s)
    assert f[0] == pytest.approx(-f[1], abs=1e-12)
    if x < y:
        assert f[0] <= f[2] + 1e-12
    if form == "saturating":
        assert abs(f[0]) <= x_s + 1e-12
    assert fx.phi(np.array([0.0]), form, p, x_s)[0] == 0.0
