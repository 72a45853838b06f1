"""The job behind `torchsoil export RUN --out DIR` (and `estimate --export`): a run's soil maps
where people look (docs/export.md).

DIR/soil.tif        Cloud-Optimized GeoTIFF, one band per layer (torchsoil.geo.geotiff)
DIR/soil.gpkg       GeoPackage: windows, window_visits, ruts, path (torchsoil.geo.vectors)
DIR/soil_gridmap/   rosbag2 (mcap) of grid_map_msgs/GridMap (torchsoil.geo.gridmap)
DIR/georef.json     how the map frame was tied to the Earth (torchsoil.geo.georef.Georef)
DIR/preview.png     the rut depth as a GIS shows it, with the windows and path (torchsoil.geo.preview)

The map frame is tied by, in this order: `anchor` (lat, lon, heading), the run's own
georef.json, the RTK fixes of the recording the run came from (or `bag`), else it stays a
local engineering frame, said in georef.json, the GeoTIFF's tags and the returned lines.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from torchsoil.geo.georef import Georef, GeorefError, fit_gnss, from_anchor
from torchsoil.geo.geotiff import read_block, write_geotiff
from torchsoil.geo.gridmap import write_gridmap_bag
from torchsoil.geo.layers import Run, layer_units, load_run, raster_layers
from torchsoil.geo.vectors import write_geopackage

FORMATS = ("geotiff", "gpkg", "mcap")
GRIDMAP_LAYERS = ("h_front", "h_back", "h_delta", "rut_depth", "passes")   # and the fitted parameters


def resolve_georef(run: Run, anchor: tuple[float, float, float] | None = None, bag: str | Path | None = None,
                   gnss_topic: str = "") -> tuple[Georef, list[str]]:
    """The run's Georef (module docstring) and what was said on the way (bad GNSS, no GNSS)."""
    notes: list[str] = []
    if anchor is not None:
        return from_anchor(*anchor, run.poses[0]), notes
    own = run.path / "georef.json" if run.path.is_dir() else None
    if own is not None and own.is_file() and bag is None:
        return Georef.load(own), notes
    bag = Path(bag) if bag is not None else run.bag
    if bag is None:
        return Georef.local("no recording to read GNSS from and no --anchor"), notes
    from torchsoil.io.gnss import read_fixes

    fixes = read_fixes(bag, gnss_topic)
    if fixes is None:
        return Georef.local(f"{bag} has no sensor_msgs/NavSatFix topic; give --anchor LAT,LON,HEADING_DEG"), notes
    notes += fixes.problems
    try:
        g = fit_gnss(run.poses[:, 0], run.poses, fixes)
    except GeorefError as e:
        notes.append(f"GNSS not used: {e}")
        return Georef.local(str(e)), notes
    return g, notes


def export(run_path: str | Path, out_dir: str | Path, anchor: tuple[float, float, float] | None = None,
           formats: tuple[str, ...] = FORMATS, bag: str | Path | None = None, gnss_topic: str = "",
           topic: str = "/soil/grid_map") -> list[str]:
    """Export the run at `run_path` (a run folder or terrain pair) into `out_dir`; returns lines
    saying what was written, how it was georeferenced and how long it took."""
    unknown = sorted(set(formats) - set(FORMATS))
    if unknown:
        raise ValueError(f"unknown export format(s) {unknown}; choose from {list(FORMATS)}")
    t0 = time.perf_counter()
    run = load_run(run_path)
    georef, notes = resolve_georef(run, anchor, bag, gnss_topic)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    georef.save(out / "georef.json")
    units = layer_units(run)

    def block(i0: int, i1: int, j0: int, j1: int) -> dict:   # a block at a time: memory set by the block
        return raster_layers(run, i0, i1, j0, j1)

    lines = [f"warning: {n}" for n in notes] + [f"georeference: {georef.note}"
                                                + (f" ({georef.crs})" if georef.crs else "")]
    written = []
    with tempfile.TemporaryDirectory(dir=out) as tmp:
        # the layers are computed once, block by block, into the GeoTIFF; the other formats read it back
        tif = out / "soil.tif" if "geotiff" in formats else Path(tmp) / "soil.tif"
        write_geotiff(tif, run.grid, georef, units, block, tags={"source": str(run.path)})
        if "geotiff" in formats:
            written.append(tif)
        if "gpkg" in formats:
            written.append(write_geopackage(out / "soil.gpkg", run, georef))
        if "geotiff" in formats:     # after the GeoPackage, whose windows and path it draws
            from torchsoil.geo.preview import preview

            written.append(preview(out))
        if "mcap" in formats:
            names = [n for n in (*GRIDMAP_LAYERS, *run.names) if n in units]
            written.append(write_gridmap_bag(out / "soil_gridmap", run.grid, names,
                                             lambda *b: read_block(tif, names, *b), run.poses, topic=topic))
    X, Y = run.grid.shape
    lines += [f"wrote {p}" for p in written]
    lines.append(f"exported {len(units)} layers of {X} x {Y} cells ({run.grid.dx:g} m) and "
                 f"{len(run.final_rows())} windows in {time.perf_counter() - t0:.1f} s")
    return lines
