"""The export of a hand-built run (tests/geo/handbuilt.py) read back by other readers: rasterio
for the GeoTIFF, geopandas for the GeoPackage, mcap-ros2-support for the GridMap MCAP; the
values are the run's arrays and the hand-placed windows, ruts and path."""

from __future__ import annotations

import math

import geopandas as gpd
import numpy as np
import pytest
import rasterio
import shapely
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from pyproj import Transformer

from tests.geo import handbuilt as hb
from torchsoil.geo.layers import layer_units, load_run
from torchsoil.jobs.export import export

LAT, LON = 47.3986, 8.5491


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    root = tmp_path_factory.mktemp("export")
    run = hb.write_run(root / "run")
    lines = export(run, root / "out", anchor=(LAT, LON, 90.0))   # map x due east
    return root / "run", root / "out", lines


def cell(i: int, j: int) -> np.ndarray:
    return np.array([-1.0 + i * hb.DX, -1.49 + j * hb.DX])


def test_the_geotiff_has_the_crs_pixel_size_bands_and_the_runs_arrays(exported):
    run_dir, out, lines = exported
    run = load_run(run_dir)
    with rasterio.open(out / "soil.tif") as src:
        assert src.crs.to_epsg() == 32632
        assert src.res[0] == pytest.approx(hb.DX, rel=1e-3) and src.res[1] == pytest.approx(hb.DX, rel=1e-3)
        assert list(src.descriptions) == list(layer_units(run))
        assert src.overviews(1)                          # tiled and overviewed: QGIS opens it at once
        assert src.profile["tiled"] and src.width == 300 and src.height == 150
        assert math.isnan(src.nodata)
        bands = {name: src.read(b + 1) for b, name in enumerate(src.descriptions)}
        assert src.tags(bands and list(src.descriptions).index("beta") + 1)["unit"] == "deg"
        T = src.transform
    # raster column c = cell i, row r = cell j counted from the top (largest y)
    for name, arr in (("h_front", run.pair.h_front), ("h_back", run.pair.h_back), ("h_sim", run.h_sim)):
        np.testing.assert_array_equal(bands[name], arr.T[::-1])
    # a pixel's centre lies where the cell centre lies on the Earth: anchored at the first
    # pose (0, 0), heading east, so 2 m along x is 2 m east on the same parallel
    i, j = 150, 74                                       # x = 2.0 m, y = -0.01 m
    e, n = T @ (i + 0.5, (150 - 1 - j) + 0.5)
    lon, lat = Transformer.from_crs("EPSG:32632", "EPSG:4326", always_xy=True).transform(e, n)
    assert (lat - LAT) * 111_200 == pytest.approx(-0.01, abs=0.005)
    assert (lon - LON) * 111_200 * math.cos(math.radians(LAT)) == pytest.approx(2.0, abs=0.01)


def test_window_values_are_painted_on_the_central_stride_of_their_ground(exported):
    run_dir, out, _ = exported
    with rasterio.open(out / "soil.tif") as src:
        bands = {name: src.read(b + 1)[::-1].T for b, name in enumerate(src.descriptions)}
    i = lambda x: round((x + 1.0) / hb.DX)                       # noqa: E731
    j = lambda y: round((y + 1.49) / hb.DX)                      # noqa: E731
    assert bands["d1"][i(0.76), j(0.25)] == pytest.approx(0.8 / 100)     # nearest centre 0.8
    assert bands["d1"][i(0.58), j(0.25)] == pytest.approx(0.4 / 100)     # nearest centre 0.4
    assert bands["beta"][i(2.0), j(-0.5)] == pytest.approx(22.0)
    assert np.isnan(bands["chi"][i(2.0), j(1.3)])                        # outside corridor / 2 = 1 m
    assert np.isnan(bands["d2"][i(4.9), j(0.0)])                         # beyond the last window's reach
    # validity: bit 0 measured, bit 1 fitted, bit 2 the fitting window flagged
    assert bands["validity"][i(2.0), j(0.0)] == 3
    assert bands["validity"][i(1.2), j(0.0)] == 7
    assert bands["validity"][0, 0] == 0
    assert bands["rut_depth"][i(2.0), j(0.25)] == pytest.approx(hb.RUT, abs=1e-6)
    assert np.isnan(bands["rut_depth"][i(2.0), j(0.9)])                  # far from any wheel
    assert bands["passes"][i(2.0), j(0.25)] == 2                        # front and rear wheel
    assert bands["passes"][i(2.0), j(0.0)] == 0


