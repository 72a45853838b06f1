"""Statistics of mismatch location: honest p-values for autocorrelated series, spectral
lines, paired comparisons and the cross-track zones."""

import math

import numpy as np
import pytest

from torchsoil.diagnosis.locate import ZONES, Profiles, line_zone, spectral_line, zone_of
from torchsoil.diagnosis.stats import (
    combined_z,
    correlation,
    evidence_basis,
    gain_correlation,
    lag1,
    paired_improvement,
)


def ar1(rng, n, phi):
    x = np.zeros(n)
    e = rng.standard_normal(n)
    for i in range(1, n):
        x[i] = phi * x[i - 1] + e[i]
    return x


def test_effective_sample_size_keeps_false_alarms_near_nominal():
    rng = np.random.default_rng(0)
    naive = corrected = 0
    trials = 300
    for _ in range(trials):
        x, y = ar1(rng, 50, 0.9), ar1(rng, 50, 0.9)           # independent, slowly drifting
        c = correlation(x, y)
        corrected += c.p < 0.05
        r = c.r
        t = r * np.sqrt((c.n - 2) / (1 - r * r))
        from scipy import stats
        naive += 2 * stats.t.sf(abs(t), c.n - 2) < 0.05
    assert naive / trials > 0.3                                # the plain test is fooled
    assert corrected / trials < 0.12                           # the corrected one is not


def test_real_dependence_is_found():
    rng = np.random.default_rng(1)
    x = rng.standard_normal(40)
    c = correlation(x, 0.8 * x + 0.3 * rng.standard_normal(40))
    assert c.r > 0.8 and c.p < 1e-6


def test_correlation_of_constant_series_is_not_significant():
    assert correlation(np.ones(10), np.arange(10.0)).p == 1.0


def test_spectral_line_found_at_its_wavelength_and_absent_in_noise():
    rng = np.random.default_rng(2)
    dx = 0.02
    s = np.arange(0, 10, dx)
    line = spectral_line(0.003 * np.cos(2 * np.pi * s / 0.25) + 0.003 * rng.standard_normal(len(s)), dx)
    assert line["p"] < 1e-4 and abs(line["wavelength"] - 0.25) < 0.01
    assert abs(line["amplitude"] - 0.003) < 0.0006          # the cosine's amplitude, put in by hand
    false = sum(spectral_line(0.003 * rng.standard_normal(len(s)), dx)["p"] < 0.01 for _ in range(60))
    assert false <= 4


def test_paired_improvement_recovers_a_shift():
    rng = np.random.default_rng(3)
    base = 3e-3 + 3e-4 * rng.standard_normal(200)
    m, se, z = paired_improvement(base, base - 1e-4 + 2e-5 * rng.standard_normal(200))
    assert abs(m - 1e-4) < 3 * se and z > 10
    m0, _, z0 = paired_improvement(base, base)
    assert m0 == 0 and z0 == 0


def test_paired_comparison_tests_the_windows_a_term_changes():
    """A term that acts on 16 of 80 windows (a revisited stretch) with a steady 0.3 mm gain:
    the 64 windows it leaves exactly as they were say nothing about the noise of the gain.
    Counted as samples, they would hold z near the square root of the 4 blocks it touches
    (at most 2), however large and steady the gain."""
    rng = np.random.default_rng(7)
    base = 3e-3 + 3e-4 * rng.standard_normal(80)
    ext = base.copy()
    ext[32:48] -= 3e-4 + 3e-5 * rng.standard_normal(16)
    m, se, z = paired_improvement(base, ext)
    assert abs(m - 3e-4) < 3 * se and z > 3
    hits = 0
    for _ in range(300):                                     # no gain, only noise where it acts
        noisy = base.copy()
        noisy[32:48] += 3e-5 * rng.standard_normal(16)
        hits += paired_improvement(base, noisy)[2] > 1.96
    assert hits / 300 < 0.08                                 # nominal 0.025


def test_a_gain_that_follows_the_effect_along_the_drive_is_not_its_noise():
    """A term whose gain shrinks steadily along a 10 m drive (its effect follows the ruts'
    depth, which the soil changes), from 1.4 mm to 0.5 mm, with 0.05 mm of noise per window:
    every block gains, and the trend is the term's, not noise. Counted as noise (the spread
    of the block means about their mean), it held z near 2 on six blocks."""
    rng = np.random.default_rng(11)
    base = 3e-3 + 3e-4 * rng.standard_normal(24)
    gain = np.linspace(1.4e-3, 0.5e-3, 24)
    m, se, z = paired_improvement(base, base - gain - 5e-5 * rng.standard_normal(24))
    assert abs(m - gain.mean()) < 3 * se and z > 3


