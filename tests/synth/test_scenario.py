"""Scenarios, trajectories and the terrain pair straight from the truth."""

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from torchsoil.settings import LandmarkConfig, SettingsError, SynthConfig, TrajectorySegment, load_settings, validate
from torchsoil.synth import effects as fx
from torchsoil.synth.scenario import SCENARIO_DIR, available, build_truth, load_scenario, make_terrain_pair
from torchsoil.synth.terrain import Relief, micro_topography, soil_at
from torchsoil.synth.trajectory import build_trajectory, planar_path

SMALL = {"name": "small", "trajectory": {"segments": [{"straight": 3.0, "speed": 1.0}]},
         "terrain": {"margin": 1.0}, "landmarks": {"poles": 2, "trunks": 1, "shed": True, "fence": True}}
REQUIRED = {"watered", "gravel", "road", "revisit", "flat", "tread", *fx.CATALOGUE}


def test_named_scenarios_exist_and_load():
    assert REQUIRED <= set(available())
    for name in available():
        scn = load_scenario(name)
        assert isinstance(scn, SynthConfig) and scn.name == name
        fx.resolve(scn.effects)                    # every effect section is valid
    for name in fx.CATALOGUE + fx.OUT_OF_CATALOGUE:
        assert list(fx.resolve(load_scenario(name).effects)) == [name]
    assert load_scenario("road").soil.base["d"] == 0.0
    assert load_scenario("flat").landmarks == LandmarkConfig(poles=0, trunks=0, shed=False, fence=False)
    assert load_scenario("demo").lidar.columns == 512


@pytest.mark.parametrize("name", available())
def test_every_shipped_scenario_validates_as_a_synth_section(name):
    """Each shipped YAML is a document of the settings' synth section, and holds only keys the
    section knows (validated directly, without the loader's merging)."""
    doc = yaml.safe_load((SCENARIO_DIR / f"{name}.yaml").read_text())
    direct = validate(SynthConfig, {**doc, "name": name}, name, prefix="synth.")
    assert load_scenario(name) == direct
    assert load_scenario(direct) is direct
    assert load_settings({"synth": {**doc, "name": name}}).synth == direct


def test_defaults_are_the_settings_defaults_and_lists_replace():
    assert load_scenario({}) == SynthConfig()
    assert load_scenario({}).name == "custom"
    # one arc replaces the default straight (merged element-wise it would be both and refused)
    scn = load_scenario({"trajectory": {"segments": [{"arc": 2.0, "angle_deg": 90}]}})
    assert scn.trajectory.segments == (TrajectorySegment(arc=2.0, angle_deg=90.0),)
    assert scn.trajectory.accel_limit == SynthConfig().trajectory.accel_limit
    # mappings merge key by key: the other soil base values keep their defaults
    assert load_scenario({"soil": {"base": {"d": 0.05}}}).soil.base == {"d": 0.05, "chi": 0.2, "beta_deg": 30.0,
                                                                          "moisture": 0.0}


def test_scenario_files_name_and_settings_documents(tmp_path):
    plain = tmp_path / "my_field.yaml"
    plain.write_text(yaml.safe_dump({"terrain": {"margin": 2.5}}))
    assert load_scenario(plain).name == "my_field" and load_scenario(str(plain)).terrain.margin == 2.5
    named = tmp_path / "other.yaml"
    named.write_text(yaml.safe_dump({"name": "kept", "terrain": {"margin": 2.5}}))
    assert load_scenario(named).name == "kept"
    # a full settings document: the synth section is the scenario, the rest is checked too
    full = tmp_path / "settings.yaml"
    full.write_text(yaml.safe_dump({"estimator": {"window": 1.0}, "synth": {"terrain": {"margin": 3.0}}}))
    scn = load_scenario(full)
    assert scn.terrain.margin == 3.0 and scn.name == "settings"
    assert load_scenario({"synth": {"name": "x", "lidar": {"columns": 512}}}).lidar.columns == 512
    full.write_text(yaml.safe_dump({"estimator": {"windw": 1.0}, "synth": {}}))
    with pytest.raises(SettingsError, match=r"settings.yaml: unknown setting `estimator.windw`"):
        load_scenario(full)
    # errors name the file and the key
    plain.write_text(yaml.safe_dump({"terrain": {"relief": {"amplitud": 0.1}}}))
    with pytest.raises(SettingsError, match=r"my_field.yaml: unknown setting `synth.terrain.relief.amplitud` "
                                            r"\(known here: amplitude, wavelength, slope_x, slope_y\)"):
        load_scenario(plain)


