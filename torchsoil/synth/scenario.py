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
    later_sessions: [{gap: s, start: [x, y, yaw_deg], segments: [...], accel_limit, gnss}, ...]
                 (a season: below)

`SynthConfig.realistic()` (or `torchsoil record --pair-only --realistic`) turns on the
nuisances and tyre draws of real data (settings.REALISTIC); by default they are off.

A season (`later_sessions`) is several sessions, drives of other days, on the same field:
one terrain, one set of landmarks, one soil, the world simulated session after session, each
starting on the ground the sessions before it left (`build_season`). Session k's clock
starts `gap` s after the end of session k - 1 (the first at 0). Each session is recorded as
its own recording, and its terrain pair lies in that recording's own map frame, as the lidar
pipeline's would (`map_frame`, `in_map_frame`).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.ndimage import map_coordinates

from torchsoil.grid import Grid
from torchsoil.io.trajectory import rows_to_poses
from torchsoil.pipeline.gravity import levelling_rotation
from torchsoil.robot import Robot, load_robot
from torchsoil.settings import Settings, SettingsError, SynthConfig, TyreConfig, merge, read_yaml, validate
from torchsoil.synth import effects as fx
from torchsoil.synth.measurement import apply_measurement
from torchsoil.synth.terrain import Landmarks, Relief, check_patch, farm_landmarks, micro_topography
from torchsoil.synth.trajectory import Trajectory, build_trajectory
from torchsoil.synth.world import SoilState, WorldResult, simulate_world

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
    session: which session of a season this is (1: the first, or a scenario without
    later_sessions); sessions: how many the season has; clock: the season's clock at this
    session's trajectory time 0, s; start: the ground at its start (SoilState: the earlier
    sessions' passes; fresh for the first). traj, world and their times are the session's own
    (from 0 at its start), in the world frame.
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
    session: int = 1
    sessions: int = 1
    clock: float = 0.0
    start: SoilState | None = None

    @property
    def T_world_map(self) -> np.ndarray:
        """(4, 4) this recording's map frame in the world (`map_frame`)."""
        return map_frame(self.traj)


def map_frame(traj: Trajectory) -> np.ndarray:
    """T_world_map (4, 4): where the lidar pipeline's map frame of a recording of this drive
    lies in the world. The pipeline's world frame is base_link at the first sweep (the first
    front sweep starts at trajectory time 0: the pose poses[0]), turned upright about its
    origin by the smallest rotation (pipeline.gravity.levelling_rotation), so T_world_map's
    rotation is a turn about the vertical by about the start's yaw, and its translation is
    base_link's position at t = 0. A point p_map of the recording's maps is T_world_map p_map
    in the world."""
    T = rows_to_poses(traj.poses[:1])[0]
    R = levelling_rotation(T[:3, :3].T @ np.array([0.0, 0.0, -1.0]))
    T[:3, :3] = T[:3, :3] @ R.T
    return T


def _wheel_box(poses: np.ndarray, robot: Robot) -> tuple[float, float, float, float]:
    """(xmin, ymin, xmax, ymax) of the wheel contacts along the (N, 7) poses, CORRIDOR m wider."""
    c, s = np.cos(poses[:, 6]), np.sin(poses[:, 6])
    wx = poses[:, 1, None] + c[:, None] * robot.wheels[:, 0] - s[:, None] * robot.wheels[:, 1]
    wy = poses[:, 2, None] + s[:, None] * robot.wheels[:, 0] + c[:, None] * robot.wheels[:, 1]
    return wx.min() - CORRIDOR, wy.min() - CORRIDOR, wx.max() + CORRIDOR, wy.max() + CORRIDOR


def to_map(poses: np.ndarray, T_world_map: np.ndarray) -> np.ndarray:
    """(N, 7) world poses rows -> the same in the map frame of T_world_map (a turn about the
    vertical, `map_frame`): positions moved and turned, yaw less the map's, roll and pitch
    kept."""
    psi = float(np.arctan2(T_world_map[1, 0], T_world_map[0, 0]))
    c, s = np.cos(psi), np.sin(psi)
    d = poses[:, 1:4] - T_world_map[:3, 3]
    out = poses.copy()
    out[:, 1], out[:, 2], out[:, 3] = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]
    out[:, 6] = poses[:, 6] - psi
    return out


