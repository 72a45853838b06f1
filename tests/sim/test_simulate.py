import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.conftest import straight_window
from torchsoil.grid import Grid
from torchsoil.robot import Robot
from torchsoil.sim import Modifiers, ParamSpec, SimConfig, simulate, wheel_geometry

SPEC = ParamSpec.base(2)


def theta(B=1, d1=0.03, d2=0.02, chi=1.0, beta=30.0, dtype=torch.float64):
    return SPEC.make(B, d1=d1, d2=d2, chi=chi, beta=math.radians(beta), dtype=dtype)


@pytest.fixture(scope="module")
def setup(robot=None):
    from torchsoil.robot import paper_platform

    robot = paper_platform()
    grid, poses, h = straight_window()
    geom = wheel_geometry(grid, poses, robot, dtype=torch.float64)
    return grid, poses, robot, geom, h


def test_chi_one_conserves_volume(setup):
    *_, geom, h = setup
    r = simulate(h, geom, theta(chi=1.0))
    assert r.removed.item() > 1e-4 and r.lost.item() == 0
    assert abs(r.h.sum().item() - h.sum().item()) * geom.dx**2 < 1e-12
    assert abs(r.deposited.item() - r.removed.item()) < 1e-12


def test_chi_zero_loses_exactly_removed(setup):
    *_, geom, h = setup
    r = simulate(h, geom, theta(chi=0.0))
    lost = (h.sum() - r.h.sum()).item() * geom.dx**2
    assert r.deposited.item() == 0
    assert abs(lost - r.removed.item()) < 1e-12


@settings(max_examples=12, deadline=None)
@given(d1=st.floats(0, 0.1), d2=st.floats(0, 0.1), chi=st.floats(0, 2), beta=st.floats(3, 89))
def test_volume_balance_hypothesis(setup, d1, d2, chi, beta):
    *_, geom, h = setup
    r = simulate(h, geom, theta(d1=d1, d2=d2, chi=chi, beta=beta))
    change = (r.h.sum() - h.sum()).item() * geom.dx**2
    assert abs(change - (chi - 1.0) * r.removed.item()) < 1e-11
    assert torch.all(r.h_unrelaxed <= h + 1e-15) or chi > 0  # without deposits nothing rises


def test_deeper_sinkage_removes_more(setup):
    *_, geom, h = setup
    vols = [simulate(h, geom, theta(d1=d, d2=d, chi=0.0)).removed.item() for d in (0.0, 0.01, 0.03, 0.06)]
    assert all(b > a for a, b in zip(vols, vols[1:], strict=False))


def test_zero_sinkage_leaves_untouched_ground(setup):
    *_, geom, h = setup
    r = simulate(h, geom, theta(d1=0.0, d2=0.0, chi=0.0))
    # outside the footprints nothing moves; inside only bumps above the local mean are pressed
    outside = ~geom.nominal.covered_any[0]
    assert torch.equal(r.h_unrelaxed[0][outside], h[outside])
    assert torch.all(r.h_unrelaxed[0] <= h)
    flat = torch.zeros_like(h)
    r = simulate(flat, geom, theta(d1=0.0, d2=0.0, chi=0.0))
    assert torch.equal(r.h[0], flat)


def test_rut_depth_matches_d(setup):
    grid, poses, robot, geom, _ = setup
    flat = torch.zeros(grid.shape, dtype=torch.float64)
    r = simulate(flat, geom, theta(d1=0.04, d2=0.02, chi=0.0, beta=89))
    x, y = grid.centers()
    i = len(x) // 2
    left = np.argmin(abs(y - 0.5 - 0.003))
    right = np.argmin(abs(y + 0.5 - 0.003))
    assert r.h[0, i, left].item() == pytest.approx(-0.04, abs=0.002)
    assert r.h[0, i, right].item() == pytest.approx(-0.02, abs=0.001)


def test_berm_beside_rut_not_in_it(setup):
    grid, poses, robot, geom, _ = setup
    flat = torch.zeros(grid.shape, dtype=torch.float64)
    r = simulate(flat, geom, theta(d1=0.03, d2=0.03, chi=1.0, beta=89.0))
    added = (r.h_unrelaxed[0] > 0)
    assert added.any()
    assert not (added & geom.nominal.covered_any[0]).any()


