"""Pose signals of a robot driving backwards, against the same physics as
test_covariates_by_hand.py (specific force a - g in the body axes, tests/drive_by_hand.py).

Reversing, the body x axis points against the motion: speeding up backwards needs the wheels
to push toward -x (traction demand < 0 in the body frame, like braking when driving
forwards), and a counter-clockwise turn taken backwards has its centre on the robot's right,
so its outer wheels, which take the load, are the LEFT ones (lateral load < 0).
"""

import math

import numpy as np
import pytest

from tests.drive_by_hand import G, reversing_straight, reversing_turn
from torchsoil.diagnosis.catalogue import CATALOGUE, depth_factor
from torchsoil.diagnosis.covariates import DriveSignals
from torchsoil.robot import paper_platform

DRIVES = {d.name: d for d in (
    reversing_straight("reverse_speeding_up", heading=0.0, grade=0.0, v0=0.3, a=0.5),
    reversing_straight("reverse_slowing_down", heading=0.0, grade=0.0, v0=2.3, a=-0.5),
    reversing_straight("reverse_uphill_constant_speed", heading=0.4, grade=0.10, v0=1.0, a=0.0),
    reversing_turn("reverse_turn_ccw", v=1.5, yaw_rate=0.3),
)}
HAND = {  # traction demand, lateral load, in g (body frame)
    "reverse_speeding_up": (-0.5 / G, 0.0),
    "reverse_slowing_down": (0.5 / G, 0.0),
    "reverse_uphill_constant_speed": (-math.sin(math.atan(0.10)), 0.0),
    "reverse_turn_ccw": (0.0, -1.5 * 0.3 / G),
}


@pytest.fixture(scope="module")
def robot():
    return paper_platform()


@pytest.mark.parametrize("name", sorted(HAND))
def test_hand_numbers(name):
    d = DRIVES[name]
    m = d.interior()
    np.testing.assert_allclose(d.traction[m], HAND[name][0], atol=1e-12)
    np.testing.assert_allclose(d.lateral_load[m], HAND[name][1], atol=1e-12)


@pytest.mark.parametrize("name", sorted(HAND))
def test_reversing_traction_and_lateral_load(robot, name):
    d = DRIVES[name]
    sig = DriveSignals.from_poses(d.poses, robot).signals
    m = d.interior()
    np.testing.assert_allclose(sig["traction"][m], d.traction[m], atol=1e-3, err_msg="traction")
    np.testing.assert_allclose(sig["lateral_load"][m], d.lateral_load[m], atol=1e-3, err_msg="lateral_load")


def test_reversing_turn_loads_the_outer_left_wheels(robot):
    d = DRIVES["reverse_turn_ccw"]
    drive = DriveSignals.from_poses(d.poses, robot)
    f = depth_factor(CATALOGUE["lateral_load_transfer"], drive, robot, drive.poses4[d.interior()], 2.0, {})
    left = np.array(["left" in n for n in robot.names])
    assert (f[left] > 1.05).all() and (f[~left] < 0.95).all()