def test_a_trend_through_zero_is_no_gain():
    """A term that helps on the first half of a drive and hurts as much on the second (it
    stands in for soil that changes along it), with correlated noise on 24 windows: the line
    through the block means does not make a gain of it."""
    from scipy.signal import lfilter

    rng = np.random.default_rng(5)
    trend = np.linspace(1.0, -1.0, 24)
    hits = sum(paired_improvement(trend + lfilter([1], [1, -0.5], rng.standard_normal(24)), np.zeros(24))[2] > 1.96
               for _ in range(400))
    assert hits / 400 < 0.08                                      # nominal 0.025


def test_combined_z_by_hand():
    """Stouffer's z of two tests: independent, sqrt(2) times their mean; fully dependent,
    their mean; a negative correlation is not trusted (as independent); an own-fit z not
    measured leaves the held-out z alone."""
    assert combined_z(2.0, 2.0, 0.0) == pytest.approx(2.0 * math.sqrt(2.0))
    assert combined_z(2.0, 1.0, 1.0) == pytest.approx(1.5)
    assert combined_z(2.0, 1.0, 0.5) == pytest.approx(3.0 / math.sqrt(3.0))
    assert combined_z(2.0, -1.0, -0.8) == pytest.approx(1.0 / math.sqrt(2.0))
    assert combined_z(1.7, math.inf, 0.0) == 1.7 and combined_z(1.7, math.nan, 0.0) == 1.7


def test_gain_correlation_of_block_means_about_their_line():
    """Six blocks of four windows: the correlation of the block means' scatter about a line
    (numpy's polyfit here), clipped at 0; a NaN window drops out of both series; fewer than
    three blocks give 1."""
    rng = np.random.default_rng(2)
    ma, mb = rng.standard_normal(6), rng.standard_normal(6)
    ga, gb = np.repeat(ma, 4) + 0.3 * np.arange(24), np.repeat(mb, 4) - 0.1 * np.arange(24)
    x = np.arange(6.0)
    ra, rb = (m - np.polyval(np.polyfit(x, m, 1), x) for m in (ga.reshape(6, 4).mean(1), gb.reshape(6, 4).mean(1)))
    want = max(float(np.corrcoef(ra, rb)[0, 1]), 0.0)
    zero = np.zeros(24)
    assert gain_correlation(ga, zero, gb, zero) == pytest.approx(want)
    assert gain_correlation(ga, zero, 2 * ga + 5, zero) == pytest.approx(1.0)
    assert gain_correlation(ga, zero, -ga, zero) == 0.0
    holed = np.r_[ga[:1], np.nan, ga[1:23]]                           # window 1 unmeasured: the rest shift up
    assert gain_correlation(holed, np.zeros(24), np.r_[gb[:1], 0.0, gb[1:23]], zero) == pytest.approx(
        gain_correlation(ga[:23], zero[:23], gb[:23], zero[:23]))
    assert gain_correlation(ga[:8], zero[:8], gb[:8], zero[:8]) == 1.0


def test_combined_test_counts_one_piece_of_evidence_once():
    """No gain, only noise: when the own-fit gain is the held-out gain's own noise again
    (the same windows' misfit seen twice), the combination must not count it twice; when it
    is independent noise it keeps the level too. A gain on both tests, each short of the
    level alone, passes it together."""
    rng = np.random.default_rng(8)
    zero, level, n = np.zeros(32), 1.96, 400
    same = indep = 0
    for _ in range(n):
        a, b = 3e-4 * rng.standard_normal(32), 3e-4 * rng.standard_normal(32)
        za, zb = paired_improvement(a, zero)[2], paired_improvement(b, zero)[2]
        zs = paired_improvement(0.5 * a, zero)[2]
        same += combined_z(za, zs, gain_correlation(a, zero, 0.5 * a, zero)) > level
        indep += combined_z(za, zb, gain_correlation(a, zero, b, zero)) > level
    assert same / n < 0.05 and indep / n < 0.05                      # nominal 0.025
    a = 1.2e-4 + 3e-4 * rng.standard_normal(32)
    b = 1.2e-4 + 3e-4 * rng.standard_normal(32)
    za, zb = paired_improvement(a, zero)[2], paired_improvement(b, zero)[2]
    zc = combined_z(za, zb, gain_correlation(a, zero, b, zero))
    assert max(za, zb) < level < zc


