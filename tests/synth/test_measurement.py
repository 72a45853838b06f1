"""The generator's measurement nuisances and tyre draws (synth.measurement, synth.tyre),
each checked against what a hand calculation recovers from the maps."""

import json
import math

import numpy as np
import pytest
from scipy import ndimage, stats

from tests.synth.test_world import STRAIGHT, scenario, world
from torchsoil.grid import Grid
from torchsoil.settings import REALISTIC, MeasurementConfig, SettingsError, SynthConfig, TyreConfig, load_settings
from torchsoil.synth import effects as fx
from torchsoil.synth.measurement import apply_measurement
from torchsoil.synth.scenario import draw_tyre, make_terrain_pair
from torchsoil.synth.world import section_profile

GRID = Grid(0.02, (-1.0, -2.0), (600, 200))          # 12 m x 4 m
POSES = np.column_stack([np.linspace(0, 10, 501), np.linspace(0.0, 10.0, 501), np.zeros((501, 4)),
                         np.zeros(501)])             # along +x at y = 0
SURFACE = np.random.default_rng(0).normal(0.0, 0.01, GRID.shape)


def measure(seed=1, **cfg):
    """Measured maps of one untouched surface (H_f and H_b truths equal) and the draws."""
    return apply_measurement(SURFACE, SURFACE.copy(), GRID, POSES, MeasurementConfig(**cfg), seed)


def test_defaults_are_gaussian_noise_only():
    hf, hb, drawn = measure()
    assert drawn == {"noise_dof": None, "offset": 0.0, "tilt_x_deg": 0.0, "tilt_y_deg": 0.0,
                     "lost_front": 0.0, "lost_back": 0.0}
    for h in (hf, hb):
        assert np.std(h - SURFACE) == pytest.approx(0.003, rel=0.02)
    assert SynthConfig().measurement == MeasurementConfig() and SynthConfig().tyre == TyreConfig()


def test_offset_is_the_median_difference_on_untouched_ground():
    offsets = []
    for seed in range(6):
        hf, hb, drawn = measure(seed, offset=0.002)
        assert abs(drawn["offset"]) <= 0.002
        assert np.median(hb - hf) == pytest.approx(drawn["offset"], abs=5e-5)
        offsets.append(drawn["offset"])
    assert np.ptp(offsets) > 1e-3                    # drawn anew per seed, both signs likely
    _, hb2, drawn2 = measure(3, offset=0.002)
    np.testing.assert_array_equal(hb2, measure(3, offset=0.002)[1])   # reproducible from the seed


def test_tilt_is_the_slope_of_a_plane_fit():
    xs, ys = GRID.centers()
    X, Y = np.meshgrid(xs - xs.mean(), ys - ys.mean(), indexing="ij")
    A = np.column_stack([np.ones(X.size), X.ravel(), Y.ravel()])
    for seed in range(3):
        hf, hb, drawn = measure(seed, tilt_deg=0.05)
        c = np.linalg.lstsq(A, (hb - hf).ravel(), rcond=None)[0]
        for slope, key in zip(c[1:], ("tilt_x_deg", "tilt_y_deg"), strict=True):
            assert abs(drawn[key]) <= 0.05
            assert math.degrees(math.atan(slope)) == pytest.approx(drawn[key], abs=2e-3)
        assert c[0] == pytest.approx(0.0, abs=5e-5)  # tilted about the grid centre


def test_dropouts_are_the_drawn_fraction_independently_per_map():
    hf, hb, drawn = measure(dropout=(0.01, 0.01))
    n = hf.size
    for h, key in ((hf, "lost_front"), (hb, "lost_back")):
        assert np.isnan(h).mean() == pytest.approx(0.01, abs=4 * math.sqrt(0.01 / n))
        assert drawn[key] == np.isnan(h).mean()
    assert (np.isnan(hf) & np.isnan(hb)).mean() == pytest.approx(1e-4, abs=1e-4)


