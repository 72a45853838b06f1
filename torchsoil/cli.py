"""The `torchsoil` command: one subcommand per job, each a thin layer over one library call.

    torchsoil estimate [INPUT] [--robot NAME|PATH] [--out DIR] [--config YAML] [--set KEY=VALUE]
    torchsoil estimate INPUT... | --manifest CSV [--engine local|ray] [--workers N] [--out DIR]
    torchsoil process-bag BAG --robot NAME|PATH --out DIR
    torchsoil diagnose INPUT... | --manifest CSV --out DIR [--engine local|ray]
    (each command that takes a bag also: --front-topic, --back-topic, --imu-topic, --extrinsic)
    torchsoil export RUN --out DIR [--anchor LAT,LON,HEADING_DEG] [--formats geotiff gpkg mcap]
    torchsoil record --scenario NAME --out PATH [--pair-only [--realistic]] [--convention C] [--no-imu] [--session K]
    torchsoil study [--quick | --randomized N [--null M] [--learned L] | --foreign DIR] [--out DIR] [--engine local|ray]
    torchsoil rollout --out DIR
    torchsoil bench [--only sim estimator] [--quick]
    torchsoil settings [SECTION ...]          # the effective settings as YAML

This entry, not the library, chooses process-wide things: the OpenMP wait policy (passive,
so torch's and numba's thread pools do not starve each other on a busy robot computer) and
torch's intra-op threads (`--threads`, default 1 for estimation: a window's tensors are
small, and the relaxation kernel parallelises over the batch itself).
"""

from __future__ import annotations

import argparse
import errno
import json
import os
import sys
from pathlib import Path


def _settings_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", action="append", default=[], metavar="YAML",
                   help="settings YAML overriding the defaults (repeatable; `torchsoil settings` lists them)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override one setting, e.g. estimator.window=1.0 (repeatable)")


def _bag_options(p: argparse.ArgumentParser) -> None:
    """The options of every command that takes a recording: pipeline settings (--config, --set),
    topics and extrinsics (read by `_bag_settings`)."""
    _settings_options(p)
    g = p.add_argument_group("recording", "how a bag is read (the manual: docs/recording.md, docs/formats.md; "
                                          "ignored for a terrain pair)")
    g.add_argument("--front-topic", metavar="TOPIC", help="front lidar PointCloud2 topic (= --set "
                                                          "pipeline.read.front_topic=TOPIC)")
    g.add_argument("--back-topic", metavar="TOPIC", help="back lidar PointCloud2 topic")
    g.add_argument("--imu-topic", metavar="TOPIC", help="sensor_msgs/msg/Imu topic levelling the world frame "
                                                        "(default: the bag's only one); none: level by the ground")
    g.add_argument("--extrinsic", nargs=7, action="append", default=[],
                   metavar=("FRAME|TOPIC", "X", "Y", "Z", "ROLL", "PITCH", "YAW"),
                   help="a lidar's (or the IMU's) pose in base_link (m, rad), by frame or by topic, overriding "
                        "the recording's and the robot YAML's (repeatable)")


def _job_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--threads", type=int, default=None,
                   help="torch intra-op threads for the run (default 1; with many recordings: per recording, "
                        "= --set fleet.cpus_per_task=N)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the outputs of another run in --out (otherwise refused)")
    p.add_argument("--no-tensorboard", action="store_true")


def _engine_options(p: argparse.ArgumentParser):
    """Where the tasks of many recordings (or study drives) run (torchsoil.jobs.fleet); returns the
    option group."""
    g = p.add_argument_group("many recordings", "one task per recording, each writing OUT/<name>/ as a single run "
                                                "would, and OUT/fleet.csv (manual: docs/fleet.md)")
    g.add_argument("--engine", choices=["local", "ray"], default=None,
                   help="local: a process pool on this machine (default); ray: a Ray cluster (--ray-address) or a "
                        "local Ray instance (pip install 'torchsoil[fleet]')")
    g.add_argument("--workers", type=int, metavar="N", help="tasks at once (default: as many as the cores and "
                                                            "memory hold, fleet.cpus_per_task and "
                                                            "fleet.memory_mb_per_task each)")
    g.add_argument("--ray-address", metavar="ADDR", help="a running Ray cluster, e.g. ray://head:10001 or auto "
                                                         "(default: start a local Ray instance)")
    return g


