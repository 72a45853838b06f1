"""The out-of-catalogue laws a learned modifier names (effects.LEARNED): each changes the world
as its law says, against numbers worked out by hand on tiny drives.

- speed_deposit: chi x (1 + k (v / v_ref - 1)): with chi 0.3, k 0.6, v_ref 1 m/s, the ground
  dug at 0.5 m/s gets 0.3 x 0.7 = 0.21 of the removed volume back beside the rut, at 1.5 m/s
  0.3 x 1.3 = 0.39; the ruts stay d deep (beta 89 deg: nothing relaxes).
- turn_scrub: d x (1 + k |yaw rate| / r_ref): a 2 m radius turn at 1 m/s turns at 0.5 rad/s,
  with k 0.6, r_ref 0.5 rad/s both ruts sink 0.03 x 1.6 = 0.048 m, in a left or a right turn.
- pass_loosening: beta x (1 + k passes before): beta 30 deg, k -0.5: ground a footprint
  covered twice relaxes to 15 deg (slope tan 15 deg = 0.268), ground covered once to 30 deg
  (0.577).
"""

import math

import numpy as np
import pytest

from tests.synth.test_world import LOOP, rut_depth, scenario, world
from torchsoil.synth import effects as fx

NO_RELAX = {"base": {"d": 0.03, "chi": 0.3, "beta_deg": 89.0, "moisture": 0.0}}


def deposit_ratio(w, xs):
    """Volume added over volume removed on the ground x0 <= x <= x1 (all y)."""
    gx, _ = w.grid.centers()
    dh = (w.h_after - w.h_before)[(gx >= xs[0]) & (gx <= xs[1])]
    return dh[dh > 0].sum() / -dh[dh < 0].sum()


def test_speed_deposit_shares_follow_the_speed():
    segs = [{"straight": 4.0, "speed": 0.5}, {"straight": 4.0, "speed": 1.5}]
    on = world(scenario(segs, {"speed_deposit": {"form": "linear", "k": 0.6}}, soil=NO_RELAX, accel_limit=2.0))
    off = world(scenario(segs, soil=NO_RELAX, accel_limit=2.0))
    # the front wheels dig the ground x = base + 0.69: slow ground x in [1, 2.5], fast in [6, 7]
    slow, fast = (1.0, 2.5), (6.0, 7.0)
    assert deposit_ratio(off, slow) == pytest.approx(0.3, rel=1e-6)
    assert deposit_ratio(off, fast) == pytest.approx(0.3, rel=1e-6)
    assert deposit_ratio(on, slow) == pytest.approx(0.21, rel=1e-3)
    assert deposit_ratio(on, fast) == pytest.approx(0.39, rel=1e-3)
    for xs in (slow, fast):                                  # the sinkage is not the law's
        assert rut_depth(on, xs, 0.5) == pytest.approx(rut_depth(off, xs, 0.5), abs=1e-9)


def test_speed_deposit_share_stays_within_0_and_1():
    eff = fx.resolve({"speed_deposit": {"form": "linear", "k": 2.0}})
    chi = np.array([0.3, 0.3, 0.3, 0.6])
    v = np.array([1.0, 0.5, 1.5, 1.5])                    # factors 1, 0.05 (clipped from 0), 2, 2
    np.testing.assert_allclose(fx.deposit_share(eff, chi, v), [0.3, 0.015, 0.6, 1.0])
    assert fx.deposit_share({}, chi, v) is chi


@pytest.mark.parametrize("form, x_s, want", [("linear", 1.0, 1 + 0.6 * 1.2), ("threshold", 0.5, 1 + 0.6 * 0.7),
                                             ("saturating", 0.5, 1 + 0.6 * 0.5 * math.tanh(2.4))])
def test_turn_scrub_factor_by_hand(form, x_s, want):
    """|yaw rate| 0.6 rad/s either way over r_ref 0.5 rad/s: x = 1.2 for every wheel; straight: 1."""
    eff = fx.resolve({"turn_scrub": {"form": form, "k": 0.6, "x_s": x_s, "r_ref": 0.5}})
    z = np.zeros(3)
    f = fx.pose_depth_factor(eff, np.ones(3), z, z, z, np.array([0.6, -0.6, 0.0]), np.array([0.5, -0.5]), 1.0)
    np.testing.assert_allclose(f, [[want, want, 1.0]] * 2)


@pytest.mark.parametrize("side", [1, -1], ids=["left", "right"])
def test_turn_scrub_sinks_both_ruts_deeper_in_a_turn(side):
    turn = [{"straight": 3.0, "speed": 1.0}, {"arc": 2.0, "angle_deg": 90 * side, "speed": 1.0},
            {"straight": 1.0, "speed": 1.0}]
    on = world(scenario(turn, {"turn_scrub": {"form": "linear", "k": 0.6, "r_ref": 0.5}}))
    off = world(scenario(turn))
    gx, gy = on.grid.centers()
    X, Y = np.meshgrid(gx, gy, indexing="ij")
    r = np.hypot(X - 3.0, Y - 2.0 * side)                  # the turn's centre (3, +-2)
    ang = np.arctan2(side * (Y - 2.0 * side), X - 3.0)
    mid = (ang > -math.pi / 2 + 0.6) & (ang < -0.6)         # its middle, away from where it starts and ends
    straight = (gx > 0.8) & (gx < 2.0)                     # x = 0: the law leaves it alone
    np.testing.assert_allclose((on.h_before - on.h_after)[straight], (off.h_before - off.h_after)[straight],
                               atol=1e-9)
    for w, want in ((off, 0.03), (on, 0.048)):
        dug = w.h_before - w.h_after
        for inner in (True, False):                                                      # both tracks alike
            assert dug[mid & ((r < 2.0) if inner else (r > 2.2))].max() == pytest.approx(want, abs=5e-4)