def test_unknown_scenario_keys_are_refused_naming_the_key():
    with pytest.raises(FileNotFoundError, match="available: .*watered"):
        load_scenario("no_such_field")
    with pytest.raises(SettingsError, match=r"unknown setting `synth.wheather`"):
        load_scenario({"trajectory": {}, "wheather": 1})
    with pytest.raises(SettingsError, match=r"unknown setting `synth.terrain.relief.amplitud`"):
        load_scenario({"terrain": {"relief": {"amplitud": 0.1}}})
    with pytest.raises(SettingsError, match=r"unknown setting `synth.world.chunks`"):
        load_scenario({"world": {"chunks": 0.1}})
    with pytest.raises(SettingsError, match=r"unknown setting `synth.trajectory.segments.1.spiral`"):
        load_scenario({"trajectory": {"segments": [{"straight": 1.0}, {"straight": 1.0, "spiral": 2.0}]}})
    with pytest.raises(SettingsError, match=r"`synth.effects.wind`: unknown effect 'wind'"):
        load_scenario({"effects": {"wind": {"k": 1.0}}})
    with pytest.raises(SettingsError, match=r"`synth.effects.tread`: .*unknown parameters \['colour'\]"):
        load_scenario({"effects": {"tread": {"colour": 2}}})
    with pytest.raises(SettingsError, match=r"`synth.soil.base` = a mapping: .*unknown keys \['wetness'\]"):
        load_scenario({"soil": {"base": {"wetness": 0.3}}})
    with pytest.raises(SettingsError, match=r"`synth.soil.patches.1`: a band_x patch .*unknown \['sigm'\]"):
        load_scenario({"soil": {"patches": [{"kind": "disc", "center": [0, 0], "sigma": 1.0},
                                            {"kind": "band_x", "center": 1.0, "sigm": 1.0}]}})
    with pytest.raises(SettingsError, match=r"`synth.soil.patches.0`: delta: unknown key 'wet'"):
        load_scenario({"soil": {"patches": [{"kind": "band_x", "center": 1.0, "sigma": 1.0, "delta": {"wet": 1}}]}})
    with pytest.raises(SettingsError, match=r"`synth.robot`: robot description 'no_robot' not found"):
        load_scenario({"robot": "no_robot"})


def test_wrong_types_are_refused_naming_the_key():
    with pytest.raises(SettingsError, match=r"`synth.terrain.micro.rms` = 'rough'"):
        load_scenario({"terrain": {"micro": {"rms": "rough"}}})
    with pytest.raises(SettingsError, match=r"`synth.landmarks.shed` = 'maybe'"):
        load_scenario({"landmarks": {"shed": "maybe"}})
    with pytest.raises(SettingsError, match=r"`synth.landmarks.poles` = 2.5"):
        load_scenario({"landmarks": {"poles": 2.5}})
    with pytest.raises(SettingsError, match=r"`synth.trajectory.segments` = 20"):
        load_scenario({"trajectory": {"segments": 20}})
    with pytest.raises(SettingsError, match=r"`synth.world.chunk` = 'big'"):
        load_scenario({"world": {"chunk": "big"}})
    with pytest.raises(SettingsError, match=r"`synth.lidar.columns` = 300"):
        load_scenario({"lidar": {"columns": 300}})
    with pytest.raises(SettingsError, match=r"`synth.terrain.margin` = -1"):
        load_scenario({"terrain": {"margin": -1}})
    with pytest.raises(SettingsError, match=r"`synth.soil.track_scale` = \[1.0, 1.0, 1.0\]: .* 2 tracks"):
        load_scenario({"soil": {"track_scale": [1, 1, 1]}})
    with pytest.raises(SettingsError, match=r"`synth.soil.patches.0`: `x1` must be a number"):
        load_scenario({"soil": {"patches": [{"kind": "lane", "x0": 0.0, "x1": "far"}]}})


