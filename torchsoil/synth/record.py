"""A full synthetic recording: scenario -> truth -> dual-lidar sweeps -> rosbag2.

Files written for `make_recording(..., out=PATH)`::

    PATH/                 the rosbag2 directory (docs/formats.md section 1), nothing else inside:
                          both lidars, /tf_static, unless imu=False IMU_TOPIC and unless
                          gnss=False RTK fixes on GNSS_TOPIC
    PATH.robot.yaml       the robot description (docs/formats.md section 2)
    PATH.pair.npz         terrain pair straight from the truth, 3 mm per-cell noise (section 3)
    PATH.truth.npz        the truth: noise-free surfaces, per-visit states and times, soil
                          fields, true poses, time of last wheel passage, and on ground driven
                          twice or more the noise-free visit layers (tools under test must not
                          read it)
    PATH.truth.json       scenario, effects and parameters, seed, the verdict a correct
                          diagnosis gives (`expected`, effects.expected), extrinsics, clock, and the
                          datum tying the world to UTM (`datum`: epsg, east, north, yaw,
                          scale, up, as torchsoil.geo.georef.Georef)

A season (a scenario with `later_sessions`, `make_season`) writes one such recording per
session into a directory DIR, and the season's overview::

    DIR/season.json       scenario, seed, datum, and per session its name, clock, bag time of
                          its t = 0, duration, gnss and T_world_map
    DIR/session_K/        session K's bag (K = 1, 2, ...), its clock the season's: bag time
                          T0_NS + the session's clock; its own map frame starts where it starts
    DIR/session_K.*       its sidecars as above; the pair in the session's own map frame
                          (synth.scenario.in_map_frame), the truth in the world frame with, in
                          addition, T_world_map (4, 4), the map frame in the world, and on the
                          pair's grid (pair_origin) the earlier sessions' counts:
                          passes_before_session and visits_before_session (X, Y)

--pair-only writes the same without the bags (and without the robot YAML).
"""

from __future__ import annotations

import heapq
import json
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import yaml

from torchsoil.settings import SynthConfig, merge, validate
from torchsoil.synth import effects as fx
from torchsoil.synth.bagwriter import POINT_DTYPE, BagWriter, imu_message, navsatfix_message
from torchsoil.synth.conventions import driver_message, driver_of
from torchsoil.synth.gnss import Datum, GnssSpec, gnss_fixes
from torchsoil.synth.imu import ImuSpec, imu_samples
from torchsoil.synth.lidar import LidarSpec, Scene, matrix_quaternion, paper_lidars, scan
from torchsoil.synth.scenario import (
    Truth,
    build_season,
    build_truth,
    in_map_frame,
    load_scenario,
    season_pair,
    session_seed,
    visit_layers,
)

T0_NS = 1_750_000_000 * 1_000_000_000   # bag clock of trajectory time 0, ns
IMU_TOPIC = "/imu/data"
GNSS_TOPIC = "/gnss/fix"
DATUM = Datum()   # where the synthetic world lies on the Earth


def sidecar(out: str | Path, suffix: str) -> Path:
    """PATH.<suffix> beside the bag directory PATH."""
    out = Path(out)
    return out.with_name(out.name + "." + suffix)


def bag_t0_ns(truth: Truth) -> int:
    """Bag time [ns] of the truth's trajectory time 0: T0_NS plus its session's clock."""
    return T0_NS + int(round(truth.clock * 1e9))


def lidars_for(truth: Truth) -> list[LidarSpec]:
    lid = truth.scenario.lidar
    return paper_lidars(lid.columns, lid.rate_hz, lid.beams, lid.tilt_deg)


def scene_for(truth: Truth) -> Scene:
    w = truth.world
    return Scene(truth.field, truth.h_field.astype(np.float32), truth.corridor,
                 w.states.astype(np.float32), w.visit_time.astype(np.float32),
                 truth.landmarks.cylinders, truth.landmarks.boxes)


