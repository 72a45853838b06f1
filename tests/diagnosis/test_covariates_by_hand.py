"""Pose signals and catalogue sinkage factors against physics worked out by hand.

The drives (tests/drive_by_hand.py) are built from a direction of travel and a ground
normal; the expected traction demand and lateral load come from the specific force a - g
in the body axes (see that module), not from the formula the code uses. Signs are stated
physically: climbing or accelerating needs the wheels to push (traction > 0), descending or
braking to hold back (< 0); a left turn loads the outer (right) wheels, a slope whose left
side is higher loads the downhill (right) wheels.
"""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import torchsoil.diagnosis.covariates as covariates
from tests.drive_by_hand import G, catalogue
from torchsoil.diagnosis.catalogue import CATALOGUE, depth_factor
from torchsoil.diagnosis.covariates import DriveSignals
from torchsoil.robot import paper_platform

DRIVES = catalogue()


@pytest.fixture(scope="module")
def robot():
    return paper_platform()


@pytest.fixture(scope="module")
def signals(robot):
    return {name: DriveSignals.from_poses(d.poses, robot) for name, d in DRIVES.items()}


def sides(robot):
    right = np.array(["right" in n for n in robot.names])
    left = np.array(["left" in n for n in robot.names])
    assert right.sum() == 2 and left.sum() == 2
    return left, right


def test_the_angle_convention_by_construction():
    """REP 103 fixed-axis roll, pitch, yaw = scipy extrinsic 'xyz' = Rz(yaw) Ry(pitch) Rx(roll);
    with it a nose-up climb has NEGATIVE pitch and a left-high side slope POSITIVE roll."""
    r, p, y = 0.1, -0.2, 0.7
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    np.testing.assert_allclose(Rotation.from_euler("xyz", [r, p, y]).as_matrix(), Rz @ Ry @ Rx, atol=1e-12)

    climb = DRIVES["climb_10pct"]
    assert climb.R[0][2, 0] > 0                                    # the body x axis points upward
    np.testing.assert_allclose(climb.pitch, -math.atan(0.10), atol=1e-12)
    np.testing.assert_allclose(DRIVES["descend_10pct"].pitch, +math.atan(0.10), atol=1e-12)
    slope = DRIVES["side_slope_left_high"]
    assert slope.R[0][2, 1] > 0                                    # the body y (left) axis points upward
    np.testing.assert_allclose(slope.roll, math.atan(0.10), atol=1e-12)
    np.testing.assert_allclose(DRIVES["turn_left"].poses[:, 6][DRIVES["turn_left"].interior()][:5],
                               1.5 / 5.0 * DRIVES["turn_left"].poses[:, 0][DRIVES["turn_left"].interior()][:5],
                               atol=1e-9)                          # heading grows counter-clockwise


# traction demand and lateral load in g, worked out by hand for each drive
HAND = {
    "climb_10pct": (math.sin(math.atan(0.10)), 0.0),                # 0.0995: weight component along the slope
    "descend_10pct": (-math.sin(math.atan(0.10)), 0.0),
    "accelerate": (0.5 / G, 0.0),                                  # 0.0510 g
    "brake": (-0.5 / G, 0.0),
    "turn_left": (0.0, 1.5**2 / 5.0 / G),                          # v^2 / R = 0.45 m/s^2 = 0.0459 g
    "turn_right": (0.0, -1.5**2 / 5.0 / G),
    "side_slope_left_high": (0.0, math.sin(math.atan(0.10))),      # weight component across the slope
    "side_slope_left_high_driving": (0.0, math.sin(math.atan(0.10))),
}


@pytest.mark.parametrize("name", sorted(HAND))
def test_the_specific_force_matches_the_numbers_by_hand(name):
    d = DRIVES[name]
    m = d.interior()
    np.testing.assert_allclose(d.traction[m], HAND[name][0], atol=1e-12)
    np.testing.assert_allclose(d.lateral_load[m], HAND[name][1], atol=1e-12)


