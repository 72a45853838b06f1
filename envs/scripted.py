"""Scripted driving on the soil-traverse env: pure pursuit along waypoints, and the
straight-line vs detour comparison of `scripts/rollout.py`."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np


class WaypointPolicy:
    """Pure pursuit along the polyline through waypoints (M, 2) [m] at a constant speed [m/s].

    The polyline is sampled every 0.05 m; the look-ahead point is the first sample at least
    `lookahead` m ahead of the closest one (which only moves forward), and the curvature
    2 y / L^2 towards it is clipped to +-curvature_max [1/m].
    """

    def __init__(self, waypoints, speed: float = 1.0, lookahead: float = 1.2,
                 curvature_max: float = 0.8, start=None):
        wps = np.asarray(waypoints, dtype=np.float64).reshape(-1, 2)
        if len(wps) == 0:
            raise ValueError("a waypoint policy needs at least one waypoint")
        self.waypoints, self.start = wps, start
        self.speed, self.lookahead, self.kmax = speed, lookahead, curvature_max
        self.path: np.ndarray | None = None
        self.closest = 0

    def reset(self) -> None:
        self.path, self.closest = None, 0

    def _densify(self, x: float, y: float) -> np.ndarray:
        pts = np.vstack([[x, y], self.waypoints])
        out = [pts[:1]]
        for a, b in zip(pts[:-1], pts[1:], strict=True):
            n = max(1, int(np.ceil(np.linalg.norm(b - a) / 0.05)))
            out.append(a + (b - a) * (np.arange(1, n + 1) / n)[:, None])
        return np.vstack(out)

    def __call__(self, obs: dict) -> np.ndarray:
        """Action (speed, curvature) from obs["state"] = (speed, curvature, x, y, yaw)."""
        x, y, yaw = (float(v) for v in obs["state"][2:5])
        if self.path is None:
            self.path = self._densify(x, y)
        d = np.hypot(self.path[:, 0] - x, self.path[:, 1] - y)
        window = slice(self.closest, min(self.closest + 60, len(d)))
        self.closest += int(np.argmin(d[window]))
        ahead = np.flatnonzero(d[self.closest:] >= self.lookahead)
        tx, ty = self.path[self.closest + ahead[0]] if len(ahead) else self.path[-1]
        dx, dy = tx - x, ty - y
        ly = -math.sin(yaw) * dx + math.cos(yaw) * dy           # target left of the robot
        kappa = float(np.clip(2.0 * ly / max(dx * dx + dy * dy, 1e-6), -self.kmax, self.kmax))
        return np.array([self.speed, kappa], dtype=np.float32)


def run_episode(env, policy, seed: int = 0) -> dict:
    """One episode; per-step time [s], cumulative displaced and compacted volume [m^3],
    max rut [m], total reward, outcome and the final (Y, X, 3) top view if the env renders."""
    obs, _ = env.reset(seed=seed)
    policy.reset()
    dt = env.unwrapped.params.config.dt
    t, disp, comp, rut, total = [0.0], [0.0], [0.0], 0.0, 0.0
    info, term, trunc = {}, False, False
    while not (term or trunc):
        obs, r, term, trunc, info = env.step(policy(obs))
        total += r
        t.append(t[-1] + dt)
        disp.append(info["episode_displaced"])
        comp.append(info["episode_compacted"])
        rut = info["episode_max_rut"]
    frame = env.render() if env.render_mode == "rgb_array" else None
    return {"time": t, "displaced": disp, "compacted": comp, "max_rut": rut, "reward": total,
            "reached_goal": bool(info.get("reached_goal", False)), "frame": frame}


def detour_waypoints(cfg, detour_y: float = 8.4) -> tuple[list, list]:
    """Waypoints of the straight line start -> goal (of the env settings `cfg`), and of a
    detour that leaves the line, runs along y = detour_y [m] (default: the packed lane of the
    default field) and comes back; ramps scale with the route length."""
    (sx, sy), (gx, gy) = cfg.start[:2], cfg.goal
    length = math.dist((sx, sy), (gx, gy))
    a, ramp = 0.15 * length, 0.22 * length
    straight = [[gx, gy]]
    detour = [[sx + a, sy], [sx + a + ramp, detour_y], [gx - a - ramp, detour_y], [gx - a, gy], [gx, gy]]
    return straight, detour


def compare_detour(config=None, out: str | Path | None = None, seed: int = 0, speed: float = 1.0,
                   detour_y: float = 8.4, progress: bool = True) -> dict[str, dict]:
    """Drive the straight line through the wet patch and the detour on the same field (config:
    anything `SoilTraverseEnv` takes; None: the default env); print and return the soil
    damage vs time trade-off; with `out`, write rollout.json and rollout.png (top views of
    H_delta and cumulative damage against time)."""
    from tqdm import tqdm

    from envs.soil_traverse import SoilTraverseEnv

    env = SoilTraverseEnv(config, render_mode="rgb_array")
    cfg = env.params.config
    straight, detour = detour_waypoints(cfg, detour_y)
    results = {}
    for name, wps in tqdm([("straight", straight), ("detour", detour)], disable=not progress,
                          desc="policies"):
        pol = WaypointPolicy(wps, speed=speed, curvature_max=cfg.curvature_max)
        results[name] = run_episode(env, pol, seed)
    print(f"{'policy':10s} {'time [s]':>9s} {'displaced [m3]':>15s} {'compacted [m3]':>15s} "
          f"{'max rut [mm]':>13s} {'reward':>8s} goal")
    for name, r in results.items():
        print(f"{name:10s} {r['time'][-1]:9.1f} {r['displaced'][-1]:15.4f} {r['compacted'][-1]:15.4f} "
              f"{1000 * r['max_rut']:13.1f} {r['reward']:8.2f} {r['reached_goal']}")
    if out is not None:
        _write(results, Path(out))
    return results


def _write(results: dict, out: Path) -> None:
    from matplotlib.figure import Figure

    out.mkdir(parents=True, exist_ok=True)
    summary = {k: {"time_s": v["time"][-1], "displaced_m3": v["displaced"][-1],
                   "compacted_m3": v["compacted"][-1], "max_rut_m": v["max_rut"],
                   "reward": v["reward"], "reached_goal": v["reached_goal"]} for k, v in results.items()}
    (out / "rollout.json").write_text(json.dumps(summary, indent=1))
    fig = Figure(figsize=(15, 3.6))
    ax = fig.subplots(1, 3, gridspec_kw={"width_ratios": [2, 2, 1.3]})
    for a, (name, r) in zip(ax[:2], results.items(), strict=True):
        a.imshow(r["frame"])
        a.set_title(f"{name}: H_delta (red: rut, blue: berm), path")
        a.axis("off")
    for name, r in results.items():
        ax[2].plot(r["time"], r["displaced"], label=f"{name} displaced")
        ax[2].plot(r["time"], r["compacted"], "--", label=f"{name} compacted")
    ax[2].set_xlabel("time [s]")
    ax[2].set_ylabel("cumulative volume [m$^3$]")
    ax[2].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "rollout.png", dpi=110)
