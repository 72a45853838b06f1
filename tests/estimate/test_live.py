"""Estimation while the recording streams in: windows come as their ground is complete, agree
with the estimator run on the whole drive's terrain pair, far tiles leave memory, and the
message-level API a robot's own code calls gives the same rows as playing the bag."""

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from torchsoil.estimate.estimator import Estimator
from torchsoil.estimate.live import LiveEstimator, play
from torchsoil.robot import Robot
from torchsoil.settings import load_settings
from torchsoil.synth.bagwriter import TYPESTORE
from torchsoil.synth.record import make_recording

# the long tier (`python3 -m pytest -m long`): the streamed drive takes a minute to play; the
# node's tests (tests/node/test_node_body.py) run the live estimator in the quick tier
pytestmark = pytest.mark.long

DRIVE = {"name": "soft", "trajectory": {"segments": [{"straight": 13.0, "speed": 1.0}]},
         "terrain": {"margin": 4.0},
         "soil": {"base": {"d": 0.03, "chi": 0.3, "beta_deg": 30.0}},
         "landmarks": {"poles": 6, "trunks": 3, "shed": True, "fence": True},
         "lidar": {"columns": 512}}


@pytest.fixture(scope="session")  # tests/conftest.py SHARED_FIXTURES: built once per worker
def streamed(tmp_path_factory):
    """A 12 s drive on soft soil played through LiveEstimator: (bag, robot, settings, live,
    rows, how many came before the recording ended). The fits run on the worker thread, with
    at most one stretch queued: how far they may fall behind the feed is then set by the
    queue, not by how busy the machine is (the test suite runs a process per core)."""
    root = tmp_path_factory.mktemp("live")
    make_recording(DRIVE, root / "soft", seed=2, duration=12.0)
    robot = Robot.from_yaml(root / "soft.robot.yaml")
    settings = load_settings(overrides=["pipeline.raster.max_range=8",   # tiles leave memory sooner
                                        "estimator.online.max_pending=1"])
    live = LiveEstimator(robot, settings, spill_dir=str(root / "tiles"))
    rows, online = [], 0
    for w in play(root / "soft", live):
        rows.append(w.output.row)
        online += not live.pipeline.finished
    return root / "soft", robot, settings, live, rows, online


def test_windows_come_while_driving_and_agree_with_the_whole_drive(streamed):
    _, _, settings, live, rows, online = streamed
    stride = settings.estimator.stride
    centres = [r["s"] - settings.estimator.window / 2 for r in rows]
    np.testing.assert_allclose(centres, stride * np.arange(len(rows)), atol=1e-9)   # each window once, in order
    assert online >= len(rows) / 2
    batch = [o.row for o in Estimator(live.pipeline.terrain(), settings.estimator, settings.sim).run()]
    assert [round(r["s"], 6) for r in rows] == [round(r["s"], 6) for r in batch]
    both = [(a, b) for a, b in zip(rows, batch, strict=True) if np.isfinite(a["d1"]) and np.isfinite(b["d1"])]
    assert len(both) >= 8
    for name, tol in (("d1", 0.004), ("d2", 0.004), ("beta", 4.0)):
        live_mean = np.mean([a[name] for a, _ in both])
        batch_mean = np.mean([b[name] for _, b in both])
        assert abs(live_mean - batch_mean) < tol, (name, live_mean, batch_mean)
    assert np.mean([a["d1"] for a, _ in both]) == pytest.approx(0.03, abs=0.008)


def test_far_tiles_leave_memory_and_come_back_unchanged(streamed):
    """Spilled tiles hold what memory would have: the whole drive's maps equal those of the
    same pipeline run without spilling (front and back tiles kept apart on disk)."""
    from torchsoil.pipeline.run import process_bag

    bag, robot, settings, live, _, _ = streamed
    kept = process_bag(bag, robot, settings.pipeline).terrain
    spilled = live.pipeline.terrain()
    for key in ("h_front", "h_back"):
        np.testing.assert_array_equal(getattr(kept, key), getattr(spilled, key))
    layers = [t for name in ("front", "back", "back_before") for t in live.pipeline.tiles[name]]
    assert len({t.spill_dir for t in layers}) == len(layers)   # one tile file per stream, visit layer and cell
    back = (live.pipeline.tiles["back"][0], live.pipeline.tiles["back_before"][0])
    assert any(t.spilled for t in back), "a 12 m drive with an 8 m raster range leaves tiles behind"
    x_end = live.pipeline.trajectory()[1][-1, 0, 3]
    keep = settings.pipeline.raster.max_range + settings.pipeline.raster.corridor_width
    for tiles in back:
        side = tiles.size * tiles.dx
        for i, _ in tiles.tiles:  # what is still in memory is near the end of the drive
            assert (i + 1) * side > x_end - keep - side


