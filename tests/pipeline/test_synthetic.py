"""The pipeline on recordings from the synthetic recorder (farm scene, 2 x 32-beam lidars,
range noise, motion distortion), scored against their truth (torchsoil.synth.evaluate)."""

import numpy as np
import pytest

from torchsoil.pipeline.run import process_bag
from torchsoil.robot import Robot
from torchsoil.synth.evaluate import pipeline_errors, truth_poses
from torchsoil.synth.record import make_recording
from torchsoil.synth.truthfile import load_truth


@pytest.fixture(scope="session")  # tests/conftest.py SHARED_FIXTURES: built once per worker
def s_turn(tmp_path_factory):
    """25 s S-turn on an 8 % side slope (poles, posts and a shed around it)."""
    bag = tmp_path_factory.mktemp("sturn") / "sturn"
    make_recording("lateral_load_transfer", bag, seed=2)
    res = process_bag(bag, Robot.from_yaml(bag.parent / "sturn.robot.yaml"))
    return res, load_truth(bag)


def test_s_turn_trajectory_and_heightmaps_within_targets(s_turn):
    res, truth = s_turn
    e = pipeline_errors(res.terrain, truth)
    assert res.duration > 20.0 and res.problems == []
    assert e["ate_aligned_m"] < 0.02 and e["ate_first_m"] < 0.03
    assert e["yaw_rms_deg"] < 0.2
    assert e["h_front_plane_rms_m"] < 0.004 and e["h_back_plane_rms_m"] < 0.004


def test_errors_vanish_for_the_truth_itself(s_turn):
    """The scoring is not lenient: the truth scored against itself gives zero, and a 2 cm
    shift of the path shows as 2 cm."""
    res, truth = s_turn
    tp = res.terrain
    true = truth_poses(truth, tp.poses[:, 0])
    from scipy.spatial.transform import Rotation

    rows = np.column_stack([tp.poses[:, 0], true[:, :3, 3], Rotation.from_matrix(true[:, :3, :3]).as_euler("xyz")])
    perfect = type(tp)(truth.grid.dx, np.array(truth.grid.origin), truth["h_before"], truth["h_after"], rows,
                       tp.wheels, tp.wheel_width)
    e = pipeline_errors(perfect, truth)
    assert e["ate_first_m"] < 1e-6 and e["yaw_rms_deg"] < 1e-6 and e["h_front_rms_m"] < 1e-9
    shifted = rows.copy()
    shifted[1:, 1] += 0.02
    assert pipeline_errors(type(tp)(truth.grid.dx, np.array(truth.grid.origin), truth["h_before"],
                                    truth["h_after"], shifted, tp.wheels, tp.wheel_width), truth)[
        "ate_first_m"] == pytest.approx(0.02, rel=0.01)
