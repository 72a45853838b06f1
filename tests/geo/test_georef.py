"""Tying the map frame to UTM: a known transform recovered from RTK fixes made with pyproj
directly (the antenna placed by hand), bad fixes left out or refused with a reason, the
anchor and the UTM zones checked against the projection's own conventions."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pyproj import Proj, Transformer

from torchsoil.geo.georef import Georef, GeorefError, fit_gnss, from_anchor, utm_epsg
from torchsoil.io.gnss import Fixes

EPSG = 32632
E0, N0, YAW, UP = 466_000.0, 5_250_000.0, 1.1, 452.0
ANTENNA = np.array([-0.25, 0.1, 0.9])
T0 = 1.75e9


def drive(n: int = 201) -> np.ndarray:
    """A curving drive in the map, (n, 7) rows t, x, y, z, roll, pitch, yaw (20 s at 10 Hz)."""
    t = np.linspace(0.0, 20.0, n)
    x, y = 0.5 * t, 0.02 * t**2
    yaw = np.arctan2(0.04 * t, 0.5)
    return np.column_stack([T0 + t, x, y, 0.01 * t, np.zeros(n), np.zeros(n), yaw])


def truth_k() -> float:
    lon, lat = Transformer.from_crs(f"EPSG:{EPSG}", "EPSG:4326", always_xy=True).transform(E0, N0)
    return Proj(f"EPSG:{EPSG}").get_factors(lon, lat).meridional_scale


def fixes_along(rows: np.ndarray, sigma: float = 0.01, seed: int = 0, status: int = 2) -> Fixes:
    """RTK fixes of the antenna on `rows`, placed by hand: base_link + R(yaw) antenna, mapped to
    UTM by (E0, N0) + k R(YAW) (x, y), to lat/lon by pyproj."""
    rng = np.random.default_rng(seed)
    c, s = np.cos(rows[:, 6]), np.sin(rows[:, 6])
    ax = rows[:, 1] + c * ANTENNA[0] - s * ANTENNA[1]
    ay = rows[:, 2] + s * ANTENNA[0] + c * ANTENNA[1]
    k = truth_k()
    e = E0 + k * (math.cos(YAW) * ax - math.sin(YAW) * ay) + rng.normal(0, sigma, len(rows))
    n = N0 + k * (math.sin(YAW) * ax + math.cos(YAW) * ay) + rng.normal(0, sigma, len(rows))
    lon, lat = Transformer.from_crs(f"EPSG:{EPSG}", "EPSG:4326", always_xy=True).transform(e, n)
    m = len(rows)
    cov = np.zeros((m, 3, 3))
    cov[:, 0, 0] = cov[:, 1, 1] = sigma**2
    cov[:, 2, 2] = (2 * sigma) ** 2
    return Fixes(rows[:, 0].copy(), np.asarray(lat), np.asarray(lon), UP + rows[:, 3] + ANTENNA[2],
                 cov, np.full(m, 2), np.full(m, status), "gnss_link", ANTENNA, "/gnss/fix", [])


def test_a_known_transform_is_recovered_from_rtk_fixes():
    rows = drive()
    g = fit_gnss(rows[:, 0], rows, fixes_along(rows))
    assert g.kind == "gnss" and g.epsg == EPSG
    assert abs(math.degrees(g.yaw - YAW)) < 0.02
    assert abs(g.east - E0) < 0.005 and abs(g.north - N0) < 0.005
    assert abs(g.up - UP) < 0.01
    assert g.scale == pytest.approx(truth_k(), abs=1e-6)
    assert 0.007 < g.fit["residual_rms_m"] < 0.02        # sqrt(2) x 1 cm of noise
    assert g.fit["outliers"] == 0 and g.fit["used"] == len(rows)


def test_a_2m_jump_and_float_fixes_are_left_out():
    rows = drive()
    fx = fixes_along(rows)
    jump = slice(60, 90)                       # 3 s of fixes 2 m off, still claiming RTK
    e, n = Transformer.from_crs("EPSG:4326", f"EPSG:{EPSG}", always_xy=True).transform(fx.lon[jump], fx.lat[jump])
    fx.lon[jump], fx.lat[jump] = Transformer.from_crs(f"EPSG:{EPSG}", "EPSG:4326", always_xy=True).transform(
        np.asarray(e) + 2.0, n)
    floating = slice(120, 160)                 # a float solution: 40 cm, and saying so
    fx.cov[floating, 0, 0] = fx.cov[floating, 1, 1] = 0.4**2
    fx.lat[floating] += 0.3 / 111_000
    g = fit_gnss(rows[:, 0], rows, fx)
    assert g.fit["outliers"] == 30
    assert g.fit["rtk"] == len(rows) - 40
    assert abs(g.east - E0) < 0.005 and abs(g.north - N0) < 0.005 and abs(math.degrees(g.yaw - YAW)) < 0.02


@pytest.mark.parametrize("case, says", [
    ("float_only", "RTK-fixed"), ("no_fix", "no fix"), ("standing", "heading cannot"), ("other_time", "within"),
])
def test_fixes_that_cannot_tie_the_map_are_refused_with_a_reason(case, says):
    rows = drive()
    fx = fixes_along(rows)
    if case == "float_only":
        fx.cov[:, 0, 0] = fx.cov[:, 1, 1] = 0.3**2
    elif case == "no_fix":
        fx.status[:] = -1
    elif case == "standing":
        rows[:, 1:3] = rows[0, 1:3] + 0.001 * np.arange(len(rows))[:, None]
        rows[:, 6] = 0.0
        fx = fixes_along(rows)
    elif case == "other_time":
        fx.t += 100.0
    with pytest.raises(GeorefError, match=says):
        fit_gnss(rows[:, 0], rows, fx)


@pytest.mark.parametrize("lat, lon, epsg", [
    (47.4, 8.55, 32632), (-33.87, 151.21, 32756), (40.0, -105.0, 32613), (0.0, 180.0, 32660),
    (60.39, 5.32, 32632),                                           # Bergen: 32V, Norway's exception to 31
    (78.2, 15.6, 32633), (78.2, 8.0, 32631), (79.0, 25.0, 32635),   # Svalbard: 31X, 33X, 35X
])
def test_utm_zones_follow_the_grid_and_its_exceptions(lat, lon, epsg):
    assert utm_epsg(lat, lon) == epsg


def test_a_place_outside_utm_is_refused():
    with pytest.raises(GeorefError, match="outside UTM"):
        utm_epsg(86.0, 10.0)


@pytest.mark.parametrize("heading, moves", [(0.0, "north"), (90.0, "east")])
def test_an_anchor_places_the_first_pose_and_its_heading(heading, moves):
    lat0, lon0 = 47.3986, 8.5491
    first = np.array([0.0, 3.0, -2.0, 0.0, 0.0, 0.0, 0.4])
    g = from_anchor(lat0, lon0, heading, first)
    inv = Transformer.from_crs(f"EPSG:{g.epsg}", "EPSG:4326", always_xy=True)
    lon, lat = inv.transform(*g.to_crs(first[1:3]))
    assert lat == pytest.approx(lat0, abs=1e-9) and lon == pytest.approx(lon0, abs=1e-9)
    ahead = first[1:3] + 50.0 * np.array([math.cos(0.4), math.sin(0.4)])   # 50 m along the robot's x
    lon1, lat1 = inv.transform(*g.to_crs(ahead))
    dlat_m, dlon_m = (lat1 - lat0) * 111_200, (lon1 - lon0) * 111_200 * math.cos(math.radians(lat0))
    if moves == "north":                      # along the meridian: true north, not grid north
        assert dlat_m == pytest.approx(50.0, abs=0.1) and abs(dlon_m) < 0.01
    else:
        assert dlon_m == pytest.approx(50.0, abs=0.2) and abs(dlat_m) < 0.01


def test_the_geotransform_puts_each_pixel_centre_on_its_cell():
    g = Georef("gnss", EPSG, 0.7, E0, N0, 0.9996)
    dx, x0, y_top = 0.02, -1.01, 2.01
    a, b, c, d, e, f = g.affine(x0, y_top, dx)
    col, row = 17, 40                          # cell centre x = x0 + (col + 0.5) dx, y = y_top - (row + 0.5) dx
    want = g.to_crs(np.array([x0 + (col + 0.5) * dx, y_top - (row + 0.5) * dx]))
    np.testing.assert_allclose([a * (col + 0.5) + b * (row + 0.5) + c, d * (col + 0.5) + e * (row + 0.5) + f], want,
                               atol=1e-9)
    assert math.hypot(a, d) == pytest.approx(0.9996 * dx)


def test_a_saved_georef_reads_back(tmp_path):
    g = Georef("gnss", EPSG, 0.7, E0, N0, 0.9996, UP, "n", {"used": 3})
    assert Georef.load(g.save(tmp_path / "georef.json")) == g


def test_an_antenna_missing_from_tf_is_fitted_where_the_drive_turns():
    rows = drive()                                          # turns by about 58 deg
    fx = fixes_along(rows)
    fx.antenna, fx.antenna_known = np.zeros(3), False
    g = fit_gnss(rows[:, 0], rows, fx)
    np.testing.assert_allclose(g.fit["antenna_m"][:2], ANTENNA[:2], atol=0.01)
    assert abs(g.east - E0) < 0.01 and abs(g.north - N0) < 0.01 and abs(math.degrees(g.yaw - YAW)) < 0.05
    straight = rows.copy()
    straight[:, 2], straight[:, 6] = 0.0, 0.0
    fx = fixes_along(straight)
    fx.antenna, fx.antenna_known = np.zeros(3), False
    assert "too little" in fit_gnss(straight[:, 0], straight, fx).note