def test_mirror_symmetry(robot):
    """Terrain and path mirrored across the x axis give the mirrored result (d1 <-> d2)."""
    grid, poses, h = straight_window(y0=0.0)
    assert abs(grid.origin[1] + (grid.shape[1] - 1) * grid.dx / 2) < 1e-12  # y-symmetric grid
    mirrored_poses = poses * np.array([1, -1, -1])
    hm = torch.flip(h, dims=[1])
    g1 = wheel_geometry(grid, poses, robot, dtype=torch.float64)
    g2 = wheel_geometry(grid, mirrored_poses, robot, dtype=torch.float64)
    a = simulate(h, g1, theta(d1=0.03, d2=0.015, chi=1.2, beta=25))
    b = simulate(hm, g2, theta(d1=0.015, d2=0.03, chi=1.2, beta=25))
    assert torch.allclose(torch.flip(b.h_unrelaxed, dims=[2]), a.h_unrelaxed, atol=1e-12)
    # forward differences make the relaxation stencil one-sided: mirror-equal to within a
    # small fraction of the deformation, and exactly equal in volume
    diff = (torch.flip(b.h, dims=[2]) - a.h).abs()
    deformation = (a.h - h).abs().max().item()
    assert diff.max().item() < 0.15 * deformation
    assert diff.mean().item() < 0.01 * deformation
    assert abs(a.h.sum().item() - b.h.sum().item()) < 1e-10


def test_batched_equals_one_by_one(setup):
    *_, geom, h = setup
    th = torch.cat([theta(d1=0.01, chi=0.3, beta=20), theta(d1=0.05, d2=0.0, chi=1.8, beta=45),
                    theta(d1=0.0, d2=0.08, chi=1.0, beta=70)])
    batch = simulate(h, geom, th)
    for i in range(3):
        one = simulate(h, geom, th[i:i + 1])
        assert torch.allclose(one.h[0], batch.h[i], atol=1e-12)
        assert one.iterations.item() == batch.iterations[i].item()


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_float32_agrees_with_float64(setup, backend):
    grid, poses, robot, _, h = setup
    cfg = SimConfig(backend=backend)
    g64 = wheel_geometry(grid, poses, robot, dtype=torch.float64)
    g32 = wheel_geometry(grid, poses, robot, dtype=torch.float32)
    a = simulate(h, g64, theta(), cfg)
    b = simulate(h.float(), g32, theta(dtype=torch.float32), cfg)
    assert b.h.dtype == torch.float32
    assert (a.h - b.h.double()).abs().max().item() < 2e-4  # m; the stop may differ by an iteration