def test_a_segment_is_a_straight_or_an_arc():
    both = {"trajectory": {"segments": [{"straight": 2.0}, {"straight": 1.0, "arc": 2.0, "angle_deg": 30}]}}
    with pytest.raises(SettingsError, match=r"`synth.trajectory.segments.1` = a mapping: .*either \{straight"):
        load_scenario(both)
    with pytest.raises(SettingsError, match=r"`synth.trajectory.segments.0` .*either \{straight"):
        load_scenario({"trajectory": {"segments": [{"speed": 1.0}]}})
    with pytest.raises(SettingsError, match=r"`synth.trajectory.segments.0` .*an arc segment needs angle_deg"):
        load_scenario({"trajectory": {"segments": [{"arc": 2.0}]}})


def test_path_and_soil_errors_name_the_problem():
    with pytest.raises(SettingsError, match=r"unknown setting `trajectory.segments\[1\].spiral`"):
        planar_path([{"straight": 1.0}, {"spiral": 2.0}])
    with pytest.raises(SettingsError, match=r"segments\[0\]\.speed` = 0.0: Input should be greater than 0"):
        planar_path([{"straight": 1.0, "speed": 0.0}])
    with pytest.raises(SettingsError, match=r"segments\[1\]\.arc` = -1.0: Input should be greater than 0"):
        planar_path([{"straight": 1.0}, {"arc": -1.0, "angle_deg": 10.0}])
    with pytest.raises(ValueError, match="soil.patches\\[0\\].delta: unknown key 'wetness'"):
        soil_at({"patches": [{"kind": "disc", "center": [0, 0], "sigma": 1, "delta": {"wetness": 1}}]}, 0.0, 0.0)
    with pytest.raises(SettingsError, match=r"unknown setting `soil.bse`"):
        soil_at({"bse": {"d": 0.1}}, 0.0, 0.0)


def test_dict_scenarios_of_the_diagnosis_study_are_accepted():
    from torchsoil.diagnosis.study_cases import STUDY_CASES

    for case, doc, *_ in STUDY_CASES:
        scn = load_scenario(doc)
        assert scn.name == doc["name"] and scn.world.chunk == 0.1, case
        assert scn.effects == doc.get("effects", {}), case


def test_terrain_pair_follows_formats_section_3():
    pair = make_terrain_pair(SMALL, seed=1)
    X, Y = pair["h_front"].shape
    assert pair["h_front"].dtype == pair["h_back"].dtype == np.float32
    assert pair["h_back"].shape == (X, Y)
    assert pair["dx"].shape == () and float(pair["dx"]) == 0.02
    assert pair["origin"].shape == (2,) and pair["origin"].dtype == np.float64
    assert pair["poses"].ndim == 2 and pair["poses"].shape[1] == 7
    assert np.all(np.diff(pair["poses"][:, 0]) > 0)
    np.testing.assert_allclose(pair["wheels"], [[0.69, 0.5, 0], [0.69, -0.5, 1], [-0.69, 0.5, 0], [-0.69, -0.5, 1]])
    assert float(pair["wheel_width"]) == 0.14
    # the whole drive's wheel paths lie inside the grid with margin
    x0, y0 = pair["origin"]
    assert x0 < -0.69 - 0.5 and x0 + (X - 1) * 0.02 > 3.0 + 0.69 + 0.5
    assert y0 < -1.0 and y0 + (Y - 1) * 0.02 > 1.0


