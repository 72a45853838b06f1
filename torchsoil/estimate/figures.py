"""Figures of an estimation run: the paper's Fig. 4 (parameters along the drive) and Fig. 6
(measured vs simulated height-difference maps with cross-sections), and the Table I summary."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from scipy import ndimage

from torchsoil.plotting import coarse, coarse_extent

CMAP = "PiYG"  # pink: excavation, green: deposition (as in the paper)


def _col(rows, key):
    return np.array([r[key] for r in rows], dtype=float)


def parameter_curves(rows: list[dict], reference: list[dict], names, path: Path) -> Path:
    """Fig. 4: sinkages (mm), chi, beta (deg) and costs (mm) against arc length s (m)."""
    s = _col(rows, "s")
    fig = Figure(figsize=(8, 9))
    ax = fig.subplots(4, 1, sharex=True)
    for n in names:
        if n.startswith("d"):
            ax[0].plot(s, 1e3 * _col(rows, n), ".-", label=f"{n} (track {int(n[1:]) - 1})" if n[1:].isdigit() else n)
    ax[0].set_title("fitted per window: sinkage d, deposit share $\\chi$, angle of repose $\\beta$; "
                    "costs against the noise floor", fontsize=10)
    ax[0].set_ylabel("sinkage d\n[mm]")
    ax[0].legend(loc="best", fontsize=8)
    ax[1].plot(s, _col(rows, "chi"), ".-", color="C2")
    ax[1].set_ylabel("deposit share $\\chi$ [-]")
    ax[2].plot(s, _col(rows, "beta"), ".-", color="C3")
    ax[2].set_ylabel("angle of repose\n$\\beta$ [deg]")
    ax[3].plot(s, 1e3 * _col(rows, "residual"), ".-", label="residual")
    ax[3].plot(s, 1e3 * _col(rows, "prediction"), ".-", label="prediction")
    if reference:
        ax[3].plot(s, 1e3 * _col(reference, "floor"), "--", color="gray", label="noise floor")
        ax[3].plot(s, 1e3 * _col(reference, "signal"), ":", color="k", label="deformation signal")
    ax[3].set_ylabel("cost [mm]\n(mean |simulated - measured|)")
    ax[3].set_xlabel("distance along the drive s [m] (window centres)")
    ax[3].legend(loc="best", fontsize=8)
    for a in ax:
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    return path


def cross_section(h: np.ndarray, origin, dx: float, centre, heading: float, half_width: float,
                  half_length: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Profile of h (X, Y) across the travel direction at `centre` (x, y) [m], averaged over
    +-half_length along it: lateral offsets (left positive) [m] and heights [m]."""
    lat = np.arange(-half_width, half_width + 1e-9, dx)
    along = np.arange(-half_length, half_length + 1e-9, dx)
    c, s = math.cos(heading), math.sin(heading)
    px = centre[0] + along[:, None] * c - lat[None] * s
    py = centre[1] + along[:, None] * s + lat[None] * c
    ij = np.stack([(px - origin[0]) / dx, (py - origin[1]) / dx])
    good = np.isfinite(h)
    val = ndimage.map_coordinates(np.where(good, h, 0.0), ij, order=1, cval=np.nan)
    cnt = ndimage.map_coordinates(good.astype(float), ij, order=1, cval=0.0)
    val = np.where(cnt > 0.99, val, np.nan)
    with np.errstate(invalid="ignore"):
        return lat, np.nanmean(val, axis=0)


def _heading(poses: np.ndarray, t: float) -> float:
    i = int(np.clip(np.searchsorted(poses[:, 0], t), 0, len(poses) - 1))
    return float(poses[i, 6])