def _fleet_options(p: argparse.ArgumentParser) -> None:
    _engine_options(p).add_argument("--manifest", metavar="CSV",
                                    help="recordings listed in a CSV: columns input, and optionally name, robot, "
                                         "config, set (several values separated by ;)")


def _robot_option(p: argparse.ArgumentParser, required: bool = False, extra: str = "") -> None:
    p.add_argument("--robot", required=required, metavar="NAME|PATH",
                   help="robot description: a shipped name (paper_platform) or a YAML path" + extra)


def _add_estimate(sub) -> None:
    p = sub.add_parser("estimate", help="estimate soil parameters along a drive (sliding windows)",
                       description="Estimate (d_1..d_T, chi, beta) window by window. Writes OUT/params.csv, "
                                   "reference.csv, simulated.npz, summary.md, run.json, figures and TensorBoard "
                                   "events; on a terrain pair with visit layers, one row per visit of a window's "
                                   "ground and passes.npz, passes.png, multipass.png (docs/visits.md).")
    p.add_argument("input", nargs="*", help="rosbag (ROS 2 directory or ROS 1 .bag) or terrain-pair .npz "
                                            "(default: the bundled demo recording of a source checkout); several "
                                            "paths, globs or CSV manifests: one task each (--engine)")
    _robot_option(p, extra=" (default: the demo's, or the pair's own wheels)")
    p.add_argument("--out", help="output directory (default: out/<input name>; many recordings: OUT/<name>/, "
                                 "default out/)")
    _bag_options(p)
    p.add_argument("--grad", choices=["autograd", "fd"], help="= --set estimator.grad=...")
    p.add_argument("--merged-sinkage", action="store_true", help="ablation: one sinkage for all tracks")
    p.add_argument("--capped", type=int, metavar="N", help="ablation: relaxation capped at N iterations")
    p.add_argument("--resume", action="store_true", help="continue the interrupted run in --out")
    p.add_argument("--realtime", action="store_true", help="play the recording at its own pace, as on the robot, "
                                                           "printing each window's estimate and latency as it comes")
    p.add_argument("--export", action="store_true", help="also write the georeferenced maps into OUT/export "
                                                         "(GeoTIFF, GeoPackage, GridMap MCAP; see `torchsoil export`)")
    _anchor_option(p)
    _job_options(p)
    _fleet_options(p)


def _add_node(sub) -> None:
    p = sub.add_parser("node", help="run as a live ROS node on the robot (ROS 2 or ROS 1): soil, terrain and "
                                    "health published as the robot drives",
                       description="Subscribe to the lidars, /tf, /tf_static and the IMU; publish each window's "
                                   "estimate on ~/soil and ~/soil/values, the terrain near the robot on "
                                   "~/terrain/cloud, ~/terrain/rut_depth (and ~/terrain/grid_map), the node's "
                                   "health on /diagnostics; write OUT as `estimate` does. Arguments after the "
                                   "options are ROS arguments (remappings from:=to, __name:=, __ns:=). Manual: "
                                   "docs/node.md.")
    _robot_option(p, required=True)
    p.add_argument("--out", help="run folder (default: out/node-<UTC date and time>, a new one per start)")
    p.add_argument("--ros", choices=["auto", "1", "2"], default="auto",
                   help="which ROS (default: the one sourced, ROS 2 first)")
    _bag_options(p)
    p.add_argument("--resume", action="store_true", help="continue the run in --out (its recording replayed)")
    p.add_argument("--overwrite", action="store_true", help="replace the outputs of another run in --out")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1, as `estimate`)")
    p.add_argument("ros_args", nargs="*", metavar="ROS_ARG",
                   help="remappings (/lidar_front/points:=/ouster/points, __name:=soil, __ns:=/robot)")
    p.add_argument("--ros-args", nargs=argparse.REMAINDER, default=[], dest="ros2_args", metavar="ARG",
                   help="ROS 2 arguments, the rest of the line (--ros-args -r from:=to -p ...)")


