import numpy as np
import pytest

from tests.synthetic_pair import sim_pair
from torchsoil.settings import EstimatorConfig
from torchsoil.sim import SimConfig
from torchsoil.windows import _stopped, path_index, plan_windows, prepare_window


def test_plan_windows():
    w = plan_windows(4.0, 0.8, 0.4)
    assert len(w) == 9 and w[0].s0 == 0 and w[-1].s1 == pytest.approx(4.0)
    assert all(b.s0 - a.s0 == pytest.approx(0.4) for a, b in zip(w, w[1:], strict=False))
    assert plan_windows(0.5, 0.8, 0.4) == []
    with pytest.raises(ValueError):
        plan_windows(4.0, 0.0, 0.4)


@pytest.fixture(scope="module")
def pair():
    return sim_pair(length=3.0)[0]


def test_path_index(pair):
    idx = path_index(pair.grid, pair.poses, pair.robot, 1.6)
    x, y = pair.grid.centers()
    j = np.argmin(abs(y))
    s = idx.s[:, j]
    on = np.isfinite(s)
    assert np.all(np.diff(s[on]) >= 0)  # arc length grows along a straight drive
    i = np.argmin(abs(x - 1.5))
    assert s[i] == pytest.approx(1.5, abs=0.02)
    jw = np.argmin(abs(y - 0.503))
    assert idx.wheel_dist[i, jw] < 0.02 and idx.offset[i, jw] == pytest.approx(0.5, abs=0.02)


def test_prepare_window_masks(pair):
    idx = path_index(pair.grid, pair.poses, pair.robot, 1.6)
    spec = plan_windows(3.0, 0.8, 0.4)[2]
    wd = prepare_window(pair, idx, spec, EstimatorConfig(), SimConfig())
    assert wd.flags == ()
    i0, i1, j0, j1 = wd.crop
    x, _ = pair.grid.crop(*wd.crop).centers()
    ground_x = x[wd.ground.numpy().any(1)]
    assert ground_x.min() >= spec.s0 - 0.03 and ground_x.max() <= spec.s1 + 0.03
    assert (wd.weight.numpy() > 0).sum() > 0.9 * (wd.ground.numpy() & (wd.weight.numpy() > 0)).sum()
    assert not (wd.floor.numpy() & (wd.weight.numpy() > 0)).any()  # beside the rut, not in it


def test_unmeasured_window_is_flagged(pair):
    idx = path_index(pair.grid, pair.poses, pair.robot, 1.6)
    spec = plan_windows(3.0, 0.8, 0.4)[2]
    holed = sim_pair(length=3.0)[0]
    x, _ = holed.grid.centers()
    holed.h_back[(x > spec.s0 - 0.1) & (x < spec.s1 + 0.1)] = np.nan
    wd = prepare_window(holed, idx, spec, EstimatorConfig(), SimConfig())
    assert "few_valid" in wd.flags
    holed.h_front[:] = np.nan
    assert prepare_window(holed, idx, spec, EstimatorConfig(), SimConfig()) is None


def test_stopped():
    t = np.arange(0, 4, 0.1)
    moving = np.column_stack([t, t, 0 * t, 0 * t, 0 * t, 0 * t, 0 * t])
    assert not _stopped(moving, 0.05, 0.5)
    x = np.where(t < 1, t, np.where(t < 2, 1.0, t - 1))
    still = np.column_stack([t, x, 0 * t, 0 * t, 0 * t, 0 * t, 0 * t])
    assert _stopped(still, 0.05, 0.5)


def test_ground_driven_twice_belongs_to_the_last_pass(pair):
    """Out along +x and back over the same line: the cells take the return pass's arc length."""
    t = np.arange(0, 6.0001, 0.05)
    x = np.where(t <= 3, t, 6 - t)
    yaw = np.where(t <= 3, 0.0, np.pi)
    poses = np.column_stack([t, x, 0 * t, 0 * t, 0 * t, 0 * t, yaw])
    idx = path_index(pair.grid, poses, pair.robot, 1.6)
    xs, ys = pair.grid.centers()
    j = np.argmin(abs(ys))
    for xc in (0.2, 0.6, 1.0):  # nearer the turning point the two passes are one
        i = np.argmin(abs(xs - xc))
        assert idx.s[i, j] == pytest.approx(6.0 - xc, abs=0.05)
    straight = path_index(pair.grid, pair.poses, pair.robot, 1.6)  # one pass: nearest point
    i = np.argmin(abs(xs - 1.5))
    assert straight.s[i, j] == pytest.approx(1.5, abs=0.05)