@pytest.mark.parametrize("name", sorted(HAND))
def test_pose_signals_match_the_physics(signals, name):
    d = DRIVES[name]
    sig = signals[name].signals
    m = d.interior()
    # traction demand and lateral load in units of g
    np.testing.assert_allclose(sig["traction"][m], d.traction[m], atol=1e-3)
    np.testing.assert_allclose(sig["lateral_load"][m], d.lateral_load[m], atol=1e-3)
    # kinematics: speed along the path (the code measures it on the ground plane: 0.5 % less
    # on a 10 % grade), its rate of change, turn rate, centripetal acceleration toward the left
    np.testing.assert_allclose(sig["speed"][m], d.speed[m], rtol=6e-3, atol=1e-3)
    np.testing.assert_allclose(sig["accel"][m], d.accel[m], atol=2e-3)
    np.testing.assert_allclose(sig["yaw_rate"][m], d.yaw_rate[m], atol=1e-3)
    a_left = np.einsum("ni,ni->n", d.R[:, :, 1], d.a_world)
    np.testing.assert_allclose(sig["lateral_accel"][m], a_left[m], atol=2e-3)
    np.testing.assert_allclose(sig["pitch"][m], d.pitch[m], atol=1e-9)
    np.testing.assert_allclose(sig["roll"][m], d.roll[m], atol=1e-9)


def test_signs_said_physically(signals):
    def mean(name, key):
        return float(signals[name].signals[key][DRIVES[name].interior()].mean())

    # the wheels must push harder climbing and accelerating than at constant speed on the flat
    assert mean("climb_10pct", "traction") > 0.09 and mean("accelerate", "traction") > 0.045
    assert mean("descend_10pct", "traction") < -0.09 and mean("brake", "traction") < -0.045
    # climbing 10 % at constant speed needs about twice the push of 0.5 m/s^2 on the flat
    assert mean("climb_10pct", "traction") == pytest.approx(2 * mean("accelerate", "traction"), rel=0.05)
    # the load moves to the right wheels: outer ones in a left turn, downhill ones on a left-high slope
    assert mean("turn_left", "lateral_load") > 0.04 and mean("side_slope_left_high", "lateral_load") > 0.09
    assert mean("turn_right", "lateral_load") < -0.04
    assert mean("turn_left", "yaw_rate") > 0 and mean("turn_left", "lateral_accel") > 0
    # ... which is what the module documents for lateral_load > 0
    assert "load shift to the right wheels when > 0" in covariates.__doc__


@pytest.mark.parametrize("name", sorted(HAND))
def test_catalogue_slip_sinkage_factor(robot, signals, name):
    d, drive = DRIVES[name], signals[name]
    m = d.interior()
    k = 4.0
    f = depth_factor(CATALOGUE["slip_sinkage"], drive, robot, drive.poses4[m], k, {})
    assert f.shape == (len(robot.wheels), int(m.sum()))
    # every wheel sinks by the same factor 1 + k * traction demand (in g)
    np.testing.assert_allclose(f, np.broadcast_to(1 + k * d.traction[m], f.shape), atol=k * 1e-3)


def test_catalogue_slip_sinkage_deeper_climbing_and_accelerating(robot, signals):
    def fac(name):
        drive = signals[name]
        return depth_factor(CATALOGUE["slip_sinkage"], drive, robot, drive.poses4[DRIVES[name].interior()], 4.0, {})

    assert (fac("climb_10pct") > 1.3).all() and (fac("accelerate") > 1.15).all()
    assert (fac("descend_10pct") < 0.7).all() and (fac("brake") < 0.85).all()
    assert np.allclose(fac("turn_left"), 1.0, atol=4e-3)


@pytest.mark.parametrize("name", sorted(HAND))
def test_catalogue_lateral_load_transfer_factor(robot, signals, name):
    d, drive = DRIVES[name], signals[name]
    m = d.interior()
    k = 2.0
    left, right = sides(robot)
    f = depth_factor(CATALOGUE["lateral_load_transfer"], drive, robot, drive.poses4[m], k, {})
    load = d.lateral_load[m]                      # > 0: load on the right wheels
    np.testing.assert_allclose(f[right], np.broadcast_to(1 + k * load, f[right].shape), atol=k * 1e-3)
    np.testing.assert_allclose(f[left], np.broadcast_to(1 - k * load, f[left].shape), atol=k * 1e-3)


@pytest.mark.parametrize("name, deeper", [("turn_left", "right"), ("turn_right", "left"),
                                          ("side_slope_left_high", "right"),
                                          ("side_slope_left_high_driving", "right")])
def test_catalogue_outer_and_downhill_wheels_sink_deeper(robot, signals, name, deeper):
    drive = signals[name]
    left, right = sides(robot)
    f = depth_factor(CATALOGUE["lateral_load_transfer"], drive, robot, drive.poses4[DRIVES[name].interior()],
                     2.0, {})
    heavy, light = (right, left) if deeper == "right" else (left, right)
    assert (f[heavy] > 1.05).all() and (f[light] < 0.95).all()
