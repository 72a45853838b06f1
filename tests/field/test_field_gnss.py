"""A session tied to UTM by GNSS: placed by the fixes, refused when the fit disagrees with them."""

import math

import numpy as np
import pytest

from tests.field.sessions import World, planar
from torchsoil.field.register import transform_error
from torchsoil.field.store import Field, Refused, Session
from torchsoil.geo.georef import Georef

T_A = planar(math.radians(10.0), 0.5, 0.2, 0.0)
T_B = T_A @ planar(math.pi, 7.0, 0.03, -0.1)
FIT = {"residual_rms_m": 0.01, "yaw_sd_deg": 0.02}


def _georefs(rel: np.ndarray, yaw_error_deg: float = 0.0):
    """The field's (session A's) tie to UTM and session B's, consistent with B -> A = rel: from
    E = k R(yaw) xy + e, B's points x_A = M x_B + m give yaw_B = yaw_A + yaw(M), e_B = R_A m + e_A."""
    a = Georef("gnss", 32633, 0.3, 500000.0, 5.0e6, 1.0, 100.0, "test", FIT)
    m = rel[:2, 3]
    R = np.array([[math.cos(a.yaw), -math.sin(a.yaw)], [math.sin(a.yaw), math.cos(a.yaw)]])
    e = R @ m + [a.east, a.north]
    yaw = a.yaw + math.atan2(rel[1, 0], rel[0, 0]) + math.radians(yaw_error_deg)
    return a, Georef("gnss", 32633, yaw, float(e[0]), float(e[1]), 1.0, 100.0 + rel[2, 3], "test", FIT)


@pytest.mark.parametrize("yaw_error_deg", [0.0, 1.0])
def test_gnss_places_the_session_and_checks_the_fit(tmp_path, yaw_error_deg):
    world = World(seed=2)
    a, _ = world.drive(T_A, 7.0, t0=0.0)
    b, _ = world.drive(T_B, 7.0, t0=1e5)
    rel = np.linalg.inv(T_A) @ T_B
    ga, gb = _georefs(rel, yaw_error_deg)
    f = Field.open(tmp_path / "f", create=True)
    f.add(Session(a, None, ga, "a", "a", "a"), log=lambda s: None)
    assert f.manifest["georef"]["epsg"] == 32633
    if yaw_error_deg:       # the fixes say 1 deg (12 cm at 7 m) off the ground's fit
        with pytest.raises(Refused, match="disagrees with GNSS"):
            f.add(Session(b, None, gb, "b", "b", "b"), log=lambda s: None)
        assert len(Field.open(tmp_path / "f").sessions) == 1
        return
    entry = f.add(Session(b, None, gb, "b", "b", "b"), log=lambda s: None)
    assert entry["registration"]["method"] == "gnss+heights"
    assert entry["registration"]["ambiguity"] == 0.0                    # no search was needed
    err = transform_error(np.array(entry["transform"]), rel, np.c_[b.poses[:, 1:3], np.zeros(len(b.poses))])
    assert err[0] < 0.01 and err[1] < 0.1
    assert entry["registration"]["gnss_m"] < 0.01
