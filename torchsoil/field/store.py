"""The field store: a folder holding a field's frame, its sessions and per-cell layers across
sessions as tiles on disk (a season stays on disk, not in memory).

    FIELD/field.json                 the manifest: frame, cell size, sessions (id, source,
                                     content key, times, transform session -> field,
                                     registration figures), the files of this generation
    FIELD/sessions/ID/terrain.npz    the session's terrain pair, in its own map frame
    FIELD/sessions/ID/map.npz        its lidar map's landmarks and ground (when it had one)
    FIELD/sessions/ID/trajectory.csv its base_link poses in the field frame (t, x, y, z, roll,
                                     pitch, yaw; s, m, rad)
    FIELD/sessions/ID/tiles/I_J.npz  the session's layers on the field grid (written once)
    FIELD/tiles/I_J.gN.npz           the season's layers after generation N (N sessions)
    FIELD/reference.gN.npz           the field's registration reference (ground + landmarks)

The field grid: cell (i, j) is centred at (i dx, j dx) in the field frame; a tile holds
TILE x TILE cells, tile (I, J) the cells i in [I TILE, (I + 1) TILE). The field frame is the
first session's map frame.

Layers of a session on the field grid (float32 heights in the field frame, m; NaN where it did
not see the ground): `before`, `after` (the surface before its first and after its last visit
of the cell), `passes` (int16 wheel passes in the session), `visits` (int16), `time` (float64,
the session's first visit of the cell, s, NaN none). The season's layers: `first`, `latest`
(surface before the season's first visit and after its last), `passes` (wheel passes over the
season), `visits`, `sessions` (how many sessions drove the cell, int16).

An add is atomic: everything it writes has a new name (generation N + 1, a session folder
renamed into place) and the manifest is replaced last (`os.replace`); until then readers see the
field as it was, and a killed add leaves files that no manifest names, removed by the next add.
Adds are serialised by a lock file.
"""

from __future__ import annotations

import fcntl
import json
import math
import os
import re
import shutil
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from torchsoil.field import register as reg
from torchsoil.io.terrain_pair import TerrainPair

FORMAT = "torchsoil field"
VERSION = 1
TILE = 256
MIN_OVERLAP = 0.2          # share of a session's ground on the field's after the fit
MIN_RELIEF = 0.8           # correlation of the two grounds' relief there (10 cm pixels: noise averages out)
MAX_AMBIGUITY = 0.85       # second distinct candidate / best, without GNSS
MIN_GROUND = 500           # ground points (every 4 cm: 0.8 m^2) a session must bring
MAX_RMSE = 0.02            # m, the refinement's height residual RMS
SEASON = ("first", "latest", "passes", "visits", "sessions")
EPOCH = 1.0e8              # s: times above this are clock times (1973 on), below a recording's own


class FieldError(ValueError):
    """A field store that cannot be read, or a session it refuses; the message says why."""


class Refused(FieldError):
    """A session not merged into the field (another field, an ambiguous or disagreeing
    registration, a session already there or older than the last); the field is unchanged."""


@dataclass
class Session:
    """What a session brings to a field: its terrain pair (own map frame), its lidar map points
    (M, 3) or None, its Georef or None, a name and the recording's content key."""

    pair: TerrainPair
    map_points: np.ndarray | None
    georef: object | None
    name: str
    source: str
    key: str


