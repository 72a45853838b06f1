"""The field store on hand-built sessions of one world with known transforms and passes."""

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from tests.field.sessions import World, planar
from torchsoil.field.register import transform_error
from torchsoil.field.store import Field, Refused, Session

T_A = planar(math.radians(3.0), 0.2, -0.3, 0.10)                 # session A's map frame in the world
# B: back along A's lane from its far end, 3 cm aside: B's tracks (its y = -0.5, +0.5) land at A's
# y = +0.53 and -0.47, each in one of A's ruts
T_B = T_A @ planar(math.pi, 8.0, 0.03, -0.15)


def _session(pair, name, key=None):
    return Session(pair, None, None, name, name, key or name)


@pytest.fixture(scope="module")
def season(tmp_path_factory):
    world = World(seed=1)
    a, pa = world.drive(T_A, 7.0, t0=1000.0)
    b, pb = world.drive(T_B, 7.0, t0=90000.0)
    root = tmp_path_factory.mktemp("field") / "field"
    f = Field.open(root, create=True)
    f.add(_session(a, "monday"), log=lambda s: None)
    f.add(_session(b, "tuesday"), log=lambda s: None)
    return root, (a, pa), (b, pb), world


def test_registration_recovers_the_known_transform(season):
    root, (a, _), (b, _), _ = season
    f = Field.open(root)
    assert [s["name"] for s in f.sessions] == ["monday", "tuesday"]
    np.testing.assert_allclose(f.transform(f.sessions[0]["id"]), np.eye(4))
    truth = np.linalg.inv(T_A) @ T_B                                  # B's frame in A's (= the field's)
    got = f.transform(f.sessions[1]["id"])
    pts = np.c_[b.poses[:, 1:3], np.zeros(len(b.poses))]
    err_m, err_deg = transform_error(got, truth, pts)
    assert err_m < 0.01 and err_deg < 0.1
    assert abs(got[2, 3] - truth[2, 3]) < 0.005
    assert f.sessions[1]["registration"]["relief"] > 0.8


def test_passes_before_a_session_are_the_earlier_sessions_wheel_passes(season):
    root, (a, pa), (b, pb), _ = season
    f = Field.open(root)
    prior = f.session_pair(f.sessions[1]["id"]).extras["passes_prior"]
    # the truth: A's passes at each of B's cells, through the known transforms
    xs = b.origin[0] + np.arange(b.h_front.shape[0]) * b.dx
    ys = b.origin[1] + np.arange(b.h_front.shape[1]) * b.dx
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    M = np.linalg.inv(T_A) @ T_B
    q = np.stack([gx, gy], -1) @ M[:2, :2].T + M[:2, 3]
    i = np.rint((q[..., 0] - a.origin[0]) / a.dx).astype(int)
    j = np.rint((q[..., 1] - a.origin[1]) / a.dx).astype(int)
    inside = (i >= 0) & (j >= 0) & (i < pa.shape[0]) & (j < pa.shape[1])
    truth = np.zeros(gx.shape, int)
    truth[inside] = pa[i[inside], j[inside]]
    interior = (gx > 1.0) & (gx < 6.0)                # away from where a wheel's disc starts and stops
    # two axles on a track: 2 passes; a cell within a cell's width of a rut edge may differ
    edge = np.zeros_like(truth, bool)
    for s in (-2, -1, 1, 2):
        edge |= np.roll(truth, s, axis=1) != truth
    ok = interior & ~edge
    assert (truth[ok] == 2).sum() > 1000
    assert np.mean(prior[ok] == truth[ok]) > 0.98
    assert (f.session_pair(f.sessions[0]["id"]).extras["passes_prior"] == 0).all()


def test_the_season_adds_passes_and_keeps_the_first_and_latest_surface(season):
    root, (a, pa), (b, pb), world = season
    f = Field.open(root)
    grid, lay = f.season_grid()
    assert lay["passes"].sum() == sum(s["passes"] for s in f.sessions)
    assert lay["passes"].max() == 4                               # the shared rut: 2 + 2 wheel passes
    assert lay["sessions"].max() == 2
    # the latest surface is the world after both sessions, in the field frame (A's)
    xs, ys = grid.centers()
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    w = np.stack([gx, gy], -1) @ T_A[:2, :2].T + T_A[:2, 3]
    truth = world.height(w) - T_A[2, 3]
    ok = np.isfinite(lay["latest"]) & np.isfinite(truth)
    assert ok.sum() > 50000
    assert np.median(np.abs(lay["latest"][ok] - truth[ok])) < 0.002
    deep = lay["first"] - lay["latest"]
    assert np.nanmax(deep) > 0.035                               # two sessions' ruts, 2 cm each