def session_seed(seed: int, session: int) -> int:
    """The noise seed of a season's session (1-based): the season's own for the first, one drawn
    from it for each later one (its lidar, IMU, GNSS and terrain-pair noise its own)."""
    if session == 1:
        return int(seed)
    return int(np.random.SeedSequence([int(seed), 41, int(session)]).generate_state(1)[0] % 2**31)


def season_clock(scn: SynthConfig, trajs: list[Trajectory]) -> list[float]:
    """The season's clock [s] at each session's trajectory time 0: 0 for the first, then the
    end of the session before plus the session's gap."""
    clock = [0.0]
    for traj, spec in zip(trajs[:-1], scn.later_sessions, strict=True):
        clock.append(clock[-1] + traj.duration + spec.gap)
    return clock


def build_truth(scenario: str | Path | dict | SynthConfig, seed: int = 0, dx: float = 0.02,
                field_margin: float | None = None) -> Truth:
    """Field, trajectory and the world's deformation for a scenario and seed (of a season: its
    first session, on the season's field; `build_season`).

    field_margin: metres of terrain around the path (default: the scenario's terrain.margin);
    the corridor (wheel paths + CORRIDOR m) is where the soil model runs."""
    return build_season(scenario, seed, dx, field_margin, sessions=1)[0]


def build_season(scenario: str | Path | dict | SynthConfig, seed: int = 0, dx: float = 0.02,
                 field_margin: float | None = None, sessions: int | None = None) -> list[Truth]:
    """The truths of a season's sessions 1..`sessions` (default all; a scenario without
    later_sessions has one): one field, landmarks, soil and tyre, each session's world
    simulated on the ground the one before left (its `WorldResult.end`).

    The corridor grid covers every session's wheel paths + CORRIDOR m, and in a season also
    each session's map-frame corridor (`in_map_frame`); field_margin as `build_truth`."""
    scn = load_scenario(scenario)
    t0 = time.perf_counter()
    ss = np.random.SeedSequence([int(seed), 7])
    r_relief, r_micro, r_land = (np.random.default_rng(s) for s in ss.spawn(3))
    robot = load_robot(scn.robot)
    ter = scn.terrain
    rel = ter.relief
    relief = Relief.random(r_relief, rel.amplitude, rel.wavelength, rel.slope_x, rel.slope_y)
    trajs = [build_trajectory(spec, relief, robot) for spec in (scn.trajectory, *scn.later_sessions)]
    n = len(trajs) if sessions is None else int(sessions)
    if not 1 <= n <= len(trajs):
        raise ValueError(f"scenario {scn.name!r} has {len(trajs)} session(s), not {n}")
    # wheel paths -> corridor box (in a season also each map frame's corridor); field box around it
    boxes = np.array([_wheel_box(tr.poses, robot) for tr in trajs])
    if len(trajs) > 1:
        for tr in trajs:
            T = map_frame(tr)
            xs, ys = _map_grid(tr, T, robot, dx).centers()
            corners = np.array([[x, y, 0.0, 1.0] for x in xs[[0, -1]] for y in ys[[0, -1]]]) @ T.T
            boxes = np.vstack([boxes, [*corners[:, :2].min(0) - dx, *corners[:, :2].max(0) + dx]])
    cx0, cy0 = boxes[:, :2].min(0)
    cx1, cy1 = boxes[:, 2:].max(0)
    m = float(ter.margin if field_margin is None else field_margin)
    nx0, ny0 = int(np.ceil(m / dx)), int(np.ceil(m / dx))
    corridor_grid = Grid.covering(cx0, cy0, cx1, cy1, dx)
    field = Grid(dx, (corridor_grid.origin[0] - nx0 * dx, corridor_grid.origin[1] - ny0 * dx),
                 (corridor_grid.shape[0] + 2 * nx0, corridor_grid.shape[1] + 2 * ny0))
    xs, ys = field.centers()
    mic = ter.micro
    h_field = relief.height(xs[:, None], ys[None, :]) + micro_topography(
        field, r_micro, mic.rms, mic.corr_length)
    pts = np.vstack([tr.poses[:, 1:3] for tr in trajs])
    landmarks = farm_landmarks(scn.landmarks, relief,
                               (xs[0], ys[0], xs[-1], ys[-1]), r_land, pts[::10])
    t1 = time.perf_counter()
    X, Y = corridor_grid.shape
    h0 = h_field[nx0:nx0 + X, ny0:ny0 + Y]
    tyre = draw_tyre(scn.tyre, seed)
    world_cfg = scn.world if tyre["dig_order"] is None else scn.world.replace(dig_order=tyre["dig_order"])
    clock = season_clock(scn, trajs)
    out, ground = [], SoilState.fresh(h0)
    for k, traj in enumerate(trajs[:n]):
        ta = time.perf_counter()
        world = simulate_world(corridor_grid, h0 if k == 0 else ground, traj, robot, scn.soil, scn.effects,
                               world_cfg, section=tyre["section"], width_scale=tyre["width_scale"])
        timings = {"terrain_s": t1 - t0, "world_s": time.perf_counter() - ta}
        out.append(Truth(scn, int(seed), robot, relief, landmarks, traj, field, h_field, (nx0, ny0), world,
                         timings, tyre, k + 1, len(trajs), clock[k], ground))
        ground = world.end
    return out