def difference_maps(pair, h_start: np.ndarray, h_sim: np.ndarray, rows: list[dict], path: Path,
                    n_insets: int = 4, h_back: np.ndarray | None = None) -> Path:
    """Fig. 6: measured (H_b - H_f) and simulated (h_sim - h_start, the surface the simulation
    started from) height change over the drive, drawn over the x range of the measured or
    simulated ground, with cross-sections at windows A-D. h_back:
    (X, Y) the after map the estimator used (net of the map offset; default pair.h_back)."""
    measured = (pair.h_back if h_back is None else h_back) - pair.h_front
    simulated = np.where(np.isfinite(h_sim), h_sim - h_start, np.nan)
    fitted = [r for r in rows if not math.isnan(r["residual"])]
    clean = [r for r in fitted if not r["flags"]] or fitted
    if len(clean) > n_insets + 2:
        clean = clean[1:-1]  # the first and last windows often see only part of the ground
    picks = [clean[int(i)] for i in np.linspace(0, len(clean) - 1, min(n_insets, len(clean)))] if clean else []
    x0, y0 = pair.origin
    lim = float(np.nanpercentile(np.abs(measured), 99)) if np.isfinite(measured).any() else 0.05
    seen = np.flatnonzero(np.isfinite(measured).any(axis=1) | np.isfinite(simulated).any(axis=1))
    extent = coarse_extent(pair.origin, pair.dx, measured.shape, 1)
    xlim = (x0 + (seen[0] - 1) * pair.dx, x0 + (seen[-1] + 1) * pair.dx) if len(seen) else extent[:2]
    fig = Figure(figsize=(12, 8))
    gs = fig.add_gridspec(3, max(len(picks), 1), height_ratios=[1, 1, 1.1])
    for row_i, (title, img) in enumerate([("measured $H_\\Delta$", measured), ("simulated $H_\\Delta$", simulated)]):
        ax = fig.add_subplot(gs[row_i, :])
        img, f = coarse(img)
        im = ax.imshow(img.T, origin="lower", extent=coarse_extent(pair.origin, pair.dx, measured.shape, f), cmap=CMAP,
                       vmin=-lim, vmax=lim, aspect="equal")
        ax.plot(pair.poses[:, 1], pair.poses[:, 2], color="k", lw=0.5, alpha=0.5)
        for letter, r in zip("ABCDEFGH", picks, strict=False):
            ax.annotate(letter, (r["x"], r["y"]), color="k", fontsize=10, weight="bold", ha="center")
        ax.set_title(title)
        ax.set_xlim(*xlim)            # the ground the maps hold, not the grid's margins
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        fig.colorbar(im, ax=ax, label="height change [m]", fraction=0.02)
    half = float(np.abs(pair.wheels[:, 1]).max() + 2.5 * pair.wheel_width)
    for k, (letter, r) in enumerate(zip("ABCDEFGH", picks, strict=False)):
        ax = fig.add_subplot(gs[2, k])
        head = _heading(pair.poses, r["t"])
        for img, label, style in [(measured, "measured", "-"), (simulated, "simulated", "--")]:
            lat, prof = cross_section(img, pair.origin, pair.dx, (r["x"], r["y"]), head, half)
            ax.plot(lat, 1e3 * prof, style, label=label)
        ax.set_title(f"{letter}: s = {r['s']:.1f} m", fontsize=9)
        ax.set_xlabel("lateral [m]")
        if k == 0:
            ax.set_ylabel("height change [mm]")
            ax.legend(fontsize=8)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def window_figure(h_front: np.ndarray, h_start: np.ndarray, h_back: np.ndarray, h_sim: np.ndarray,
                  weight: np.ndarray, title: str):
    """Measured (H_b - H_f) vs simulated (h_sim - h_start) H_delta of one window's crop."""
    meas = np.where(weight > 0, h_back - h_front, np.nan)
    sim = h_sim - h_start
    lim = float(np.nanpercentile(np.abs(meas), 99)) if np.isfinite(meas).any() else 0.05
    fig = Figure(figsize=(8, 3.5))
    ax = fig.subplots(1, 2)
    for a, img, t in [(ax[0], meas, "measured"), (ax[1], sim, "simulated")]:
        im = a.imshow(img.T, origin="lower", cmap=CMAP, vmin=-lim, vmax=lim)
        a.set_title(f"{t} $H_\\Delta$")
    fig.colorbar(im, ax=ax, label="m", fraction=0.03)
    fig.suptitle(title)
    return fig


def _stats(v: np.ndarray) -> str:
    v = v[np.isfinite(v)] * 1e3
    if len(v) == 0:
        return "n/a | n/a | n/a"
    return f"{v.mean():.2f} | {v.std():.2f} | {v.min():.1f}/{v.max():.1f}"


def summary_table(rows: list[dict], reference: list[dict]) -> str:
    """Table I of the paper: mean, std, min/max of the costs (x 1e-3 m)."""
    res, pred = _col(rows, "residual"), _col(rows, "prediction")
    sig, floor = _col(reference, "signal"), _col(reference, "floor")
    lines = ["| row | residual mean | std | min/max | prediction mean | std | min/max |",
             "| --- | --- | --- | --- | --- | --- | --- |",
             f"| deformation signal | {_stats(sig)} | / | / | / |",
             f"| noise floor | {_stats(floor)} | / | / | / |",
             f"| model | {_stats(res)} | {_stats(pred)} |"]
    return "\n".join(lines)


def write_summary(path: Path, rows: list[dict], reference: list[dict], meta: dict) -> Path:
    fitted = [r for r in rows if not math.isnan(r["residual"])]
    floor = np.nanmean(_col(reference, "floor")) if reference else math.nan
    pred = np.nanmean(_col(rows, "prediction")) if rows else math.nan
    flagged = [r for r in rows if r["flags"]]
    secs = _col(fitted, "seconds") if fitted else np.array([math.nan])
    n_windows = len({r["s"] for r in rows})
    per_visit = f", {len(rows)} visit rows" if len(rows) != n_windows else ""
    text = [f"# Soil-parameter estimation: {meta.get('input', '')}", "",
            f"{n_windows} windows{per_visit} ({len(fitted)} fitted, {len(flagged)} flagged) of "
            f"{meta.get('window', '?')} m every {meta.get('stride', '?')} m; gradients: {meta.get('grad', '?')}; "
            f"median {1e3 * np.nanmedian(secs):.0f} ms per window.", "",
            f"Removed from H_b before estimation: {meta['removed']}." if "removed" in meta else "", "",
            f"Online: {meta['online']}." if "online" in meta else "", "",
            "Costs: weighted mean L1 height difference, x 1e-3 m (paper Table I).", "",
            summary_table(rows, reference), "",
            f"Mean prediction cost / mean noise floor: {pred / floor:.3f}" if floor > 0 else "", ""]
    if "multipass" in meta:
        text += ["## Ground driven more than once", "",
                 "Each visit of a window's ground fitted on its own before and after maps (docs/visits.md); "
                 "mean ± standard deviation over windows (multipass.png; passes per cell and cumulative rut depth "
                 "in passes.npz, passes.png).", "", meta["multipass"], ""]
    if flagged:
        text += ["Flagged windows:", ""] + flag_runs(flagged, float(meta.get("stride", 0.4)))[:50]
        if any("driven_again" in r["flags"] for r in flagged):
            text += ["", "driven_again: the drive came back over this ground; the window of the later stretch "
                         "fits it (on a pair with visit layers, every visit; docs/visits.md)."]
    Path(path).write_text("\n".join(text) + "\n")
    return Path(path)


