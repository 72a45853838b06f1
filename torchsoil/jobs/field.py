"""The jobs behind `torchsoil field`: add a session to a field store, say what a field holds,
draw its season, estimate every session with passes counted over the season
(torchsoil.field.store; docs/field.md)."""

from __future__ import annotations

import csv
import shutil
import sys
from pathlib import Path

import numpy as np

from torchsoil.field.store import Field, FieldError, Session
from torchsoil.io.terrain_pair import TerrainPair
from torchsoil.jobs.provenance import input_identity


def load_session(recording: str | Path, work: Path, robot=None, settings=None, extrinsics=None,
                 gnss_topic: str = "", name: str | None = None) -> Session:
    """What a session brings (store.Session) from: a `process-bag` folder (terrain.npz, with
    map.npz and georef.json when there), a terrain-pair .npz (registered by its ground alone),
    or a recording (ROS 2 bag directory, ROS 1 .bag), put through the lidar pipeline into `work`
    (resumable) with its RTK fixes, when it has them, tying it to UTM."""
    path = Path(recording)
    if not path.exists():
        raise FileNotFoundError(f"recording not found: {path}")
    key = input_identity(path)["key"]
    name = name or path.stem
    georef, bag = None, None
    if path.suffix == ".npz":
        return Session(TerrainPair.load(path), None, None, name, str(path), key)
    if path.is_dir() and (path / "terrain.npz").is_file():
        folder = path
    else:
        if robot is None:
            raise ValueError(f"{path}: a recording needs a robot description (--robot NAME or PATH)")
        from torchsoil.jobs.process_bag import process_bag_job
        from torchsoil.settings import Settings

        folder, bag = work / "pipeline", path
        print(process_bag_job(path, folder, settings or Settings(), robot, extrinsics=extrinsics,
                              resume=(folder / "checkpoint").exists()), file=sys.stderr)
    pair = TerrainPair.load(folder / "terrain.npz")
    points = None
    if (folder / "map.npz").is_file():
        with np.load(folder / "map.npz") as d:
            points = d["points"].astype(np.float64)
    if (folder / "georef.json").is_file():
        from torchsoil.geo.georef import Georef

        georef = Georef.load(folder / "georef.json")
    elif bag is not None:
        georef = _bag_georef(bag, pair, gnss_topic)
    return Session(pair, points, georef, name, str(path), key)


def _bag_georef(bag: Path, pair: TerrainPair, topic: str):
    """The recording's tie to UTM by its RTK fixes, or None (said on stderr)."""
    from torchsoil.geo.georef import GeorefError, fit_gnss
    from torchsoil.io.gnss import read_fixes

    fixes = read_fixes(bag, topic)
    if fixes is None:
        return None
    try:
        return fit_gnss(pair.poses[:, 0], pair.poses, fixes)
    except GeorefError as e:
        print(f"warning: GNSS not used: {e}", file=sys.stderr)
        return None


def field_add(field: str | Path, recording: str | Path, robot=None, settings=None, extrinsics=None,
              gnss_topic: str = "", name: str | None = None) -> list[str]:
    """Add a recording to the field store at `field` (made when missing); lines saying what was
    registered and merged. store.Refused when it is not merged (the field unchanged)."""
    field = Path(field)
    work = field / ".incoming" / (name or Path(recording).stem)
    try:
        session = load_session(recording, work, robot, settings, extrinsics, gnss_topic, name)
        f = Field.open(field, create=True)
        lines: list[str] = []
        entry = f.add(session, log=lines.append)
    except FieldError:
        shutil.rmtree(work, ignore_errors=True)
        raise
    shutil.rmtree(work, ignore_errors=True)
    if field.joinpath(".incoming").is_dir() and not any(field.joinpath(".incoming").iterdir()):
        field.joinpath(".incoming").rmdir()
    return [*lines, f"added {entry['id']} to {field}: {entry['cells']} cells driven, {entry['passes']} wheel passes; "
            f"the field holds {len(f.sessions)} session(s)"]