def _wall_slopes(w, cells):
    """Slopes |grad h| of the final surface on dug ground among `cells` (X, Y) bool."""
    gx = np.diff(w.h_after, axis=0)[:, :-1] / w.grid.dx
    gy = np.diff(w.h_after, axis=1)[:-1, :] / w.grid.dx
    sel = (cells & (w.h_after < w.h_before - 0.005))[:-1, :-1]
    return np.hypot(gx, gy)[sel]


def _interior(mask):
    return mask & np.roll(mask, 1, 0) & np.roll(mask, -1, 0) & np.roll(mask, 1, 1) & np.roll(mask, -1, 1)


def test_pass_loosening_lowers_the_angle_of_ground_driven_twice():
    """The loop's last straight runs over its first: the ground footprints covered on both
    visits relaxes, after the second, to beta (1 - 0.5 x 1) = 15 deg; the ground covered once
    to 30 deg, and it is the same as without the law before the revisit."""
    soil = {"base": {"d": 0.04, "chi": 0.3, "beta_deg": 30.0, "moisture": 0.0}}
    on = world(scenario(LOOP, {"pass_loosening": {"form": "linear", "k": -0.5}}, soil=soil))
    off = world(scenario(LOOP, soil=soil))
    gx, gy = on.grid.centers()
    X, Y = np.meshgrid(gx, gy, indexing="ij")
    assert (on.end.passes == off.end.passes).all() and on.end.passes.max() == 2
    twice = _interior(on.end.passes == 2) & (X > 0.5) & (X < 2.5)
    once = _interior(on.end.passes == 1) & (Y > 1.5)                  # the second straight, y = 2.8
    tan30, tan15 = math.tan(math.radians(30.0)), math.tan(math.radians(15.0))
    for w, want_twice in ((off, tan30), (on, tan15)):
        s2, s1 = _wall_slopes(w, twice), _wall_slopes(w, once)
        assert len(s2) > 500 and len(s1) > 2000
        # the walls stand at the angle the pass left them, none steeper
        assert np.median(s2) == pytest.approx(want_twice, abs=0.005) and np.percentile(s2, 99) < want_twice + 0.01
        assert np.median(s1) == pytest.approx(tan30, abs=0.005)
    before_revisit = on.n_visits == 2
    np.testing.assert_array_equal(on.states[1][before_revisit], off.states[1][before_revisit])


def test_pass_loosening_factor_by_hand():
    eff = fx.resolve({"pass_loosening": {"form": "linear", "k": -0.25}})
    beta = np.radians(np.full(4, 32.0))
    tan_beta = np.tan(beta)
    got = fx.repose_tan_beta(eff, beta, tan_beta, np.array([0, 1, 2, 5]))
    np.testing.assert_allclose(got, np.tan(np.radians([32.0, 24.0, 16.0, 32.0 * 0.05])))   # 1 - 1.25 clips at 0.05
    assert fx.repose_tan_beta({}, beta, tan_beta, 1) is tan_beta
    steep = fx.resolve({"pass_loosening": {"form": "linear", "k": 3.0}})
    assert fx.repose_tan_beta(steep, beta, tan_beta, np.array([1]))[0] == pytest.approx(math.tan(math.radians(89.0)))


@pytest.mark.parametrize("eid, law, want", [
    ("speed_deposit", {"k": 0.8}, {"parameter": "chi", "covariate": "speed", "direction": "+"}),
    ("speed_deposit", {"form": "saturating", "k": -1.0}, {"parameter": "chi", "covariate": "speed", "direction": "-"}),
    ("turn_scrub", {}, {"parameter": "d", "covariate": "turn_rate", "direction": "+"}),
    ("pass_loosening", {}, {"parameter": "beta", "covariate": "passes", "direction": "-"}),
    ("pass_loosening", {"k": 0.3}, {"parameter": "beta", "covariate": "passes", "direction": "+"}),
])
def test_expected_verdict_of_a_learned_law(eid, law, want):
    exp = fx.expected(fx.resolve({eid: law}))
    assert exp == {"verdict": "missing_physics", "missing_physics": "learned", **fx.SIGNATURES[eid], **want}
    assert fx.expected({}) == {"verdict": "adequate", "missing_physics": None, "cross_track": None, "covariate": None}
    assert fx.expected(fx.resolve({"tread": True}))["verdict"] == "unexplained"
    both = fx.expected(fx.resolve({eid: law, "slip_sinkage": True}))        # a catalogue law comes first
    assert both["missing_physics"] == "slip_sinkage" and "parameter" not in both


def test_truth_file_expected_falls_back_on_the_effects():
    from torchsoil.grid import Grid
    from torchsoil.synth.truthfile import TruthFile

    eff = fx.resolve({"turn_scrub": True})
    old = TruthFile(Grid(0.02, (0.0, 0.0), (2, 2)), {}, {"effects": eff})
    assert old.expected["missing_physics"] == "learned" and old.expected["covariate"] == "turn_rate"
    new = TruthFile(Grid(0.02, (0.0, 0.0), (2, 2)), {}, {"effects": eff, "expected": {"verdict": "x"}})
    assert new.expected == {"verdict": "x"}
