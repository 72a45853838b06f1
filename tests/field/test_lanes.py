"""Lanes from a boustrophedon drive built by hand: three rows 1.05 m apart joined by U-turns,
wheel tracks 1.05 m apart, so the rows share two ruts."""

import math

import numpy as np

from torchsoil.field.lanes import group_lanes, legs, track_mask, wheel_tracks


def _rows(n=3, length=8.0, spacing=1.05, r=0.525, ds=0.05, t0=0.0):
    pts, yaw = [], []
    for k in range(n):
        x = np.arange(0.0, length + 1e-9, ds)
        y = np.full_like(x, k * spacing)
        h = 0.0
        if k % 2:
            x, h = x[::-1], math.pi
        pts.append(np.c_[x, y])
        yaw.append(np.full(len(x), h))
        if k < n - 1:                                  # a half circle of radius r to the next row
            a = np.arange(ds / r, math.pi, ds / r)
            cx, cy = (length, k * spacing + r) if k % 2 == 0 else (0.0, k * spacing + r)
            sgn = 1 if k % 2 == 0 else -1
            pts.append(np.c_[cx + sgn * r * np.sin(a), cy - r * np.cos(a)])
            yaw.append(h + a * (1 if k % 2 == 0 else -1))
    p = np.vstack(pts)
    t = t0 + np.arange(len(p)) * ds
    return np.c_[t, p, np.zeros((len(p), 3)), np.concatenate(yaw)]


def test_rows_are_legs_and_neighbouring_rows_share_a_rut():
    poses = _rows()
    found = legs(poses, 0)
    assert len(found) == 3
    for k, leg in enumerate(found):
        assert abs(leg.length - 8.0) < 0.1 and abs(leg.start[1] - 1.05 * k) < 1e-9
    tracks = [t for leg in found for t in wheel_tracks(leg, np.array([-0.525, 0.525]))]
    lanes = group_lanes(tracks)
    assert len(lanes) == 4                     # 6 track lines: the middle two ruts each driven twice
    assert sorted(len(lane.legs) for lane in lanes) == [1, 1, 2, 2]
    ys = sorted(round(float(lane.legs[0].start[1]), 3) for lane in lanes)
    np.testing.assert_allclose(ys, [-0.525, 0.525, 1.575, 2.625])


def test_a_later_session_a_few_cm_aside_joins_the_lanes_and_the_mask_is_the_track():
    one = legs(_rows(), 0)
    two = legs(_rows(t0=1e5)[::-1] + np.r_[0, 0, 0.03, 0, 0, 0, 0], 1)      # driven backwards, 3 cm aside
    tracks = [t for leg in one + two for t in wheel_tracks(leg, np.array([-0.525, 0.525]))]
    lanes = group_lanes(tracks)
    assert len(lanes) == 4 and sorted(len(lane.legs) for lane in lanes) == [2, 2, 4, 4]
    xs, ys = np.arange(-1, 9, 0.02), np.arange(-1, 3.5, 0.02)
    m = track_mask(lanes[0], xs, ys, 0.1)
    cols = np.flatnonzero(m.any(0))
    assert abs(ys[cols].mean() - lanes[0].origin[1]) < 0.02 and np.ptp(ys[cols]) <= 0.2 + 1e-9
    rows = np.flatnonzero(m.any(1))
    assert xs[rows].min() >= 0.5 - 1e-9 and xs[rows].max() <= 7.5 + 1e-9