def field_info(field: str | Path) -> str:
    """A table of the field's sessions: times, registration, cells and passes."""
    f = Field.open(field)
    rows = ["| session | source | start [s] | length [s] | registration | overlap | RMS [mm] | GNSS [cm / deg] "
            "| cells | passes |", "|---|---|---|---|---|---|---|---|---|---|"]
    for s in f.sessions:
        r = s["registration"]
        g = "-" if r.get("gnss_m") is None else f"{100 * r['gnss_m']:.1f} / {r['gnss_deg']:.2f}"
        rows.append(f"| {s['id']} | {s['source']} | {s['t0']:.1f} | {s['t1'] - s['t0']:.1f} | {r['method']} | "
                    f"{100 * r['overlap']:.0f} % | {1000 * r['rmse_m']:.1f} | {g} | {s['cells']} | {s['passes']} |")
    geo = f.manifest.get("georef")
    frame = (f"field frame: {f.sessions[0]['id']}'s map frame" if f.sessions else "empty field") + (
        f", tied to {geo.get('epsg') and 'EPSG:' + str(geo['epsg'])}" if geo else ", local (no GNSS)")
    return f"{f.path}: {len(f.sessions)} session(s), cells {f.dx} m; {frame}\n\n" + "\n".join(rows)


def field_maps(field: str | Path, out: str | Path) -> list[Path]:
    """season.npz (the season's layers on the field grid) and season.png: wheel passes per cell
    over the season, cumulative rut depth (first surface minus latest, m), sessions per cell;
    lanes.csv / lanes.md (`lane_table`) and multipass.png (rut depth against passes per lane,
    a point per session); season.tif, the same layers for GIS (`season_geotiff`)."""
    from matplotlib.figure import Figure

    from torchsoil.plotting import coarse

    f = Field.open(field)
    grid, layers = f.season_grid()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    depth = layers["first"] - layers["latest"]
    np.savez_compressed(out / "season.npz", dx=grid.dx, origin=np.array(grid.origin), rut_depth=depth,
                        **{k: v for k, v in layers.items()})
    used = np.flatnonzero((layers["visits"] > 0).any(1)), np.flatnonzero((layers["visits"] > 0).any(0))
    i0, i1, j0, j1 = used[0].min(), used[0].max() + 1, used[1].min(), used[1].max() + 1
    ext = (grid.origin[1] + j0 * grid.dx, grid.origin[1] + j1 * grid.dx,
           grid.origin[0] + i0 * grid.dx, grid.origin[0] + i1 * grid.dx)
    fig = Figure(figsize=(13, 6))
    axes = fig.subplots(1, 3)
    lim = float(np.nanpercentile(np.abs(depth), 99)) if np.isfinite(depth).any() else 0.01
    for ax, (title, img, kw) in zip(axes, (
            ("wheel passes over the season", layers["passes"].astype(float), {"cmap": "magma"}),
            ("cumulative rut depth [m]", depth, {"cmap": "RdBu", "vmin": -lim, "vmax": lim}),
            ("sessions that drove the cell", layers["sessions"].astype(float), {"cmap": "viridis"})), strict=True):
        sub, k = coarse(img[i0:i1, j0:j1])
        im = ax.imshow(sub, origin="lower", extent=ext, aspect="equal", **kw)
        for s in f.sessions:
            p = np.loadtxt(f.path / "sessions" / s["id"] / "trajectory.csv", delimiter=",", skiprows=1, ndmin=2)
            ax.plot(p[:, 2], p[:, 1], lw=0.6, label=s["id"])
        ax.set_title(title)
        ax.set_xlabel("field y [m]")
        ax.set_ylabel("field x [m]")
        fig.colorbar(im, ax=ax, shrink=0.7)
    axes[0].legend(fontsize=6)
    fig.savefig(out / "season.png", dpi=120, bbox_inches="tight")
    rows = lane_table(field)
    with open(out / "lanes.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, ["lane", "session", "cells", "passes_before", "passes", "rut_depth_mm"])
        w.writeheader()
        w.writerows(rows)
    (out / "lanes.md").write_text(lane_markdown(rows) + "\n")
    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    for lane in sorted({r["lane"] for r in rows}):
        rs = [r for r in rows if r["lane"] == lane]
        ax.plot([0] + [r["passes_before"] + r["passes"] for r in rs], [0] + [r["rut_depth_mm"] for r in rs], "o-",
                label=f"lane {lane}")
        for r in rs:
            ax.annotate(r["session"].split("_")[0], (r["passes_before"] + r["passes"], r["rut_depth_mm"]), fontsize=6)
    ax.set_xlabel("wheel passes over the season (after the session)")
    ax.set_ylabel("cumulative rut depth [mm]")
    ax.set_title("multi-pass curve per lane, a point per session")
    if rows:
        ax.legend(fontsize=6)
    fig.savefig(out / "multipass.png", dpi=120, bbox_inches="tight")
    tif = season_geotiff(f, grid, out / "season.tif")
    return [out / "season.npz", tif, out / "season.png", out / "lanes.csv", out / "lanes.md", out / "multipass.png"]


SEASON_BANDS = {"passes": ("1", "wheel passes over the season"),
                "rut_depth": ("m", "cumulative rut depth: the season's first surface less its latest"),
                "sessions": ("1", "sessions that drove the cell"),
                "first": ("m", "surface before the season's first visit (field frame z)"),
                "latest": ("m", "surface after the season's last visit (field frame z)")}


def season_geotiff(f: Field, grid, path: Path) -> Path:
    """season.tif: the season's layers (SEASON_BANDS) as a Cloud-Optimized GeoTIFF in the field's
    frame, tied to UTM when the field's first session was (else its local frame, said in the
    tags), read tile by tile from the store."""
    from torchsoil.geo.georef import Georef
    from torchsoil.geo.geotiff import write_geotiff

    g = f.manifest.get("georef")
    georef = Georef(**g) if g else Georef.local("the field's frame: its first session's map frame")
    o = np.rint(np.asarray(grid.origin) / f.dx).astype(int)

    def block(i0, i1, j0, j1):
        box = (o[0] + i0, o[0] + i1, o[1] + j0, o[1] + j1)
        first, latest = f.read("first", box), f.read("latest", box)
        seen = f.read("visits", box) > 0
        nan = lambda a: np.where(seen, a, np.nan).astype(np.float32)  # noqa: E731
        return {"passes": nan(f.read("passes", box)), "rut_depth": nan(first - latest),
                "sessions": nan(f.read("sessions", box)), "first": first.astype(np.float32),
                "latest": latest.astype(np.float32)}

    return write_geotiff(path, grid, georef, SEASON_BANDS, block, tags={"source": str(f.path)})


def lane_table(field: str | Path, min_cells: int = 50) -> list[dict]:
    """The season's multi-pass table: per lane (a wheel track of straight legs, shared by the rows
    and sessions whose wheels ran on it: field.lanes) and per session that drove it, the wheel
    passes its track cells had before and after the session (median) and the cumulative rut
    depth after it (the season's first surface less the session's after surface, median, m)."""
    from torchsoil.field import lanes as ln

    f = Field.open(field)
    tracks = []
    for k, s in enumerate(f.sessions):
        poses = np.loadtxt(f.path / "sessions" / s["id"] / "trajectory.csv", delimiter=",", skiprows=1, ndmin=2)
        with np.load(f.path / "sessions" / s["id"] / "terrain.npz") as d:
            offsets, width = np.unique(np.round(d["wheels"][:, 1], 4)), float(d["wheel_width"])
        for leg in ln.legs(poses, k):
            tracks += ln.wheel_tracks(leg, offsets)
    rows = []
    dx = f.dx
    for n, lane in enumerate(ln.group_lanes(tracks), start=1):
        pts = np.array([p for g in lane.legs for p in (g.start, g.end)])
        lo = np.floor((pts.min(0) - width) / dx).astype(int)
        hi = np.ceil((pts.max(0) + width) / dx).astype(int) + 1
        box = (lo[0], hi[0], lo[1], hi[1])
        xs, ys = np.arange(lo[0], hi[0]) * dx, np.arange(lo[1], hi[1]) * dx
        mask = ln.track_mask(lane, xs, ys, width / 2)
        first = f.read("first", box)
        total = np.zeros(mask.shape, np.int64)            # wheel passes of the sessions so far
        on_lane = {g.session for g in lane.legs}
        for k, s in enumerate(f.sessions):
            passes = f.read("passes", box, s["id"])
            before, total = total, total + passes
            drove = mask & (passes > 0)
            if k not in on_lane or drove.sum() < min_cells:
                continue
            depth = first - f.read("after", box, s["id"])
            rows.append({"lane": n, "session": s["id"], "cells": int(drove.sum()),
                         "passes_before": float(np.median(before[drove])), "passes": float(np.median(passes[drove])),
                         "rut_depth_mm": float(1000 * np.nanmedian(depth[drove]))})
    return rows


def lane_markdown(rows: list[dict]) -> str:
    out = ["| lane | session | cells | passes before | passes | rut depth after [mm] |", "|---|---|---|---|---|---|"]
    out += [f"| {r['lane']} | {r['session']} | {r['cells']} | {r['passes_before']:.0f} | {r['passes']:.0f} | "
            f"{r['rut_depth_mm']:.1f} |" for r in rows]
    return "\n".join(out)


def field_pair(field: str | Path, session: str, out: str | Path) -> Path:
    """Write a session's terrain pair (its own frame) with `passes_prior`, the wheel passes its
    cells had in the field's earlier sessions: any command (estimate, diagnose, export) then
    counts passes over the season."""
    return Field.open(field).session_pair(session).save(out)


def field_diagnose(field: str | Path, out: str | Path, sessions: list[str] | None = None, settings=None,
                   robot=None, workers: int | None = 1) -> list[str]:
    """`diagnose` on sessions of the field (default: every one after the first), each on its
    pair with the passes of the earlier sessions (`field_pair`), into OUT/ID/; lines with each
    verdict."""
    from torchsoil.jobs.diagnose import diagnose_input

    f = Field.open(field)
    ids = [f.session(s)["id"] for s in sessions] if sessions else [s["id"] for s in f.sessions[1:] or f.sessions]
    out = Path(out)
    lines = []
    for sid in ids:
        pair_path = field_pair(field, sid, out / "pairs" / f"{sid}.npz")
        d = diagnose_input(pair_path, out / sid, settings, robot, tensorboard=False,
                           resume=(out / sid / "run.json").exists(), workers=workers)
        lines.append(f"{sid}: {d['verdict']}" + (f" ({d['missing_physics']})" if d.get("missing_physics") else "")
                     + f" -> {out / sid}")
    return lines


def field_estimate(field: str | Path, out: str | Path, settings=None, robot=None, threads: int = 1,
                   tensorboard: bool = False) -> list[str]:
    """`estimate` on every session of the field, each on its own pair with the wheel passes its
    ground had in the earlier sessions (OUT/ID/), then OUT/season.csv: every window row with its
    session and the window centre in the field frame, passes_before counted over the season."""
    from torchsoil.jobs.estimate import estimate

    f = Field.open(field)
    if not f.sessions:
        raise FieldError(f"{f.path}: the field holds no session yet")
    out = Path(out)
    lines, rows = [], []
    for s in f.sessions:
        pair = f.session_pair(s["id"])
        pair_path = out / "pairs" / f"{s['id']}.npz"
        pair.save(pair_path)
        estimate(pair_path, out / s["id"], settings, robot=robot, resume=(out / s["id"] / "run.json").exists(),
                 tensorboard=tensorboard, threads=threads)
        T = f.transform(s["id"])
        with open(out / s["id"] / "params.csv") as fh:
            for r in csv.DictReader(fh):
                xy = np.array([float(r.get("x", "nan")), float(r.get("y", "nan"))]) @ T[:2, :2].T + T[:2, 3]
                rows.append({"session": s["id"], "field_x": f"{xy[0]:.4f}", "field_y": f"{xy[1]:.4f}", **r})
        lines.append(f"{s['id']}: {out / s['id']}")
    keys = list(dict.fromkeys(k for r in rows for k in r))
    with open(out / "season.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, keys)
        w.writeheader()
        w.writerows(rows)
    return [*lines, f"wrote {out / 'season.csv'}: {len(rows)} window rows over {len(f.sessions)} session(s)"]