# ---------------------------------------------------------------------------- pure helpers
def session_layers(pair: TerrainPair) -> dict[str, np.ndarray]:
    """A pair's per-cell layers on its own grid: before, after (X, Y) m, passes, visits (X, Y)
    int, time (X, Y) s of its first visit (NaN none). A pair without visit layers is one visit,
    timed by the nearest pose."""
    from torchsoil.estimate.visits import wheel_passes

    if pair.visit_time is not None:
        vt = np.asarray(pair.visit_time, np.float64)
        vf, vb = pair.visit_front, pair.visit_back
    else:
        seen = np.isfinite(pair.h_front) | np.isfinite(pair.h_back)
        xs, ys = pair.grid.centers()
        ii, jj = np.nonzero(seen)
        vt = np.full((1, *pair.h_front.shape), np.nan)
        if len(ii) and len(pair.poses):
            _, k = cKDTree(pair.poses[:, 1:3]).query(np.stack([xs[ii], ys[jj]], 1))
            vt[0, ii, jj] = pair.poses[k, 0]
        vf, vb = pair.h_front[None], pair.h_back[None]
    passes = wheel_passes(pair.poses, pair.wheels, pair.wheel_width, pair.grid, vt).sum(0)
    has = np.isfinite(vt)
    visits = has.sum(0)
    first = np.argmax(has, 0)
    last = vt.shape[0] - 1 - np.argmax(has[::-1], 0)
    take = lambda a, k: np.take_along_axis(np.asarray(a, np.float32), k[None], 0)[0]  # noqa: E731
    before = np.where(visits > 0, take(vf, first), np.asarray(pair.h_front, np.float32))
    after = np.where(visits > 0, take(vb, last), np.asarray(pair.h_back, np.float32))
    t = np.where(visits > 0, np.take_along_axis(vt, first[None], 0)[0], np.nan)
    return {"before": before, "after": after, "passes": passes.astype(np.int16), "visits": visits.astype(np.int16),
            "time": t}


def _sample(layer: np.ndarray, pair: TerrainPair, xy: np.ndarray, linear: bool) -> np.ndarray:
    """Values of a (X, Y) layer of the pair's grid at session-frame points (N, 2): bilinear over
    the finite neighbours (heights) or the nearest cell (counts, times); NaN / 0 outside."""
    u = (xy[:, 0] - pair.origin[0]) / pair.dx
    v = (xy[:, 1] - pair.origin[1]) / pair.dx
    if not linear:
        i, j = np.rint(u).astype(np.int64), np.rint(v).astype(np.int64)
        ok = (i >= 0) & (j >= 0) & (i < layer.shape[0]) & (j < layer.shape[1])
        out = np.zeros(len(xy), layer.dtype) if layer.dtype.kind in "iu" else np.full(len(xy), np.nan, layer.dtype)
        out[ok] = layer[i[ok], j[ok]]
        return out
    finite = np.isfinite(layer)
    num = ndimage.map_coordinates(np.where(finite, layer, 0.0).astype(np.float64), [u, v], order=1, cval=0.0)
    den = ndimage.map_coordinates(finite.astype(np.float64), [u, v], order=1, cval=0.0)
    return np.where(den > 0.5, num / np.maximum(den, 1e-12), np.nan).astype(np.float32)


def tiles_of(pair: TerrainPair, T: np.ndarray, dx: float) -> list[tuple[int, int]]:
    """Field tiles (I, J) the pair's grid covers once placed by T (4, 4) session -> field."""
    (x0, y0), (X, Y) = pair.origin, pair.h_front.shape
    e = pair.dx
    corners = np.array([[x0 - e, y0 - e], [x0 + X * e, y0 - e], [x0 - e, y0 + Y * e], [x0 + X * e, y0 + Y * e]])
    c = corners @ T[:2, :2].T + T[:2, 3]
    lo = np.floor(c.min(0) / (dx * TILE)).astype(int)
    hi = np.floor(c.max(0) / (dx * TILE)).astype(int)
    return [(i, j) for i in range(lo[0], hi[0] + 1) for j in range(lo[1], hi[1] + 1)]


def layers_on_tile(layers: dict[str, np.ndarray], pair: TerrainPair, T: np.ndarray, dx: float,
                   tile: tuple[int, int]) -> dict[str, np.ndarray] | None:
    """A session's layers (`session_layers`) resampled onto one field tile (TILE, TILE): each
    field cell's centre taken into the session frame by T^-1, heights carried into the field
    frame by T. None when the session saw no cell of the tile."""
    i = (tile[0] * TILE + np.arange(TILE)) * dx
    j = (tile[1] * TILE + np.arange(TILE)) * dx
    fx, fy = np.meshgrid(i, j, indexing="ij")
    Ti = np.linalg.inv(T)
    f = np.stack([fx.ravel(), fy.ravel()], 1)
    s = f @ Ti[:2, :2].T + Ti[:2, 3]           # horizontal part (a session's tilt is a few mrad)
    visits = _sample(layers["visits"], pair, s, False)
    if not (visits > 0).any() and not np.isfinite(_sample(layers["before"], pair, s, True)).any():
        return None
    out = {"visits": visits.reshape(TILE, TILE),
           "passes": _sample(layers["passes"], pair, s, False).reshape(TILE, TILE),
           "time": _sample(layers["time"], pair, s, False).reshape(TILE, TILE)}
    for k in ("before", "after"):
        h = _sample(layers[k], pair, s, True)
        out[k] = (T[2, 0] * s[:, 0] + T[2, 1] * s[:, 1] + T[2, 2] * h + T[2, 3]).astype(np.float32).reshape(TILE, TILE)
    return out