def test_messages_fed_one_by_one_give_the_same_rows(streamed):
    """The robot-side API: TF, PointCloud2 and Imu messages as a node's callbacks get them,
    fitted in the caller's thread, give the rows `play` got from the worker thread."""
    bag, robot, settings, _, rows, _ = streamed
    assert settings.estimator.online.worker == "thread"
    settings = load_settings(overrides=["pipeline.raster.max_range=8", "estimator.online.worker=none"])
    live = LiveEstimator(robot, settings)
    r = settings.pipeline.read
    got = []
    with AnyReader([bag], default_typestore=TYPESTORE) as reader:
        for conn, _, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.msgtype == "tf2_msgs/msg/TFMessage":
                live.add_transforms(msg)
            elif conn.msgtype == "sensor_msgs/msg/Imu":
                live.add_imu(msg)
            elif conn.topic in (r.front_topic, r.back_topic):
                live.add_message(conn.topic, msg, conn.msgtype)
                got += [w.output.row for w in live.poll()]
    got += [w.output.row for w in live.finish()]
    assert len(got) == len(rows)
    for a, b in zip(got, rows, strict=True):
        assert a["s"] == b["s"] and (a["d1"] == b["d1"] or np.isnan(a["d1"]) and np.isnan(b["d1"]))


def test_an_interrupted_streamed_run_resumes_without_refitting(streamed, straight, tmp_path):
    """`estimate BAG` streams; cut after 6 windows (as a killed run leaves it: no terrain pair
    yet), `--resume` keeps those rows and fits only the rest."""
    import csv
    import shutil

    from torchsoil.jobs.estimate import estimate

    bag, robot, settings, _, _, _ = streamed
    out = tmp_path / "run"        # the drive estimated straight through (`straight`: the same settings), copied
    shutil.copytree(straight, out)
    with (out / "params.csv").open() as f:
        full = list(csv.DictReader(f))
    assert (out / "terrain_pair.npz").exists() and len(full) >= 12
    # the stitched simulation lies on the final maps: windows fitted before the world frame's
    # levelling was corrected (the recorder's IMU bias, told at the end) add their change to
    # the final H_f, so the simulated change beside the ruts has no ramp along the drive
    with np.load(out / "simulated.npz") as f:
        change, dx = f["h_sim"] - f["h_front"], float(f["dx"])
    per_metre = [np.nanmedian(change[i:i + int(1 / dx)]) for i in range(0, len(change), int(1 / dx))
                 if np.isfinite(change[i:i + int(1 / dx)]).sum() > 1000]
    assert len(per_metre) >= 8 and np.ptp(per_metre) < 1e-3, np.round(1e3 * np.array(per_metre), 2)
    for name in ("params.csv", "reference.csv"):
        lines = (out / name).read_text().splitlines()
        (out / name).write_text("\n".join(lines[:7]) + "\n")
    (out / "terrain_pair.npz").unlink()
    estimate(bag, out, settings, robot=robot, tensorboard=False, progress=False, resume=True)
    with (out / "params.csv").open() as f:
        again = list(csv.DictReader(f))
    assert len(again) == len(full)
    assert again[:6] == full[:6]                       # kept as written, not refitted
    for a, b in zip(again[6:], full[6:], strict=True):
        assert a["s"] == b["s"]
        if a["d1"] != "nan":
            assert abs(float(a["d1"]) - float(b["d1"])) < 0.002


@pytest.mark.parametrize("worker", ["thread", "none"])
def test_a_failed_fit_reaches_the_caller(streamed, worker):
    """A window fit that fails in the worker (here: too few untouched cells to fit the map
    offset on) raises in the caller's thread with its own message, not silently."""
    bag, robot, _, _, _, _ = streamed
    settings = load_settings(overrides=[f"estimator.online.worker={worker}", "estimator.nuisance.min_cells=10000000"])
    live = LiveEstimator(robot, settings)
    with pytest.raises(ValueError, match="untouched cells"):
        for _ in play(bag, live):
            pass
    live.close()


# ---- faults: a killed run resumes to the straight run's rows; a full disk stops with a clear error

SETS = ["--set", "pipeline.raster.max_range=8", "--set", "estimator.online.max_pending=1"]   # as `streamed`