def sweep_points(sw: dict, organized: bool = False) -> np.ndarray:
    """One sweep as POINT_DTYPE: the valid returns (N,) in row-major (ring, column) order, or,
    organized, the full (beams, columns) image with NaN coordinates where nothing returned."""
    if organized:
        pts = np.empty(sw["xyz"].shape[:2], dtype=POINT_DTYPE)
        pts["x"], pts["y"], pts["z"] = (sw["xyz"][..., i] for i in range(3))
        pts["intensity"], pts["t"], pts["ring"] = sw["intensity"], sw["t_ns"], sw["ring"]
        return pts
    ok = np.isfinite(sw["xyz"][..., 0])
    pts = np.empty(int(ok.sum()), dtype=POINT_DTYPE)
    pts["x"], pts["y"], pts["z"] = (sw["xyz"][..., i][ok] for i in range(3))
    pts["intensity"] = sw["intensity"][ok]
    pts["t"] = sw["t_ns"][ok]
    pts["ring"] = sw["ring"][ok]
    return pts


def sweep_starts(truth: Truth, duration: float | None = None) -> np.ndarray:
    """Start times [s] of the full sweeps within the drive (or its first `duration` s)."""
    end = truth.traj.duration if duration is None else min(duration, truth.traj.duration)
    period = 1.0 / truth.scenario.lidar.rate_hz
    return np.arange(0.0, end - period + 1e-9, period)


def iter_sweeps(truth: Truth, seed: int, duration: float | None = None):
    """Yield (t_start [s], LidarSpec, points POINT_DTYPE (N,)) for every sweep of both
    lidars in recording order; deterministic for (truth, seed)."""
    specs = lidars_for(truth)
    scene = scene_for(truth)
    lid = truth.scenario.lidar
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 23]))
    for ts in sweep_starts(truth, duration):
        for s in specs:
            sw = scan(scene, s, truth.traj.poses, float(ts), rng, lid.range_noise, lid.dropout)
            yield float(ts), s, sweep_points(sw, lid.organized)


def with_lidar(scenario: SynthConfig, columns: int | None = None, organized: bool | None = None) -> SynthConfig:
    """The scenario with its lidar columns and/or organized setting replaced (None: kept),
    validated like the scenario (SettingsError naming `synth.lidar.columns`)."""
    change = {k: v for k, v in (("columns", columns), ("organized", organized)) if v is not None}
    if not change:
        return scenario
    return validate(SynthConfig, merge(scenario.model_dump(), {"lidar": change}), "recorder arguments",
                    prefix="synth.")


def make_recording(scenario: str | Path | dict | SynthConfig, out: str | Path, seed: int = 0,
                   dx: float = 0.02, storage: str = "mcap", compress: bool = True,
                   duration: float | None = None, columns: int | None = None,
                   organized: bool | None = None, progress: bool = False, convention: str = "ouster",
                   imu: bool = True, gnss: bool = True) -> dict:
    """Write the bag directory `out` and its sidecar files (module docstring); of a season
    (later_sessions), its first session (`make_season` writes them all).

    scenario: a shipped name, a YAML path, a dict or a SynthConfig (see
    `scenario.load_scenario`); seed: terrain, landmark and lidar noise seed; dx: terrain
    cell edge, m; storage: mcap or sqlite3; compress: mcap zstd chunk compression;
    duration: record only the first `duration` s of the drive (default: all of it);
    columns, organized: override the scenario's lidar settings (organized: full (beams,
    columns) clouds with NaN for no return instead of the returns only); convention: the
    lidar driver layout and stamp convention the sweeps are written in (synth.conventions:
    ouster, velodyne, hesai, robosense_start, robosense_end, livox, livox_custom, mixed);
    imu: also write a MEMS IMU (synth.imu.ImuSpec) on IMU_TOPIC in frame imu_link; gnss: also
    write RTK fixes (synth.gnss.GnssSpec) on GNSS_TOPIC in frame gnss_link. Returns a
    dict of figures (timings [s], bag size [MB], number of sweeps and points)."""
    out = Path(out)
    if out.exists():
        raise FileExistsError(f"bag output {out} already exists; remove it or choose another path")
    driver_of(convention, "lidar_front")   # an unknown convention fails before any work
    t0 = time.perf_counter()
    scn = with_lidar(load_scenario(scenario), columns, organized)
    truth = build_truth(scn, seed, dx)
    t1 = time.perf_counter()
    stats = write_recording(truth, out, seed, storage, compress, duration, progress, convention, imu, gnss)
    return {"truth_s": t1 - t0, **stats, "total_s": time.perf_counter() - t0}