def _anchor_option(p) -> None:
    p.add_argument("--anchor", metavar="LAT,LON,HEADING_DEG",
                   help="place the first pose at this latitude, longitude (deg, WGS 84) and compass heading (deg "
                        "clockwise from north) instead of fitting the recording's RTK GNSS fixes")


def _add_export(sub) -> None:
    p = sub.add_parser("export", help="georeferenced maps of a run: GeoTIFF, GeoPackage, GridMap MCAP",
                       description="Write RUN's soil maps into DIR: soil.tif (Cloud-Optimized GeoTIFF, a band per "
                                   "layer), soil.gpkg (windows, ruts, path), soil_gridmap/ (grid_map_msgs/GridMap "
                                   "in MCAP) and georef.json. The map frame is tied to UTM by the recording's RTK "
                                   "GNSS fixes (sensor_msgs/NavSatFix), or by --anchor; without either the maps "
                                   "stay in the run's local frame, and say so (docs/export.md).")
    p.add_argument("run", type=Path, help="a run folder of `estimate` or `process-bag`, or a terrain pair .npz")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    _anchor_option(p)
    p.add_argument("--bag", type=Path, help="the recording to read GNSS from (default: the one in RUN/run.json)")
    p.add_argument("--gnss-topic", default="", help="NavSatFix topic (default: the bag's only one)")
    p.add_argument("--formats", nargs="+", default=["geotiff", "gpkg", "mcap"], choices=["geotiff", "gpkg", "mcap"])


def _add_field(sub) -> None:
    p = sub.add_parser("field", help="a field across sessions: add recordings, see the season, estimate it all",
                       description="A field store (a folder) holds a field's frame, each session's trajectory and "
                                   "registration, and per-cell layers across sessions as tiles (docs/field.md).")
    fs = p.add_subparsers(dest="field_command", required=True, metavar="ACTION")
    a = fs.add_parser("add", help="register a recording onto the field and merge its visits and passes (the field "
                                  "is made by its first session); refused, leaving the field as it was, when the "
                                  "session shares no ground with it, its placement is ambiguous or disagrees "
                                  "with GNSS, or it is already there")
    a.add_argument("field", type=Path, help="field store folder")
    a.add_argument("recording", type=Path, help="a process-bag output folder, a terrain pair .npz, or a "
                                                "recording (ROS 2 bag directory / ROS 1 .bag, run through the "
                                                "lidar pipeline)")
    a.add_argument("--name", help="session name (default: the recording's)")
    a.add_argument("--gnss-topic", default="", help="NavSatFix topic (default: the bag's only one)")
    _robot_option(a, extra=" (needed for a recording)")
    _bag_options(a)
    i = fs.add_parser("info", help="the field's sessions: times, registration, cells and passes")
    i.add_argument("field", type=Path)
    m = fs.add_parser("maps", help="the season's layers: OUT/season.npz and season.png (passes, cumulative rut "
                                   "depth, sessions per cell)")
    m.add_argument("field", type=Path)
    m.add_argument("--out", type=Path, required=True)
    e = fs.add_parser("estimate", help="estimate every session with passes counted over the season: OUT/ID/ "
                                       "and OUT/season.csv")
    e.add_argument("field", type=Path)
    e.add_argument("--out", type=Path, required=True)
    _settings_options(e)
    _robot_option(e, extra=" (default: each session's own wheels)")
    e.add_argument("--threads", type=int, default=1)
    d = fs.add_parser("diagnose", help="diagnose sessions with passes counted over the season: OUT/ID/")
    d.add_argument("field", type=Path)
    d.add_argument("--out", type=Path, required=True)
    d.add_argument("--session", action="append", default=[], metavar="ID",
                   help="a session id or name (repeatable; default: every session after the first)")
    _settings_options(d)
    _robot_option(d, extra=" (default: each session's own wheels)")
    d.add_argument("--pass-workers", type=int, default=None, metavar="N", help="as for `diagnose`")
    q = fs.add_parser("pair", help="a session's terrain pair with the wheel passes of the earlier sessions "
                                   "(passes_prior), for estimate, diagnose or export")
    q.add_argument("field", type=Path)
    q.add_argument("session", help="session id or name")
    q.add_argument("--out", type=Path, required=True, help=".npz to write")