def test_terrain_pair_noise_and_truth():
    truth = build_truth(SMALL, seed=2)
    pair = make_terrain_pair(SMALL, seed=2)
    w = truth.world
    nf, nb = pair["h_front"] - w.h_before, pair["h_back"] - w.h_after
    for n in (nf, nb):
        assert abs(n.mean()) < 2e-4
        assert n.std() == pytest.approx(0.003, rel=0.05)
    assert abs(np.corrcoef(nf.ravel(), nb.ravel())[0, 1]) < 0.02      # independent noise
    # the deformation stands out of the noise where the wheels went
    assert (pair["h_front"] - pair["h_back"]).max() > 0.02


def test_visit_layers_of_ground_driven_twice():
    """A short out-and-back through a keyhole turn (back on the same ruts): with visits, the
    pair holds two layers where the wheels came twice (FORMATS v1.1): the first before is
    h_front, each cell's last after is h_back, and the state between the visits, seen twice,
    is the world's (states[1]) up to the 3 mm noise, independently drawn in the two layers. A
    drive that never comes back gets no layers."""
    scn = {"name": "bulb", "trajectory": {"segments": [
        {"straight": 2.0, "speed": 1.0}, {"arc": 1.5, "angle_deg": -60, "speed": 1.0},
        {"arc": 1.5, "angle_deg": 300, "speed": 1.0}, {"arc": 1.5, "angle_deg": -60, "speed": 1.0},
        {"straight": 2.0, "speed": 1.0}]}, "terrain": {"margin": 1.0}}
    truth = build_truth(scn, seed=3)
    pair = make_terrain_pair(scn, seed=3, visits=True)
    w = truth.world
    n = np.isfinite(pair["visit_time"]).sum(0)
    assert pair["visit_front"].shape[0] == 2 and (n == 2).sum() > 2000
    np.testing.assert_array_equal(n, w.n_visits)
    np.testing.assert_array_equal(pair["visit_front"][0], np.where(n > 0, pair["h_front"], np.nan))
    last = np.take_along_axis(pair["visit_back"], np.maximum(n - 1, 0)[None], 0)[0]
    np.testing.assert_array_equal(last[n > 0], pair["h_back"][n > 0])
    twice = n == 2
    out, back = pair["visit_back"][0][twice] - w.states[1][twice], pair["visit_front"][1][twice] - w.states[1][twice]
    assert out.std() == pytest.approx(0.003, rel=0.1) and back.std() == pytest.approx(0.003, rel=0.1)
    assert abs(np.corrcoef(out, back)[0, 1]) < 0.05
    assert np.all(np.isnan(pair["visit_front"][1][n < 2]))
    assert not any(k.startswith("visit") for k in make_terrain_pair(SMALL, seed=1, visits=True))


def test_generation_is_deterministic_for_a_seed():
    a, b, c = (make_terrain_pair(SMALL, seed=s) for s in (4, 4, 5))
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    assert not np.array_equal(a["h_front"], c["h_front"])


def test_micro_topography_statistics():
    from torchsoil.grid import Grid

    g = Grid(0.02, (0.0, 0.0), (256, 256))
    h = micro_topography(g, np.random.default_rng(0), rms=0.008, corr_length=0.08)
    assert h.std() == pytest.approx(0.008, rel=1e-6)
    # correlation at one correlation length is well below 1 and clearly positive at one cell
    def corr(lag):
        return np.corrcoef(h[:-lag].ravel(), h[lag:].ravel())[0, 1]
    assert corr(1) > 0.8
    assert 0.05 < corr(4) < 0.7
    assert abs(corr(20)) < 0.1


