"""The diagnosis's statistics: pure functions of arrays and numbers, upstream of the modules
that run the estimator (`fit`, `revisits`), locate the mismatch (`locate`) and decide (`phases`).

* autocorrelated series: lag-1 autocorrelation, effective sample sizes, the normal z of a t
  statistic, and the Pearson correlation of two per-window series (fitted parameters, costs,
  covariates from the poses) with an effective sample size corrected for the autocorrelation
  of both.
* paired costs: two cost series on the same windows compared window by window, over blocks of
  neighbouring windows (`paired_improvement`, what a gain rests on, the correlation of two
  gains and their combined z, one term's tests against the base model); windows that do not
  overlap as independent (`paired_z`), and windows that share no ground on revisited ground
  (`spaced_z`).
* cross-validation folds: alternating blocks of windows, the coefficient each fold is scored
  with, and the per-window series of the fold coefficients.
* levels: the z levels and thresholds of the tests (fallback procedure over candidates,
  acceptance level by the number of coefficient signs, materiality of a gain), and outlying
  entries of a gain series.

Nothing here imports from the rest of the diagnosis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

# ------------------------------------------------------------------ autocorrelated series
SAME = 1e-9  # [m] two costs this close are the same: the term changed nothing there


def lag1(x: np.ndarray) -> float:
    """Lag-1 autocorrelation of a series (0 for fewer than 4 values or no variance)."""
    x = np.asarray(x, np.float64)
    if len(x) < 4:
        return 0.0
    x = x - x.mean()
    den = float((x * x).sum())
    return float((x[1:] * x[:-1]).sum() / den) if den > 0 else 0.0


def t_z(t: float, dof: float) -> float:
    """The normal z of the same one-sided p as Student's t with dof degrees of freedom."""
    p = float(stats.t.sf(t, dof))
    return float(stats.norm.isf(min(max(p, 1e-300), 1 - 1e-16)))


def effective_n(n: int, *series: np.ndarray, floor: float = 3.0) -> float:
    """Effective sample size of n autocorrelated values: n (1 - r) / (1 + r) with r the product
    of the series' lag-1 autocorrelations (one series: its own), floored at `floor`."""
    r = float(np.prod([max(lag1(s), 0.0) for s in series])) if len(series) > 1 else max(lag1(series[0]), 0.0)
    r = min(r, 0.95)
    return float(max(floor, n * (1 - r) / (1 + r)))


@dataclass(frozen=True)
class Correlation:
    """Pearson r of y on x over n values, its effective sample size and two-sided p-value."""

    r: float
    n: int
    n_eff: float
    p: float