def test_zones_across_the_rut():
    r, dx = 0.07, 0.02
    got = [ZONES[i] for i in zone_of(np.array([0.0, -0.03, 0.05, -0.07, 0.1, 0.2]), r, dx)]
    assert got == ["rut_floor", "rut_floor", "rut_wall", "rut_wall", "berm", "outside"]


def test_paired_comparison_keeps_false_alarms_low_on_correlated_windows():
    from scipy.signal import lfilter

    rng = np.random.default_rng(4)
    hits = sum(paired_improvement(lfilter([1], [1, -0.5], rng.standard_normal(40)), np.zeros(40))[2] > 1.96
               for _ in range(300))
    assert hits / 300 < 0.08                                     # nominal 0.025


def test_paired_comparison_needs_the_same_windows():
    import pytest

    with pytest.raises(ValueError, match="same windows"):
        paired_improvement(np.zeros(10), np.zeros(9))


def test_spectral_line_summed_over_ruts_out_of_phase():
    """One tread on both ruts, half a period apart: averaging the ruts first cancels it, summing
    their periodograms does not."""
    rng = np.random.default_rng(5)
    dx = 0.02
    s = np.arange(0, 12, dx)
    mark = 0.0015 * np.cos(2 * np.pi * s / 0.2)
    left = mark + 0.004 * rng.standard_normal(len(s))
    right = -mark + 0.004 * rng.standard_normal(len(s))
    assert spectral_line(0.5 * (left + right), dx)["p"] > 0.01
    both = spectral_line(np.stack([left, right]), dx)
    assert both["p"] < 1e-3 and abs(both["wavelength"] - 0.2) < 0.01
    assert abs(both["amplitude"] - 0.0015) < 0.0005
    false = sum(spectral_line(0.004 * rng.standard_normal((2, len(s))), dx)["p"] < 0.01 for _ in range(60))
    assert false <= 4


def _profiles_with(offset_mm: dict[int, float], n_seg: int = 30, noise_mm: float = 0.2, seed: int = 0):
    """Profiles of n_seg segments whose residual (model - recording) is offset_mm[|bin|] [mm]
    on both sides of the rut, plus segment noise."""
    from torchsoil.diagnosis.locate import Profiles

    p = Profiles.empty(radius=0.07, dx=0.02, reach=0.12)
    rng = np.random.default_rng(seed)
    L = len(p.bins)
    true = np.array([offset_mm.get(abs(int(round(b / 0.02))), 0.0) for b in p.bins]) * 1e-3
    for g in range(n_seg):
        count = np.full((2, L), 5.0)
        res = count * (true[None] + noise_mm * 1e-3 * rng.standard_normal((2, L)))
        p.seg_s.append(0.4 * g)
        p.res.append(res)
        for name in ("meas", "sim"):
            getattr(p, name).append(np.zeros((2, L)))
        p.count.append(count)
    return p


def test_the_shape_of_a_rut_residual_is_read_across_the_rut():
    # a rounder rut than the model's: the recording above the model at the centre and at the
    # rim, below it halfway out (residual = model - recording)
    p = _profiles_with({0: -1.0, 1: -1.0, 2: 1.2, 4: -1.3})
    runs = p.shape(z=4.0)
    assert [(round(a, 3), round(b, 3)) for a, b, _ in runs] == [(0.0, 0.02), (0.04, 0.04), (0.08, 0.08)]
    assert [np.sign(m) for _, _, m in runs] == [-1, 1, -1]
    assert abs(runs[1][2] - 1.2e-3) < 0.2e-3


def test_noise_alone_gives_no_rut_shape():
    assert _profiles_with({}, seed=3).shape(z=4.0) == []


def test_a_one_sided_residual_is_kept_at_half_its_size_when_folded():
    p = _profiles_with({})
    for r in p.res:
        r[:, -2] += r[:, -2] * 0 + 5.0 * 3e-3          # +3 mm at the second-outermost outward bin
    runs = p.shape(z=4.0)
    assert len(runs) == 1 and abs(runs[0][0] - 0.10) < 1e-9 and abs(runs[0][2] - 1.5e-3) < 0.3e-3