def test_trajectory_speed_profile_and_attitude(robot):
    relief = Relief(0.05, 0.1, np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0))
    spec = {"segments": [{"straight": 3.0, "speed": 0.5}, {"straight": 5.0, "speed": 1.5},
                         {"arc": 2.0, "angle_deg": 90, "speed": 1.0}], "accel_limit": 0.5}
    tr = build_trajectory(spec, relief, robot)
    assert tr.speed.max() == pytest.approx(1.5, abs=1e-6) and tr.speed[0] == pytest.approx(0.5)
    assert np.abs(tr.accel).max() < 0.5 + 0.02
    assert tr.arc[-1] == pytest.approx(8.0 + math.pi, abs=0.05)
    assert tr.poses[-1, 6] == pytest.approx(math.pi / 2, abs=0.01)   # last sample < 10 ms from the end
    np.testing.assert_allclose(np.diff(tr.poses[:, 0]), 0.01)
    # on the straight heading +x: climbing 5 % (nose up, pitch < 0), left side 10 % higher
    i = np.searchsorted(tr.arc, 1.0)
    assert tr.poses[i, 5] == pytest.approx(-math.atan(0.05), abs=1e-3)
    assert tr.poses[i, 4] == pytest.approx(math.atan(0.1), abs=2e-3)
    assert tr.poses[i, 3] == pytest.approx(0.05 * tr.poses[i, 1] + 0.1 * tr.poses[i, 2], abs=1e-9)


def test_soil_fields_patch_weights():
    soil = {"base": {"d": 0.02, "beta_deg": 30.0},
            "patches": [{"kind": "band_x", "center": 5.0, "sigma": 1.0, "delta": {"d": 0.03, "beta_deg": 10.0}}]}
    s = soil_at(soil, np.array([5.0, 6.0, 50.0]), 0.0)
    np.testing.assert_allclose(s["d"], [0.05, 0.02 + 0.03 * math.exp(-0.5), 0.02])
    np.testing.assert_allclose(np.degrees(s["beta"]), [40.0, 30 + 10 * math.exp(-0.5), 30.0])


def _script_main():
    from torchsoil.cli import main

    return lambda argv: main(["record", *argv])


def test_make_recording_script_pair_only(tmp_path, capsys):
    import yaml

    main = _script_main()
    scn = tmp_path / "small.yaml"
    scn.write_text(yaml.safe_dump(SMALL))
    out = tmp_path / "p.npz"
    assert main(["--scenario", str(scn), "--out", str(out), "--seed", "1", "--pair-only"]) == 0
    with np.load(out) as d:
        np.testing.assert_array_equal(d["h_back"], make_terrain_pair(SMALL, seed=1)["h_back"])
    assert main(["--scenario", "nowhere", "--out", str(tmp_path / "x")]) == 2
    assert "available" in capsys.readouterr().err


def test_make_recording_script_runs_as_a_command(tmp_path):
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")])}
    r = subprocess.run([sys.executable, str(root / "scripts/make_recording.py"), "--help"],
                       capture_output=True, text=True, env=env)
    assert r.returncode == 0 and "--pair-only" in r.stdout
    assert all(name in r.stdout for name in ("watered", "multi_pass_hardening", "road"))   # shipped names


def test_every_effect_has_a_signature():
    assert set(fx.SIGNATURES) == set(fx.EFFECTS)
    for sig in fx.SIGNATURES.values():
        assert sig["cross_track"] in {"rut_floor", "rut_wall", "berm", "outside", "mixed"}


def test_no_wall_stands_across_a_narrow_field():
    """On a field 4 m either side of a 20 m drive the shed's side wall (4 m long, at the
    middle of the field plus 5 m) would reach the path; it is turned away from it, and every
    wall keeps its distance from the path (points along each wall's length, by hand)."""
    from torchsoil.synth.terrain import farm_landmarks

    path = np.column_stack([np.linspace(0.0, 20.0, 201), np.zeros(201)])
    flat = Relief(0.0, 0.0, np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0))
    lm = farm_landmarks(LandmarkConfig(poles=0, trunks=0, shed=True, fence=False), flat,
                        (-4.0, -4.0, 24.0, 4.0), np.random.default_rng(0), path)
    assert len(lm.boxes) == 2
    for cx, cy, _, half_length, _, _, yaw, _ in lm.boxes:
        t = np.linspace(-half_length, half_length, 81)
        x, y = cx + t * math.cos(yaw), cy + t * math.sin(yaw)
        beside = (x >= 0) & (x <= 20)
        assert np.abs(y[beside]).min() > 1.5, (cx, cy, yaw)
