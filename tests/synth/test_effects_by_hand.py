"""Pose-driven effects of the synthetic world against numbers worked out by hand.

The drives come from tests/drive_by_hand.py (attitude from a rotation matrix built on the
direction of travel and the ground normal). Expected factors:

- slip_sinkage: 1 + k * phi(traction demand), the demand in g being the forward specific
  force (a - g_vec) . x_body / g: > 0 climbing or accelerating (deeper ruts).
- lateral_load_transfer: the moment balance about the roll axis of a chassis with its centre
  of gravity h_cg above the ground and wheels `track` apart moves dN = m * f_left * h_cg / track
  of load onto the right wheels (f_left: leftward specific force, v^2/R in a left turn,
  g sin(roll) on a left-high slope); each side carries m g / 2 on the flat, so the right
  wheels' load changes by the fraction +2 h_cg f_left / (g track), the left ones' by minus
  that, and each wheel's sinkage by 1 + k * phi(that fraction): the outer / downhill wheels
  sink deeper.
"""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from tests.drive_by_hand import body_axes, catalogue
from torchsoil.robot import paper_platform
from torchsoil.synth import effects as fx
from torchsoil.synth.terrain import Relief
from torchsoil.synth.trajectory import chassis_attitude

DRIVES = catalogue()
NAMES = sorted(DRIVES)


@pytest.fixture(scope="module")
def robot():
    return paper_platform()


def pose_factor(effects, d, robot):
    """(K, N) factors of `effects` on drive d, fed with the hand-built kinematics and attitude."""
    track = float(np.ptp(robot.wheels[:, 1]))                     # 1.0 m on the paper's platform
    return fx.pose_depth_factor(fx.resolve(effects), d.speed, d.accel, d.pitch, d.roll, d.yaw_rate,
                                robot.wheels[:, 1], track)


def sides(robot):
    right = np.array(["right" in n for n in robot.names])
    left = np.array(["left" in n for n in robot.names])
    assert right.sum() == 2 and left.sum() == 2
    return left, right


@pytest.mark.parametrize("name", NAMES)
def test_slip_sinkage_linear(robot, name):
    d = DRIVES[name]
    k = 6.0
    f = pose_factor({"slip_sinkage": {"form": "linear", "k": k}}, d, robot)
    np.testing.assert_allclose(f, np.broadcast_to(1 + k * d.traction, f.shape), atol=k * 5e-4)


def test_slip_sinkage_numbers(robot):
    """The four traction cases with the numbers written out (k = 6, linear)."""
    eff = {"slip_sinkage": {"form": "linear", "k": 6.0}}
    expect = {"climb_10pct": 1 + 6 * 0.0995037,      # 1.597: sin(atan 0.1) of the weight along the slope
              "descend_10pct": 1 - 6 * 0.0995037,    # 0.403
              "accelerate": 1 + 6 * 0.5 / 9.80665,   # 1.306: 0.5 m/s^2 is 0.051 g
              "brake": 1 - 6 * 0.5 / 9.80665}        # 0.694
    for name, value in expect.items():
        f = pose_factor(eff, DRIVES[name], robot)
        np.testing.assert_allclose(f, value, atol=3e-3, err_msg=name)
    assert expect["climb_10pct"] > expect["accelerate"] > 1 > expect["brake"] > expect["descend_10pct"]


def test_slip_sinkage_saturating_keeps_the_sign(robot):
    k, xs = 6.0, 0.1
    eff = {"slip_sinkage": {"form": "saturating", "k": k, "x_s": xs}}
    climb = pose_factor(eff, DRIVES["climb_10pct"], robot)
    descend = pose_factor(eff, DRIVES["descend_10pct"], robot)
    x = math.sin(math.atan(0.1))
    np.testing.assert_allclose(climb, 1 + k * xs * math.tanh(x / xs), atol=3e-3)    # 1.456
    np.testing.assert_allclose(descend, 1 - k * xs * math.tanh(x / xs), atol=3e-3)
    assert climb.min() > 1.4 and descend.max() < 0.6


