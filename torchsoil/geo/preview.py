"""A look at an export as a GIS shows it: the GeoTIFF's rut depth warped north up in its CRS
(as QGIS and GDAL warp a rotated raster on the fly), the GeoPackage's windows and path drawn
over it, axes in easting and northing; read back from the files, so it shows what they hold."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

MAX_PIXELS = 900    # the warped image's longer side (about the figure's own pixels)


def preview(export_dir: str | Path, png: str | Path | None = None, band: str = "rut_depth") -> Path:
    """Draw `band` of export_dir/soil.tif with export_dir/soil.gpkg's windows and path into
    `png` (default export_dir/preview.png); returns its path."""
    import geopandas as gpd
    import rasterio
    from matplotlib.figure import Figure
    from rasterio.transform import Affine, from_origin
    from rasterio.warp import Resampling, reproject

    export_dir = Path(export_dir)
    png = Path(png) if png is not None else export_dir / "preview.png"
    with rasterio.open(export_dir / "soil.tif") as src:
        b = list(src.descriptions).index(band) + 1
        corners = np.array([src.transform * (c, r) for c, r in ((0, 0), (src.width, 0), (0, src.height),
                                                                (src.width, src.height))])
        (e0, n0), (e1, n1) = corners.min(0), corners.max(0)
        step = max((e1 - e0), (n1 - n0)) / MAX_PIXELS
        step = max(step, math.hypot(src.transform.a, src.transform.d))
        w, h = int(math.ceil((e1 - e0) / step)), int(math.ceil((n1 - n0) / step))
        if src.crs is None:       # a local frame: north up already (no rotation), only resampled
            img = src.read(b, out_shape=(h, w), resampling=Resampling.nearest)
        else:                     # decimated first (from the overviews), so memory is set by the picture
            f = max(1, math.ceil(max(src.width, src.height) / MAX_PIXELS))
            small = src.read(b, out_shape=(math.ceil(src.height / f), math.ceil(src.width / f)),
                             resampling=Resampling.nearest)
            at = src.transform * Affine.scale(src.width / small.shape[1], src.height / small.shape[0])
            img = np.full((h, w), np.nan, np.float32)
            reproject(small, img, src_transform=at, src_crs=src.crs, src_nodata=np.nan,
                      dst_transform=from_origin(e0, n1, step, step), dst_crs=src.crs, dst_nodata=np.nan,
                      resampling=Resampling.nearest)
        crs = src.crs
        unit = src.tags(b).get("unit", "")
    fig = Figure(figsize=(9, 9 * max(h / w, 0.3) + 1.0), layout="constrained")
    ax = fig.add_subplot()
    scale = 1000.0 if unit == "m" else 1.0
    finite = img[np.isfinite(img)] * scale
    lo, hi = (np.percentile(finite, [2, 98]) if finite.size else (0.0, 1.0))
    im = ax.imshow(img * scale, extent=(e0, e0 + w * step, n1 - h * step, n1), origin="upper", cmap="viridis",
                   vmin=lo, vmax=max(hi, lo + 1e-6))
    fig.colorbar(im, ax=ax, shrink=0.6, label=f"{band} [{'mm' if unit == 'm' else unit}]")
    gpkg = export_dir / "soil.gpkg"
    if gpkg.is_file():
        layers = set(gpd.list_layers(gpkg)["name"])
        if "windows" in layers:
            gpd.read_file(gpkg, layer="windows").boundary.plot(ax=ax, color="0.45", linewidth=0.4)
        if "path" in layers:
            gpd.read_file(gpkg, layer="path").plot(ax=ax, color="red", linewidth=1.0)
    where = f"{crs.to_string()}" if crs is not None else "local frame (not georeferenced)"
    ax.set_xlabel("easting [m]" if crs is not None else "map x [m]")
    ax.set_ylabel("northing [m]" if crs is not None else "map y [m]")
    ax.set_title(f"{band}, windows (grey) and path (red), {where}")
    ax.ticklabel_format(useOffset=False, style="plain")
    fig.savefig(png, dpi=110)
    return png
