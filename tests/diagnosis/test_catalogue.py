"""Catalogue extensions: k = 0 is the paper's model; each term acts through its hook in the
direction its name says."""

import math

import numpy as np
import pytest
import torch

from tests.drive_by_hand import racetrack
from torchsoil.diagnosis import catalogue
from torchsoil.diagnosis.catalogue import CATALOGUE, ExtensionModel, PassCounts, depth_factor, intact_angle
from torchsoil.diagnosis.covariates import DriveSignals
from torchsoil.grid import Grid
from torchsoil.robot import paper_platform
from torchsoil.sim import ParamSpec, simulate, wheel_geometry

REQUIRED = ("multi_pass_hardening", "speed_dependent_sinkage", "slip_sinkage", "lateral_load_transfer",
            "cohesive_walls", "footprint_width")


class Window:
    """The fields of a WindowData that extensions read."""

    def __init__(self, geom, grid=None):
        self.geom, self.grid = geom, grid
        self.spec = type("S", (), {"s0": 0.0, "s1": 1.0})()
        self.crop = (0, 0, 0, 0)


@pytest.fixture(scope="module")
def setup():
    robot = paper_platform()
    t = np.arange(0, 4, 0.05)
    v = np.where(t < 2, 0.6, 1.4)
    x = np.concatenate([[0], np.cumsum(v[:-1] * 0.05)])
    yaw = 0.05 * t
    poses = np.column_stack([t, x, 0 * t, 0 * t, 0.05 + 0 * t, 0 * t, yaw])
    drive = DriveSignals.from_poses(poses, robot)
    grid = Grid.covering(-1.0, -1.0, 3.5, 1.0, 0.02)
    geom = wheel_geometry(grid, poses[::4], robot, dtype=torch.float64)
    rng = np.random.default_rng(0)
    h = torch.as_tensor(0.002 * rng.standard_normal(grid.shape))
    theta = ParamSpec.base(robot.n_tracks).make(1, d1=0.03, d2=0.03, chi=0.3, beta=math.radians(30))
    return robot, drive, geom, h, theta, grid


def test_catalogue_holds_the_format_ids():
    assert set(REQUIRED) <= set(CATALOGUE)
    assert all(CATALOGUE[i].bounds[0] <= 0 <= CATALOGUE[i].bounds[1] for i in REQUIRED)


@pytest.mark.parametrize("ext_id", REQUIRED)
def test_zero_coefficient_is_the_base_model(setup, ext_id):
    robot, drive, geom, h, theta, grid = setup
    model = ExtensionModel(CATALOGUE[ext_id], 0.0, drive, robot)
    a = simulate(h, geom, theta).h
    b = simulate(h, geom, theta, modifiers=model.modifiers(Window(geom, grid), theta)).h
    assert torch.allclose(a, b, atol=1e-12)


def test_effect_size_by_hand(setup):
    """2 s at 0.6 m/s (1.2 m), 2 s at 1.4 (2.8 m): over the ground the mean speed is
    (1.2 x 0.6 + 2.8 x 1.4) / 4 = 1.16 m/s, and k_speed 0.5 changes the sinkage on the slow
    30 % of it by 0.5 x (1 - 0.6 / 1.16) = 0.241; lateral load is sin(roll 0.05) + v x yaw
    rate 0.05 / g, largest at 1.4 m/s (70 % of the ground); the other terms' change is |k|."""
    robot, drive, *_ = setup
    size = lambda eid, k: catalogue.effect_size(CATALOGUE[eid], k, drive, robot)  # noqa: E731
    assert size("speed_dependent_sinkage", 0.5) == pytest.approx(0.241, abs=0.01)
    assert size("speed_dependent_sinkage", -0.5) == pytest.approx(0.241, abs=0.01)
    assert size("lateral_load_transfer", 2.0) == pytest.approx(2 * (math.sin(0.05) + 1.4 * 0.05 / 9.81), rel=0.01)
    assert size("slip_sinkage", 0.0) == 0.0
    assert (size("multi_pass_hardening", -0.3), size("footprint_width", -0.2), size("cohesive_walls", 1.5)) \
        == pytest.approx((0.3, 0.2, 1.5))