def write_recording(truth: Truth, out: Path, seed: int, storage: str = "mcap", compress: bool = True,
                    duration: float | None = None, progress: bool = False, convention: str = "ouster",
                    imu: bool = True, gnss: bool = True) -> dict:
    """The bag directory `out` of a truth (the sweeps' noise from `seed`, bag times from
    `bag_t0_ns`) and its sidecars; options as `make_recording`. Returns its figures."""
    t1 = time.perf_counter()
    specs = lidars_for(truth)
    starts = sweep_starts(truth, duration)
    period = 1.0 / specs[0].rate_hz
    n_points = 0
    out.parent.mkdir(parents=True, exist_ok=True)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=2 * len(starts), unit="sweep", desc=f"recording {out.name}")
    imu_spec = ImuSpec() if imu else None
    gnss_spec = GnssSpec() if gnss else None
    end = float(starts[-1] + period) if len(starts) else 0.0
    aux = heapq.merge(imu_messages(truth, seed, end, imu_spec), fix_messages(truth, seed, end, gnss_spec),
                      key=lambda m: m[0])
    pending = next(aux, None)
    t0_ns = bag_t0_ns(truth)
    with BagWriter(out, storage=storage, compress=compress) as bag:
        tfs = [("base_link", s.name, np.asarray(s.xyz), matrix_quaternion(s.transform()[:3, :3]))
               for s in specs]
        if imu_spec is not None:
            tfs.append(("base_link", imu_spec.name, np.asarray(imu_spec.xyz),
                        matrix_quaternion(imu_spec.transform()[:3, :3])))
        if gnss_spec is not None:
            tfs.append(("base_link", gnss_spec.name, np.asarray(gnss_spec.xyz), np.array([0.0, 0.0, 0.0, 1.0])))
        bag.write_tf_static(tfs, t0_ns)
        for ts, s, pts in iter_sweeps(truth, seed, duration):
            stamp_ns = t0_ns + int(round(ts * 1e9))
            while pending is not None and pending[0] <= stamp_ns + int(round(period * 1e9)):
                bag.write_message(*pending[1], pending[0])
                pending = next(aux, None)
            n_points += int(np.isfinite(pts["x"]).sum())
            msgtype, msg = driver_message(pts, s.name, stamp_ns, driver_of(convention, s.name))
            bag.write_message(f"/{s.name}/points", msgtype, msg, stamp_ns + int(round(period * 1e9)))
            if bar is not None:
                bar.update(1)
        for t_ns, msg in ([pending] if pending is not None else []) + list(aux):
            bag.write_message(*msg, t_ns)
    if bar is not None:
        bar.close()
    t2 = time.perf_counter()
    write_sidecars(truth, out, seed, specs, imu_spec, gnss_spec)
    t3 = time.perf_counter()
    size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    return {"lidar_s": t2 - t1, "sidecars_s": t3 - t2,
            "drive_s": float(len(starts) * period), "sweeps": float(2 * len(starts)), "points": float(n_points),
            "bag_mb": size / 1e6}