def test_a_session_already_there_is_refused(season):
    root, (a, _), _, _ = season
    f = Field.open(root)
    before = (root / "field.json").read_bytes()
    with pytest.raises(Refused, match="already in the field"):
        f.add(_session(a, "monday again", key="another key"), log=lambda s: None)
    assert (root / "field.json").read_bytes() == before


def test_a_session_of_another_field_is_refused(season, tmp_path):
    root, *_ = season
    other, _ = World(seed=7).drive(T_A, 7.0, t0=5.0e5)
    before = (root / "field.json").read_bytes()
    with pytest.raises(Refused, match="another field"):
        Field.open(root).add(_session(other, "elsewhere"), log=lambda s: None)
    assert (root / "field.json").read_bytes() == before
    assert sorted(p.name for p in (root / "sessions").iterdir()) == [s["id"] for s in Field.open(root).sessions]


def test_an_ambiguous_registration_is_refused(tmp_path):
    world = World(flat_lanes=True)                       # straight furrows: nothing fixes a slide along them
    a, _ = world.drive(planar(0.0, 0.0, 0.0), 7.0, t0=0.0, depth=0.0)
    b, _ = world.drive(planar(0.0, 1.5, 0.0), 5.0, t0=1e5, depth=0.0)
    f = Field.open(tmp_path / "f", create=True)
    f.add(_session(a, "a"), log=lambda s: None)
    with pytest.raises(Refused, match="ambiguous"):
        f.add(_session(b, "b"), log=lambda s: None)
    assert len(Field.open(tmp_path / "f").sessions) == 1


KILL = """
import os, sys, numpy as np
from torchsoil.field import store
from torchsoil.io.terrain_pair import TerrainPair
real = os.replace
def replace(a, b):
    if str(b).endswith("field.json"):
        os.kill(os.getpid(), 9)                  # killed just before the commit
    real(a, b)
store.os.replace = replace
pair = TerrainPair.load(sys.argv[2])
store.Field.open(sys.argv[1]).add(store.Session(pair, None, None, "late", "late", "late"), log=print)
"""


def test_a_kill_during_add_leaves_the_field_as_it_was(tmp_path):
    world = World(seed=1)
    a, _ = world.drive(T_A, 7.0, t0=0.0)
    b, _ = world.drive(T_B, 7.0, t0=0.0)          # the same times and length as a: not the same session
    f = Field.open(tmp_path / "f", create=True)
    f.add(_session(a, "a"), log=lambda s: None)
    before = (tmp_path / "f" / "field.json").read_bytes()
    tiles_before = Field.open(tmp_path / "f").season_grid()[1]["passes"]
    b.save(tmp_path / "b.npz")
    r = subprocess.run([sys.executable, "-c", KILL, str(tmp_path / "f"), str(tmp_path / "b.npz")],
                       capture_output=True, text=True, env={**os.environ, "PYTHONPATH": os.getcwd()})
    assert r.returncode == -9, r.stderr
    assert (tmp_path / "f" / "field.json").read_bytes() == before
    g = Field.open(tmp_path / "f")
    assert len(g.sessions) == 1
    np.testing.assert_array_equal(g.season_grid()[1]["passes"], tiles_before)
    assert any(p.name.endswith(".part") or p.name not in {s["id"] for s in g.sessions}
               for p in (tmp_path / "f" / "sessions").iterdir())          # the killed add's files are there...
    g.add(_session(b, "b"), log=lambda s: None)                             # ... and gone after the next add
    names = json.loads((tmp_path / "f" / "field.json").read_text())
    assert sorted(p.name for p in (tmp_path / "f" / "sessions").iterdir()) == [s["id"] for s in names["sessions"]]
    referenced = set(names["tiles"].values())
    assert {f"tiles/{p.name}" for p in (tmp_path / "f" / "tiles").iterdir()} == referenced


def test_a_session_older_than_the_last_is_refused_when_times_are_clock_times(tmp_path):
    world = World(seed=1)
    a, _ = world.drive(T_A, 7.0, t0=1.7e9 + 86400)          # Tuesday, added first
    b, _ = world.drive(T_B, 7.0, t0=1.7e9)                  # Monday
    f = Field.open(tmp_path / "f", create=True)
    f.add(_session(a, "tuesday"), log=lambda s: None)
    with pytest.raises(Refused, match="in the order they were driven"):
        f.add(_session(b, "monday"), log=lambda s: None)


def test_a_session_without_ground_is_refused(tmp_path):
    a, _ = World(seed=1).drive(T_A, 7.0, t0=0.0)
    a.h_front[:] = np.nan
    with pytest.raises(Refused, match="unusable recording"):
        Field.open(tmp_path / "f", create=True).add(_session(a, "blind"), log=lambda s: None)
    assert not (tmp_path / "f" / "field.json").exists()