def _cli(bag: Path, out: Path, *extra: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    return subprocess.Popen([sys.executable, "-m", "torchsoil", "estimate", str(bag), "--robot",
                             f"{bag}.robot.yaml", "--out", str(out), "--no-tensorboard", *SETS, *extra],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _cli_here(bag: Path, out: Path, *extra: str) -> int:
    """The same command line run in this process (`torchsoil.cli.main`, no interpreter and imports to
    start again), for the runs that are not killed."""
    from torchsoil.cli import main

    return main(["estimate", str(bag), "--robot", f"{bag}.robot.yaml", "--out", str(out), "--no-tensorboard", *SETS,
                 *extra])


def _rows(path: Path) -> list[dict]:
    with path.open() as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def straight(streamed, tmp_path_factory) -> Path:
    """Output folder of the streamed drive estimated in one go by the command line."""
    out = tmp_path_factory.mktemp("straight")
    assert _cli_here(streamed[0], out) == 0
    assert len(_rows(out / "params.csv")) >= 12
    return out


def _same_rows(rows: list[dict], full: list[dict]) -> None:
    assert [r["s"] for r in rows] == [r["s"] for r in full]           # each window once, none lost
    for a, b in zip(rows, full, strict=True):
        for k in ("d1", "d2", "chi", "beta", "residual"):
            x, y = float(a[k]), float(b[k])
            assert (np.isnan(x) and np.isnan(y)) or abs(x - y) <= 1e-3 * max(abs(y), 1e-3), (a["s"], k, x, y)


def test_a_killed_streamed_estimate_resumes_to_the_straight_run(streamed, straight, tmp_path):
    """SIGKILL once a third of the windows are written, then `--resume`: the same windows, the
    rows written before the kill kept as they were, the rest equal to a straight run's."""
    bag, full = streamed[0], _rows(straight / "params.csv")
    out = tmp_path / "killed"
    run = _cli(bag, out)
    params = out / "params.csv"
    while run.poll() is None and not (params.exists() and len(params.read_text().splitlines()) > len(full) // 3):
        time.sleep(0.05)
    assert run.poll() is None, "the run ended before it could be killed"
    run.send_signal(signal.SIGKILL)
    run.wait()
    before = _rows(params)[:len(_rows(out / "reference.csv"))]   # a window is written once both its rows are
    assert 0 < len(before) < len(full)
    again = _cli(bag, out, "--resume")
    assert again.wait(timeout=600) == 0, again.stderr.read().decode()[-2000:]
    rows = _rows(params)
    assert rows[:len(before)] == before                               # kept as written
    _same_rows(rows, full)


def test_a_run_stopped_inside_a_stretch_resumes_to_the_straight_run(streamed, straight, tmp_path):
    """Windows are fitted a few at a time on one stretch cut out of the maps, and a window's
    H_b and map offset depend on its stretch. A run stopped after one, then after two, windows
    of the same stretch (one of two consecutive counts falls inside one: estimator.online.batch
    2) resumes to the straight run's rows: the stretches are cut where they were."""
    bag, full = streamed[0], _rows(straight / "params.csv")
    for n in (len(full) // 2, len(full) // 2 + 1):
        out = tmp_path / f"stopped{n}"
        out.mkdir()
        (out / "run.json").write_text((straight / "run.json").read_text())
        for name in ("params.csv", "reference.csv"):      # the header and the first n windows
            lines = (straight / name).read_text().splitlines(keepends=True)
            (out / name).write_text("".join(lines[:n + 1]))
        assert _cli_here(bag, out, "--resume") == 0
        _same_rows(_rows(out / "params.csv"), full)


def test_a_drive_too_long_for_one_pair_is_written_as_pieces_that_export_reads(streamed, tmp_path):
    """Over estimator.online.max_cells the heightmaps stay as tiles and the drive is written as
    terrain pairs of piece_length m: consecutive, on one lattice, holding the whole drive's
    heights (those of the fixture's own run of the pipeline, all but a few cells), and
    `export` paints the rows over them."""
    from torchsoil.geo.layers import load_run, raster_layers
    from torchsoil.io.terrain_pair import TerrainPair
    from torchsoil.jobs.estimate import estimate

    bag, robot, _, live, _, _ = streamed
    settings = load_settings(overrides=["pipeline.raster.max_range=8", "estimator.online.max_pending=1",
                                        "estimator.online.max_cells=1000", "estimator.online.piece_length=4"])
    out = estimate(bag, tmp_path / "run", settings, robot=robot, tensorboard=False, progress=False)
    assert not (out / "terrain_pair.npz").exists()
    pieces = sorted((out / "pieces").glob("piece_*.npz"))
    assert len(pieces) >= 3
    arc0 = [float(TerrainPair.load(p).extras["arc0"]) for p in pieces]
    assert arc0[0] == 0.0 and np.all(np.diff(arc0) == pytest.approx(4.0, abs=0.2))
    run = load_run(out)
    whole = live.pipeline.terrain()
    g, w = run.grid, whole.grid
    oi, oj = (int(round((w.origin[d] - g.origin[d]) / g.dx)) for d in (0, 1))
    layers = raster_layers(run)
    X, Y = w.shape
    for name in ("h_front", "h_back"):   # the same up to a few cells (0.04 % seen, under 1 mm)
        mine = layers[name][oi:oi + X, oj:oj + Y]
        ref = getattr(whole, name)
        assert mine.shape == ref.shape
        same = (mine == ref) | (np.isnan(mine) & np.isnan(ref))
        assert same.mean() > 0.999 and np.nanmax(np.abs(mine - ref)) < 0.002
    d1 = layers["d1"][oi:oi + X, oj:oj + Y]
    assert np.isfinite(d1).mean() > 0.3 and np.nanmedian(d1) == pytest.approx(0.03, abs=0.008)