def _add_process_bag(sub) -> None:
    p = sub.add_parser("process-bag", help="lidar pipeline: a recording in, terrain pair and trajectory out")
    p.add_argument("bag", type=Path, help="ROS 2 bag directory or ROS 1 .bag file")
    _robot_option(p, required=True)
    p.add_argument("--out", type=Path, required=True, help="output directory")
    _bag_options(p)
    p.add_argument("--no-reregister", action="store_true", help="ablation: rasterize with T_ref")
    p.add_argument("--resume", action="store_true", help="continue the run in --out that was interrupted: from "
                                                         "its last checkpoint (OUT/checkpoint, every "
                                                         "pipeline.checkpoint_s)")


def _add_diagnose(sub) -> None:
    p = sub.add_parser("diagnose", help="locate model mismatch, name the missing physics, show the fit improve")
    p.add_argument("input", nargs="*", help="terrain-pair .npz or recording (ROS 2 bag directory / ROS 1 .bag); "
                                            "several paths, globs or CSV manifests: one task each (--engine)")
    p.add_argument("--out", required=True, help="output directory (many recordings: OUT/<name>/)")
    _robot_option(p, extra=" (needed for a recording; default for a pair: its own wheels)")
    _bag_options(p)
    p.add_argument("--n-fit", type=int, help="= --set diagnosis.n_fit=N")
    p.add_argument("--resume", action="store_true", help="continue the interrupted diagnosis in --out: its finished "
                                                         "passes (OUT/passes) are read back, not run again")
    p.add_argument("--pass-workers", type=int, default=None, metavar="N",
                   help="one recording: run its independent passes (tyre sections, dig orders, candidates) as N "
                        "tasks at once on a local process pool (same results; each worker holds the drive's "
                        "maps too; 1: all in this process; default: as many as the cores and memory hold "
                        "(fleet settings), at most 4); with --pass-engine ray, on RAY_ADDRESS's cluster or a "
                        "local Ray instance")
    p.add_argument("--pass-engine", choices=["local", "ray"], default="local",
                   help="where --pass-workers' tasks run (default local; ray needs pip install 'torchsoil[fleet]' "
                        "and a folder --out that every node reads and writes)")
    _job_options(p)
    _fleet_options(p)


def _add_record(sub) -> None:
    p = sub.add_parser("record", help="write a synthetic recording (bag + truth) or only its terrain pair")
    shipped = ", ".join(sorted(f.stem for f in (Path(__file__).parent / "configs" / "scenarios").glob("*.yaml")))
    p.add_argument("--scenario", required=True, help=f"shipped scenario ({shipped}) or YAML path (a synth section)")
    p.add_argument("--out", required=True, type=Path, help="bag directory to create (or .npz with --pair-only; a "
                                                          "season: the directory of its sessions)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--dx", type=float, default=0.02, help="terrain cell edge, m")
    p.add_argument("--storage", choices=["mcap", "sqlite3"], default="mcap")
    p.add_argument("--no-compress", action="store_true", help="mcap without zstd chunk compression")
    p.add_argument("--duration", type=float, default=None, help="record only the first seconds")
    p.add_argument("--columns", type=int, choices=[512, 1024, 2048], default=None)
    p.add_argument("--organized", action="store_true", help="organized clouds (beams x columns, NaN = no return)")
    p.add_argument("--pair-only", action="store_true", help="write only the terrain pair .npz")
    p.add_argument("--realistic", action="store_true", help="with --pair-only: the measurement nuisances and "
                                                            "tyre draws of real data (settings.REALISTIC)")
    p.add_argument("--convention", default="ouster",
                   help="lidar driver layout and stamp convention of the sweeps: ouster, velodyne, hesai, "
                        "robosense_start, robosense_end, livox, livox_custom, mixed (front ouster, back velodyne)")
    p.add_argument("--no-imu", action="store_true", help="no IMU topic (/imu/data) in the bag")
    p.add_argument("--no-gnss", action="store_true", help="no RTK GNSS topic (/gnss/fix) in the bag")
    p.add_argument("--session", type=int, action="append", default=None, metavar="K",
                   help="a season (scenario with later_sessions; --out is a directory, one recording per "
                        "session): only session K, 1-based (repeatable; the sessions before are simulated too)")