def test_blobs_cover_rate_times_mean_disc_area():
    hf, _, _ = measure(blobs=2.0, blob_radius=(0.02, 0.06))
    # E[pi r^2] for r uniform in [a, b] is pi (b^3 - a^3) / (3 (b - a)); 2 per m^2
    expected = 2.0 * math.pi * (0.06 ** 3 - 0.02 ** 3) / (3 * 0.04)
    assert np.isnan(hf).mean() == pytest.approx(expected, rel=0.3)


def test_occlusion_streaks_are_thin_lines_along_the_heading_near_the_path():
    hf, _, _ = measure(streaks=2.0, streak_length=(0.4, 0.8))
    lab, n = ndimage.label(np.isnan(hf), np.ones((3, 3)))
    assert 10 <= n <= 20 * 2                         # ~ 2 per m over 10 m (lines may touch)
    boxes = ndimage.find_objects(lab)
    along = np.array([b[0].stop - b[0].start for b in boxes])     # cells along x (the heading)
    across = np.array([b[1].stop - b[1].start for b in boxes])
    assert np.median(along) >= 15 and np.median(across) <= 0.35 * np.median(along)
    ys = GRID.centers()[1][np.nonzero(np.isnan(hf))[1]]
    assert np.abs(ys).max() < 1.0 + 0.8 * math.sin(math.radians(15)) + 0.05


def test_student_t_noise_has_the_level_and_the_tails_of_its_law():
    hf, _, drawn = measure(noise_dof=(3.0, 3.0))
    assert drawn["noise_dof"] == 3.0
    e = (hf - SURFACE).ravel() / 0.003               # unit variance by construction
    t = stats.t(3, scale=math.sqrt(1 / 3))
    assert np.median(np.abs(e)) == pytest.approx(t.ppf(0.75), rel=0.03)        # 0.44, Gaussian 0.67
    assert np.mean(np.abs(e) > 4) == pytest.approx(2 * t.sf(4), rel=0.15)     # ~0.9 %, Gaussian 6e-5
    _, _, d = measure(2, noise_dof=(3.0, 5.0))
    assert 3.0 <= d["noise_dof"] <= 5.0


def test_realistic_draws_stay_in_their_ranges_and_follow_the_seed():
    cfg = MeasurementConfig(**REALISTIC["measurement"])
    for seed in range(5):
        _, _, d = apply_measurement(SURFACE, SURFACE, GRID, POSES, cfg, seed)
        assert abs(d["offset"]) <= 0.002 and abs(d["tilt_x_deg"]) <= 0.05 and 3 <= d["noise_dof"] <= 5
        assert 0.005 < d["lost_front"] < 0.05
    tyres = [draw_tyre(TyreConfig(**REALISTIC["tyre"]), s) for s in range(40)]
    assert {t["section"] for t in tyres} == {"taper", "flat", "rounded", "crowned"}
    assert all(t["width_scale"] == 1.0 for t in tyres)     # a wider footprint is an effect, not a nuisance
    assert draw_tyre(TyreConfig(**REALISTIC["tyre"]), 7) == tyres[7]
    wide = [draw_tyre(TyreConfig(width_scale=(0.85, 1.25)), s)["width_scale"] for s in range(40)]
    assert all(0.85 <= w <= 1.25 for w in wide) and max(wide) - min(wide) > 0.2
    assert {t["dig_order"] for t in tyres} == {"robot", "wheel"}
    assert draw_tyre(TyreConfig(), 7) == {"section": "taper", "width_scale": 1.0, "dig_order": None}


def test_bad_ranges_are_refused():
    with pytest.raises(SettingsError, match="synth.measurement.noise_dof"):
        load_settings(overrides=["synth.measurement.noise_dof=[1.5, 3]"])
    with pytest.raises(SettingsError, match="synth.tyre.width_scale"):
        load_settings(overrides=["synth.tyre.width_scale=[0, 1]"])


def test_terrain_pair_carries_its_draws_and_the_offset_on_untouched_ground():
    small = {"name": "small", "trajectory": {"segments": [{"straight": 3.0, "speed": 1.0}]},
             "terrain": {"margin": 1.0}, "landmarks": {"poles": 0, "trunks": 0, "shed": False, "fence": False},
             "measurement": {"offset": 0.002, "noise_dof": [4, 4]}}
    pair = make_terrain_pair(small, seed=5)
    drawn = json.loads(str(pair["nuisances"]))["measurement"]
    untouched = pair["n_visits"] == 0
    assert np.median((pair["h_back"] - pair["h_front"])[untouched]) == pytest.approx(drawn["offset"], abs=1e-4)
    assert drawn["noise_dof"] == 4.0


