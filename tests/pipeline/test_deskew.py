"""De-skew: undoing a constant-velocity motion recovers the points of a rigid scene."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from torchsoil.pipeline.deskew import deskew, relative_motion


@pytest.mark.parametrize("rotvec", [(0, 0, 0), (0, 0, 0.05), (0.01, -0.02, 0.04)])
def test_recovers_static_scene(rotvec):
    rng = np.random.default_rng(1)
    world = rng.uniform(-10, 10, size=(500, 3))  # scene in the frame at time 0
    dt = 0.1
    motion = np.eye(4)
    motion[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    motion[:3, 3] = (0.1, 0.02, -0.01)
    t = rng.uniform(0, dt, len(world))
    # the sensor at time t sits at exp(t/dt log motion); it sees world points in its frame
    R = Rotation.from_rotvec((t / dt)[:, None] * np.asarray(rotvec)[None])
    trans = (t / dt)[:, None] * motion[:3, 3]
    seen = R.inv().apply(world - trans)
    np.testing.assert_allclose(deskew(seen, t, motion, dt), world, atol=1e-9)
    # without the correction the error is the motion itself (up to 10 cm here)
    assert np.abs(seen - world).max() > 0.05


def test_zero_motion_is_identity_and_bad_shapes_fail():
    p = np.arange(12.0).reshape(4, 3)
    np.testing.assert_allclose(deskew(p, np.zeros(4), np.eye(4), 0.1), p)
    with pytest.raises(ValueError, match="times"):
        deskew(p, np.zeros(3), np.eye(4), 0.1)
    with pytest.raises(ValueError, match="dt"):
        deskew(p, np.zeros(4), np.eye(4), 0.0)


def test_relative_motion_composes():
    A = np.eye(4)
    A[:3, 3] = (1, 2, 3)
    B = A.copy()
    B[:3, 3] = (2, 2, 3)
    np.testing.assert_allclose(A @ relative_motion(A, B), B)