def _add_rollout(sub) -> None:
    p = sub.add_parser("rollout", help="scripted policies on the soil-traverse environment (damage vs time)")
    p.add_argument("--config", default=None, help="env settings YAML (the env section)")
    p.add_argument("--out", default="out/rollout", help="output directory")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--speed", type=float, default=1.0, help="driving speed, m/s")
    p.add_argument("--detour-y", type=float, default=8.4, help="y of the detour's straight part, m")


def _add_bench(sub) -> None:
    p = sub.add_parser("bench", help="benchmarks: print every figure and write OUT/bench.json")
    p.add_argument("--out", default="out/bench", help="directory for bench.json")
    p.add_argument("--only", nargs="*", help="benchmark modules to run (default: all)")
    p.add_argument("--quick", action="store_true", help="fewer sizes and repeats")


def _add_ablation(sub) -> None:
    p = sub.add_parser("ablation", help="the paper's ablation table (proposed, merged sinkage, capped relaxation)")
    p.add_argument("input", help="rosbag or terrain-pair .npz")
    _robot_option(p)
    p.add_argument("--out", required=True)
    _bag_options(p)
    p.add_argument("--threads", type=int, default=1)


def _add_study(sub) -> None:
    p = sub.add_parser("study", help="confusion table of the diagnosis over drives with known truth (long: "
                                     "minutes per drive)",
                       description="Diagnose drives with known truth and print the confusion table (OUT/confusion.md; "
                                   "OUT/cases.jsonl grows one line per drive, and a rerun resumes). Default: the "
                                   "fixed synthetic cases. --randomized N --null M: N drives with a random effect, "
                                   "law and drive shape plus M null drives, all with realistic measurement nuisances. "
                                   "--foreign DIR: the terrain pairs of another simulator (NAME.npz, "
                                   "NAME_truth.json, NAME_surfaces.npz, robot.yaml), with the estimator's model "
                                   "error against the noise-free surfaces.")
    p.add_argument("--out", help="output directory (default: out/diagnosis_study[_randomized|_foreign])")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true", help="fixed cases: one case per kind")
    mode.add_argument("--randomized", type=int, metavar="N", help="N randomized drives with an effect")
    mode.add_argument("--foreign", type=Path, metavar="DIR", help="directory of foreign terrain pairs")
    p.add_argument("--null", type=int, default=20, metavar="M", help="with --randomized: M null drives (default 20)")
    p.add_argument("--seed", type=int, default=0, help="with --randomized: study seed")
    p.add_argument("--learned", type=int, default=0, metavar="L",
                   help="with --randomized: also L drives with a random law outside the catalogue that a learned "
                        "modifier names (chi with speed, d with turn rate, beta with passes; default 0), scored on "
                        "the parameter, covariate and direction named")
    p.add_argument("--revisits", action="store_true",
                   help="with --randomized: only its drives over their own ruts (out-and-back, loop, lane changes; "
                        "hardening and null drives), with the visit layers of a pipeline that keeps every visit")
    p.add_argument("--redraws", type=int, default=0, metavar="R",
                   help="with --foreign: also fit R other draws of each pair's noise (its dropouts, streaks and "
                        "map offset moved), for the model error's spread over draws (default 0)")
    _settings_options(p)
    p.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default 1; with --engine: "
                                                             "per drive, = --set fleet.cpus_per_task=N)")
    _engine_options(p)