def _map_grid(traj: Trajectory, T_world_map: np.ndarray, robot: Robot, dx: float) -> Grid:
    """The map-frame grid of a session's terrain pair: its wheel paths in the map frame of
    T_world_map, CORRIDOR m wider."""
    return Grid.covering(*_wheel_box(to_map(traj.poses, T_world_map), robot), dx)


def in_map_frame(truth: Truth) -> Truth:
    """A session's truth in its own map frame (`map_frame`), as the lidar pipeline would see
    it: its trajectory turned and moved into the map frame (times kept), and its world on a
    grid aligned with the map covering the session's own corridor, its surfaces sampled
    bilinearly at the cells' world positions (heights less the map origin's), counts, times
    and soil at the nearest world cell; `start` (the earlier sessions' passes) likewise.
    terrain_pair_from_truth of it is the session's terrain pair."""
    T = truth.T_world_map
    w = truth.world
    grid = _map_grid(truth.traj, T, truth.robot, w.grid.dx)
    xs, ys = grid.centers()
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    p = np.stack([X, Y, np.zeros_like(X), np.ones_like(X)], -1) @ T.T
    at = np.stack([(p[..., 0] - w.grid.origin[0]) / w.grid.dx, (p[..., 1] - w.grid.origin[1]) / w.grid.dx])
    z0 = float(T[2, 3])

    def surface(a):
        return map_coordinates(np.asarray(a, np.float64), at, order=1, cval=np.nan) - z0

    ij = np.round(at).astype(np.int64)
    inside = (ij[0] >= 0) & (ij[0] < w.grid.shape[0]) & (ij[1] >= 0) & (ij[1] < w.grid.shape[1])
    ii, jj = np.clip(ij[0], 0, w.grid.shape[0] - 1), np.clip(ij[1], 0, w.grid.shape[1] - 1)

    def nearest(a, outside):
        return np.where(inside, np.asarray(a)[..., ii, jj], outside)

    start = None if truth.start is None else SoilState(
        surface(truth.start.h), nearest(truth.start.passes, 0), nearest(truth.start.wheel_passes, 0),
        nearest(truth.start.visits, 0), nearest(truth.start.loose, 0.0))
    world = WorldResult(grid, surface(w.h_before), surface(w.h_after), np.stack([surface(s) for s in w.states]),
                        nearest(w.visit_time, np.inf), nearest(w.n_visits, 0), nearest(w.t_last_wheel, np.nan),
                        {k: nearest(v, np.nan) for k, v in w.soil.items()}, nearest(w.pass_time, np.nan))
    traj = truth.traj
    return replace(truth, traj=Trajectory(to_map(traj.poses, T), traj.speed, traj.accel, traj.yaw_rate, traj.arc),
                   world=world, start=start)


def season_pair(truth: Truth, seed: int, noise: float | None = None, visits: bool = True) -> dict:
    """The terrain pair of a recording of `truth`: a scenario without later sessions gives
    `terrain_pair_from_truth` (in the world frame); a season's session its own map frame's
    (`in_map_frame`), with its own noise draw (`session_seed`) and an extra key `session`."""
    if truth.sessions == 1:
        return terrain_pair_from_truth(truth, seed, noise, visits)
    pair = terrain_pair_from_truth(in_map_frame(truth), session_seed(seed, truth.session), noise, visits)
    return {**pair, "session": np.int16(truth.session)}


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