def make_season(scenario: str | Path | dict | SynthConfig, out: str | Path, seed: int = 0, dx: float = 0.02,
                sessions: list[int] | None = None, pair_only: bool = False, realistic: bool = False,
                columns: int | None = None, organized: bool | None = None, gnss: bool = True,
                **bag_options) -> dict:
    """A season's recordings into the directory `out` (module docstring): every session, or
    those in `sessions` (1-based; the sessions before the last of them are simulated too,
    their ground carried). pair_only: the terrain pairs and truths without bags (`realistic`:
    with the measurement nuisances and tyre draws of real data); gnss: False leaves the fixes
    out of every session (else a session's own `gnss` says). Each session's noise is its own
    (synth.scenario.session_seed). bag_options go to `write_recording` (storage, compress,
    duration, progress, convention, imu). Returns {session_K: its figures}."""
    out = Path(out)
    scn = with_lidar(load_scenario(scenario), columns, organized)
    if realistic:
        if not pair_only:
            raise ValueError("realistic applies to pair_only (the recorder's lidars have their own noise model)")
        scn = scn.realistic()
    n = 1 + len(scn.later_sessions)
    todo = sorted(set(range(1, n + 1) if sessions is None else sessions))
    if not todo or todo[0] < 1 or todo[-1] > n:
        raise ValueError(f"scenario {scn.name!r} has sessions 1..{n}, not {todo}")
    for k in todo:
        if (out / f"session_{k}").exists() or sidecar(out / f"session_{k}", "truth.npz").exists():
            raise FileExistsError(f"session output {out / f'session_{k}'} already exists; remove it or choose "
                                  "another directory")
    if not pair_only:
        driver_of(bag_options.get("convention", "ouster"), "lidar_front")
    t0 = time.perf_counter()
    truths = build_season(scn, seed, dx, sessions=todo[-1])
    out.mkdir(parents=True, exist_ok=True)
    (out / "season.json").write_text(json.dumps(season_meta(truths[0].scenario, seed, truths, gnss), indent=1,
                                                default=_jsonable))
    stats = {}
    for truth in truths:
        if truth.session not in todo:
            continue
        path, ks = out / f"session_{truth.session}", session_seed(seed, truth.session)
        t1 = time.perf_counter()
        on = gnss and _session_gnss(truth)
        if pair_only:
            write_sidecars(truth, path, ks, robot_yaml=False)
            figures = {"sidecars_s": time.perf_counter() - t1}
        else:
            figures = write_recording(truth, path, ks, gnss=on, **bag_options)
        stats[path.name] = {"world_s": truth.timings["world_s"], **figures}
    stats["total_s"] = time.perf_counter() - t0
    return stats


def _session_gnss(truth: Truth) -> bool:
    """Whether the scenario gives the truth's session GNSS (the first session always)."""
    return truth.session == 1 or truth.scenario.later_sessions[truth.session - 2].gnss


def season_meta(scn: SynthConfig, seed: int, truths: list[Truth], gnss: bool = True,
                datum: Datum = DATUM) -> dict:
    """DIR/season.json: the scenario, seed, datum and, per session of `truths`, its name,
    clock [s], bag time of its t = 0 [ns], duration [s], gnss and T_world_map (4, 4 rows)."""
    return {"scenario": scn.name, "seed": int(seed), "sessions": [
        {"name": f"session_{t.session}", "session": t.session, "clock_s": t.clock, "bag_time_of_t0_ns": bag_t0_ns(t),
         "duration_s": t.traj.duration, "gnss": bool(gnss and _session_gnss(t)), "T_world_map": t.T_world_map}
        for t in truths],
        "map_frame_note": MAP_FRAME_NOTE, "datum": asdict(datum.georef())}


MAP_FRAME_NOTE = ("T_world_map: the recording's map frame (the lidar pipeline's world frame: base_link at the "
                  "first sweep, trajectory time 0, levelled by the smallest rotation) in the season's world "
                  "frame; a map point p is T_world_map p in the world, and T_world_map_a^-1 T_world_map_b takes "
                  "session b's map into session a's")


def imu_messages(truth: Truth, seed: int, end: float, spec: ImuSpec | None):
    """Yield (bag time ns, (topic, type, sensor_msgs/Imu)) of the IMU from trajectory time 0 to
    `end` s (none without a spec); its own noise stream, so the lidar sweeps do not change with it."""
    if spec is None:
        return
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 29]))
    t, acc, gyro = imu_samples(truth.traj.poses, spec, rng, end)
    acc_var, gyro_var = (spec.acc_noise**2 * spec.rate_hz, spec.gyro_noise**2 * spec.rate_hz)
    t0_ns = bag_t0_ns(truth)
    for k in range(len(t)):
        t_ns = t0_ns + int(round(t[k] * 1e9))
        yield t_ns, (IMU_TOPIC, "sensor_msgs/msg/Imu", imu_message(spec.name, t_ns, acc[k], gyro[k], acc_var, gyro_var))


def fix_messages(truth: Truth, seed: int, end: float, spec: GnssSpec | None, datum: Datum = DATUM):
    """Yield (bag time ns, (topic, type, sensor_msgs/NavSatFix)) of the RTK receiver from
    trajectory time 0 to `end` s (none without a spec); its own noise stream."""
    if spec is None:
        return
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 31]))
    t, lat, lon, alt = gnss_fixes(truth.traj.poses, spec, datum, rng, end)
    t0_ns = bag_t0_ns(truth)
    for k in range(len(t)):
        t_ns = t0_ns + int(round(t[k] * 1e9))
        yield t_ns, (GNSS_TOPIC, "sensor_msgs/msg/NavSatFix",
                     navsatfix_message(spec.name, t_ns, lat[k], lon[k], alt[k], spec.sigma_h**2, spec.sigma_v**2))


