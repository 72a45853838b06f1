"""The run's layers as a Cloud-Optimized GeoTIFF (rasterio / GDAL): one float32 band per layer,
band names and units in the band descriptions and tags, NaN nodata, the CRS and geotransform
of the run's Georef; written block by block, tiled, deflate-compressed, with overviews.

Raster layout: column c runs along map x (cell i = c), row r along map -y (cell j = Y - 1 - r),
so that a map frame with x east is north up. In a georeferenced frame the geotransform is
rotated by the map's yaw (GDAL's affine with rotation terms; QGIS and GDAL warp it on the fly).
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from torchsoil.geo.georef import Georef
from torchsoil.grid import Grid

BLOCK = 512     # cells per side of the blocks computed and written at a time
CACHE_MB = 64   # GDAL's block cache while writing (its default, 5 % of the machine's memory, grows with the file)


def write_geotiff(path: str | Path, grid: Grid, georef: Georef, units: dict[str, tuple[str, str]],
                  block: Callable[[int, int, int, int], dict[str, np.ndarray]], tags: dict | None = None,
                  block_cells: int = BLOCK) -> Path:
    """Write the COG `path`: bands `units` (name -> (unit, description)) in that order, each
    block of cells [i0:i1, j0:j1] from `block(i0, i1, j0, j1)` ({name: (i1-i0, j1-j0) array}).
    Returns path."""
    import rasterio
    from rasterio.shutil import copy as rio_copy
    from rasterio.transform import Affine

    path = Path(path)
    X, Y = grid.shape
    dx = grid.dx
    x0 = grid.origin[0] - dx / 2
    y_top = grid.origin[1] + (Y - 1) * dx + dx / 2
    profile = {"driver": "GTiff", "width": X, "height": Y, "count": len(units), "dtype": "float32",
               "nodata": np.nan, "transform": Affine(*georef.affine(x0, y_top, dx)), "tiled": True,
               "blockxsize": 256, "blockysize": 256, "compress": "deflate", "BIGTIFF": "IF_SAFER",
               "SPARSE_OK": "TRUE"}
    if georef.crs is not None:
        profile["crs"] = georef.crs
    names = list(units)
    with tempfile.TemporaryDirectory(dir=path.parent) as tmp, rasterio.Env(GDAL_CACHEMAX=CACHE_MB):
        staged = Path(tmp) / "staged.tif"
        with rasterio.open(staged, "w", **profile) as dst:
            for b, name in enumerate(names, 1):
                unit, text = units[name]
                dst.set_band_description(b, name)
                dst.update_tags(b, name=name, unit=unit, description=text)
            dst.units = tuple(units[n][0] for n in names)
            dst.update_tags(crs_note=georef.note, georef_kind=georef.kind, cell_m=f"{dx:g}",
                            layout="column = map x cell i; row = map -y (cell j = height - 1 - row)",
                            **{k: str(v) for k, v in (tags or {}).items()})
            for i0 in range(0, X, block_cells):
                for j0 in range(0, Y, block_cells):
                    i1, j1 = min(i0 + block_cells, X), min(j0 + block_cells, Y)
                    arrays = block(i0, i1, j0, j1)
                    if _empty(arrays):     # ground the drive never saw (a field's box): left sparse, nodata
                        continue
                    win = rasterio.windows.Window(i0, Y - j1, i1 - i0, j1 - j0)
                    for b, name in enumerate(names, 1):
                        dst.write(np.ascontiguousarray(arrays[name].T[::-1]).astype(np.float32), b, window=win)
        rio_copy(staged, path, driver="COG", COMPRESS="DEFLATE", PREDICTOR="3", BLOCKSIZE="256",
                 OVERVIEWS="AUTO", OVERVIEW_RESAMPLING="NEAREST", BIGTIFF="IF_SAFER", SPARSE_OK="TRUE")
    return path


def _empty(arrays: dict[str, np.ndarray]) -> bool:
    """No layer holds a finite non-zero value (NaN, or counts and bits of nothing)."""
    return not any(np.any(np.nan_to_num(a)) for a in arrays.values())


def read_block(path: str | Path, names: list[str], i0: int, i1: int, j0: int, j1: int) -> dict[str, np.ndarray]:
    """Bands `names` of cells [i0:i1, j0:j1] of an exported GeoTIFF, (i1-i0, j1-j0) float32 each,
    in the run's orientation (a block read back, for the other formats)."""
    import rasterio
    from rasterio.windows import Window

    with rasterio.open(path) as src:
        H = src.height
        bands = [list(src.descriptions).index(n) + 1 for n in names]
        data = src.read(bands, window=Window(i0, H - j1, i1 - i0, j1 - j0))
    return {n: np.ascontiguousarray(d[::-1].T) for n, d in zip(names, data, strict=True)}


def read_layer(path: str | Path, name: str) -> tuple[np.ndarray, tuple]:
    """A band of an exported GeoTIFF back on the run's grid, (X, Y) float32, and the raster's
    geotransform (a, b, c, d, e, f): for tests and readers that want the run's array."""
    import rasterio

    with rasterio.open(path) as src:
        X, Y, transform = src.width, src.height, tuple(src.transform)[:6]
    return read_block(path, [name], 0, X, 0, Y)[name], transform
