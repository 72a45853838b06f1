"""Scenarios: a YAML (configs/scenarios/NAME.yaml) -> field, trajectory, world truth, and
from them a terrain pair (FORMATS.md section 3) or a full recording (section 1).

Scenario keys (all optional except trajectory; see configs/scenarios/*.yaml):

    trajectory: {start: [x, y, yaw_deg], segments: [{straight: m, speed: m/s} |
                 {arc: radius m, angle_deg: deg, speed: m/s}], accel_limit: m/s^2}
    terrain:    {relief: {amplitude: m, wavelength: m, slope_x: m/m, slope_y: m/m},
                 micro: {rms: m, corr_length: m}, margin: m of field around the path}
    soil:       {base: {d: m, chi, beta_deg, moisture}, patches: [...], track_scale: [..]}
    effects:    {id: {form: linear|power|saturating, k: .., ...}}   (torchsoil.synth.effects)
    landmarks:  {poles: n, trunks: n, shed: bool, fence: bool}
    lidar:      {columns: 512|1024, rate_hz: 10, range_noise: m, dropout: fraction,
                 organized: bool (full beams x columns clouds, NaN where nothing returned)}
    world:      {chunk: m}
    robot:      path to a robot YAML (default configs/robot/paper_platform.yaml)
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from torchsoil.config import dataclass_from_dict
from torchsoil.grid import Grid
from torchsoil.robot import Robot
from torchsoil.synth.terrain import Landmarks, Relief, farm_landmarks, micro_topography
from torchsoil.synth.trajectory import Trajectory, build_trajectory
from torchsoil.synth.world import WorldConfig, WorldResult, simulate_world

SCENARIO_DIR = Path(__file__).resolve().parents[1] / "configs" / "scenarios"
DEFAULT_ROBOT = Path(__file__).resolve().parents[1] / "configs" / "robot" / "paper_platform.yaml"

DEFAULTS: dict = {
    "trajectory": {"start": [0.0, 0.0, 0.0], "segments": [{"straight": 20.0, "speed": 1.0}],
                   "accel_limit": 0.5},
    "terrain": {"relief": {"amplitude": 0.05, "wavelength": 25.0, "slope_x": 0.0, "slope_y": 0.0},
                "micro": {"rms": 0.007, "corr_length": 0.07}, "margin": 10.0},
    "soil": {"base": {"d": 0.03, "chi": 0.2, "beta_deg": 30.0, "moisture": 0.0}, "patches": []},
    "effects": {},
    "landmarks": {"poles": 10, "trunks": 6, "shed": True, "fence": True},
    "lidar": {"columns": 1024, "rate_hz": 10.0, "range_noise": 0.01, "dropout": 0.02, "organized": False},
    "world": {"chunk": 0.4},
    "robot": None,
}
SECTIONS = set(DEFAULTS) | {"name", "description"}
CORRIDOR = 1.2  # m of corridor beyond the outermost wheel path (truth and terrain pair extent)


def _merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _check_types(doc: dict, ref: dict, where: str, source: str) -> None:
    """Values must have the type of their default (numbers, booleans, sections)."""
    for k, v in doc.items():
        if k not in ref or ref[k] is None:
            continue
        r, path = ref[k], f"{where}{k}"
        if isinstance(r, dict):
            if not isinstance(v, dict):
                raise ValueError(f"{source}: `{path}` must be a mapping, got {v!r}")
            _check_types(v, r, path + ".", source)
        elif isinstance(r, bool):
            if not isinstance(v, bool):
                raise ValueError(f"{source}: `{path}` must be true or false, got {v!r}")
        elif isinstance(r, (int, float)) and (isinstance(v, bool) or not isinstance(v, (int, float))):
            raise ValueError(f"{source}: `{path}` must be a number, got {v!r}")
    segs = doc.get("trajectory", {}).get("segments") if where == "" else None
    if segs is not None and (not isinstance(segs, list) or not all(isinstance(x, dict) for x in segs)):
        raise ValueError(f"{source}: `trajectory.segments` must be a list of mappings, got {segs!r}")


def available() -> list[str]:
    """Names of the scenarios in configs/scenarios."""
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.yaml"))


def load_scenario(scenario: str | Path | dict) -> dict:
    """A scenario name (configs/scenarios/NAME.yaml), a YAML path, or a dict -> full dict."""
    if isinstance(scenario, dict):
        doc, source = scenario, "scenario dict"
    else:
        path = Path(scenario)
        if not path.suffix:
            path = SCENARIO_DIR / f"{scenario}.yaml"
        if not path.is_file():
            raise FileNotFoundError(f"scenario {scenario!r} not found (looked for {path}); "
                                    f"available: {', '.join(available())}")
        doc, source = yaml.safe_load(path.read_text()) or {}, str(path)
        doc.setdefault("name", path.stem)
    unknown = set(doc) - SECTIONS
    if unknown:
        raise ValueError(f"{source}: unknown sections {sorted(unknown)}; known: {sorted(SECTIONS)}")
    _check_types(doc, DEFAULTS, "", source)
    out = _merge(DEFAULTS, doc)
    out.setdefault("name", "custom")
    if "segments" in doc.get("trajectory", {}):
        out["trajectory"]["segments"] = doc["trajectory"]["segments"]
    return out


@dataclass
class Truth:
    """Everything the recorder knows and the tools under test must not read.

    field: lidar-visible grid; h_field: (X, Y) initial surface on it, m.
    corridor: (i0, j0) offset of the world grid inside the field grid.
    """

    scenario: dict
    seed: int
    robot: Robot
    relief: Relief
    landmarks: Landmarks
    traj: Trajectory
    field: Grid
    h_field: np.ndarray
    corridor: tuple[int, int]
    world: WorldResult
    timings: dict


def build_truth(scenario: str | Path | dict, seed: int = 0, dx: float = 0.02,
                field_margin: float | None = None) -> Truth:
    """Field, trajectory and the world's deformation for a scenario and seed.

    field_margin: metres of terrain around the path (default: the scenario's terrain.margin);
    the corridor (wheel paths + CORRIDOR m) is where the soil model runs."""
    scn = load_scenario(scenario)
    t0 = time.perf_counter()
    ss = np.random.SeedSequence([int(seed), 7])
    r_relief, r_micro, r_land = (np.random.default_rng(s) for s in ss.spawn(3))
    robot = Robot.from_yaml(scn["robot"] or DEFAULT_ROBOT)
    ter = scn["terrain"]
    rel = ter["relief"]
    relief = Relief.random(r_relief, float(rel["amplitude"]), float(rel["wavelength"]),
                           float(rel.get("slope_x", 0.0)), float(rel.get("slope_y", 0.0)))
    traj = build_trajectory(scn["trajectory"], relief, robot)
    # wheel paths -> corridor box; field box around it
    c, s = np.cos(traj.poses[:, 6]), np.sin(traj.poses[:, 6])
    wx = traj.poses[:, 1, None] + c[:, None] * robot.wheels[:, 0] - s[:, None] * robot.wheels[:, 1]
    wy = traj.poses[:, 2, None] + s[:, None] * robot.wheels[:, 0] + c[:, None] * robot.wheels[:, 1]
    cx0, cy0 = wx.min() - CORRIDOR, wy.min() - CORRIDOR
    cx1, cy1 = wx.max() + CORRIDOR, wy.max() + CORRIDOR
    m = float(ter["margin"] if field_margin is None else field_margin)
    nx0, ny0 = int(np.ceil(m / dx)), int(np.ceil(m / dx))
    corridor_grid = Grid.covering(cx0, cy0, cx1, cy1, dx)
    field = Grid(dx, (corridor_grid.origin[0] - nx0 * dx, corridor_grid.origin[1] - ny0 * dx),
                 (corridor_grid.shape[0] + 2 * nx0, corridor_grid.shape[1] + 2 * ny0))
    xs, ys = field.centers()
    mic = ter["micro"]
    h_field = relief.height(xs[:, None], ys[None, :]) + micro_topography(
        field, r_micro, float(mic["rms"]), float(mic["corr_length"]))
    pts = np.column_stack([traj.poses[:, 1], traj.poses[:, 2]])
    landmarks = farm_landmarks(scn["landmarks"] or {}, relief,
                               (xs[0], ys[0], xs[-1], ys[-1]), r_land, pts[::10])
    t1 = time.perf_counter()
    X, Y = corridor_grid.shape
    h0 = h_field[nx0:nx0 + X, ny0:ny0 + Y]
    world = simulate_world(corridor_grid, h0, traj, robot, scn["soil"], scn["effects"],
                           dataclass_from_dict(WorldConfig, scn["world"], "world"))
    t2 = time.perf_counter()
    return Truth(scn, int(seed), robot, relief, landmarks, traj, field, h_field, (nx0, ny0), world,
                 {"terrain_s": t1 - t0, "world_s": t2 - t1})


def terrain_pair_from_truth(truth: Truth, seed: int, noise: float = 0.003) -> dict:
    """Noisy before/after heightmaps straight from the truth (FORMATS.md section 3).

    h_front: the surface before the last visit of the wheels to each cell (before the robot
    for single passes); h_back: the final surface; each with independent per-cell Gaussian
    noise of `noise` m. Extra keys: `n_visits` (X, Y) and `scenario` (its name)."""
    w = truth.world
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 11]))
    last = np.maximum(w.n_visits - 1, 0)
    h_pre = np.take_along_axis(w.states, last[None], 0)[0]
    h_front = (h_pre + noise * rng.standard_normal(h_pre.shape)).astype(np.float32)
    h_back = (w.h_after + noise * rng.standard_normal(h_pre.shape)).astype(np.float32)
    r = truth.robot
    return {
        "dx": np.float64(w.grid.dx),
        "origin": np.asarray(w.grid.origin, dtype=np.float64),
        "h_front": h_front,
        "h_back": h_back,
        "poses": truth.traj.poses.astype(np.float64),
        "wheels": r.wheels.astype(np.float64),
        "wheel_width": np.float64(r.wheel_width),
        "wheel_flat_fraction": np.float64(r.wheel_flat_fraction),
        "n_visits": w.n_visits.astype(np.int16),
        "scenario": np.asarray(truth.scenario.get("name", "custom")),
    }


def make_terrain_pair(scenario: str | Path | dict, seed: int = 0, dx: float = 0.02,
                      noise: float = 0.003) -> dict:
    """Terrain pair dict (FORMATS.md section 3 keys) for a scenario, without lidars.

    The noise-free truth is identical to that of a recording of the same scenario, seed
    and dx."""
    return terrain_pair_from_truth(build_truth(scenario, seed, dx), seed, noise)
