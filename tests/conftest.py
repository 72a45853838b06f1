import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch starts its thread pool

import math  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np
import pytest
import torch

from torchsoil.grid import Grid
from torchsoil.robot import Robot, paper_platform

# with pytest-xdist (the README's `-n auto --dist loadgroup`) the workers share the cores: torch threads, a share each
_workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if _workers > 1:
    torch.set_num_threads(max(1, (os.cpu_count() or 1) // _workers))

# module and session fixtures that take seconds to build (a drive to diagnose, a bag to map):
# the tests that use one run on one worker (`--dist loadgroup`, the README's command), so each
# is built once rather than once per worker
SHARED_FIXTURES = {"speed_power": "speed_power", "s_turn": "s_turn", "streamed": "streamed",
                   "moving_bag": "moving_bag", "side_slope": "side_slope", "rec": "recording",
                   "drives": "fleet", "ray_instance": "fleet", "keyhole": "keyhole",
                   "out_and_back": "out_and_back", "out_and_back_pair": "out_and_back",
                   "ros1_run": "node_ros1", "ros2_run": "node_ros2", "in_order": "node_body",
                   "first_seconds": "node_body"}


# test folders whose tests compile the same numba kernels (envs._step_numba: a fused soil step,
# serial and parallel, about 20 s on a clean checkout): on one worker they are compiled once,
# the other tests reading them from numba's cache
SHARED_KERNELS = {"envs": "envs_kernels"}

# the quick tier's modules whose tests or shared fixtures take longest (--durations), run
# first, longest first, so that the two workers do not wait at the end on one long test
LONG_FIRST = ("node/test_node_ros1.py", "diagnosis/test_diagnose.py", "node/test_node_body.py",
              "diagnosis/test_learned.py", "diagnosis/test_checkpoint.py", "test_manual.py",
              "pipeline/test_synthetic.py", "jobs/test_fleet.py", "diagnosis/test_parallel.py")


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist reads the marks
def pytest_collection_modifyitems(config, items):
    tests = Path(__file__).parent
    for item in items:
        groups = sorted({SHARED_FIXTURES[f] for f in getattr(item, "fixturenames", ()) if f in SHARED_FIXTURES})
        if not groups and item.path.is_relative_to(tests):
            folder = item.path.relative_to(tests).parts[0]
            groups = [SHARED_KERNELS[folder]] if folder in SHARED_KERNELS else []
        if groups:
            item.add_marker(pytest.mark.xdist_group(groups[0]))
    rank = {tests / m: i for i, m in enumerate(LONG_FIRST)}
    items.sort(key=lambda item: rank.get(item.path, len(rank)))     # stable: each module's own order kept


@pytest.fixture(scope="session")
def robot() -> Robot:
    return paper_platform()


def straight_window(dx=0.02, length=0.6, half_width=1.0, y0=0.003, noise=0.003, seed=0,
                    step=0.02, slope=(0.0, 0.0), robot=None):
    """A straight drive along +x over a small noisy field: (grid, poses (N, 3), h (X, Y) f64)."""
    robot = robot or paper_platform()
    margin = robot.wheel_width / 2
    grid = Grid.covering(-margin, -half_width, length + margin, half_width, dx)
    reach = robot.wheels[:, 0].max() + margin
    xs = np.arange(-reach - 0.05, length + reach + 0.05 + 1e-9, step)
    poses = np.column_stack([xs, np.full_like(xs, y0), np.zeros_like(xs)])
    rng = np.random.default_rng(seed)
    x, y = grid.centers()
    plane = slope[0] * x[:, None] + slope[1] * y[None, :]
    h = torch.as_tensor(plane + rng.normal(0.0, noise, grid.shape))
    return grid, poses, h


@pytest.fixture
def window():
    return straight_window()


def deg(a):
    return math.radians(a)


# 3 m out, a light-bulb turn of radius 1.5 m (60 deg one way, 300 the other, 60), 3 m back on
# the same ruts (torchsoil.diagnosis.study_cases, random_path "out_and_back"), 2 x 16 x 512 beams
OUT_AND_BACK = {
    "name": "out_and_back",
    "trajectory": {"segments": [{"straight": 3.0, "speed": 1.0}, {"arc": 1.5, "angle_deg": -60, "speed": 1.0},
                                {"arc": 1.5, "angle_deg": 300, "speed": 1.0},
                                {"arc": 1.5, "angle_deg": -60, "speed": 1.0}, {"straight": 3.0, "speed": 1.0}],
                   "accel_limit": 0.5},
    "soil": {"base": {"d": 0.03, "chi": 0.2, "beta_deg": 30.0, "moisture": 0.3}},
    "lidar": {"columns": 512, "beams": 16},
}


@pytest.fixture(scope="session")  # SHARED_FIXTURES: built once
def out_and_back(tmp_path_factory):
    """A 17 s recording that drives back over its own ruts: the bag path and its truth
    (torchsoil.synth.truthfile.TruthFile)."""
    from torchsoil.synth.record import make_recording
    from torchsoil.synth.truthfile import load_truth

    bag = tmp_path_factory.mktemp("out_and_back") / "out_and_back"
    make_recording(OUT_AND_BACK, bag, seed=0)
    return bag, load_truth(bag)


@pytest.fixture(scope="session")  # SHARED_FIXTURES: built once
def out_and_back_pair(out_and_back):
    """`out_and_back` through the pipeline: (its PipelineResult, the truth)."""
    from torchsoil.pipeline.run import process_bag

    bag, truth = out_and_back
    return process_bag(bag, Robot.from_yaml(bag.parent / (bag.name + ".robot.yaml"))), truth
