"""PointCloud2 decoding: any layout gives back exactly the points encoded."""

import itertools

import numpy as np
import pytest

from torchsoil.io.pointcloud import decode
from torchsoil.io.write import encode

ORDERS = list(itertools.permutations(("x", "y", "z", "t")))[::5]


def cloud(n=24, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, 3)).astype(np.float32), rng.integers(0, 10**8, n).astype(np.uint32)


@pytest.mark.parametrize("order", ORDERS)
@pytest.mark.parametrize("big_endian", [False, True])
@pytest.mark.parametrize("height, pad, row_pad", [(1, 0, 0), (4, 3, 0), (6, 1, 7)])
def test_any_layout_round_trips(order, big_endian, height, pad, row_pad):
    xyz, t = cloud()
    msg = encode(xyz, t, 12.25, "lidar_front", order=(*order, "ring", "intensity"),
                 pad=pad, row_pad=row_pad, big_endian=big_endian, height=height)
    c = decode(msg)
    np.testing.assert_array_equal(c.xyz, xyz)
    np.testing.assert_allclose(c.t, t * 1e-9, rtol=1e-6)
    assert c.stamp == pytest.approx(12.25) and c.frame == "lidar_front" and c.n_raw == len(xyz)


def test_no_return_points_are_dropped():
    xyz, t = cloud()
    xyz[3] = np.nan
    xyz[5] = 0.0
    xyz[7, 1] = np.inf
    c = decode(encode(xyz, t, 0.0, "f"))
    keep = np.setdiff1d(np.arange(len(xyz)), [3, 5, 7])
    np.testing.assert_array_equal(c.xyz, xyz[keep])
    assert c.n_raw == len(xyz)


def test_empty_cloud_decodes_to_nothing():
    c = decode(encode(np.zeros((0, 3)), np.zeros(0, np.uint32), 1.0, "f"))
    assert c.xyz.shape == (0, 3) and c.t.shape == (0,)


def test_missing_field_and_truncated_data_are_named():
    xyz, t = cloud()
    msg = encode(xyz, t, 0.0, "f", order=("x", "y", "t"))
    with pytest.raises(ValueError, match="'z'"):
        decode(msg)
    msg = encode(xyz, t, 0.0, "f")
    msg.data = msg.data[: len(msg.data) // 2]
    with pytest.raises(ValueError, match="truncated"):
        decode(msg)