def test_speed_reference_and_effect_size_weigh_ground_not_time():
    """20 m at 1 m/s, 60 s standing still, 20 m at 2 m/s: over the ground the mean speed is
    1.5 m/s (over time 0.3), and k_speed 0.5 changes the sinkage by 0.5 x 1/3 on either half."""
    robot = paper_platform()
    t = np.arange(0.0, 90.0, 0.05)
    v = np.where(t < 20, 1.0, np.where(t < 80, 0.0, 2.0))
    x = np.concatenate([[0], np.cumsum(v[:-1] * 0.05)])
    poses = np.column_stack([t, x, 0 * t, 0 * t, 0 * t, 0 * t, 0 * t])
    drive = DriveSignals.from_poses(poses, robot)
    assert catalogue.references(drive)["speed"] == pytest.approx(1.5, abs=0.02)
    size = catalogue.effect_size(CATALOGUE["speed_dependent_sinkage"], 0.5, drive, robot)
    assert size == pytest.approx(0.5 / 3, abs=0.01)


def test_speed_term_sinks_fast_poses_more(setup):
    robot, drive, geom, *_ = setup
    p4 = geom.poses.numpy()
    f = depth_factor(CATALOGUE["speed_dependent_sinkage"], drive, robot, p4, 0.5, {"speed": 1.0})
    fast = drive.at("speed", p4[:, 0]) > 1.2
    slow = drive.at("speed", p4[:, 0]) < 0.8
    assert f[:, fast].min() > 1.1 and f[:, slow].max() < 0.9


def test_lateral_term_shifts_load_between_sides(setup):
    robot, drive, geom, *_ = setup
    f = depth_factor(CATALOGUE["lateral_load_transfer"], drive, robot, geom.poses.numpy(), 2.0, {})
    left, right = robot.wheels[:, 1] > 0, robot.wheels[:, 1] < 0
    # roll > 0 and a left turn both load the right wheels
    assert (f[right] > 1).all() and (f[left] < 1).all()


def test_wider_footprint_and_steeper_walls_change_the_rut(setup):
    robot, drive, geom, h, theta, _ = setup
    base = simulate(h, geom, theta).h
    wide = ExtensionModel(CATALOGUE["footprint_width"], 0.3, drive, robot)
    hw = simulate(h, geom, theta, modifiers=wide.modifiers(Window(geom), theta)).h
    assert (h - hw > 0.005).sum() > (h - base > 0.005).sum()          # more ground dug
    wall = ExtensionModel(CATALOGUE["cohesive_walls"], 1.5, drive, robot)
    mod = wall.modifiers(Window(geom), theta)
    tan_beta = torch.tan(theta[:, -1])
    assert torch.allclose(mod.tan_beta_intact, 2.5 * tan_beta)        # intact ground: tan(beta) (1 + k)
    assert not torch.allclose(simulate(h, geom, theta, modifiers=mod).h, base)
    none = ExtensionModel(CATALOGUE["cohesive_walls"], 0.0, drive, robot)
    assert torch.equal(simulate(h, geom, theta, modifiers=none.modifiers(Window(geom), theta)).h, base)  # k 0


def test_intact_angle_of_two_angle_soil():
    assert intact_angle(32.0, math.tan(math.radians(75)) / math.tan(math.radians(32)) - 1) == pytest.approx(75.0)
    assert intact_angle(30.0, 0.0) == pytest.approx(30.0)
    with pytest.raises(ValueError, match="k_wall"):
        intact_angle(30.0, -0.1)


def test_coefficient_outside_bounds_is_named(setup):
    robot, drive, *_ = setup
    with pytest.raises(ValueError, match="k_width"):
        ExtensionModel(CATALOGUE["footprint_width"], 2.0, drive, robot)
    with pytest.raises(ValueError, match="k_wall"):                    # walls looser than loose soil
        ExtensionModel(CATALOGUE["cohesive_walls"], -0.2, drive, robot)


