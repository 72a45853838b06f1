"""Scenarios: a YAML (configs/scenarios/NAME.yaml) -> field, trajectory, world truth, and
from them a terrain pair (docs/formats.md section 3) or a full recording (section 1).

A scenario is the `synth` section of the settings tree (`torchsoil.settings.SynthConfig`:
its keys, defaults and units); a scenario YAML is a document of that section:

    trajectory: {start: [x, y, yaw_deg], segments: [{straight: m, speed: m/s} |
                 {arc: radius m, angle_deg: deg, speed: m/s}], accel_limit: m/s^2}
    terrain:    {relief: {amplitude: m, wavelength: m, slope_x: m/m, slope_y: m/m},
                 micro: {rms: m, corr_length: m}, margin: m of field around the path}
    soil:       {base: {d: m, chi, beta_deg, moisture}, patches: [...], track_scale: [..]}
    effects:    {id: {form: linear|power|saturating|threshold, k: .., ...}}   (torchsoil.synth.effects)
    landmarks:  {poles: n, trunks: n, shed: bool, fence: bool}
    lidar:      {columns: 512|1024|2048, rate_hz: 10, range_noise: m, dropout: fraction,
                 organized: bool (full beams x columns clouds, NaN where nothing returned)}
    world:      {chunk: m, and the simulator's settings (section sim)}
    robot:      shipped robot name or path to a robot YAML (default paper_platform)
    tyre:       {sections: [taper|flat|rounded|crowned, ..], width_scale: [low, high],
                 dig_orders: [robot|wheel, ..]}  (drawn per seed)
    measurement: {noise: m, noise_dof: [low, high] | null, offset: m, tilt_deg: deg,
                 dropout: [low, high], blobs: 1/m^2, blob_radius: [m, m], streaks: 1/m,
                 streak_length: [m, m]}   (terrain-pair nuisances, drawn per seed: synth.measurement)

`SynthConfig.realistic()` (or `torchsoil record --pair-only --realistic`) turns on the
nuisances and tyre draws of real data (settings.REALISTIC); by default they are off.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchsoil.grid import Grid
from torchsoil.robot import Robot, load_robot
from torchsoil.settings import Settings, SettingsError, SynthConfig, TyreConfig, merge, read_yaml, validate
from torchsoil.synth import effects as fx
from torchsoil.synth.measurement import apply_measurement
from torchsoil.synth.terrain import Landmarks, Relief, check_patch, farm_landmarks, micro_topography
from torchsoil.synth.trajectory import Trajectory, build_trajectory
from torchsoil.synth.world import WorldResult, simulate_world

SCENARIO_DIR = Path(__file__).resolve().parents[1] / "configs" / "scenarios"
CORRIDOR = 1.2  # m of corridor beyond the outermost wheel path (truth and terrain pair extent)


def available() -> list[str]:
    """Names of the shipped scenarios (torchsoil/configs/scenarios)."""
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.yaml"))


def scenario_path(name_or_path: str | Path) -> Path:
    """The YAML of a shipped scenario name, or a path to a scenario (or settings) YAML."""
    path = Path(name_or_path)
    shipped = SCENARIO_DIR / f"{name_or_path}.yaml"
    if path.suffix == "" and shipped.is_file():
        return shipped
    if path.is_file():
        return path
    raise FileNotFoundError(f"scenario {str(name_or_path)!r} not found (looked for "
                            f"{path if path.suffix else shipped}); available: {', '.join(available())}")


def load_scenario(scenario: str | Path | dict | SynthConfig) -> SynthConfig:
    """A scenario: a shipped name (configs/scenarios/NAME.yaml), a YAML path, a dict or a
    SynthConfig (returned as is).

    A YAML or dict is a document of the `synth` section, or a full settings document whose
    `synth:` key holds it. It is validated over the defaults (mappings merge key by key,
    lists such as trajectory.segments replace); unknown keys, wrong types, unknown effects
    and bad soil patches raise SettingsError naming the key (`synth.terrain.relief.amplitud`).
    A file without `name` is named after its stem."""
    if isinstance(scenario, SynthConfig):
        return scenario
    if isinstance(scenario, dict):
        doc, source, stem = scenario, "scenario dict", None
    elif isinstance(scenario, (str, Path)):
        path = scenario_path(scenario)
        doc, source, stem = read_yaml(path), str(path), path.stem
    else:
        raise TypeError(f"a scenario is a name, a YAML path, a dict or a SynthConfig, not {type(scenario).__name__}")
    if "synth" in doc:                                  # a full settings document
        others = {k: v for k, v in doc.items() if k != "synth"}
        body = doc["synth"] if doc["synth"] is not None else {}
        if not isinstance(body, dict):
            raise SettingsError(f"{source}: `synth` must be a mapping, got {body!r}")
        if stem is not None and "name" not in body:
            body = {**body, "name": stem}
        settings = validate(Settings, merge(Settings().model_dump(), {**others, "synth": body}), source)
        scn = settings.synth
    else:
        if stem is not None and "name" not in doc:
            doc = {**doc, "name": stem}
        scn = validate(SynthConfig, merge(SynthConfig().model_dump(), doc), source, prefix="synth.")
    _check_free_form(scn, source)
    return scn


def _check_free_form(scn: SynthConfig, source: str) -> None:
    """What the section's types leave open: effect ids and parameters, soil patches, the
    robot and one track_scale factor per track."""
    for eid, params in scn.effects.items():
        try:
            fx.resolve({eid: params})
        except ValueError as e:
            raise SettingsError(f"{source}: `synth.effects.{eid}`: {e}") from None
    for i, patch in enumerate(scn.soil.patches):
        try:
            check_patch(patch)
        except ValueError as e:
            raise SettingsError(f"{source}: `synth.soil.patches.{i}`: {e}") from None
    try:
        robot = load_robot(scn.robot)
    except (FileNotFoundError, ValueError) as e:
        raise SettingsError(f"{source}: `synth.robot`: {e}") from None
    ts = scn.soil.track_scale
    if ts is not None and len(ts) != robot.n_tracks:
        raise SettingsError(f"{source}: `synth.soil.track_scale` = {list(ts)}: the robot {scn.robot!r} has "
                            f"{robot.n_tracks} tracks, one factor each")


@dataclass
class Truth:
    """Everything the recorder knows and the tools under test must not read.

    field: lidar-visible grid; h_field: (X, Y) initial surface on it, m.
    corridor: (i0, j0) offset of the world grid inside the field grid.
    tyre: the world's tyre drawn from the seed: {section, width_scale, dig_order} (synth.world).
    """

    scenario: SynthConfig
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
    tyre: dict


def build_truth(scenario: str | Path | dict | SynthConfig, seed: int = 0, dx: float = 0.02,
                field_margin: float | None = None) -> Truth:
    """Field, trajectory and the world's deformation for a scenario and seed.

    field_margin: metres of terrain around the path (default: the scenario's terrain.margin);
    the corridor (wheel paths + CORRIDOR m) is where the soil model runs."""
    scn = load_scenario(scenario)
    t0 = time.perf_counter()
    ss = np.random.SeedSequence([int(seed), 7])
    r_relief, r_micro, r_land = (np.random.default_rng(s) for s in ss.spawn(3))
    robot = load_robot(scn.robot)
    ter = scn.terrain
    rel = ter.relief
    relief = Relief.random(r_relief, rel.amplitude, rel.wavelength, rel.slope_x, rel.slope_y)
    traj = build_trajectory(scn.trajectory, relief, robot)
    # wheel paths -> corridor box; field box around it
    c, s = np.cos(traj.poses[:, 6]), np.sin(traj.poses[:, 6])
    wx = traj.poses[:, 1, None] + c[:, None] * robot.wheels[:, 0] - s[:, None] * robot.wheels[:, 1]
    wy = traj.poses[:, 2, None] + s[:, None] * robot.wheels[:, 0] + c[:, None] * robot.wheels[:, 1]
    cx0, cy0 = wx.min() - CORRIDOR, wy.min() - CORRIDOR
    cx1, cy1 = wx.max() + CORRIDOR, wy.max() + CORRIDOR
    m = float(ter.margin if field_margin is None else field_margin)
    nx0, ny0 = int(np.ceil(m / dx)), int(np.ceil(m / dx))
    corridor_grid = Grid.covering(cx0, cy0, cx1, cy1, dx)
    field = Grid(dx, (corridor_grid.origin[0] - nx0 * dx, corridor_grid.origin[1] - ny0 * dx),
                 (corridor_grid.shape[0] + 2 * nx0, corridor_grid.shape[1] + 2 * ny0))
    xs, ys = field.centers()
    mic = ter.micro
    h_field = relief.height(xs[:, None], ys[None, :]) + micro_topography(
        field, r_micro, mic.rms, mic.corr_length)
    pts = np.column_stack([traj.poses[:, 1], traj.poses[:, 2]])
    landmarks = farm_landmarks(scn.landmarks, relief,
                               (xs[0], ys[0], xs[-1], ys[-1]), r_land, pts[::10])
    t1 = time.perf_counter()
    X, Y = corridor_grid.shape
    h0 = h_field[nx0:nx0 + X, ny0:ny0 + Y]
    tyre = draw_tyre(scn.tyre, seed)
    world_cfg = scn.world if tyre["dig_order"] is None else scn.world.replace(dig_order=tyre["dig_order"])
    world = simulate_world(corridor_grid, h0, traj, robot, scn.soil, scn.effects, world_cfg,
                           section=tyre["section"], width_scale=tyre["width_scale"])
    t2 = time.perf_counter()
    return Truth(scn, int(seed), robot, relief, landmarks, traj, field, h_field, (nx0, ny0), world,
                 {"terrain_s": t1 - t0, "world_s": t2 - t1}, tyre)


def draw_tyre(cfg: TyreConfig, seed: int) -> dict:
    """The world's tyre for a seed: {section: one of cfg.sections, width_scale: uniform in
    cfg.width_scale, dig_order: one of cfg.dig_orders, or None when they are not set (then
    world.dig_order holds)}."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 17]))
    section = str(cfg.sections[rng.integers(len(cfg.sections))])
    width_scale = float(rng.uniform(*cfg.width_scale))
    orders = cfg.dig_orders
    return {"section": section, "width_scale": width_scale,
            "dig_order": str(orders[rng.integers(len(orders))]) if orders else None}