def write_sidecars(truth: Truth, out: Path, seed: int, specs: list[LidarSpec] | None = None,
                   imu: ImuSpec | None = None, gnss: GnssSpec | None = None, datum: Datum = DATUM,
                   robot_yaml: bool = True) -> None:
    """Robot YAML (unless robot_yaml=False), terrain pair and truth files beside the bag path
    `out`; a season's session's with its map frame and the earlier sessions' counts (module
    docstring)."""
    specs = specs or lidars_for(truth)
    out.parent.mkdir(parents=True, exist_ok=True)
    if robot_yaml:
        sidecar(out, "robot.yaml").write_text(yaml.safe_dump(truth.robot.to_dict(), sort_keys=False))
    np.savez_compressed(sidecar(out, "pair.npz"), **season_pair(truth, seed, visits=True))
    season = {}
    if truth.sessions > 1:
        mapped = in_map_frame(truth)
        season = {"T_world_map": truth.T_world_map, "pair_origin": np.asarray(mapped.world.grid.origin),
                  "passes_before_session": mapped.start.passes.astype(np.int16),
                  "visits_before_session": mapped.start.visits.astype(np.int16)}
    w = truth.world
    np.savez_compressed(
        sidecar(out, "truth.npz"),
        dx=np.float64(w.grid.dx), origin=np.asarray(w.grid.origin),
        h_before=w.h_before.astype(np.float32), h_after=w.h_after.astype(np.float32),
        states=w.states.astype(np.float32), visit_time=w.visit_time.astype(np.float32),
        n_visits=w.n_visits.astype(np.int16), t_last_wheel=w.t_last_wheel.astype(np.float32),
        poses=truth.traj.poses, speed=truth.traj.speed, accel=truth.traj.accel,
        yaw_rate=truth.traj.yaw_rate, arc=truth.traj.arc,
        soil_d=w.soil["d"].astype(np.float32), soil_chi=w.soil["chi"].astype(np.float32),
        soil_beta=w.soil["beta"].astype(np.float32), soil_moisture=w.soil["moisture"].astype(np.float32),
        cylinders=truth.landmarks.cylinders, boxes=truth.landmarks.boxes,
        pass_time=w.pass_time.astype(np.float32),
        **{k: v for k, v in visit_layers(w).items() if k != "visit_time"},   # visit_time: the states' (above)
        **season,
    )
    eff = fx.resolve(truth.scenario.effects)
    meta = {
        "scenario": truth.scenario.name,
        "seed": int(seed),
        "effects": eff,
        "catalogue_effects": [e for e in eff if e in fx.CATALOGUE],
        "out_of_catalogue_effects": [e for e in eff if e in fx.OUT_OF_CATALOGUE],
        "effect_signatures": {e: fx.SIGNATURES[e] for e in eff},
        "expected_verdict": fx.expected(eff)["verdict"],
        "expected": fx.expected(eff),
        "scenario_spec": truth.scenario.model_dump(mode="json"),
        "bag_time_of_t0_ns": bag_t0_ns(truth),
        "time_note": "truth and pair pose times t are seconds after bag_time_of_t0_ns",
        "extrinsics": {s.name: {"parent": "base_link", "xyz": list(s.xyz), "rpy": list(s.rpy),
                                "beams": s.beams, "vfov_deg": s.vfov_deg, "columns": s.columns,
                                "rate_hz": s.rate_hz} for s in specs},
        "imu": None if imu is None else {"topic": IMU_TOPIC, "parent": "base_link", **asdict(imu)},
        "gnss": None if gnss is None else {"topic": GNSS_TOPIC, "parent": "base_link", **asdict(gnss)},
        "datum": asdict(datum.georef()),
    }
    if truth.sessions > 1:
        meta["season"] = {"session": truth.session, "sessions": truth.sessions, "clock_s": truth.clock,
                          "T_world_map": truth.T_world_map, "map_frame_note": MAP_FRAME_NOTE}
    sidecar(out, "truth.json").write_text(json.dumps(meta, indent=1, default=_jsonable))


def _jsonable(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serializable: {type(o)}")