def correlation(x, y) -> Correlation:
    """Correlation of two per-window series with the effective-sample-size correction.

    NaN entries (in either) are dropped. p = 1 when x or y does not vary."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    if x.shape != y.shape:
        raise ValueError(f"correlation: series of different shapes {x.shape} and {y.shape}")
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    n = len(x)
    if n < 4 or np.std(x) < 1e-12 or np.std(y) < 1e-12:
        return Correlation(0.0, n, float(n), 1.0)
    r = float(np.corrcoef(x, y)[0, 1])
    ne = effective_n(n, x, y)
    dof = max(ne - 2.0, 1.0)
    t = r * math.sqrt(dof / max(1e-12, 1 - r * r))
    return Correlation(r, n, ne, float(2 * stats.t.sf(abs(t), dof)))


# ------------------------------------------------------------------ paired costs
def _about_line(means: np.ndarray, place: np.ndarray) -> np.ndarray:
    """Block means (n,) about the line through them along the drive (place: their block
    numbers), or about their mean with fewer than 5 blocks."""
    m = means - means.mean()
    if len(m) < 5:
        return m
    x = place - place.mean()
    return m - x * float((x * m).sum() / (x * x).sum())


def paired_improvement(base, ext, block: int = 4, same: float = SAME) -> tuple[float, float, float]:
    """Per-window improvement base - ext [m] of two cost series on the same windows.

    Neighbouring windows share ground (and held-out costs reach several windows), so the
    differences are averaged over consecutive blocks of `block` windows. A real term's gain
    follows the size of its effect, which changes along the drive with the soil and the
    covariate (a footprint term gains most where the ruts are deepest), so the block means are
    regressed on their place along the drive: the mean gain is tested against their scatter
    about that line, with the effective-sample-size correction for the block means' own lag-1
    correlation (a trend only raises it: the correction errs on the cautious side), as a t
    statistic with n_eff - 2 degrees of freedom, returned as the normal z of the same one-sided
    p. Without an effect the line costs one degree of freedom and the test keeps its level;
    with one, a steady trend in the gain is no longer counted as its noise. With
    fewer than 5 blocks the spread about the mean is used instead (n_eff - 1 degrees of
    freedom). Windows where either cost is NaN are dropped, and so are blocks where the two
    series agree to `same` [m] on every window: a term that acts only on some ground (a pass
    count on revisited ground) leaves the others' costs exactly as they were, and such blocks
    say nothing about the noise of the difference; counted as samples of it, they would cap z
    near the square root of the number of blocks the term touches, however large and steady
    its gain there. Returns (mean over the blocks kept, se, z)."""
    d, blocks, kept, _ = _paired_blocks(base, ext, block, same)
    blocks, place = blocks[kept], np.flatnonzero(kept).astype(np.float64)
    nb = len(blocks)
    if nb < 3:
        return (float(d.mean()) if len(d) else 0.0), math.inf, 0.0
    means = blocks.mean(1)
    m = float(means.mean())
    scatter, fitted = _about_line(means, place), 2 if nb >= 5 else 1
    n_eff = min(float(nb), max(effective_n(nb, means), fitted + 2.0))
    se = float(math.sqrt((scatter ** 2).sum() / (nb - fitted) / n_eff))
    if se <= 0:
        return m, 0.0, 0.0 if m == 0 else math.copysign(math.inf, m)
    return m, se, t_z(m / se, max(n_eff - fitted, 1.0))


def _paired_blocks(base, ext, block: int, same: float, s=None):
    """The differences base - ext over the windows where both are finite (D,); their blocks of
    `block` consecutive ones (nb, block) and which blocks to keep (nb,) bool (those where the
    two series differ by more than `same` somewhere); and s (W,) of the same windows in the
    same blocks (nb, block), or None."""
    b, e = np.asarray(base, np.float64), np.asarray(ext, np.float64)
    if b.shape != e.shape:
        raise ValueError(f"paired costs must cover the same windows, got {b.shape} and {e.shape}")
    ok = np.isfinite(b) & np.isfinite(e)
    d = b[ok] - e[ok]
    nb = len(d) // max(1, block)
    blocks = d[: nb * block].reshape(nb, block)
    at = None if s is None else np.asarray(s, np.float64)[ok][: nb * block].reshape(nb, block)
    return d, blocks, np.abs(blocks).max(1) > same, at


def evidence_basis(base, ext, s, block: int = 4, same: float = SAME, share: float = 0.5) -> dict:
    """What a paired gain (`paired_improvement` of base - ext, (W,) costs on the windows centred
    at arc lengths s (W,) [m]) rests on: the windows and blocks it counts (blocks where the two
    agree on every window left out, as there), their effective number (`effective_n` of the
    block means, not floored: the test floors it, a reader should not), and the fewest blocks
    whose gains hold `share` of the summed positive gain, as spans of arc length [m] (touching
    blocks merged). Returns {windows, blocks, n_eff, carrier_blocks, carriers: [[s0, s1], ...]}."""
    _, blocks, kept, spans = _paired_blocks(base, ext, block, same, s)
    means, spans = blocks[kept].mean(1), spans[kept]
    out = {"windows": int(kept.sum()) * block, "blocks": int(kept.sum()),
           "n_eff": effective_n(len(means), means, floor=0.0) if len(means) else 0.0,
           "carrier_blocks": 0, "carriers": []}
    gain = np.maximum(means, 0.0)
    if gain.sum() <= 0:
        return out
    order = np.argsort(-gain)
    n = int(np.searchsorted(np.cumsum(gain[order]), share * gain.sum()) + 1)
    carriers: list[list[float]] = []
    for i in sorted(order[:n]):
        lo, hi = float(spans[i].min()), float(spans[i].max())
        if carriers and lo - carriers[-1][1] <= 1.5 * (hi - lo) / max(block - 1, 1):
            carriers[-1][1] = hi
        else:
            carriers.append([lo, hi])
    return {**out, "carrier_blocks": n, "carriers": carriers}


def gain_correlation(base_a, ext_a, base_b, ext_b, block: int = 4, same: float = SAME) -> float:
    """Correlation, clipped to [0, 1], of two paired gains (base - ext, each on the same (W,)
    windows) along the drive, as `paired_improvement` sees them: the block means, on the
    windows where all four costs are measured, about a line through them (about their mean
    with fewer than 5 blocks), over the blocks where either term changed a cost by more than
    `same`. 1 (nothing gained by combining) with fewer than 3 such blocks or no scatter."""
    a = np.asarray(base_a, np.float64) - np.asarray(ext_a, np.float64)
    b = np.asarray(base_b, np.float64) - np.asarray(ext_b, np.float64)
    ok = np.isfinite(a) & np.isfinite(b)
    a, b = a[ok], b[ok]
    nb = len(a) // max(1, block)
    ba, bb = a[: nb * block].reshape(nb, block), b[: nb * block].reshape(nb, block)
    keep = (np.abs(ba).max(1, initial=0.0) > same) | (np.abs(bb).max(1, initial=0.0) > same)
    if keep.sum() < 3:
        return 1.0
    place = np.flatnonzero(keep).astype(np.float64)
    sa, sb = _about_line(ba[keep].mean(1), place), _about_line(bb[keep].mean(1), place)
    den = math.sqrt(float((sa * sa).sum() * (sb * sb).sum()))
    return float(np.clip((sa * sb).sum() / den, 0.0, 1.0)) if den > 0 else 1.0


def combined_z(z_held: float, z_own: float, rho: float) -> float:
    """Stouffer's z of two one-sided paired tests of one term on the same windows, whose
    statistics correlate by rho: (z_held + z_own) / sqrt(2 + 2 rho). The held-out test
    scores each window's fit on its neighbours' ground (where the term's covariate changes
    between windows), the own-fit test the window on its own ground (where it changes within
    it): a missing term gains in both, while a term standing in for a misfit of the base
    model gains on one at the other's expense. rho is clipped to [0, 1] (a negative estimate
    from a few blocks is not trusted); z_own not finite (not measured): z_held alone."""
    if not math.isfinite(z_own) or not math.isfinite(z_held):
        return z_held
    return (z_held + z_own) / math.sqrt(2.0 + 2.0 * min(max(rho, 0.0), 1.0))


def term_test(base_held, ext_held, base_res=None, ext_res=None, same: float = SAME
              ) -> tuple[float, float, float, float, float]:
    """One term's paired tests against the base model, on (W,) per-window costs: held-out
    (each window's fit on its neighbours' ground) and, when given, the windows' own residuals,
    combined (`combined_z`, with their `gain_correlation`). same: `paired_improvement`'s, in
    the costs' unit. Returns (mean held-out gain, its se, held-out z, own-fit z (inf without
    residuals), combined z (the held-out z without residuals))."""
    gain, se, held_z = paired_improvement(base_held, ext_held, same=same)
    if base_res is None:
        return gain, se, held_z, math.inf, held_z
    own_z = paired_improvement(base_res, ext_res, same=same)[2]
    rho = gain_correlation(base_held, ext_held, base_res, ext_res, same=same)
    return gain, se, held_z, own_z, combined_z(held_z, own_z, rho)


def paired_z(base: np.ndarray, other: np.ndarray) -> float:
    """How much better `other` fits than `base` (W,) window by window [m]: the mean of base -
    other over the windows both fitted, over its standard error (windows that do not overlap
    taken as independent). With fewer than 3 such windows (or a score kept by an older
    version) the means decide: +-inf."""
    base, other = np.asarray(base, np.float64), np.asarray(other, np.float64)
    both = np.isfinite(base) & np.isfinite(other) if base.shape == other.shape else np.zeros(0, bool)
    diff = (base - other)[both] if both.any() else np.zeros(0)
    sd = float(np.std(diff, ddof=1)) if len(diff) >= 3 else 0.0
    if sd == 0.0:
        return math.inf if np.nanmean(other) < np.nanmean(base) else -math.inf
    return float(diff.mean() / (sd / math.sqrt(len(diff))))


def spaced_z(s, gain, stride: float, apart: int = 2) -> float:
    """One-sided z that the mean of a per-window gain (W,) is above 0, counting only windows
    that share no ground as independent: windows of `apart` strides of `stride` [m] (the window
    length over the stride) are grouped by their centre s (W,) [m] into `apart` sets whose
    windows lie at least a window apart (the gains of the visits of one window averaged
    first), a t test in each, and the smaller z of the sets. On the ground driven again the
    soil is the same at every visit and cancels: what is left between disjoint windows is
    their own measurement noise, while the gain itself follows the passes and the rut depth
    along the drive (a drive's middle gains more than its ends), so block means about a line
    along the drive would count the gain's own shape as noise. 0 where a set has fewer than
    3 windows."""
    s, gain, apart = np.asarray(s, np.float64), np.asarray(gain, np.float64), max(1, apart)
    ok = np.isfinite(gain)
    at = np.round(s[ok] / stride).astype(np.int64)
    cells, inv = np.unique(at, return_inverse=True)
    per = np.bincount(inv, weights=gain[ok]) / np.bincount(inv)
    zs = []
    for r in range(apart):
        x = per[cells % apart == r]
        if len(x) < 3:
            return 0.0
        sd = float(np.std(x, ddof=1))
        if sd == 0:
            zs.append(0.0 if x.mean() == 0 else math.copysign(math.inf, x.mean()))
            continue
        zs.append(t_z(x.mean() / (sd / math.sqrt(len(x))), len(x) - 1))
    return min(zs)


# ------------------------------------------------------------------ cross-validation folds
def folds(n: int, block: int) -> np.ndarray:
    """(n,) fold label 0/1 of each window: alternating blocks of `block` windows."""
    return (np.arange(n) // max(1, block)) % 2


def finite_mean(x: np.ndarray, sel: np.ndarray) -> float:
    """Mean of the finite values of x (W,) on the windows sel (W,) bool; math.inf when none."""
    v = x[sel & np.isfinite(x)]
    return float(v.mean()) if len(v) else math.inf


def fold_choice(held: dict[float, np.ndarray], lab: np.ndarray) -> tuple[float, float]:
    """The coefficient each fold is scored with: the one whose (W,) held-out cost [m] is
    lowest on the other fold's windows (lab: (W,) fold labels, `folds`); the smaller |k| on a
    tie, so the base model (0) wins one."""
    f0, f1 = (min(held, key=lambda k: (finite_mean(held[k], lab != f), abs(k))) for f in (0, 1))
    return f0, f1


def by_fold(series: dict[float, np.ndarray], k_fold: tuple[float, float], lab: np.ndarray) -> np.ndarray:
    """(W,) each window's value from the series of the coefficient its fold was scored with."""
    out = np.full(len(lab), np.nan)
    for f, k in enumerate(k_fold):
        out[lab == f] = np.asarray(series[k])[lab == f]
    return out


# ------------------------------------------------------------------ levels
def z_two_sided(alpha: float) -> float:
    """The normal z whose two-sided tail probability is alpha."""
    return float(stats.norm.isf(alpha / 2))


def thresholds(p: list[float], alpha: float, lead_share: float) -> list[float]:
    """Base one-sided levels (alphas) of candidates tested in order of their location
    evidence p (ascending) by the fallback procedure (Wiens 2003): the leading candidates
    (all tied at the smallest p) share alpha * lead_share, the others share the rest. They
    sum to alpha; the level of an accepted candidate carries over to the next (see
    `phases.accept_in_order`), so the family-wise error stays at alpha."""
    n = len(p)
    if n == 0:
        return []
    lead = [abs(q - p[0]) <= 1e-12 + 1e-9 * abs(p[0]) for q in p]
    n_lead = sum(lead)
    if n_lead == n:
        return [alpha / n] * n
    return [alpha * lead_share / n_lead if is_lead else alpha * (1 - lead_share) / (n - n_lead) for is_lead in lead]


def level_z(alpha: float, signs: int = 1) -> float:
    """The combined z a term must exceed to be accepted at one-sided level alpha, for a
    coefficient of `signs` possible signs (catalogue.signs).

    Each fold is scored at the coefficient chosen on the other fold's windows, and a term is
    only accepted when both folds chose the same sign. With no effect, a fold's statistic X_f
    is centred normal and the other fold picks the sign that helped it, so the combined z is
    (|X_0| + |X_1|) / sqrt(2) when the folds agree: a two-signed term's folds agree half the
    time, a one-signed term's (k above 0 on both) a quarter. Since |X_0| + |X_1| <= t exactly
    when |X_0 + X_1| and |X_0 - X_1| (independent, each sqrt(2) times a standard normal) are at
    most t, P(z > c) = signs Q(c) (1 - Q(c)) with Q the normal tail: 0.095 at c 1.645 for a
    two-signed term. The level solves signs Q (1 - Q) = alpha (z 1.95 for alpha 0.05 with two
    signs, 1.62 with one). The folds' statistics correlate less than fully (held-out and
    own-fit gains on other windows), which only makes this bound conservative."""
    q = 0.5 * (1.0 - math.sqrt(max(0.0, 1.0 - 4.0 * alpha / signs)))
    return float(stats.norm.isf(q))


def gain_material(share: float, base_held_out) -> float:
    """The smallest mean held-out improvement an accepted term must bring: `share`
    (diagnosis.gain_materiality) of the base model's mean (W,) held-out cost, in its unit."""
    return share * float(np.nanmean(np.asarray(base_held_out, np.float64)))


def outliers(x: np.ndarray, n_sd: float = 2.0) -> np.ndarray:
    """Entries of a per-window gain series (base minus extended cost) above n_sd noise
    standard deviations; the noise is measured on the losses (gain < 0), which a helpful
    term only gets by chance, so it is symmetric about 0 there."""
    ok = np.isfinite(x)
    neg = x[ok & (x < 0)]
    if len(neg) >= 3:
        sd = float(np.sqrt(np.mean(neg ** 2)))
    elif ok.sum() >= 4:
        sd = 1.4826 * float(np.median(np.abs(x[ok] - np.median(x[ok]))))
    else:
        return np.zeros(len(x), bool)
    return ok & (np.nan_to_num(x) > n_sd * sd) & (sd > 0)