def test_the_geopackage_has_one_polygon_per_window_the_ruts_and_the_path(exported):
    _, out, _ = exported
    layers = gpd.list_layers(out / "soil.gpkg")["name"].tolist()
    assert set(layers) == {"windows", "ruts", "path"}
    win = gpd.read_file(out / "soil.gpkg", layer="windows")
    assert win.crs.to_epsg() == 32632 and len(win) == len(hb.CENTRES)
    np.testing.assert_allclose(win["d1"], np.array(hb.CENTRES) / 100)
    assert win.loc[np.isclose(win["s"], hb.FLAGGED), "flags"].item() == "few_valid"
    k = 0.9996
    assert win.geometry.area.to_numpy() == pytest.approx(0.8 * hb.CORRIDOR * k * k, rel=2e-3)
    tif = rasterio.open(out / "soil.tif")
    for s, poly in zip(win["s"], win.geometry, strict=True):     # the path point at s lies inside its window
        x = s
        e, n = tif.transform @ ((x + 1.0) / hb.DX + 0.5, 150 - (0.0 + 1.49) / hb.DX - 0.5)
        assert poly.contains(shapely.Point(e, n))
    ruts = gpd.read_file(out / "soil.gpkg", layer="ruts")
    assert set(ruts["track"]) == {0, 1}
    mid = ruts[(ruts["s_start"] > 0.5) & (ruts["s_end"] < 3.5)]
    np.testing.assert_allclose(mid["depth_m"], hb.RUT, atol=1e-6)
    path = gpd.read_file(out / "soil.gpkg", layer="path")
    np.testing.assert_allclose(path["speed_m_s"], 1.0, rtol=1e-6)
    assert path.geometry.length.sum() == pytest.approx(4.0 * k, rel=1e-3)


def test_the_gridmap_decodes_with_a_second_reader_to_the_runs_arrays(exported):
    run_dir, out, _ = exported
    run = load_run(run_dir)
    with open(next((out / "soil_gridmap").glob("*.mcap")), "rb") as f:
        msgs = [(s.name, m.log_time, d) for s, _, m, d in
                make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()]
    assert [n for n, _, _ in msgs] == ["grid_map_msgs/msg/GridMap"]
    _, t_ns, gm = msgs[0]
    X, Y = run.pair.h_front.shape
    assert gm.info.resolution == hb.DX and gm.info.length_x == pytest.approx(X * hb.DX)
    assert gm.info.pose.position.x == pytest.approx(-1.0 + (X - 1) * hb.DX / 2)
    assert gm.header.frame_id == "map" and gm.outer_start_index == gm.inner_start_index == 0
    assert {"h_front", "h_back", "h_delta", "rut_depth", "passes", "d1", "d2", "chi", "beta"} <= set(gm.layers)
    data = gm.data[gm.layers.index("h_back")]
    assert [d.label for d in data.layout.dim] == ["column_index", "row_index"]
    v = np.asarray(data.data)
    a = run.pair.h_back
    # grid_map: index (0, 0) at the largest x and y, column-major
    assert v[0] == a[X - 1, Y - 1] and v[1] == a[X - 2, Y - 1] and v[X] == a[X - 1, Y - 2]
    np.testing.assert_array_equal(v.reshape(Y, X).T[::-1, ::-1], a)


def test_without_gnss_or_anchor_the_maps_stay_local_and_say_so(tmp_path):
    run = hb.write_run(tmp_path / "run")
    lines = export(run, tmp_path / "out", formats=("geotiff", "gpkg"))
    assert any("local engineering frame" in ln for ln in lines)
    with rasterio.open(tmp_path / "out" / "soil.tif") as src:
        assert src.crs is None and "local" in src.tags()["crs_note"]
        assert src.transform.c == pytest.approx(-1.0 - hb.DX / 2)         # map metres as they are
    assert gpd.read_file(tmp_path / "out" / "soil.gpkg", layer="windows").crs is None
    assert not (tmp_path / "out" / "soil_gridmap").exists()
    assert (tmp_path / "out" / "preview.png").stat().st_size > 10_000


def test_a_geotiff_written_in_small_blocks_equals_the_whole(exported, tmp_path):
    """Block by block (bounded memory on a long drive) gives the bands of one whole block."""
    from torchsoil.geo.georef import from_anchor
    from torchsoil.geo.geotiff import write_geotiff
    from torchsoil.geo.layers import raster_layers

    run_dir, out, _ = exported
    run = load_run(run_dir)
    g = from_anchor(LAT, LON, 90.0, run.pair.poses[0])
    small = write_geotiff(tmp_path / "small.tif", run.grid, g, layer_units(run),
                          lambda *b: raster_layers(run, *b), block_cells=64)
    with rasterio.open(small) as a, rasterio.open(out / "soil.tif") as b:
        assert a.transform == b.transform
        np.testing.assert_array_equal(a.read(), b.read())
