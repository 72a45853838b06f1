"""process-bag's outputs: terrain.npz, trajectory.csv, map.npz and PNGs of H_f, H_b and H_delta."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from torchsoil.pipeline.icp import voxel_downsample
from torchsoil.pipeline.run import PipelineResult
from torchsoil.plotting import coarse, coarse_extent

MAP_VOXEL = 0.05  # m


def write_outputs(result: PipelineResult, out_dir: str | Path) -> dict[str, Path]:
    """Write `terrain.npz` (docs/formats.md section 3 + extras), `trajectory.csv` (t, x, y, z,
    roll, pitch, yaw of T_ref), `map.npz` (`points` (M, 3) float32: the reference map P_ref,
    one point per MAP_VOXEL voxel, m; what a field store registers a session by) and PNGs
    of H_f, H_b and H_delta (diverging colour map:
    blue excavation, red deposition). Each file is written to a temporary name first."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tp = result.terrain
    paths = {"terrain": tp.save(out / "terrain.npz")}
    traj = out / "trajectory.csv"
    np.savetxt(traj.with_suffix(".tmp"), tp.poses, delimiter=",", fmt="%.9f",
               header="t,x,y,z,roll,pitch,yaw", comments="")
    traj.with_suffix(".tmp").replace(traj)
    paths["trajectory"] = traj
    points = result.mapping.map_points
    pts = voxel_downsample(points, MAP_VOXEL) if len(points) else np.zeros((0, 3))
    np.savez_compressed(out / "map.tmp.npz", points=pts.astype(np.float32))
    (out / "map.tmp.npz").replace(out / "map.npz")
    paths["map"] = out / "map.npz"
    hd = tp.h_delta
    lim = float(np.nanpercentile(np.abs(hd), 99)) if np.isfinite(hd).any() else 0.01
    for name, h, kw in (("h_front", tp.h_front, {"cmap": "viridis"}),
                        ("h_back", tp.h_back, {"cmap": "viridis"}),
                        ("h_delta", hd, {"cmap": "RdBu_r", "vmin": -lim, "vmax": lim})):
        fig = Figure(figsize=(4, 8))
        ax = fig.subplots()
        h, f = coarse(h)
        x0, x1, y0, y1 = coarse_extent(tp.origin, tp.dx, tp.h_front.shape, f)
        im = ax.imshow(h, origin="lower", extent=(y0, y1, x0, x1), aspect="equal", **kw)
        ax.plot(tp.poses[:, 2], tp.poses[:, 1], "k-", lw=0.5)
        ax.set_xlabel("y [m]")
        ax.set_ylabel("x [m]")
        ax.set_title({"h_front": "H_f (before)", "h_back": "H_b (after)",
                      "h_delta": "H_delta = H_b - H_f"}[name])
        fig.colorbar(im, ax=ax, label="m")
        png = out / f"{name}.png"
        fig.savefig(png.with_suffix(".tmp.png"), dpi=120, bbox_inches="tight")
        png.with_suffix(".tmp.png").replace(png)
        paths[name] = png
    return paths