def terrain_pair_from_truth(truth: Truth, seed: int, noise: float | None = None, visits: bool = False) -> dict:
    """Measured before/after heightmaps from the truth (docs/formats.md section 3).

    h_front: the surface before the last visit of the wheels to each cell (before the robot
    for single passes), or with probability measurement.first_view the surface before the
    robot everywhere; h_back: the final surface; each with the scenario's measurement
    nuisances drawn from `seed` (synth.measurement; by default independent per-cell Gaussian
    noise of 3 mm only). noise: overrides measurement.noise, m. Extra keys: `n_visits`
    (X, Y), `scenario` (its name) and `nuisances` (JSON: the tyre and measurement draws).

    visits: where ground was driven twice or more, also the visit layers (docs/formats.md
    section 3, v1.1) as a pipeline keeping every visit writes them: h_front is then the first
    view everywhere (= visit_front[0]) and h_back the last (= the last visit's visit_back); the
    layers between are the world's states with their own noise of the same level."""
    w = truth.world
    cfg = truth.scenario.measurement
    first_view = bool(np.random.default_rng(np.random.SeedSequence([int(seed), 19])).random() < cfg.first_view)
    first_view = first_view or (visits and bool((w.n_visits > 1).any()))
    last = np.zeros_like(w.n_visits) if first_view else np.maximum(w.n_visits - 1, 0)
    h_pre = np.take_along_axis(w.states, last[None], 0)[0]
    half_width = float(np.abs(truth.robot.wheels[:, 1]).max()) + CORRIDOR / 2
    h_front, h_back, drawn = apply_measurement(h_pre, w.h_after, w.grid, truth.traj.poses, cfg, seed, noise,
                                               half_width)
    drawn["front_view"] = "first_view" if first_view else "last_visit"
    r = truth.robot
    layers = visit_layers(w) if visits else {}
    for v in range(len(layers.get("visit_front", ()))):   # each visit measured on its own: noise per layer
        there = np.isfinite(layers["visit_front"][v])
        vf, vb, _ = apply_measurement(w.states[v], w.states[v + 1], w.grid, truth.traj.poses, cfg, seed, noise,
                                      half_width, layer=v + 1)
        layers["visit_front"][v] = np.where(there, vf, np.nan)
        layers["visit_back"][v] = np.where(there, vb, np.nan)
    if layers:   # the first view before and each cell's last after are H_f and H_b themselves
        n = w.n_visits
        layers["visit_front"][0] = np.where(n > 0, h_front, np.nan)
        last = (np.arange(len(layers["visit_back"]))[:, None, None] == np.maximum(n - 1, 0)[None]) & (n > 0)[None]
        layers["visit_back"] = np.where(last, h_back[None], layers["visit_back"]).astype(np.float32)
    return {**layers,
        "dx": np.float64(w.grid.dx),
        "origin": np.asarray(w.grid.origin, dtype=np.float64),
        "h_front": h_front,
        "h_back": h_back,
        "poses": truth.traj.poses.astype(np.float64),
        "wheels": r.wheels.astype(np.float64),
        "wheel_width": np.float64(r.wheel_width),
        "wheel_flat_fraction": np.float64(r.wheel_flat_fraction),
        "n_visits": w.n_visits.astype(np.int16),
        "scenario": np.asarray(truth.scenario.name),
        "nuisances": np.asarray(json.dumps({"tyre": truth.tyre, "measurement": drawn})),
    }