def test_backends_agree(setup):
    *_, geom, h = setup
    a = simulate(h, geom, theta(B=2), SimConfig(backend="torch"))
    b = simulate(h, geom, theta(B=2), SimConfig(backend="numba"))
    assert torch.allclose(a.h, b.h, atol=1e-12)


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_autograd_matches_finite_differences(setup, backend):
    """Gradient of a smooth scalar of the output w.r.t. theta, fixed iterations so the
    number of relaxation steps does not jump between the perturbed runs."""
    *_, geom, h = setup
    cfg = SimConfig(fixed_iter=6, backend=backend)
    w = torch.randn(h.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    th = theta(d1=0.03, d2=0.02, chi=0.8, beta=28).requires_grad_(True)
    f = lambda t: (simulate(h, geom, t, cfg).h[0] * w).sum()  # noqa: E731
    f(th).backward()
    # steps small enough not to cross the kinks (min, relu) of this piecewise-smooth map
    for p, step in zip(range(4), (1e-8, 1e-8, 1e-8, 1e-8), strict=True):
        e = torch.zeros_like(th)
        e[0, p] = step
        fd = (f(th.detach() + e) - f(th.detach() - e)).item() / (2 * step)
        assert th.grad[0, p].item() == pytest.approx(fd, rel=2e-3, abs=1e-6), SPEC.names[p]


def test_out_of_bounds_parameters_rejected(setup):
    *_, geom, h = setup
    for bad, name in [(theta(d1=0.31), "d1"), (theta(chi=2.5), "chi"), (theta(beta=1.0), "beta"),
                      (theta(d2=-0.01), "d2")]:
        with pytest.raises(ValueError, match=name):
            simulate(h, geom, bad)
    nan = theta()
    nan[0, 2] = float("nan")
    with pytest.raises(ValueError, match="chi"):
        simulate(h, geom, nan)


def test_nan_heights_rejected(setup):
    *_, geom, h = setup
    bad = h.clone()
    bad[3, 4] = float("nan")
    with pytest.raises(ValueError, match=r"NaN.*\[3, 4\]"):
        simulate(bad, geom, theta())
    with pytest.raises(ValueError, match="heights must be"):
        simulate(h[:-1], geom, theta())


def test_modifiers(setup):
    *_, geom, h = setup
    base = simulate(h, geom, theta(chi=0.0))
    K, N = geom.n_wheels, geom.poses.shape[0]
    half = simulate(h, geom, theta(chi=0.0), modifiers=Modifiers(depth_scale=torch.full((1, K, N), 0.5,
                                                                                        dtype=torch.float64)))
    same = simulate(h, geom, theta(d1=0.015, d2=0.01, chi=0.0))
    assert torch.allclose(half.h, same.h)
    wide = simulate(h, geom, theta(chi=0.0), modifiers=Modifiers(radius_scale=torch.tensor([1.3],
                                                                                          dtype=torch.float64)))
    assert wide.removed.item() > 1.2 * base.removed.item()


def test_cohesive_soil_hook(setup):
    """A second (intact) angle: deposits are loose and settle at beta, the cut stands steeper;
    an intact angle equal to beta is the one-angle model, and no second angle is today's."""
    *_, geom, h = setup
    th = theta(chi=1.0, beta=25)
    base = simulate(h, geom, th)

    def intact(deg):
        return Modifiers(tan_beta_intact=torch.tensor([math.tan(math.radians(deg))], dtype=torch.float64))

    assert torch.equal(simulate(h, geom, th, modifiers=Modifiers()).h, base.h)
    assert torch.allclose(simulate(h, geom, th, modifiers=intact(25)).h, base.h, atol=1e-14, rtol=0)
    bare = simulate(h, geom, theta(chi=0.0, beta=25), modifiers=intact(85))
    assert torch.equal(bare.h, bare.h_unrelaxed) and bare.iterations.item() == 0   # the cut stands
    assert not torch.allclose(simulate(h, geom, theta(chi=0.0, beta=25)).h, bare.h_unrelaxed)
    steep = simulate(h, geom, th, modifiers=intact(85))
    assert abs(steep.h.sum().item() - steep.h_unrelaxed.sum().item()) < 1e-9
    deposit = steep.h_unrelaxed - bare.h_unrelaxed                        # the loose soil
    assert deposit.max().item() > 1e-3 and not torch.allclose(steep.h, steep.h_unrelaxed)
    assert (steep.h >= steep.h_unrelaxed - 1e-12)[deposit == 0].all()     # intact ground never loses
    with pytest.raises(ValueError, match="tan\\(beta_loose\\) <= tan\\(beta_intact\\)"):
        simulate(h, geom, th, modifiers=intact(20))


def test_turning_and_standing_still(robot):
    grid = Grid.covering(-2.0, -2.0, 2.0, 2.0, 0.04)
    a = np.linspace(0, math.pi / 2, 40)
    poses = np.column_stack([1.5 * np.sin(a) - 0.5, 1.5 * (1 - np.cos(a)) - 1.0, a])
    geom = wheel_geometry(grid, poses, robot, dtype=torch.float64)
    r = simulate(torch.zeros(grid.shape, dtype=torch.float64), geom, theta(chi=1.0))
    assert r.lost.item() < 0.02 * r.removed.item()
    still = np.zeros((5, 3))
    geom = wheel_geometry(grid, still, robot, dtype=torch.float64)
    r = simulate(torch.zeros(grid.shape, dtype=torch.float64), geom, theta(chi=1.0))
    assert r.removed.item() > 0 and abs(r.h.sum().item()) < 1e-12  # four dimples, soil conserved


def test_robot_validation():
    with pytest.raises(ValueError, match="track"):
        Robot(0.14, np.array([[0, 0, 0], [0, 1, 2]]))
    with pytest.raises(ValueError, match="wheel_width"):
        Robot(-0.1, np.array([[0, 0, 0]]))


def test_dig_order_turns():
    """Hand cases: forward, the front axle meets the ground first; reversing, the rear one;
    a three-axle robot counts the axles ahead of each wheel."""
    from torchsoil.sim.geometry import dig_order

    fwd = np.array([[0, 0.0, 0, 0], [1, 0.1, 0, 0], [2, 0.2, 0, 0]], float)
    rev = fwd[::-1].copy()
    rev[:, 0] = fwd[:, 0]
    x = np.array([0.69, 0.69, -0.69, -0.69])
    assert dig_order(fwd, x).T.tolist() == [[0, 0, 1, 1]] * 3
    assert dig_order(rev, x).T.tolist() == [[1, 1, 0, 0]] * 3
    assert dig_order(fwd, np.array([0.8, 0.0, -0.8]))[:, 0].tolist() == [0, 1, 2]
    turned = fwd.copy()
    turned[:, 3] = math.pi                                # moving along +x while facing -x
    assert dig_order(turned, x)[:, 1].tolist() == [1, 1, 0, 0]


def test_wheels_dig_in_turn():
    """dig_order "wheel" on flat ground under a flat tread (f = 0.5, r = 3.5 cells, the wheel's
    centre line on a cell row): d where one axle passed, and where both did, the rear wheel
    rests on the front's rut as a rigid footprint does, at the mean height over its whole disc
    of 37 cells (lateral offsets 0, +-1, +-2, +-3 in 7, 14, 10 and 6 of them; s = 1, 1, 0.95048,
    0.18826), and sinks d from there: 1.85498 d at the centre line. The paper's small disc
    (revisit_ref "disc") sits on the flat floor: 2 d. The same rut when the drive runs in
    reverse; "robot" digs d everywhere."""
    from dataclasses import replace

    from torchsoil.robot import paper_platform

    robot = replace(paper_platform(), wheel_flat_fraction=0.5)
    grid = Grid.covering(-1.0, -0.3, 3.0, 0.8, 0.02)
    xs = np.arange(0.0, 2.0 + 1e-9, 0.02)                  # base_link from 0 to 2 m: front 0.69..2.69
    poses = np.column_stack([xs, np.zeros_like(xs), np.zeros_like(xs)])
    back = np.column_stack([xs[::-1], np.zeros_like(xs), np.zeros_like(xs)])
    flat = torch.zeros(grid.shape, dtype=torch.float64)
    x, y = grid.centers()
    j = int(np.argmin(abs(y - 0.5)))
    at = {name: int(np.argmin(abs(x - v))) for name, v in
          (("rear_only", 0.0), ("both", 1.0), ("front_only", 2.4))}
    contact = (7 + 14 + 10 * 0.95048 + 6 * 0.18826) / 37          # front rut's mean over the rear's disc, / d
    th = theta(d1=0.03, d2=0.03, chi=0.0, beta=89.9)
    for p in (poses, back):
        geom = wheel_geometry(grid, p, robot, dtype=torch.float64)
        turn = simulate(flat, geom, th, SimConfig(dig_order="wheel")).h[0, :, j]
        disc = simulate(flat, geom, th, SimConfig(dig_order="wheel", revisit_ref="disc")).h[0, :, j]
        paper = simulate(flat, geom, th, SimConfig(dig_order="robot")).h[0, :, j]
        assert turn[at["both"]].item() == pytest.approx(-0.03 * (1 + contact), abs=1e-6)
        assert disc[at["both"]].item() == pytest.approx(-0.06, abs=1e-9)
        assert turn[at["rear_only"]].item() == pytest.approx(-0.03, abs=1e-9)
        assert turn[at["front_only"]].item() == pytest.approx(-0.03, abs=1e-9)
        assert all(paper[i].item() == pytest.approx(-0.03, abs=1e-9) for i in at.values())


def test_the_trailing_wheel_finds_the_spoil_of_the_wheel_ahead():
    """The front wheel lays its spoil beside its rut before the rear wheel comes: one row off
    the centre line the rear's disc reaches 3 cells of the front's berm, chi 5.27748 d / 2
    high (its rut's cross-section, 1 + 2 (1 + 0.95048 + 0.18826) cells of d, spread over one
    band cell each side), and the other 34 cells of its rut: reference (-29.44610 + 3 x 2.63874
    chi) / 37 d, and the rear digs d below it. Without the berm (chi 0) it digs deeper."""
    from dataclasses import replace

    from torchsoil.robot import paper_platform

    robot = replace(paper_platform(), wheel_flat_fraction=0.5)
    grid = Grid.covering(-1.0, -0.3, 3.0, 0.8, 0.02)
    xs = np.arange(0.0, 2.0 + 1e-9, 0.02)
    geom = wheel_geometry(grid, np.column_stack([xs, np.zeros_like(xs), np.zeros_like(xs)]), robot,
                          dtype=torch.float64)
    x, y = grid.centers()
    i, j = int(np.argmin(abs(x - 1.0))), int(np.argmin(abs(y - 0.5))) + 1
    for chi in (0.0, 0.5):
        r = simulate(torch.zeros(grid.shape, dtype=torch.float64), geom, theta(d1=0.03, d2=0.03, chi=chi, beta=89.9),
                     SimConfig(dig_order="wheel"))
        ref = (-29.44610 + 3 * 2.63874 * chi) / 37 * 0.03
        assert r.h_unrelaxed[0, i, j].item() == pytest.approx(ref - 0.03, abs=1e-6)
