"""Field store benchmark: the two sessions of the shipped `field_season` (terrain pairs with the
measurement nuisances of real data, each in its own map frame) added to a new field: the
second session's registration (time, error against the truth's map frames), the wheel passes
it is given from the first, and the peak memory of `torchsoil field add`."""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np


def run(quick: bool = False) -> dict[str, float]:
    """Figures: field.add_first_s, field.add_second_s (registration and merge), field.register_s
    (the search and refinement alone), field.reg_error_mm (largest horizontal error along the
    second session's path), field.reg_error_deg, field.reg_dz_mm, field.visits_before_right
    (share of the second session's driven cells whose visits before it are the truth's),
    field.add_peak_rss_mb (`torchsoil field add` of the second session, from a small launcher)."""
    from torchsoil.bench._memory import peak_rss_mb
    from torchsoil.field import register as reg
    from torchsoil.field.store import Field, Session
    from torchsoil.io.terrain_pair import TerrainPair
    from torchsoil.synth.record import make_season

    tmp = Path(tempfile.mkdtemp(prefix="torchsoil_bench_field_"))
    try:
        make_season("field_season", tmp / "season", seed=0, pair_only=True, realistic=True)
        meta = json.loads((tmp / "season" / "season.json").read_text())
        pairs = [tmp / "season" / f"session_{k}.pair.npz" for k in (1, 2)]
        sessions = [Session(TerrainPair.load(p), None, None, p.stem, str(p), p.stem) for p in pairs]
        f = Field.open(tmp / "field", create=True)
        t0 = time.perf_counter()
        f.add(sessions[0], log=lambda s: None)
        first_s = time.perf_counter() - t0
        shutil.copytree(tmp / "field", tmp / "field_for_memory")
        t0 = time.perf_counter()
        entry = f.add(sessions[1], log=lambda s: None)
        second_s = time.perf_counter() - t0
        b = sessions[1].pair
        cloud = reg.cloud_from_heightmap(b.h_front, b.origin, b.dx)
        t0 = time.perf_counter()
        reg.register_session(cloud, f.reference())
        register_s = time.perf_counter() - t0
        Tw = [np.array(s["T_world_map"]) for s in meta["sessions"]]
        truth, got = np.linalg.inv(Tw[0]) @ Tw[1], np.array(entry["transform"])
        err_m, err_deg = reg.transform_error(got, truth, np.c_[b.poses[:, 1:3], np.zeros(len(b.poses))])
        with np.load(tmp / "season" / "session_2.truth.npz") as tr:
            visits_truth = tr["visits_before_session"]
        before = _visits_before(f, entry["id"], b)
        drove = np.isfinite(b.visit_time).any(0)
        rss = peak_rss_mb(["field", "add", str(tmp / "field_for_memory"), str(pairs[1])])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {"field.add_first_s": first_s, "field.add_second_s": second_s, "field.register_s": register_s,
            "field.reg_error_mm": 1000 * err_m, "field.reg_error_deg": err_deg,
            "field.reg_dz_mm": 1000 * abs(got[2, 3] - truth[2, 3]),
            "field.visits_before_right": float(np.mean(before[drove] == visits_truth[drove])),
            "field.add_peak_rss_mb": rss}


def _visits_before(f, sid: str, pair) -> np.ndarray:
    """(X, Y) visits of the sessions before `sid` at the cells of its pair, from the store."""
    T = f.transform(sid)
    xs, ys = pair.grid.centers()
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    q = np.stack([gx, gy], -1) @ T[:2, :2].T + T[:2, 3]
    i, j = np.rint(q[..., 0] / f.dx).astype(int), np.rint(q[..., 1] / f.dx).astype(int)
    box = (i.min(), i.max() + 1, j.min(), j.max() + 1)
    out = np.zeros(gx.shape, np.int64)
    for s in f.sessions[: [e["id"] for e in f.sessions].index(sid)]:
        out += f.read("visits", box, s["id"])[i - box[0], j - box[2]]
    return out


if __name__ == "__main__":
    print(json.dumps(run(), indent=1))