def test_offsets_no_segment_reached_are_left_out_of_the_rut_shape_quietly():
    import warnings

    p = _profiles_with({4: -1.3})
    for c, r in zip(p.count, p.res, strict=True):
        c[:, [0, -1]] = 0.0                              # the outermost offsets: no cell on either side
        r[:, [0, -1]] = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        runs = p.shape(z=4.0)
    assert [(round(a, 3), round(b, 3)) for a, b, _ in runs] == [(0.08, 0.08)]


def test_segments_that_drift_together_do_not_draw_a_rut_shape():
    """Segment noise correlated along the drive (lag-1 0.8, shared by every offset): the
    spread between segments understates the error of their mean, so the shape corrects for
    the effective sample size, as the zones do (48 % of drives drew a shape without it)."""
    from torchsoil.diagnosis.locate import Profiles

    def drive(seed, rho=0.8, G=40):
        rng = np.random.default_rng(seed)
        p = Profiles.empty(radius=0.07, dx=0.02, reach=0.12)
        L, x = len(p.bins), 0.0
        for g in range(G):
            x = rho * x + math.sqrt(1 - rho**2) * rng.standard_normal()
            count = np.full((2, L), 5.0)
            p.seg_s.append(0.4 * g)
            p.res.append(count * (0.3e-3 * x + 0.05e-3 * rng.standard_normal((2, L))))
            p.meas.append(np.zeros((2, L)))
            p.sim.append(np.zeros((2, L)))
            p.count.append(count)
        return p

    rate = np.mean([len(drive(s).shape(z=3.09)) > 0 for s in range(200)])
    assert rate < 0.15


def test_a_lug_line_is_found_down_to_two_and_a_half_cells():
    """Small tyres' lugs are 0.05-0.15 m apart: a 0.05 m line (2.5 cells at dx 0.02) is found
    at its wavelength, and white noise alone stays quiet over the wider range searched."""
    rng = np.random.default_rng(5)
    dx = 0.02
    s = np.arange(0, 20, dx)
    line = spectral_line(0.002 * np.cos(2 * np.pi * s / 0.05) + 0.003 * rng.standard_normal(len(s)), dx)
    assert line["p"] < 1e-4 and abs(line["wavelength"] - 0.05) < 0.001
    false = sum(spectral_line(0.003 * rng.standard_normal(len(s)), dx)["p"] < 0.01 for _ in range(60))
    assert false <= 4


def test_a_tread_on_part_of_the_drive_is_placed_there():
    """A 0.09 m lug line (4.5 cells) pressed only between 6 and 14 m of a 20 m drive, 0.8 mm
    in heavy-tailed noise of 1.2 mm per cell, left and right ruts out of phase: its segments
    are flagged there and nowhere else; noise alone flags nothing."""
    rng = np.random.default_rng(1)
    dx = 0.02
    s = np.arange(0, 20, dx)
    pressed = (s > 6) & (s < 14)
    quiet = sum(line_zone(0.0012 * rng.standard_t(4, (2, len(s))), dx, 0.09).any() for _ in range(30))
    assert quiet <= 1
    y = 0.0012 * rng.standard_t(4, (2, len(s)))
    y[:, pressed] += 0.0008 * np.cos(2 * np.pi * s[pressed] / 0.09 + np.array([[0.0], [1.5]]))
    line = spectral_line(y, dx)
    assert abs(line["wavelength"] - 0.09) < 0.001 and line["p"] < 1e-4
    on = line_zone(y, dx, line["wavelength"], segment=4.0)
    assert on.any() and not on[~((s > 5) & (s < 15))].any()
    assert on[pressed].mean() > 0.6


def test_the_tread_series_spans_the_contact_width():
    """Cells up to the footprint radius enter the tread's series with band = radius; the rut
    floor alone (|offset| < radius / 2) is the default; cells beyond the radius never."""
    prof = Profiles.empty(0.07, 0.02, 0.3)
    lat = np.array([0.0, 0.02, 0.04, 0.06, 0.08])
    prof.floor_s.append(np.full(5, 1.0))
    prof.floor_r.append(np.array([1.0, 2.0, 4.0, 8.0, 16.0]))
    prof.floor_side.append(np.zeros(5, int))
    prof.floor_lat.append(lat)
    assert prof.floor_series()[1][0] == pytest.approx(1.5)              # 0 and 0.02 m out
    assert prof.floor_series(band=0.07)[1][0] == pytest.approx(15.0 / 4)  # up to 0.06 m out