def season_tile(prev: dict[str, np.ndarray] | None, new: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The season's layers of a tile after one more session (`layers_on_tile`) over `prev`."""
    if prev is None:
        prev = {"first": np.full((TILE, TILE), np.nan, np.float32), "latest": np.full((TILE, TILE), np.nan, np.float32),
                "passes": np.zeros((TILE, TILE), np.int32), "visits": np.zeros((TILE, TILE), np.int32),
                "sessions": np.zeros((TILE, TILE), np.int16)}
    drove = new["visits"] > 0
    seen_first = np.isfinite(prev["first"])
    return {"first": np.where(seen_first, prev["first"], new["before"]).astype(np.float32),
            "latest": np.where(np.isfinite(new["after"]), new["after"], prev["latest"]).astype(np.float32),
            "passes": (prev["passes"] + new["passes"]).astype(np.int32),
            "visits": (prev["visits"] + new["visits"]).astype(np.int32),
            "sessions": (prev["sessions"] + drove).astype(np.int16)}


def transform_poses(poses: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(N, 7) poses t, x, y, z, roll, pitch, yaw in a session frame -> the field frame by T
    (yaw turned by T's heading; roll and pitch kept: a registration's tilt is a few mrad)."""
    out = np.array(poses, np.float64, copy=True)
    out[:, 1:4] = poses[:, 1:4] @ T[:3, :3].T + T[:3, 3]
    out[:, 6] = poses[:, 6] + math.atan2(T[1, 0], T[0, 0])
    return out


def _pair_sha(pair: TerrainPair) -> str:
    """SHA-256 of a pair's poses and measured surfaces: the same recording, whatever its file."""
    import hashlib

    h = hashlib.sha256(np.ascontiguousarray(pair.poses, np.float64).tobytes())
    h.update(np.ascontiguousarray(pair.h_front, np.float32).tobytes())
    h.update(np.ascontiguousarray(pair.h_back, np.float32).tobytes())
    return h.hexdigest()


def _name(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", s).strip("_")[:40] or "session"


def _save_npz(path: Path, **arrays) -> None:
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, path)


# ---------------------------------------------------------------------------- the store
class Field:
    """A field store folder (module docstring). `Field.open(path, create=True)` makes an empty
    one; `add(session)` registers and merges a session; `season(tile)` / `season_grid()` read
    the layers across sessions; `session_pair(id)` gives a session's pair with the passes its
    cells had before it (`extras["passes_prior"]`)."""

    def __init__(self, path: Path, manifest: dict):
        self.path, self.manifest = path, manifest

    # ------------------------------------------------------------------ reading
    @classmethod
    def open(cls, path: str | Path, create: bool = False, dx: float | None = None) -> Field:
        path = Path(path)
        m = path / "field.json"
        if not m.is_file():
            if not create:
                raise FieldError(f"{path}: not a field store (no field.json); `torchsoil field add {path} RECORDING` "
                                 "makes one")
            return cls(path, {"format": FORMAT, "version": VERSION, "dx": dx, "tile": TILE, "generation": 0,
                              "georef": None, "sessions": [], "tiles": {}, "reference": None})
        try:
            manifest = json.loads(m.read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise FieldError(f"{m}: unreadable manifest ({e})") from None
        if manifest.get("format") != FORMAT or manifest.get("version") != VERSION:
            raise FieldError(f"{m}: not a {FORMAT} manifest of version {VERSION}")
        return cls(path, manifest)

    @property
    def dx(self) -> float:
        return float(self.manifest["dx"])

    @property
    def sessions(self) -> list[dict]:
        return self.manifest["sessions"]

    def session(self, sid: str) -> dict:
        for s in self.sessions:
            if s["id"] == sid or s["name"] == sid:
                return s
        raise FieldError(f"{self.path}: no session {sid!r} (sessions: {', '.join(s['id'] for s in self.sessions)})")

    def season(self, tile: tuple[int, int]) -> dict[str, np.ndarray] | None:
        """The season's layers of one tile, or None where no session drove."""
        name = self.manifest["tiles"].get(f"{tile[0]},{tile[1]}")
        if name is None:
            return None
        with np.load(self.path / name) as d:
            return {k: d[k] for k in SEASON}

    def read(self, layer: str, box: tuple[int, int, int, int], session: str | None = None) -> np.ndarray:
        """One layer over the field cells i0 <= i < i1, j0 <= j < j1 (box), from the season's
        tiles or, given a session id, that session's own (NaN / 0 where none)."""
        i0, i1, j0, j1 = box
        heights = layer in ("first", "latest", "before", "after", "time")
        out = np.full((i1 - i0, j1 - j0), np.nan if heights else 0, np.float64 if heights else np.int64)
        for I in range(i0 // TILE, (i1 - 1) // TILE + 1):
            for J in range(j0 // TILE, (j1 - 1) // TILE + 1):
                if session is None:
                    name = self.manifest["tiles"].get(f"{I},{J}")
                    path = None if name is None else self.path / name
                else:
                    path = self.path / "sessions" / session / "tiles" / f"{I}_{J}.npz"
                if path is None or not path.is_file():
                    continue
                a, b = max(i0, I * TILE), min(i1, (I + 1) * TILE)
                c, d = max(j0, J * TILE), min(j1, (J + 1) * TILE)
                with np.load(path) as t:
                    out[a - i0:b - i0, c - j0:d - j0] = t[layer][a - I * TILE:b - I * TILE, c - J * TILE:d - J * TILE]
        return out

    def tiles(self) -> list[tuple[int, int]]:
        return [tuple(int(v) for v in k.split(",")) for k in self.manifest["tiles"]]

    def season_grid(self, layers: tuple[str, ...] = SEASON):
        """The season's layers over the bounding box of every tile: (Grid, {name: (X, Y)})."""
        from torchsoil.grid import Grid

        ts = self.tiles()
        if not ts:
            raise FieldError(f"{self.path}: the field holds no session yet")
        lo, hi = np.min(ts, 0), np.max(ts, 0)
        shape = tuple(int(v) for v in (hi - lo + 1) * TILE)
        out = {k: np.full(shape, np.nan, np.float32) if k in ("first", "latest") else np.zeros(shape, np.int32)
               for k in layers}
        for t in ts:
            d = self.season(t)
            a, b = (t[0] - lo[0]) * TILE, (t[1] - lo[1]) * TILE
            for k in layers:
                out[k][a:a + TILE, b:b + TILE] = d[k]
        return Grid(self.dx, (lo[0] * TILE * self.dx, lo[1] * TILE * self.dx), shape), out

    def transform(self, sid: str) -> np.ndarray:
        return np.asarray(self.session(sid)["transform"], np.float64)

    def session_pair(self, sid: str) -> TerrainPair:
        """A session's terrain pair (own frame) with `extras["passes_prior"]` (X, Y) int32: the
        wheel passes its cells had in the field's earlier sessions."""
        s = self.session(sid)
        pair = TerrainPair.load(self.path / "sessions" / s["id"] / "terrain.npz")
        T = self.transform(s["id"])
        earlier = [e["id"] for e in self.sessions[: self.sessions.index(s)]]
        xs, ys = pair.grid.centers()
        gx, gy = np.meshgrid(xs, ys, indexing="ij")
        f = np.stack([gx.ravel(), gy.ravel()], 1) @ T[:2, :2].T + T[:2, 3]
        prior = np.zeros(len(f), np.int32)
        tile = np.floor(f / (self.dx * TILE)).astype(np.int64)
        cell = np.rint(f / self.dx).astype(np.int64) - tile * TILE
        cell = np.clip(cell, 0, TILE - 1)
        for e in earlier:
            folder = self.path / "sessions" / e / "tiles"
            for key in {tuple(k) for k in np.unique(tile, axis=0)}:
                p = folder / f"{key[0]}_{key[1]}.npz"
                if not p.is_file():
                    continue
                sel = np.flatnonzero((tile[:, 0] == key[0]) & (tile[:, 1] == key[1]))
                with np.load(p) as d:
                    prior[sel] += d["passes"][cell[sel, 0], cell[sel, 1]]
        pair.extras = {**pair.extras, "passes_prior": prior.reshape(pair.h_front.shape)}
        if pair.visit_time is None:      # one visit, so that the estimator fits it with its prior passes
            pair.visit_front, pair.visit_back = pair.h_front[None].copy(), pair.h_back[None].copy()
            pair.visit_time = session_layers(pair)["time"][None]
        return pair

    # ------------------------------------------------------------------ adding
    @contextmanager
    def _locked(self):
        self.path.mkdir(parents=True, exist_ok=True)
        with open(self.path / ".lock", "w") as fh:
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise FieldError(f"{self.path}: another `field add` is running on this field") from None
            try:
                yield
            finally:
                fcntl.flock(fh, fcntl.LOCK_UN)

    def _collect_garbage(self) -> None:
        """Remove what no manifest names: an interrupted add's files, older generations."""
        keep = set(self.manifest["tiles"].values()) | {self.manifest["reference"]}
        for p in (self.path / "tiles").glob("*.npz") if (self.path / "tiles").is_dir() else []:
            if f"tiles/{p.name}" not in keep:
                p.unlink()
        for p in self.path.glob("reference.g*.npz"):
            if p.name not in keep:
                p.unlink()
        ids = {s["id"] for s in self.sessions}
        for p in (self.path / "sessions").iterdir() if (self.path / "sessions").is_dir() else []:
            if p.name not in ids:
                shutil.rmtree(p, ignore_errors=True)

    def reference(self) -> reg.Cloud:
        """The field's registration reference: the latest surface and the landmarks."""
        with np.load(self.path / self.manifest["reference"]) as d:
            cloud = reg.cloud_from_heightmap(d["h"], d["origin"], float(d["dx"]), step=float(d["dx"]))
            cloud.landmarks = d["landmarks"]
            return cloud

    def _duplicate(self, session: Session) -> str | None:
        """The id of a session of the same recording: the same content key, or the very same
        poses and surfaces."""
        sha = _pair_sha(session.pair)
        for s in self.sessions:
            if s["key"] == session.key or s.get("pair_sha") == sha:
                return s["id"]
        return None

    def _check_order(self, session: Session, log) -> None:
        """Sessions go in the order they were driven (passes before a session count the ones
        before it): one that starts before the field's last one ended is refused when both
        carry clock times (epoch seconds), else taken in the order added, with a note."""
        if not self.sessions:
            return
        t0, last = float(session.pair.poses[0, 0]), self.sessions[-1]
        if t0 >= last["t1"]:
            return
        if t0 > EPOCH and last["t0"] > EPOCH:
            raise Refused(f"{session.source}: starts at {time.strftime('%Y-%m-%d %H:%M:%S', time.gmtime(t0))} UTC, "
                          f"before the field's last session {last['id']} ended: add sessions in the order they "
                          "were driven")
        log(f"note: {session.name}'s times ({t0:.1f} s) do not follow {last['id']}'s ({last['t1']:.1f} s): not clock "
            "times, so the sessions are taken in the order they are added")

    def add(self, session: Session, log=print) -> dict:
        """Register `session` onto the field and merge it (module docstring); returns its
        manifest entry. Raises Refused (the field unchanged) for a session already there, one
        sharing no ground with the field, an ambiguous registration or one that disagrees with
        GNSS."""
        with self._locked():
            if (self.path / "field.json").is_file():
                self.manifest = Field.open(self.path).manifest
            self._collect_garbage()
            dup = self._duplicate(session)
            if dup is not None:
                raise Refused(f"{session.source}: already in the field as session {dup} (same recording)")
            pair = session.pair
            self._check_order(session, log)
            if self.manifest["dx"] is None:
                self.manifest["dx"] = float(pair.dx)
            cloud = reg.cloud_from_heightmap(pair.h_front, pair.origin, pair.dx, session.map_points)
            if len(cloud.ground) < MIN_GROUND:
                raise Refused(f"{session.source}: not merged: it measured the ground at {len(cloud.ground)} places "
                              f"(every 4 cm; {MIN_GROUND} needed): an empty or unusable recording")
            t0 = time.perf_counter()
            if not self.sessions:
                r = reg.Registration(np.eye(4), "first session: its map frame is the field's", 0.0, 1.0, 1.0)
                if session.georef is not None and getattr(session.georef, "kind", "local") != "local":
                    self.manifest["georef"] = _georef_dict(session.georef)
            else:
                r = self._register(session, cloud)
            log(f"registered {session.name} ({r.method}) in {time.perf_counter() - t0:.1f} s: overlap "
                f"{100 * r.overlap:.0f} %, relief correlation {r.relief:.2f}, height residual RMS "
                f"{1000 * r.rmse_m:.1f} mm"
                + (f", ambiguity {r.ambiguity:.2f}" if r.method.startswith("search") else "")
                + (f", {100 * r.gnss_m:.1f} cm / {r.gnss_deg:.2f} deg from GNSS" if r.gnss_m is not None else ""))
            return self._merge(session, cloud, r)

    def _register(self, session: Session, cloud: reg.Cloud) -> reg.Registration:
        ref = self.reference()
        guess = _gnss_guess(self.manifest.get("georef"), session.georef)
        r = reg.register_session(cloud, ref, guess)
        where = f"{session.source}: not merged"
        if r.overlap < MIN_OVERLAP:
            raise Refused(f"{where}: its ground does not meet the field's ({100 * r.overlap:.0f} % of its ground on "
                          f"the field's after the best fit, {100 * MIN_OVERLAP:.0f} % needed): a session of "
                          "another field, or of a part of this one no session has driven yet")
        if r.relief < MIN_RELIEF:
            raise Refused(f"{where}: its ground does not match the field's where they overlap (relief correlation "
                          f"{r.relief:.2f}, {MIN_RELIEF} needed): a session of another field")
        if guess is None and r.ambiguity > MAX_AMBIGUITY:
            raise Refused(f"{where}: its registration is ambiguous: a second placement scores {r.ambiguity:.2f} of the "
                          f"best (above {MAX_AMBIGUITY}): too few landmarks or a repetitive field; a recording with "
                          "RTK GNSS fixes gives the placement")
        if not (r.rmse_m <= MAX_RMSE):
            raise Refused(f"{where}: the registration did not converge (height residual RMS "
                          f"{1000 * r.rmse_m:.1f} mm, above {1000 * MAX_RMSE:.0f} mm)")
        if guess is not None:
            tol_m, tol_deg = _gnss_tolerance(self.manifest["georef"], session.georef)
            if r.gnss_m > tol_m or r.gnss_deg > tol_deg:
                raise Refused(f"{where}: the registration disagrees with GNSS by {100 * r.gnss_m:.1f} cm and "
                              f"{r.gnss_deg:.2f} deg (the fixes' 3 sigma: {100 * tol_m:.1f} cm, {tol_deg:.2f} deg)")
        return r

    def _merge(self, session: Session, cloud: reg.Cloud, r: reg.Registration) -> dict:
        pair, T, dx = session.pair, r.transform, self.dx
        n = len(self.sessions) + 1
        sid = f"s{n:03d}_{_name(session.name)}"
        part = self.path / "sessions" / (sid + ".part")
        shutil.rmtree(part, ignore_errors=True)
        (part / "tiles").mkdir(parents=True)
        pair.save(part / "terrain.npz")
        if session.map_points is not None:
            _save_npz(part / "map.npz", landmarks=cloud.landmarks.astype(np.float32))
        poses = transform_poses(pair.poses, T)
        np.savetxt(part / "trajectory.csv", poses, delimiter=",", fmt="%.9f", header="t,x,y,z,roll,pitch,yaw",
                   comments="")
        layers = session_layers(pair)
        gen = self.manifest["generation"] + 1
        tiles = dict(self.manifest["tiles"])
        (self.path / "tiles").mkdir(exist_ok=True)
        cells = passes = 0
        for t in tiles_of(pair, T, dx):
            new = layers_on_tile(layers, pair, T, dx, t)
            if new is None:
                continue
            _save_npz(part / "tiles" / f"{t[0]}_{t[1]}.npz", **new)
            cells += int((new["visits"] > 0).sum())
            passes += int(new["passes"].sum())
            name = f"tiles/{t[0]}_{t[1]}.g{gen}.npz"
            _save_npz(self.path / name, **season_tile(self.season(t), new))
            tiles[f"{t[0]},{t[1]}"] = name
        ref = self._new_reference(cloud, T, tiles, gen)
        entry = {"id": sid, "name": session.name, "source": session.source, "key": session.key,
                 "added": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "t0": float(pair.poses[0, 0]),
                 "t1": float(pair.poses[-1, 0]), "pair_sha": _pair_sha(pair), "transform": T.tolist(),
                 "registration": {k: v for k, v in r.to_dict().items() if k != "transform"},
                 "georef": _georef_dict(session.georef) if session.georef is not None else None,
                 "cells": cells, "passes": passes}
        os.replace(part, self.path / "sessions" / sid)
        manifest = {**self.manifest, "generation": gen, "tiles": tiles, "reference": ref,
                    "sessions": [*self.sessions, entry]}
        tmp = self.path / "field.json.tmp"
        tmp.write_text(json.dumps(manifest, indent=1))
        os.replace(tmp, self.path / "field.json")          # the commit
        self.manifest = manifest
        self._collect_garbage()
        return entry

    def _new_reference(self, cloud: reg.Cloud, T: np.ndarray, tiles: dict, gen: int) -> str:
        """reference.gN.npz: the season's latest surface every 4 cm (`h`, `origin`, `dx`) and
        every session's landmarks in the field frame (one per 5 cm voxel)."""
        from torchsoil.pipeline.icp import apply, voxel_downsample

        k = max(1, int(round(0.04 / self.dx)))
        keys = [tuple(int(v) for v in key.split(",")) for key in tiles]
        lo, hi = np.min(keys, 0), np.max(keys, 0)
        h = np.full(tuple((hi - lo + 1) * TILE // k), np.nan, np.float32)
        for key, name in zip(keys, tiles.values(), strict=True):
            with np.load(self.path / name) as d:
                a, b = (key[0] - lo[0]) * TILE // k, (key[1] - lo[1]) * TILE // k
                h[a:a + TILE // k, b:b + TILE // k] = d["latest"][::k, ::k]
        old = self.reference().landmarks if self.manifest["reference"] else np.zeros((0, 3))
        lm = np.vstack([old, apply(T, cloud.landmarks)]) if len(cloud.landmarks) else old
        lm = voxel_downsample(lm, 0.05) if len(lm) else lm
        name = f"reference.g{gen}.npz"
        _save_npz(self.path / name, h=h, origin=lo * TILE * self.dx, dx=np.float64(k * self.dx),
                  landmarks=np.asarray(lm, np.float64))
        return name


# ---------------------------------------------------------------------------- GNSS
def _georef_dict(g) -> dict:
    from dataclasses import asdict

    return asdict(g)


def _georef(d: dict | None):
    from torchsoil.geo.georef import Georef

    return None if d is None else (d if isinstance(d, Georef) else Georef(**d))


def _gnss_guess(field_georef, session_georef) -> np.ndarray | None:
    """(4, 4) session -> field from both frames' ties to the same UTM zone, or None."""
    f, s = _georef(field_georef), _georef(session_georef)
    if f is None or s is None or f.kind != "gnss" or s.kind != "gnss" or f.epsg != s.epsg:
        return None
    T = np.eye(4)                     # field xy = (k_f R_f)^-1 (k_s R_s xy_s + e_s - e_f), k_s / k_f ~ 1
    yaw = s.yaw - f.yaw
    T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    T[:2, 3] = np.linalg.inv(f.rotation()) @ (np.array([s.east, s.north]) - np.array([f.east, f.north]))
    T[2, 3] = s.up - f.up
    return T


def _gnss_tolerance(field_georef, session_georef) -> tuple[float, float]:
    """Three sigma of the two ties (their fixes' residual RMS, yaw sd), plus 1 cm and 0.05 deg."""
    f, s = _georef(field_georef), _georef(session_georef)
    m = math.hypot(f.fit.get("residual_rms_m", 0.02), s.fit.get("residual_rms_m", 0.02))
    d = math.hypot(f.fit.get("yaw_sd_deg", 0.1), s.fit.get("yaw_sd_deg", 0.1))
    return 3 * m + 0.01, 3 * d + 0.05
