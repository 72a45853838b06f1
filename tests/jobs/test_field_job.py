"""`torchsoil field`: add, info, maps and estimate on hand-built sessions of one world."""

import csv
import math

import numpy as np

from tests.field.sessions import World, planar
from torchsoil.cli import main

T_A = planar(math.radians(-20.0), 1.0, 2.0, 0.3)
T_B = T_A @ planar(math.pi, 3.0, 0.03, 0.0)           # back along A's lane, in its ruts


def test_field_commands(tmp_path, capsys):
    world = World(seed=3)
    a, _ = world.drive(T_A, 3.0, t0=0.0)
    b, _ = world.drive(T_B, 3.0, t0=86400.0)
    a.save(tmp_path / "monday.npz")
    b.save(tmp_path / "tuesday.npz")
    field = tmp_path / "field"
    assert main(["field", "add", str(field), str(tmp_path / "monday.npz")]) == 0
    assert main(["field", "add", str(field), str(tmp_path / "tuesday.npz")]) == 0
    out = capsys.readouterr().out
    assert "added s002_tuesday" in out and "the field holds 2 session(s)" in out
    assert main(["field", "add", str(field), str(tmp_path / "tuesday.npz")]) == 3      # already there
    assert "already in the field" in capsys.readouterr().err
    assert main(["field", "info", str(field)]) == 0
    info = capsys.readouterr().out
    assert "s001_monday" in info and "search+heights" in info
    assert main(["field", "maps", str(field), "--out", str(tmp_path / "maps")]) == 0
    season = np.load(tmp_path / "maps" / "season.npz")
    assert season["passes"].max() == 4 and (tmp_path / "maps" / "season.png").stat().st_size > 10000
    import rasterio

    with rasterio.open(tmp_path / "maps" / "season.tif") as src:            # the same layers, for GIS
        assert src.descriptions[:2] == ("passes", "rut_depth")
        band = src.read(1)[::-1].T                                          # rows run along -y
        np.testing.assert_array_equal(np.nan_to_num(band), np.nan_to_num(season["passes"] * (season["visits"] > 0)))
    lanes = list(csv.DictReader(open(tmp_path / "maps" / "lanes.csv")))
    # two ruts, each driven by both sessions: 2 wheel passes a day, 2 cm deeper each day
    assert sorted((r["lane"], r["session"]) for r in lanes) == [("1", "s001_monday"), ("1", "s002_tuesday"),
                                                                 ("2", "s001_monday"), ("2", "s002_tuesday")]
    for r in lanes:
        day = 1 if r["session"] == "s001_monday" else 2
        assert float(r["passes_before"]) == 2 * (day - 1) and float(r["passes"]) == 2
        assert abs(float(r["rut_depth_mm"]) - 20 * day) < 1.0
    assert main(["field", "estimate", str(field), "--out", str(tmp_path / "fit"),
                 "--set", "estimator.max_iter=5"]) == 0
    rows = list(csv.DictReader(open(tmp_path / "fit" / "season.csv")))
    first = [r for r in rows if r["session"] == "s001_monday"]
    second = [r for r in rows if r["session"] == "s002_tuesday"]
    assert first and second
    # Tuesday's wheels run in Monday's ruts: its windows start with Monday's passes (2 per rut cell)
    assert all(float(r["passes_before"]) == 0 for r in first)
    assert np.median([float(r["passes_before"]) for r in second]) >= 2
    # the window centres in the field frame: Tuesday's lie on Monday's lane
    fx = np.array([[float(r["field_x"]), float(r["field_y"])] for r in second])
    assert np.abs(fx[:, 1]).max() < 0.1 and fx[:, 0].min() > -0.2 and fx[:, 0].max() < 3.2
