"""The field_rows scenario and its null twin: four 10 m rows 1.05 m apart joined by Omega
headland turns of radius 1.5 m (the path checked against its geometry by hand), and the
visit layers of the rut the next row's wheels share, on the first two rows."""

import math

import numpy as np
import pytest

from torchsoil.estimate.visits import passes_before, wheel_passes
from torchsoil.io.terrain_pair import TerrainPair
from torchsoil.synth import effects as fx
from torchsoil.synth.scenario import load_scenario, make_terrain_pair
from torchsoil.synth.trajectory import planar_path

LANE, R, ROW = 1.05, 1.5, 10.0


def test_rows_lie_a_lane_apart_joined_by_omega_turns():
    """An Omega turn onto the next lane (1.05 m over, less than its diameter) turns away by
    a, back by 180 + 2a and away by a again, its middle arc tangent to both: its centre lies
    D = sqrt((2 R)^2 - (R + L / 2)^2) = 2.2135 m beyond the row's end, halfway between the
    lanes, so the turn reaches 10 + D + R = 13.71 m out and R - L / 2 = 0.975 m beside the first
    lane, away from the next. The rows: 10 m each at y = 0, -1.05, -2.10, -3.15, headings 0,
    180, 0, 180 deg, the turns alternately at the far and the near headland."""
    hard, null = load_scenario("field_rows"), load_scenario("field_rows_null")
    assert hard.trajectory == null.trajectory and hard.lidar == null.lidar and hard.soil == null.soil
    assert list(fx.resolve(hard.effects)) == ["multi_pass_hardening"] and not fx.resolve(null.effects)
    assert hard.lidar.tilt_deg == 20.0
    path, speed = planar_path(hard.trajectory.segments)
    s, x, y, yaw = path.T
    assert np.all(speed == 1.0)
    arcs = [g for g in hard.trajectory.segments if g.arc is not None]
    assert len(arcs) == 9 and all(g.arc == R for g in arcs)
    straight = np.r_[True, np.abs(np.diff(yaw)) < 1e-12]
    for k in range(4):                                     # the rows, in driving order
        on = straight & (np.abs(y + k * LANE) < 1e-4) & (np.abs(np.cos(yaw) - (-1) ** k) < 1e-9)
        assert np.ptp(x[on]) == pytest.approx(ROW, abs=0.02)
        assert min(x[on]) == pytest.approx(0.0, abs=0.02) and max(x[on]) == pytest.approx(ROW, abs=0.02)
    D = math.sqrt((2 * R) ** 2 - (R + LANE / 2) ** 2)
    assert x.max() == pytest.approx(ROW + D + R, abs=0.01) and x.min() == pytest.approx(-D - R, abs=0.01)
    assert y.max() == pytest.approx(R - LANE / 2, abs=0.01)
    assert y.min() == pytest.approx(-3 * LANE - R + LANE / 2, abs=0.01)      # the last turn's bulge
    assert s[-1] == pytest.approx(4 * ROW + 3 * R * math.radians(2 * 47.546 + 275.092), abs=0.02)


def test_the_next_rows_wheels_run_in_the_last_rows_rut_a_few_centimetres_off():
    """Rows 1.05 m apart under a 1.0 m track: row 2's right wheels run 5 cm off row 1's right
    rut. The cells of both ruts have two visits; row 1's rut (within half a wheel width of y
    = -0.5 m) had its two wheel passes before row 2 came, the strip row 2's wheels reach beside
    it (y -0.57 to -0.62 m) none: the wall it cuts there is fresh ground."""
    scn = load_scenario("field_rows").model_dump()
    scn["trajectory"]["segments"] = scn["trajectory"]["segments"][:5]     # rows 1 and 2, the turn
    scn["trajectory"]["segments"][0]["straight"] = scn["trajectory"]["segments"][4]["straight"] = 2.0
    scn["terrain"]["margin"] = 1.0
    pair = TerrainPair.from_mapping(make_terrain_pair(scn, seed=0, visits=True))
    assert pair.n_visits == 2
    xs, ys = pair.grid.centers()
    i = int(np.argmin(np.abs(xs - 1.0)))
    passes = wheel_passes(pair.poses, pair.wheels, pair.wheel_width, pair.grid, pair.visit_time)[:, i]
    before = passes_before(passes[:, None])[:, 0]
    visits = np.isfinite(pair.visit_time[:, i]).sum(0)
    r = pair.wheel_width / 2
    old, new = np.abs(ys + 0.5) <= r - 1e-9, np.abs(ys + LANE - 0.5) <= r - 1e-9
    assert old.sum() == new.sum() == 7 and (old & ~new).sum() == 2 and (new & ~old).sum() == 2
    assert np.all(visits[old | new] == 2)
    np.testing.assert_array_equal(passes[0][old | new], np.where(old, 2, 0)[old | new])
    np.testing.assert_array_equal(passes[1][old | new], np.where(new, 2, 0)[old | new])
    np.testing.assert_array_equal(before[1][new], np.where(old, 2, 0)[new])
    assert np.all(np.isfinite(pair.visit_front[1][i, old | new]))
