"""`export` on a run whose recording carries GNSS: a bag of /tf_static and NavSatFix fixes
made beside the hand-built run (tests/geo/handbuilt.py), good, jumping, float-only, without a
fix and without the topic. Good fixes tie the map within 2 cm; bad ones are said and the
local-frame maps still written."""

from __future__ import annotations

import json

import numpy as np
import pytest
import rasterio

from tests.geo import handbuilt as hb
from torchsoil.geo.georef import Georef
from torchsoil.jobs.export import export
from torchsoil.synth.bagwriter import BagWriter, navsatfix_message
from torchsoil.synth.gnss import Datum

ANTENNA = np.array([-0.2, 0.0, 0.8])
DATUM = Datum()


def write_bag(path, case: str) -> None:
    poses = hb.pair().poses
    truth = DATUM.georef()
    xy = poses[:, 1:3] + ANTENNA[:2]           # yaw 0 along the whole drive
    en = truth.to_crs(xy)
    rng = np.random.default_rng(1)
    en = en + rng.normal(0, 0.01, en.shape)
    status, var = np.full(len(poses), 2), np.full(len(poses), 1e-4)
    if case == "jump":
        en[30:40, 0] += 2.0
    if case == "float_only":
        status[:], var[:] = 0, 0.3**2
    if case == "no_fix":
        status[:] = -1
    from torchsoil.geo.georef import unproject

    lat, lon = unproject(truth.epsg, en)
    with BagWriter(path) as bag:
        bag.write_tf_static([("base_link", "gnss_link", ANTENNA, np.array([0.0, 0.0, 0.0, 1.0]))], int(hb.T0 * 1e9))
        if case == "no_topic":
            return
        for k, t in enumerate(poses[:, 0]):
            t_ns = int(round(t * 1e9))
            bag.write_message("/gps/fix", "sensor_msgs/msg/NavSatFix",
                              navsatfix_message("gnss_link", t_ns, lat[k], lon[k], DATUM.up + 0.8, var[k], 4 * var[k],
                                                int(status[k])), t_ns)


@pytest.mark.parametrize("case", ["good", "jump", "float_only", "no_fix", "no_topic"])
def test_export_georeferences_from_the_recording_or_says_why_not(tmp_path, case):
    run = hb.write_run(tmp_path / "run")
    bag = tmp_path / "bag"
    write_bag(bag, case)
    meta = json.loads((run / "run.json").read_text())
    meta["input"]["path"] = str(bag)
    (run / "run.json").write_text(json.dumps(meta))
    lines = export(run, tmp_path / "out", formats=("geotiff",))
    g = Georef.load(tmp_path / "out" / "georef.json")
    assert (tmp_path / "out" / "soil.tif").is_file()
    if case in ("good", "jump"):
        assert g.kind == "gnss" and g.epsg == DATUM.georef().epsg
        poses = hb.pair().poses[:, 1:3]
        err = np.linalg.norm(g.to_crs(poses) - DATUM.georef().to_crs(poses), axis=1)
        assert err.max() < 0.02
        assert g.fit["outliers"] == (10 if case == "jump" else 0)
        with rasterio.open(tmp_path / "out" / "soil.tif") as src:
            assert src.crs.to_epsg() == g.epsg
    else:
        assert g.kind == "local"
        said = {"float_only": "RTK-fixed", "no_fix": "no fix", "no_topic": "no sensor_msgs/NavSatFix"}[case]
        assert any(said in ln for ln in lines), lines