def _racetrack_hardening(view: str, dig_order: str = "robot", offset: float = 0.0):
    """The hardening term at k = -0.5 on the racetrack: (arc (N,) of its poses [m], robot,
    scale(sel, wheels) -> the sinkage factors of the footprint cells of the poses sel under
    the wheels `wheels` (K,) bool, within a quarter wheel width of the wheel's centre line)."""
    robot = paper_platform()
    poses = racetrack(offset=offset)
    drive = DriveSignals.from_poses(poses, robot)
    grid = Grid.covering(-2.0, -1.5, 6.0, 4.5, 0.05 if offset == 0 else 0.01)
    theta = ParamSpec.base(robot.n_tracks).make(1, d1=0.03, d2=0.03, chi=0.3, beta=math.radians(30))
    model = ExtensionModel(CATALOGUE["multi_pass_hardening"], -0.5, drive, robot, view, dig_order)

    def scale(sel, wheels=None):
        geom = wheel_geometry(grid, poses[sel], robot, dtype=torch.float64)
        f = model.modifiers(Window(geom, grid), theta).depth_scale[0]
        wheels = torch.ones(len(robot.wheels), dtype=torch.bool) if wheels is None else wheels
        core = (geom.lateral.abs() < robot.wheel_width / 4) & (geom.dist < robot.wheel_width / 4)
        return f[core & wheels[geom.wheel]]

    return drive.signals["arc_length"], robot, scale


def test_hardening_counts_passes_as_the_pair_shows_them():
    """A racetrack comes back over its start. From a first view every visit is simulated:
    the first lap's wheels dig fresh ground (factor 1, although that ground is driven again
    later), the second lap's the first lap's ruts (factor 1 + k). From a last-visit H_f only
    the last visit is simulated, and every visit but the last is an earlier pass."""
    arc, _, first_view = _racetrack_hardening("first_view")
    _, _, last_visit = _racetrack_hardening("last_visit")
    first = (arc > 0.5) & (arc < 1.5)                 # driven again at the end
    again = arc > arc[-1] - 1.2
    one, half = torch.ones((), dtype=torch.float64), torch.full((), 0.5, dtype=torch.float64)
    assert torch.allclose(first_view(first), one)
    assert torch.allclose(first_view(again), half)
    assert torch.allclose(last_visit(first), half)
    assert torch.allclose(last_visit(again), half)
    with pytest.raises(ValueError, match="view"):
        _racetrack_hardening("newest")


def test_hardening_models_share_their_pass_counts_across_coefficients(monkeypatch):
    """The pass counts do not depend on k: models at three coefficients sharing a PassCounts
    count each window once and give the factors of models that count alone, (1 + n)^log2(1 + k);
    a full PassCounts keeps nothing more and still counts."""
    robot = paper_platform()
    poses = racetrack()
    drive = DriveSignals.from_poses(poses, robot)
    arc = drive.signals["arc_length"]
    grid = Grid.covering(-2.0, -1.5, 6.0, 4.5, 0.05)
    geom = wheel_geometry(grid, poses[arc > arc[-1] - 1.2], robot, dtype=torch.float64)
    theta = ParamSpec.base(robot.n_tracks).make(1, d1=0.03, d2=0.03, chi=0.3, beta=0.5)
    calls = []
    count = catalogue.entry_passes
    monkeypatch.setattr(catalogue, "entry_passes", lambda *a, **kw: calls.append(1) or count(*a, **kw))
    hard = CATALOGUE["multi_pass_hardening"]
    shared = PassCounts()
    for k in (-0.6, -0.3, -0.15):
        f = ExtensionModel(hard, k, drive, robot, "last_visit", counts=shared).modifiers(Window(geom, grid), theta)
        alone = ExtensionModel(hard, k, drive, robot, "last_visit").modifiers(Window(geom, grid), theta)
        torch.testing.assert_close(f.depth_scale, alone.depth_scale, rtol=0, atol=0)
        n = count(drive, geom, grid)
        torch.testing.assert_close(f.depth_scale[0], torch.as_tensor((1 + n) ** math.log2(1 + k)))
    assert len(calls) == 1 + 3 and shared.nbytes == geom.cell.shape[0] * 8
    assert n.max() >= 1                                   # the last straight is driven twice
    full = PassCounts(max_bytes=0)
    for k in (-0.6, -0.3):
        ExtensionModel(hard, k, drive, robot, "last_visit", counts=full).modifiers(Window(geom, grid), theta)
    assert len(calls) == 6 and full.nbytes == 0