def multipass(table: list[dict], path: Path) -> Path:
    """Measured rut depth and fitted sinkage (mm, mean and standard deviation over windows)
    against the wheel passes the ground had had before each visit (`visits.multipass_table`)."""
    fig = Figure(figsize=(6, 4))
    ax = fig.subplots()
    if table:
        pb = np.array([e["passes_before"] for e in table], float)
        series = (("rut", "measured rut depth", "o", -0.05), ("d", "fitted sinkage d", "s", 0.05))   # unjoined
        for key, label, fmt, shift in series:
            ax.errorbar(pb + shift, [1e3 * e[key] for e in table], yerr=[1e3 * e[key + "_sd"] for e in table],
                        fmt=fmt, capsize=4, label=label)
        for e in table:
            ax.annotate(f"visit {e['visit']}\n{e['windows']} windows", (e["passes_before"], 1e3 * e["d"]),
                        textcoords="offset points", xytext=(8, 4), fontsize=8)
        ax.set_xticks(sorted(set(pb)))
        ax.legend(loc="best")
    else:
        ax.text(0.5, 0.5, "no ground driven more than once", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel("wheel passes before the visit")
    ax.set_ylabel("depth [mm]")
    ax.set_title("Ground driven more than once")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    return path


def pass_maps(pair, layers: dict, path: Path) -> Path:
    """Wheel passes per cell and the cumulative rut depth (mm) over the drive (passes.npz layers)."""
    fig = Figure(figsize=(12, 5))
    ax = fig.subplots(1, 2)
    passes, f = coarse(np.where(layers["visits"] > 0, layers["passes"], np.nan))
    extent = coarse_extent(pair.origin, pair.dx, layers["passes"].shape, f)
    top = max(int(np.nanmax(passes)) if np.isfinite(passes).any() else 1, 1)
    im = ax[0].imshow(passes.T, origin="lower", extent=extent, cmap="viridis", vmin=0, vmax=top,
                      interpolation="nearest")
    fig.colorbar(im, ax=ax[0], label="wheel passes", fraction=0.03, ticks=range(top + 1))
    rut = coarse(1e3 * layers["rut_depth"])[0]
    lim = float(np.nanpercentile(np.abs(rut), 99)) if np.isfinite(rut).any() else 50.0
    im = ax[1].imshow(-rut.T, origin="lower", extent=extent, cmap=CMAP, vmin=-lim, vmax=lim)
    fig.colorbar(im, ax=ax[1], label="height change over all visits [mm]", fraction=0.03)
    for a, title in zip(ax, ("wheel passes per cell", "cumulative rut depth (sum of the visits' $H_\\Delta$)"),
                        strict=True):
        a.plot(pair.poses[:, 1], pair.poses[:, 2], color="k", lw=0.5, alpha=0.5)
        a.set_title(title)
        a.set_xlabel("x [m]")
        a.set_ylabel("y [m]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def flag_runs(flagged: list[dict], stride: float) -> list[str]:
    """summary.md's lines for flagged rows, visit by visit along the drive: consecutive
    windows (`stride` m apart) with the same flags as one line, "- s = a-b m (n windows): flags"."""
    runs: list[list[dict]] = []
    for r in sorted(flagged, key=lambda r: (int(r.get("visit", 0) or 0), r["s"])):
        last = runs[-1][-1] if runs else None
        if (last is not None and last["flags"] == r["flags"] and _visit(last) == _visit(r)
                and 0 < r["s"] - last["s"] <= 1.5 * stride):
            runs[-1].append(r)
        else:
            runs.append([r])
    return [f"- s = {g[0]['s']:.2f} m{_visit(g[0])}: {g[0]['flags']}" if len(g) == 1 else
            f"- s = {g[0]['s']:.2f}-{g[-1]['s']:.2f} m{_visit(g[0])} ({len(g)} windows): {g[0]['flags']}"
            for g in runs]


def _visit(row: dict) -> str:
    v = int(row.get("visit", 0) or 0)
    return f" (visit {v})" if v else ""
