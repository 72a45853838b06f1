"""Where simulation and recording disagree, and what the disagreement follows.

Three kinds of evidence, each with honest statistics (those of arrays alone in `stats`):

* cross-track residual profiles: simulated minus measured H_b binned by the signed lateral
  offset from the nearest wheel's centre line (outward positive, one cell per bin), averaged
  along the drive over non-overlapping segments (the central stride of each window); standard
  errors come from the spread between segments, because neighbouring cells are correlated.
* along-track rut-floor residual: one value per cell of arc length; a periodic pattern shows
  as a line in its periodogram, tested against the local spectral background.
* per-window series (fitted parameters, costs) against covariates from the poses: Pearson
  correlation with an effective sample size corrected for the autocorrelation of both series
  (`stats.correlation`).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from torchsoil.diagnosis.stats import effective_n

ZONES = ("rut_floor", "rut_wall", "berm", "outside")


def zone_of(offset: np.ndarray, radius: float, dx: float) -> np.ndarray:
    """Cross-track zone index (into ZONES) of lateral offsets [m] from a wheel centre line
    (footprint radius [m], cell edge dx [m]): floor |o| < r/2, wall up to r + dx/2, berm up
    to r + 3.5 dx, outside beyond."""
    a = np.abs(np.asarray(offset, np.float64))
    return np.select([a < radius / 2, a <= radius + dx / 2, a <= radius + 3.5 * dx], [0, 1, 2], 3)


# ------------------------------------------------------------------ spectral lines
def spectral_line(series: np.ndarray, dx: float, half_width: int = 12, wavelengths=(None, 2.0)) -> dict:
    """Strongest line in the periodogram of a series spaced dx [m] apart (NaN gaps filled by
    linear interpolation, linear trend removed), against the local background (mean of the
    neighbouring +-half_width frequencies), among wavelengths in the given range [m]
    (tread-like patterns: lug pitches of small tyres are 0.05-0.15 m; None: down to the
    grid's limit, 2.2 cells). series: (S,) or (M, S) several series
    on one arc-length grid (e.g. the left and right ruts): their periodograms are summed, so a
    line present in each adds up whatever its phase in each; rows with fewer than 32 values
    are left out.

    Returns {ratio, wavelength [m], amplitude [m], p}: amplitude of the sinusoid that would
    give that line (Hann window: |X| = A N / 4, averaged over the series); p bounds the chance
    of so strong a line anywhere in the spectrum of line-free series (F test per frequency,
    Bonferroni over them)."""
    rows = np.atleast_2d(np.asarray(series, np.float64))
    P, n = None, 0
    for y in rows:
        idx = np.arange(len(y))
        ok = np.isfinite(y)
        if ok.sum() < 32:
            continue
        y = np.interp(idx, idx[ok], y[ok])
        y = y - np.polyval(np.polyfit(idx, y, 1), idx)
        p_row = np.abs(np.fft.rfft(y * np.hanning(len(y)))) ** 2
        P = p_row if P is None else P + p_row
        n += 1
    if P is None:
        return {"ratio": 0.0, "wavelength": math.nan, "amplitude": 0.0, "p": 1.0}
    N = rows.shape[1]
    f = np.fft.rfftfreq(N, dx)
    shortest = 2.2 * dx if wavelengths[0] is None else wavelengths[0]
    lo = max(3, int(N * dx / wavelengths[1]))
    hi = min(len(P), int(N * dx / shortest) + 1)
    best = (0.0, math.nan, 1.0, 0.0)
    for i in range(lo, hi):
        nb = np.r_[P[max(lo, i - half_width):max(lo, i - 2)], P[i + 3:i + half_width + 1]]
        if len(nb) < 4:
            continue
        ratio = float(P[i] / nb.mean())
        if ratio > best[0]:
            # white noise: P_i / mean(neighbours) ~ F(2 n, 2 n m) over n summed series; the Hann
            # window halves the independent neighbours
            best = (ratio, 1.0 / f[i], float(stats.f.sf(ratio, 2 * n, max(n * len(nb), 2))),
                    4 * math.sqrt(P[i] / n) / N)
    m = max(hi - lo, 1)
    p = min(1.0, m * best[2])
    return {"ratio": best[0], "wavelength": float(best[1]), "amplitude": float(best[3]), "p": float(min(1.0, p))}


def line_zone(series: np.ndarray, dx: float, wavelength: float, segment: float = 2.0,
              alpha: float = 0.01) -> np.ndarray:
    """Where along a series a spectral line stands (complex demodulation): each row of series
    ((S,) or (M, S), spaced dx [m] apart on one arc-length grid, NaN gaps filled) is shifted
    by the line's frequency 1 / wavelength [m] and averaged over a Hann segment of `segment`
    m centred on each sample; the line's power there (summed over rows) is compared with the
    same at eight off-line frequencies 2 to 5 segment bins either side, the local background.
    A sample is flagged where that ratio exceeds the F(2 M, 16 M) quantile at alpha over the
    number of independent segments (2 S dx / segment), a line-free series staying quiet.

    Returns (S,) bool: the centres of the segments that hold the line (a tread pressed only
    on part of the drive, by soft ground or a lug pattern worn flat)."""
    rows = np.atleast_2d(np.asarray(series, np.float64))
    S = rows.shape[1]
    n = max(3, int(round(segment / dx)) | 1)
    if S < 2 * n or not np.isfinite(wavelength) or wavelength <= 0:
        return np.zeros(S, bool)
    s = np.arange(S) * dx
    f0, step = 1.0 / wavelength, 1.0 / (n * dx)
    offs = [k * step for k in (-5, -4, -3, -2, 2, 3, 4, 5) if 0 < f0 + k * step < 0.5 / dx]
    win = np.hanning(n + 2)[1:-1]
    win /= win.sum()
    line, back, m = np.zeros(S), np.zeros(S), 0
    for y in rows:
        ok = np.isfinite(y)
        if ok.sum() < 2 * n:
            continue
        y = np.interp(np.arange(S), np.flatnonzero(ok), y[ok])
        y = y - np.convolve(y, np.ones(n) / n, "same")        # the rut's slow changes out
        line += _demodulated_power(y, s, f0, win)
        back += sum(_demodulated_power(y, s, f0 + o, win) for o in offs) / len(offs)
        m += 1
    if m == 0 or not offs:
        return np.zeros(S, bool)
    crit = _zone_level(m, len(offs), S * dx, segment, alpha)
    with np.errstate(invalid="ignore", divide="ignore"):
        flagged = line / back > crit
    flagged[: n // 2] = flagged[S - n // 2:] = False          # segments that run off the series
    return flagged


def _zone_level(rows: int, off_line: int, length: float, segment: float, alpha: float) -> float:
    """`line_zone`'s critical power ratio: the F(2 rows, 2 rows off_line) quantile at alpha
    over the independent segments of `segment` m in `length` m."""
    return float(stats.f.isf(alpha / max(1.0, 2 * length / segment), 2 * rows, 2 * rows * off_line))


def zone_segment(ratio: float, rows: int, length: float, shortest: float = 2.0, alpha: float = 0.01) -> float:
    """The `line_zone` segment [m] in which a line of the strength it has over a whole series of
    `length` m (ratio to its background, `spectral_line`) would stand out alone, `shortest` at
    least and half the series at most: a weak line is placed coarsely rather than in the
    fragments where noise happened to add to it."""
    segment = shortest
    for _ in range(3):             # the level depends on how many segments the series holds
        crit = _zone_level(rows, 8, length, segment, alpha)
        segment = float(np.clip(length * crit / max(ratio - 1.0, 1e-9), shortest, length / 2))
    return segment


def _demodulated_power(y: np.ndarray, s: np.ndarray, f: float, win: np.ndarray) -> np.ndarray:
    """|local amplitude|^2 of frequency f [1/m] in y sampled at s [m], averaged by window win."""
    return np.abs(np.convolve(y * np.exp(-2j * np.pi * f * s), win, "same")) ** 2


# ------------------------------------------------------------------ profiles
@dataclass
class Profiles:
    """Cross-track profiles accumulated over segments of the drive.

    bins: (L,) lateral offset of each bin centre, outward from the wheel centre line, m.
    For every segment g and side (0 left wheels, 1 right wheels): per-bin sums of the
    residual (simulated - measured H_b), of the measured and simulated deformation
    (H_b - start surface) and the cell count; floor: (S,) rut-floor residual per arc-length
    cell (NaN where none)."""

    bins: np.ndarray
    dx: float
    radius: float
    seg_s: list = field(default_factory=list)
    res: list = field(default_factory=list)
    meas: list = field(default_factory=list)
    sim: list = field(default_factory=list)
    count: list = field(default_factory=list)
    floor_s: list = field(default_factory=list)
    floor_r: list = field(default_factory=list)
    floor_side: list = field(default_factory=list)
    floor_lat: list = field(default_factory=list)
    floor: bool = True

    @classmethod
    def empty(cls, radius: float, dx: float, reach: float, floor: bool = True) -> Profiles:
        """No segment yet; floor=False: without the rut-floor series (a candidate's pass, whose
        cross-track profiles alone are drawn: half a pass's memory on a long drive)."""
        n = int(math.ceil(reach / dx))
        return cls(np.arange(-n, n + 1) * dx, dx, radius, floor=floor)

    def add(self, wd, h_sim, s_cells: np.ndarray, s0: float, s1: float, wheels_y: np.ndarray,
            outer: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Add the cells of window wd whose arc length (s_cells, (X, Y) on the window crop)
        lies in [s0, s1). h_sim: (X, Y) simulated H_b on the crop, m. outer: optional
        (offset, wheel_dist) (X, Y) crops of the path index (distance to the base_link path
        and to the nearest wheel path, m): cells beyond the wheels' footprints and deposition
        bands, which the wheel-cell incidence does not hold, then enter the profile too
        (outward sign from the offset; half to each side, as the side is not known)."""
        g = wd.geom
        cell = g.cell.cpu().numpy()
        order = np.argsort(g.dist.cpu().numpy(), kind="stable")
        first = order[np.unique(cell[order], return_index=True)[1]]
        c = cell[first]
        wheel = g.wheel.cpu().numpy()[first]
        lat = g.lateral.cpu().numpy()[first] * np.sign(wheels_y[wheel])       # outward positive
        side = (wheels_y[wheel] < 0).astype(float)
        w_side = np.ones(len(c))
        if outer is not None:
            offset, wdist = (np.asarray(a).reshape(-1) for a in outer)
            rest = np.setdiff1d(np.flatnonzero(np.isfinite(wdist)), c)
            lat_r = np.sign(offset[rest] - np.abs(wheels_y).mean()) * wdist[rest]
            c = np.concatenate([c, rest, rest])
            lat = np.concatenate([lat, lat_r, lat_r])
            side = np.concatenate([side, np.zeros(len(rest)), np.ones(len(rest))])
            w_side = np.concatenate([w_side, np.full(2 * len(rest), 0.5)])
        side = side.astype(int)
        weight = wd.weight.cpu().numpy().reshape(-1)[c] > 0
        s = s_cells.reshape(-1)[c]
        keep = weight & (s >= s0) & (s < s1)
        n = len(self.bins)
        b = np.rint(lat / self.dx).astype(int) + n // 2
        keep &= (b >= 0) & (b < n)
        c, b, side, s, lat, w_side = c[keep], b[keep], side[keep], s[keep], lat[keep], w_side[keep]
        hb = wd.h_back.cpu().numpy().reshape(-1)[c]
        hf = wd.h_front[0].cpu().numpy().reshape(-1)[c]
        hs = np.asarray(h_sim.detach().cpu().numpy() if hasattr(h_sim, "detach") else h_sim).reshape(-1)[c]
        acc = {k: np.zeros((2, n)) for k in ("res", "meas", "sim", "count")}
        for arr, val in (("res", hs - hb), ("meas", hb - hf), ("sim", hs - hf), ("count", np.ones_like(hb))):
            np.add.at(acc[arr], (side, b), val * w_side)
        self.seg_s.append(0.5 * (s0 + s1))
        for k in acc:
            getattr(self, k).append(acc[k])
        if not self.floor:
            return
        fl = (np.abs(lat) <= self.radius) & (w_side == 1)
        self.floor_s.append(s[fl])
        self.floor_r.append((hs - hb)[fl])
        self.floor_side.append(side[fl])
        self.floor_lat.append(lat[fl])

    # -------------------------------------------------------------- summaries
    def _stack(self, name: str) -> np.ndarray:
        return np.array(getattr(self, name))                       # (G, 2, L)

    def profile(self, name: str = "res", sides=(0, 1)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Mean per bin over segments (each segment weighted equally), its standard error
        from the spread between segments, and the number of segments. (L,) arrays, m."""
        v = self._stack(name)[:, list(sides)].sum(1)
        n = self._stack("count")[:, list(sides)].sum(1)
        with np.errstate(invalid="ignore", divide="ignore"):
            seg = np.where(n > 0, v / n, np.nan)
        cnt = np.isfinite(seg).sum(0)
        mean = np.nanmean(np.where(cnt[None] > 0, seg, 0.0), 0)
        with warnings.catch_warnings():       # a bin one segment covers: no spread (NaN), dropped below
            warnings.simplefilter("ignore", RuntimeWarning)
            sd = (np.nanstd(np.where(cnt[None] > 0, seg, 0.0), 0, ddof=1) if len(seg) > 1
                  else np.full(len(cnt), np.inf))
        with np.errstate(invalid="ignore", divide="ignore"):
            se = sd / np.sqrt(np.maximum(cnt, 1))
        mean[cnt < 3] = np.nan
        return mean, se, cnt

    def zone_stats(self, name: str = "res", sides=(0, 1)) -> dict[str, dict]:
        """Per zone: mean residual [m], standard error (from segment spread) and z."""
        v, n = self._stack(name)[:, list(sides)].sum(1), self._stack("count")[:, list(sides)].sum(1)
        z_idx = zone_of(self.bins, self.radius, self.dx)
        out = {}
        for zi, zname in enumerate(ZONES):
            cols = z_idx == zi
            num, den = v[:, cols].sum(1), n[:, cols].sum(1)
            ok = den > 0
            seg = num[ok] / den[ok]
            if len(seg) < 3:
                out[zname] = {"mean": math.nan, "se": math.nan, "z": 0.0, "segments": int(len(seg))}
                continue
            se = float(np.std(seg, ddof=1) / math.sqrt(effective_n(len(seg), seg)))
            m = float(seg.mean())
            out[zname] = {"mean": m, "se": se, "z": m / se if se > 0 else 0.0, "segments": int(len(seg))}
        return out

    def shape(self, z: float, name: str = "res") -> list[tuple[float, float, float]]:
        """Where across the rut the residual differs from 0: runs of adjacent offsets from the
        wheel centre line (both sides of the rut folded: the cells at +o and -o pooled per
        segment) whose mean over segments differs from 0 by more than z standard errors (from
        the spread between segments, with the effective-sample-size correction, as the zones'),
        all of one sign.

        Returns [(from [m], to [m], mean residual over the run [m]), ...], nearest the centre
        line first; [] when no offset stands out."""
        v, c = self._stack(name), self._stack("count")                      # (G, 2, L)
        n = len(self.bins) // 2
        o = np.arange(n + 1)
        num = v[:, :, n + o].sum(1) + v[:, :, n - o].sum(1)
        den = c[:, :, n + o].sum(1) + c[:, :, n - o].sum(1)
        with np.errstate(invalid="ignore", divide="ignore"):
            seg = np.where(den > 0, num / den, np.nan)                      # (G, n + 1)
        m, sign = np.zeros(n + 1), np.zeros(n + 1)
        for i in o:
            x = seg[np.isfinite(seg[:, i]), i]
            if len(x) < 3:
                continue
            m[i] = x.mean()
            se = float(np.std(x, ddof=1)) / math.sqrt(effective_n(len(x), x))
            sign[i] = np.sign(m[i]) if abs(m[i]) > z * se else 0.0
        out: list[tuple[float, float, float]] = []
        start = None
        for i in range(n + 2):
            if start is not None and (i > n or sign[i] != sign[start]):
                out.append((float(self.bins[n + start]), float(self.bins[n + i - 1]), float(np.mean(m[start:i]))))
                start = None
            if i <= n and sign[i] != 0 and start is None:
                start = i
        return out

    def segment_zone_series(self, zone: str, sides=(0, 1)) -> np.ndarray:
        """(G,) mean residual of one zone per segment, m (NaN where no cell)."""
        v, n = self._stack("res")[:, list(sides)].sum(1), self._stack("count")[:, list(sides)].sum(1)
        cols = zone_of(self.bins, self.radius, self.dx) == ZONES.index(zone)
        with np.errstate(invalid="ignore", divide="ignore"):
            return v[:, cols].sum(1) / n[:, cols].sum(1)

    def asymmetry(self) -> dict:
        """Left minus right rut-floor residual per segment: mean, se, z, and the series."""
        left = self.segment_zone_series("rut_floor", (0,))
        right = self.segment_zone_series("rut_floor", (1,))
        d = left - right
        ok = np.isfinite(d)
        if ok.sum() < 3:
            return {"mean": math.nan, "se": math.nan, "z": 0.0, "series": d}
        se = float(np.std(d[ok], ddof=1) / math.sqrt(effective_n(int(ok.sum()), d[ok])))
        m = float(d[ok].mean())
        return {"mean": m, "se": se, "z": m / se if se > 0 else 0.0, "series": d}

    def floor_series(self, by_side: bool = False, arcs: tuple | None = None, band: float | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
        """Rut-floor residual per arc-length cell: (S,) arc length [m] and mean residual [m],
        (S,) over both sides, or (2, S) left and right wheels' ruts with by_side (a tread's
        marks need not line up from one side to the other). arcs: optional per side (left,
        right) a pair ((N,) base_link arc, (N,) that side's track arc) [m], increasing: each
        side's cells are then placed by the distance its own wheels travelled (`side_arc`),
        where a tread's wavelength holds on a turn. band: the cells up to this offset [m] from
        the wheel centre line (the footprint radius at most: a tyre prints its lugs across
        its contact width); None: the rut floor, |offset| < radius / 2."""
        if not self.floor_s:
            return np.zeros(0), np.zeros((2, 0) if by_side else 0)
        s, r = np.concatenate(self.floor_s), np.concatenate(self.floor_r)
        lats = getattr(self, "floor_lat", None)          # absent from passes kept by older versions
        lat = np.abs(np.concatenate(lats)) if lats and sum(map(len, lats)) == len(s) else np.zeros(len(s))
        keep = lat < self.radius / 2 if band is None else lat <= band
        s, r = s[keep], r[keep]
        side = np.concatenate(self.floor_side)[keep] if by_side else np.zeros(len(s), int)
        if len(s) == 0:
            return np.zeros(0), np.zeros((2, 0) if by_side else 0)
        if by_side and arcs is not None:
            s = s.copy()
            for k, (base, own) in enumerate(arcs):
                s[side == k] = np.interp(s[side == k], base, own)
        i = np.floor((s - s.min()) / self.dx).astype(int)
        n = i.max() + 1
        rows = []
        for k in ((0, 1) if by_side else (0,)):
            m = side == k
            num, den = np.bincount(i[m], r[m], n), np.bincount(i[m], None, n)
            with np.errstate(invalid="ignore", divide="ignore"):
                rows.append(np.where(den > 0, num / den, np.nan))
        grid = s.min() + (np.arange(n) + 0.5) * self.dx
        return grid, (np.array(rows) if by_side else rows[0])