def _add_settings(sub) -> None:
    p = sub.add_parser("settings", help="print the effective settings as YAML (defaults + --config + --set)")
    p.add_argument("sections", nargs="*", help="only these sections (sim, estimator, pipeline, diagnosis, env, "
                                               "synth, fleet)")
    _settings_options(p)


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="torchsoil", description=__doc__,
                                 epilog="The manual: docs/index.md of the source checkout (build it with "
                                        "`python3 -m sphinx -b html docs out/docs`).",
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in (_add_estimate, _add_node, _add_process_bag, _add_diagnose, _add_export, _add_field, _add_record,
                _add_rollout,
                _add_bench,
                _add_ablation, _add_study, _add_settings):
        add(sub)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    # before torch or numba start their OpenMP runtimes: threads that spin while waiting starve
    # the other pool (3-10x slower on 2 busy cores)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from torchsoil.engines import EngineError
    from torchsoil.estimate.outputs import DiskFull
    from torchsoil.jobs.provenance import OutputMismatch
    from torchsoil.settings import SettingsError

    try:
        return COMMANDS[args.command](args)
    except (SettingsError, OutputMismatch, EngineError, FileNotFoundError, FileExistsError, ValueError,
            KeyError, ImportError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:   # a full disk (ENOSPC), wherever it is met: one clear line
        if e.errno != errno.ENOSPC:
            raise
        print(f"error: {e.strerror}" if isinstance(e, DiskFull) else
              f"error: {e}: free some space and run again with --resume", file=sys.stderr)
        return 2


def _settings(args, extra: list[str] = ()):
    from torchsoil.settings import load_settings

    return load_settings(*args.config, overrides=[*args.set, *extra])


def _topics(args) -> list[str]:
    """The topic options of a command with `_bag_options`, as settings overrides."""
    return [f"pipeline.read.{k}_topic={v}" for k in ("front", "back", "imu")
            if (v := getattr(args, f"{k}_topic")) is not None]


def _extrinsics(args) -> dict[str, list[float]]:
    """The --extrinsic poses {frame or topic: [x, y, z, roll, pitch, yaw]} (m, rad)."""
    given = {}
    for name, *values in args.extrinsic:
        try:
            given[name] = [float(v) for v in values]
        except ValueError:
            raise ValueError(f"--extrinsic {name}: X Y Z ROLL PITCH YAW must be numbers (m, rad), got "
                             f"{' '.join(values)}") from None
    return given


def _bag_settings(args, extra: list[str] = ()):
    """Settings with the topic options applied, and the --extrinsic poses {frame or topic:
    [x, y, z, roll, pitch, yaw]} (m, rad), of a command with `_bag_options`."""
    given = _extrinsics(args)
    return _settings(args, [*_topics(args), *extra]), given


def _many(args) -> bool:
    """Whether a command with `_fleet_options` runs many recordings: several inputs, a glob or
    a manifest, or an engine option."""
    inputs = args.input or []
    return (len(inputs) > 1 or any(c in i for i in inputs for c in "*?[") or any(i.endswith(".csv") for i in inputs)
            or any(getattr(args, k) is not None for k in ("manifest", "engine", "workers", "ray_address")))


def _run_many(job: str, args, extra: list[str], out: str) -> int:
    """`job` on every recording of args.input and --manifest (torchsoil.jobs.fleet.run_many)."""
    from torchsoil.jobs.fleet import run_many

    if getattr(args, "resume", False) or getattr(args, "realtime", False):
        raise ValueError("--resume and --realtime take one recording (many recordings: a rerun of the same command "
                         "skips the finished ones and runs the others again)")
    threads = [f"fleet.cpus_per_task={args.threads}"] if args.threads is not None else []
    return run_many(job, args.input, args.manifest, out, configs=args.config,
                    overrides=[*args.set, *_topics(args), *extra, *threads], robot=args.robot,
                    extrinsics=_extrinsics(args), engine=args.engine or "local", workers=args.workers,
                    address=args.ray_address, tensorboard=not args.no_tensorboard, overwrite=args.overwrite)


def _robot(name_or_path):
    from torchsoil.robot import load_robot

    return load_robot(name_or_path) if name_or_path else None


def _robot_yaml(name_or_path):
    from torchsoil.robot import robot_path

    return robot_path(name_or_path) if name_or_path else None


def cmd_estimate(args) -> int:
    from torchsoil.jobs.estimate import demo_input, estimate

    extra = [f"estimator.grad={args.grad}"] if args.grad else []
    extra += ["estimator.merged_sinkage=true"] if args.merged_sinkage else []
    extra += [f"sim.fixed_iter={args.capped}"] if args.capped else []
    if _many(args):
        return _run_many("estimate", args, extra, args.out or "out")
    settings, given = _bag_settings(args, extra)
    if args.input:
        source, robot_arg = Path(args.input[0]), args.robot
    else:
        source, demo_robot = demo_input()
        robot_arg = args.robot or demo_robot
    if not source.exists():
        raise FileNotFoundError(f"input not found: {source}")
    out = Path(args.out) if args.out else Path("out") / (source.stem if args.input else "demo")
    estimate(source, out, settings, robot=_robot(robot_arg), resume=args.resume, overwrite=args.overwrite,
             tensorboard=not args.no_tensorboard, robot_yaml=_robot_yaml(robot_arg), threads=args.threads or 1,
             extrinsics=given, realtime=args.realtime)
    print(f"wrote {out}: params.csv, summary.md, fig4_parameters.png, fig6_difference_maps.png, tensorboard/")
    print((out / "summary.md").read_text())
    if args.export or args.anchor:
        from torchsoil.jobs.export import export

        print("\n".join(export(out, out / "export", anchor=_anchor(args.anchor))))
    return 0


def cmd_field(args) -> int:
    from torchsoil.field.store import Refused
    from torchsoil.jobs import field

    if args.field_command == "add":
        settings, given = _bag_settings(args)
        try:
            lines = field.field_add(args.field, args.recording, _robot(args.robot), settings, given,
                                    args.gnss_topic, args.name)
        except Refused as e:
            print(f"refused: {e}", file=sys.stderr)
            return 3
        print("\n".join(lines))
    elif args.field_command == "info":
        print(field.field_info(args.field))
    elif args.field_command == "maps":
        print("wrote " + ", ".join(str(p) for p in field.field_maps(args.field, args.out)))
    elif args.field_command == "pair":
        print(f"wrote {field.field_pair(args.field, args.session, args.out)}")
    elif args.field_command == "diagnose":
        print("\n".join(field.field_diagnose(args.field, args.out, args.session, _settings(args), _robot(args.robot),
                                            args.pass_workers)))
    else:
        print("\n".join(field.field_estimate(args.field, args.out, _settings(args), _robot(args.robot),
                                            args.threads)))
    return 0


def _anchor(text: str | None) -> tuple[float, float, float] | None:
    if text is None:
        return None
    try:
        lat, lon, heading = (float(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"--anchor {text!r}: give LAT,LON,HEADING_DEG, three numbers (deg)") from None
    return lat, lon, heading


def cmd_node(args) -> int:
    from torchsoil.node.run import run_node

    settings, given = _bag_settings(args)
    robot_yaml = _robot_yaml(args.robot)
    from torchsoil.io.extrinsics import pipeline_settings

    settings = settings.replace(pipeline=pipeline_settings(settings, robot_yaml, given))
    import time

    out = args.out or f"out/node-{time.strftime('%Y%m%d-%H%M%S', time.gmtime())}"   # a new folder per start
    ros_args = [*args.ros_args, *(["--ros-args", *args.ros2_args] if args.ros2_args else [])]
    return run_node(_robot(args.robot), settings, out, ros=args.ros, resume=args.resume, overwrite=args.overwrite,
                    argv=ros_args, threads=args.threads)


def cmd_export(args) -> int:
    from torchsoil.jobs.export import export

    print("\n".join(export(args.run, args.out, anchor=_anchor(args.anchor), formats=tuple(args.formats),
                           bag=args.bag, gnss_topic=args.gnss_topic)))
    return 0


def cmd_process_bag(args) -> int:
    from torchsoil.jobs.process_bag import process_bag_job

    settings, given = _bag_settings(args, ["pipeline.reregister.enabled=false"] if args.no_reregister else [])
    print(process_bag_job(args.bag, args.out, settings, _robot(args.robot), _robot_yaml(args.robot), given,
                          resume=args.resume))
    return 0


def cmd_diagnose(args) -> int:
    from torchsoil.jobs.diagnose import diagnose_input

    extra = [f"diagnosis.n_fit={args.n_fit}"] if args.n_fit is not None else []
    if _many(args):
        return _run_many("diagnose", args, extra, args.out)
    if not args.input:
        raise FileNotFoundError("no input given: a recording or terrain pair, several, or --manifest CSV")
    settings, given = _bag_settings(args, extra)
    source = args.input[0]
    if not Path(source).exists():
        raise FileNotFoundError(f"input not found: {source}")
    summary = diagnose_input(source, args.out, settings, _robot(args.robot), tensorboard=not args.no_tensorboard,
                             overwrite=args.overwrite, robot_yaml=_robot_yaml(args.robot), threads=args.threads or 1,
                             extrinsics=given, resume=args.resume, workers=args.pass_workers,
                             engine=args.pass_engine)
    print(json.dumps({k: summary[k] for k in ("verdict", "missing_physics", "where")}, indent=1))
    return 0


def cmd_record(args) -> int:
    from torchsoil.jobs.record import record

    print(record(args.scenario, args.out, args.seed, args.dx, pair_only=args.pair_only, realistic=args.realistic,
                 storage=args.storage, compress=not args.no_compress, duration=args.duration, columns=args.columns,
                 organized=args.organized or None, convention=args.convention, imu=not args.no_imu,
                 gnss=not args.no_gnss, sessions=args.session))
    return 0


def cmd_rollout(args) -> int:
    from envs.scripted import compare_detour

    compare_detour(args.config, args.out, seed=args.seed, speed=args.speed, detour_y=args.detour_y)
    return 0


def cmd_bench(args) -> int:
    from torchsoil.bench import run_benchmarks

    run_benchmarks(args.out, args.only, args.quick)
    return 0


def cmd_ablation(args) -> int:
    from torchsoil.jobs.ablation import ablation

    print(ablation(args.input, args.out, args.config, [*args.set, *_topics(args)], _robot(args.robot),
                   _robot_yaml(args.robot), args.threads, _extrinsics(args)))
    return 0


def cmd_study(args) -> int:
    from torchsoil.jobs.study import study

    print(study(_settings(args), args.out, quick=args.quick, randomized=args.randomized, null=args.null,
                seed=args.seed, revisits=args.revisits, learned=args.learned, foreign=args.foreign,
                redraws=args.redraws,
                threads=args.threads, engine=args.engine, workers=args.workers, address=args.ray_address))
    return 0


def cmd_settings(args) -> int:
    print(_settings(args).to_yaml(args.sections or None), end="")
    return 0


COMMANDS = {"estimate": cmd_estimate, "process-bag": cmd_process_bag, "diagnose": cmd_diagnose, "export": cmd_export,
            "node": cmd_node, "field": cmd_field, "record": cmd_record, "rollout": cmd_rollout, "bench": cmd_bench,
            "ablation": cmd_ablation,
            "study": cmd_study, "settings": cmd_settings}


if __name__ == "__main__":
    raise SystemExit(main())