@pytest.mark.parametrize("view", ["first_view", "last_visit"])
def test_hardening_acts_on_the_ground_a_wheel_pressed(view):
    """The racetrack's last straight runs 0.2 m beside its first (0.07 m footprints): no
    cell under its wheels was pressed before, so they dig fresh soil (factor 1). 0.05 m
    beside it, a wheel's cells within a footprint radius of the first lap's wheel line
    (0.07 m) sink at 1 + k, those more than one cell (0.01 m) beyond it at 1."""
    arc, robot, scale = _racetrack_hardening(view, offset=0.2)
    last = (arc > arc[-1] - 1.2) & (arc < arc[-1] - 0.2)
    beside = scale(last)
    assert len(beside) > 100
    torch.testing.assert_close(beside, torch.ones_like(beside))

    poses = racetrack(offset=0.05)
    drive = DriveSignals.from_poses(poses, robot)
    arc = drive.signals["arc_length"]
    grid = Grid.covering(-2.0, -1.5, 6.0, 4.5, 0.01)
    geom = wheel_geometry(grid, poses[(arc > arc[-1] - 1.2) & (arc < arc[-1] - 0.2)], robot, dtype=torch.float64)
    model = ExtensionModel(CATALOGUE["multi_pass_hardening"], -0.5, drive, robot, view, "robot")
    theta = ParamSpec.base(2).make(1, d1=0.03, d2=0.03, chi=0.3, beta=0.5)
    f = model.modifiers(Window(geom, grid), theta).depth_scale[0]
    _, ys = grid.centers()
    y = torch.as_tensor(ys)[geom.cell % grid.shape[1]]
    old_line = torch.where(y > 0.0, torch.full_like(y, 0.5), torch.full_like(y, -0.5))  # first lap's wheels
    under = geom.dist <= geom.radius
    pressed, fresh = under & ((y - old_line).abs() <= 0.069), under & ((y - old_line).abs() >= 0.081)
    assert pressed.sum() > 200 and fresh.sum() > 200
    torch.testing.assert_close(f[pressed], torch.full_like(f[pressed], 0.5))
    torch.testing.assert_close(f[fresh], torch.ones_like(f[fresh]))


def test_hardening_counts_wheel_passes_when_the_wheels_dig_in_turn():
    """Under dig_order "wheel" a rear wheel in its front wheel's rut runs the second pass. On
    the racetrack's second lap (first view, k = -0.5), the front wheels find two earlier
    passes, 3^log2(0.5) = 1/3 (a line through the second pass's 1/2 would give 0), and the
    rear wheels three, 4^-1 = 1/4; on the first lap (past the rear wheels' start) the front
    wheels dig fresh ground and the rear ones at 1/2."""
    arc, robot, scale = _racetrack_hardening("first_view", "wheel")
    front = torch.as_tensor(robot.wheels[:, 0] > 0)
    first = (arc > 2.0) & (arc < 3.0)                  # rear wheels on the front ones' ground
    again = arc > arc[-1] - 0.5                        # base_link at x 1.5-2, rear wheels beyond 0.69
    for sel, f_front, f_rear in ((first, 1.0, 0.5), (again, 1 / 3, 0.25)):
        got_front, got_rear = scale(sel, front), scale(sel, ~front)
        assert len(got_front) > 10 and len(got_rear) > 10
        torch.testing.assert_close(got_front, torch.full_like(got_front, f_front))
        torch.testing.assert_close(got_rear, torch.full_like(got_rear, f_rear))