@pytest.mark.parametrize("name", NAMES)
def test_lateral_load_transfer_by_moment_balance(robot, name):
    d = DRIVES[name]
    k, h_cg, track = 1.5, 0.6, 1.0
    f = pose_factor({"lateral_load_transfer": {"form": "linear", "k": k, "h_cg": h_cg}}, d, robot)
    frac = 2 * h_cg * d.lateral_load / track      # load change of the right wheels, fraction of m g / 2
    left, right = sides(robot)
    np.testing.assert_allclose(f[right], np.broadcast_to(1 + k * frac, f[right].shape), atol=k * 5e-4)
    np.testing.assert_allclose(f[left], np.broadcast_to(1 - k * frac, f[left].shape), atol=k * 5e-4)


@pytest.mark.parametrize("name, deeper, value", [
    ("turn_left", "right", 1 + 1.5 * 2 * 0.6 * (1.5**2 / 5.0) / 9.80665),   # 1.083: outer wheels in a left turn
    ("turn_right", "left", 1 + 1.5 * 2 * 0.6 * (1.5**2 / 5.0) / 9.80665),
    ("side_slope_left_high", "right", 1 + 1.5 * 2 * 0.6 * math.sin(math.atan(0.1))),   # 1.179: downhill wheels
    ("side_slope_left_high_driving", "right", 1 + 1.5 * 2 * 0.6 * math.sin(math.atan(0.1))),
])
def test_outer_and_downhill_wheels_sink_deeper(robot, name, deeper, value):
    f = pose_factor({"lateral_load_transfer": {"form": "linear", "k": 1.5, "h_cg": 0.6}}, DRIVES[name], robot)
    left, right = sides(robot)
    heavy, light = (right, left) if deeper == "right" else (left, right)
    np.testing.assert_allclose(f[heavy], value, atol=1e-3)
    np.testing.assert_allclose(f[light], 2 - value, atol=1e-3)


def test_straight_flat_constant_speed_is_the_base_model(robot):
    d = DRIVES["accelerate"]._replace(accel=np.zeros_like(DRIVES["accelerate"].accel))
    f = pose_factor({"slip_sinkage": True, "lateral_load_transfer": True}, d, robot)
    np.testing.assert_array_equal(f, 1.0)


@pytest.mark.parametrize("slope_x, slope_y, yaw", [(0.1, 0.0, 0.0), (0.0, 0.1, 0.0), (0.08, -0.05, 2.3),
                                                    (-0.12, 0.07, -0.9)])
def test_world_attitude_on_a_plane_matches_a_rotation_built_from_the_ground(robot, slope_x, slope_y, yaw):
    """The synthetic trajectory's roll and pitch (which feed the effects) against scipy: body x
    along the heading, tangent to the plane; body z along the plane's normal."""
    relief = Relief(slope_x, slope_y, np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0))
    x, y, psi = np.array([0.3, 2.0]), np.array([-1.0, 0.5]), np.full(2, yaw)
    _, roll, pitch = chassis_attitude(x, y, psi, relief, robot)
    c, s = math.cos(yaw), math.sin(yaw)
    fwd = np.array([[c, s, slope_x * c + slope_y * s]])
    R = body_axes(fwd, np.array([-slope_x, -slope_y, 1.0]))
    r_ref, p_ref, y_ref = Rotation.from_matrix(R).as_euler("xyz")[0]
    np.testing.assert_allclose(roll, r_ref, atol=1e-12)
    np.testing.assert_allclose(pitch, p_ref, atol=1e-12)
    assert math.isclose(math.remainder(y_ref - yaw, 2 * math.pi), 0.0, abs_tol=1e-12)
    going_up = slope_x * c + slope_y * s > 0
    assert (pitch < 0).all() == going_up                               # nose up: negative pitch