def test_each_rut_is_placed_along_its_own_track_on_a_turn():
    """A left turn of radius 5 m: a tread printed every 0.09 m along each wheel's own track
    lies every 0.09 x 5 / 4.5 = 0.1 m of base_link's arc in the inner (left) rut and every
    0.09 x 5 / 5.5 = 0.0818 m in the outer one (distances along concentric circles, by hand).
    Placed by base_link's arc the two ruts disagree; by their own tracks both give 0.09 m."""
    from torchsoil.diagnosis.covariates import side_arc
    from torchsoil.diagnosis.phases import strongest_line

    R, lam, dx = 5.0, 0.09, 0.02
    turn = np.linspace(0.0, 3.0, 3001)                      # rad: 15 m of base_link arc
    poses = np.zeros((len(turn), 7))
    poses[:, 0] = R * turn
    poses[:, 1], poses[:, 2], poses[:, 6] = R * np.sin(turn), R * (1 - np.cos(turn)), turn
    base = R * turn
    np.testing.assert_allclose(side_arc(poses, 0.5)[-1], 4.5 * 3.0, rtol=1e-5)
    np.testing.assert_allclose(side_arc(poses, -0.5)[-1], 5.5 * 3.0, rtol=1e-5)
    prof = Profiles.empty(0.07, dx, 0.3)
    s = np.arange(0.0, 15.0, dx / 2)                        # floor cells along the drive (base arc)
    own = {0: s * 4.5 / R, 1: s * 5.5 / R}
    for side in (0, 1):
        prof.floor_s.append(s)
        prof.floor_r.append(0.002 * np.cos(2 * np.pi * own[side] / lam))
        prof.floor_side.append(np.full(len(s), side))
        prof.floor_lat.append(np.zeros(len(s)))
    as_seen = [spectral_line(r, dx)["wavelength"] for r in prof.floor_series(by_side=True)[1]]
    assert as_seen == pytest.approx([lam * R / 4.5, lam * R / 5.5], abs=0.002)
    arcs = ((base, side_arc(poses, 0.5)), (base, side_arc(poses, -0.5)))
    line = strongest_line(prof.floor_series(by_side=True, arcs=arcs)[1], dx)
    assert line["ruts"] == "both" and line["wavelength"] == pytest.approx(lam, abs=0.001)


def _gains(blocks_gain, block=4, stride=0.4):
    """Base and extended costs [m] over windows `stride` m apart whose block-of-`block` gains
    are blocks_gain [m] (every window of a block gains the same)."""
    gain = np.repeat(np.asarray(blocks_gain, np.float64), block)
    base = np.full(len(gain), 3e-3)
    return base, base - gain, stride * np.arange(len(gain))


def test_evidence_basis_names_the_blocks_that_carry_a_gain():
    tiny = 1e-5 * (-1.0) ** np.arange(10)              # the other blocks: alternating, kept
    g = tiny.copy()
    g[2], g[7] = 2e-3, 1e-3
    b = evidence_basis(*_gains(g))
    assert b["windows"] == 40 and b["blocks"] == 10
    assert b["n_eff"] == pytest.approx(10.0)              # lag-1 below 0: as many as the blocks
    assert b["carrier_blocks"] == 1 and b["carriers"] == [[pytest.approx(3.2), pytest.approx(4.4)]]
    b = evidence_basis(*_gains(g), share=0.9)
    assert b["carriers"] == [[pytest.approx(3.2), pytest.approx(4.4)], [pytest.approx(11.2), pytest.approx(12.4)]]
    g[3] = 2e-3                                           # touching blocks: one stretch
    assert evidence_basis(*_gains(g))["carriers"] == [[pytest.approx(3.2), pytest.approx(6.0)]]


def test_evidence_basis_counts_a_smooth_gain_as_few_blocks_and_leaves_out_the_untouched():
    g = np.concatenate([np.linspace(1e-4, 1e-3, 12), np.zeros(4)])   # a slow trend, then nothing changed
    b = evidence_basis(*_gains(g))
    assert b["blocks"] == 12 and b["windows"] == 48
    r = min(max(lag1(g[:12]), 0.0), 0.95)
    assert b["n_eff"] == pytest.approx(12 * (1 - r) / (1 + r)) and b["n_eff"] < 3   # not floored at 3
    assert evidence_basis(*_gains(np.zeros(6)))["carriers"] == []