def visit_layers(world: WorldResult) -> dict[str, np.ndarray]:
    """The noise-free visit layers of docs/formats.md section 3 from the world, where a cell was
    visited twice or more (else {}): visit_front[v] = states[v] (the surface before visit v),
    visit_back[v] = states[v + 1] (after it), visit_time[v] = pass_time[v] (base_link passed
    closest, s), each (V, X, Y) float32, NaN where the cell has fewer than v + 1 visits."""
    V = len(world.pass_time)
    if V < 2:
        return {}
    there = world.n_visits[None] > np.arange(V)[:, None, None]
    return {"visit_front": np.where(there, world.states[:V], np.nan).astype(np.float32),
            "visit_back": np.where(there, world.states[1:V + 1], np.nan).astype(np.float32),
            "visit_time": np.where(there, world.pass_time, np.nan).astype(np.float32)}


def make_terrain_pair(scenario: str | Path | dict | SynthConfig, seed: int = 0, dx: float = 0.02,
                      noise: float | None = None, visits: bool = False) -> dict:
    """Terrain pair dict (docs/formats.md section 3 keys) for a scenario, without lidars
    (`terrain_pair_from_truth`; visits: with the visit layers where ground was driven twice).

    The noise-free truth is identical to that of a recording of the same scenario, seed
    and dx."""
    return terrain_pair_from_truth(build_truth(scenario, seed, dx), seed, noise, visits)