def test_threshold_law_by_hand():
    np.testing.assert_allclose(fx.phi([-2.0, -0.5, 0.0, 0.3, 1.5], "threshold", x_s=1.0), [-1, 0, 0, 0, 0.5])
    e = fx.resolve({"multi_pass_hardening": {"form": "threshold", "k": -0.4, "x_s": 1.5}})
    # passes 1, 2 (x = 0, 1) within the threshold; pass 3: 1 - 0.4 * 0.5; pass 4: 1 - 0.4 * 1.5
    np.testing.assert_allclose(fx.pass_depth_factor(e, np.array([1, 2, 3, 4])), [1.0, 1.0, 0.8, 0.4])


def test_tyre_sections_by_hand():
    q = np.array([0.0, 0.6, -0.6, 0.85, 1.0, 1.2])
    np.testing.assert_allclose(section_profile(q, "rounded"), [1, 0.8, 0.8, math.sqrt(1 - 0.85 ** 2), 0, 0])
    np.testing.assert_allclose(section_profile(q, "crowned"), [1, 0.64, 0.64, 1 - 0.85 ** 2, 0, 0])
    np.testing.assert_allclose(section_profile(q, "flat")[:4], 1.0)
    shoulder = 0.5 * (1 + math.cos(math.pi * (0.6 - 0.5) / 0.5))                    # flat to |q| = 0.5
    np.testing.assert_allclose(section_profile(q, "taper", 0.5)[:3], [1, shoulder, shoulder])
    with pytest.raises(ValueError, match="tyre section"):
        section_profile(q, "square")


def test_world_digs_the_drawn_tyre_section_and_width():
    """beta 89 deg, flat ground: the rut floor at lateral offset y from the wheel centre sits
    d * sqrt(1 - (y / r)^2) deep for a rounded tyre of radius r = 1.3 * 0.07 m."""
    w = world({**scenario(STRAIGHT), "tyre": {"sections": ["rounded"], "width_scale": [1.3, 1.3]}})
    gx, gy = w.grid.centers()
    i = (gx > 2.0) & (gx < 5.0)
    depth = (w.h_before - w.h_after)[i].mean(0)
    r = 1.3 * 0.07
    for off in (0.0, 0.04, 0.06):
        j = np.argmin(np.abs(gy - (0.5 + off)))
        assert depth[j] == pytest.approx(0.03 * math.sqrt(1 - ((gy[j] - 0.5) / r) ** 2), abs=1.5e-3)
    near = np.abs(gy - 0.5) < 0.3                    # the left rut only
    wide = np.abs(gy - 0.5)[near & (depth > 0.005)].max()   # reaches 0.08 m out (nominal tyre: 0.06)
    assert 0.075 < wide <= r


def test_record_pair_only_realistic(tmp_path, capsys):
    import yaml

    from torchsoil.cli import main

    scn = tmp_path / "small.yaml"
    scn.write_text(yaml.safe_dump({"trajectory": {"segments": [{"straight": 3.0, "speed": 1.0}]},
                                   "terrain": {"margin": 1.0}, "landmarks": {"poles": 0, "trunks": 0}}))
    out = tmp_path / "p.npz"
    assert main(["record", "--scenario", str(scn), "--out", str(out), "--pair-only", "--realistic", "--seed", "2"]) == 0
    with np.load(out) as d:
        drawn = json.loads(str(d["nuisances"]))
        assert np.isnan(d["h_back"]).any()
    assert 3 <= drawn["measurement"]["noise_dof"] <= 5 and 0 < abs(drawn["measurement"]["offset"]) <= 0.002
    assert drawn["tyre"]["section"] in {"taper", "flat", "rounded", "crowned"}
    assert main(["record", "--scenario", str(scn), "--out", str(tmp_path / "bag"), "--realistic"]) == 2
    assert "--pair-only" in capsys.readouterr().err
