"""The run's vector features as a GeoPackage (geopandas / pyogrio): `windows` (one polygon per
window, its ground, with its parameters, costs and flags; `window_visits` adds one per visit
where ground was driven more than once), `ruts` (each track's wheel-path centreline in
segments, with the measured rut depth) and `path` (base_link's path in segments, with time
and speed). Geometry in the Georef's CRS (none when local), lengths in metres.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np

from torchsoil.geo.georef import Georef
from torchsoil.geo.layers import Run, rut_depth_at

RUT_STEP = 0.2    # m: the rut centrelines in segments of this length
PATH_STEP = 0.25  # m: the path likewise


def window_polygons(run: Run, rows: list[dict]) -> list:
    """A window's ground: base_link's path from s - window/2 to s + window/2, corridor / 2 on
    either side (flat ends), one shapely polygon per row, in the map frame."""
    import shapely
    from shapely.ops import substring

    line = _path_line(run)
    half = run.window / 2
    return [shapely.buffer(substring(line, r["s"] - half, r["s"] + half), run.corridor / 2, cap_style="flat")
            for r in rows]


def _path_line(run: Run):
    import shapely

    xy = run.poses[:, 1:3]
    keep = np.r_[True, np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-6]
    return shapely.LineString(xy[keep])


def track_lines(run: Run) -> dict[int, np.ndarray]:
    """Each track's centreline in the map, (M, 2) per track: the mean contact point of the
    track's wheels along the poses, m."""
    poses, wheels = run.poses, run.wheels
    out = {}
    c, s = np.cos(poses[:, 6]), np.sin(poses[:, 6])
    for track in np.unique(wheels[:, 2]).astype(int):
        wx, wy = wheels[wheels[:, 2] == track, :2].mean(0)
        out[track] = np.column_stack([poses[:, 1] + c * wx - s * wy, poses[:, 2] + s * wx + c * wy])
    return out


def _segments(xy: np.ndarray, step: float) -> list[tuple[int, int]]:
    """(start, end) pose indices of consecutive pieces about `step` m long along xy (M, 2)."""
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))]
    cuts = np.unique(np.searchsorted(arc, np.arange(0.0, arc[-1] + step, step)).clip(0, len(xy) - 1))
    return [(int(a), int(b)) for a, b in zip(cuts[:-1], cuts[1:], strict=True) if b > a]


def write_geopackage(path: str | Path, run: Run, georef: Georef) -> Path:
    """Write the GeoPackage `path` (module docstring); the rut depth, max(h_front - h_back, 0)
    [m], is sampled at the cells under each centreline. Returns path."""
    import geopandas as gpd
    import shapely

    path = Path(path)
    if path.exists():
        path.unlink()
    crs = georef.crs

    def to_crs(geoms):
        return [shapely.transform(g, georef.to_crs) for g in geoms]

    def write(name: str, records: list[dict], geoms: list) -> None:
        gdf = gpd.GeoDataFrame(records, geometry=to_crs(geoms), crs=crs)
        with warnings.catch_warnings():   # a local frame has no CRS, and georef.json says so
            warnings.filterwarnings("ignore", message="'crs' was not provided")
            gdf.to_file(path, layer=name, driver="GPKG", engine="pyogrio")

    rows = run.final_rows()
    if rows:
        cols = ["s", "visit", "passes_before", "t", *run.names, "rut_depth", "residual", "prediction", "map_offset",
                "iterations", "flags"]
        write("windows", [{c: r.get(c) for c in cols} for r in rows], window_polygons(run, rows))
        if len(run.rows) > len(rows):
            write("window_visits", [{c: r.get(c) for c in cols} for r in run.rows], window_polygons(run, run.rows))
    records, geoms = [], []
    for track, xy in track_lines(run).items():
        depth = rut_depth_at(run, xy)
        arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))]
        for a, b in _segments(xy, RUT_STEP):
            d = depth[a:b + 1]
            records.append({"track": track, "s_start": float(arc[a]), "s_end": float(arc[b]),
                            "depth_m": float(np.nanmedian(d)) if np.isfinite(d).any() else math.nan,
                            "t_start": float(run.poses[a, 0]), "t_end": float(run.poses[b, 0])})
            geoms.append(shapely.LineString(xy[a:b + 1]))
    write("ruts", records, geoms)
    poses = run.poses
    xy = poses[:, 1:3]
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))]
    records, geoms = [], []
    for a, b in _segments(xy, PATH_STEP):
        dt = poses[b, 0] - poses[a, 0]
        speed = float((arc[b] - arc[a]) / dt) if dt > 0 else math.nan
        records.append({"s_start": float(arc[a]), "s_end": float(arc[b]), "t_start": float(poses[a, 0]),
                        "t_end": float(poses[b, 0]), "speed_m_s": speed})
        geoms.append(shapely.LineString(xy[a:b + 1]))
    write("path", records, geoms)
    return path
