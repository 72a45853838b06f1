"""Catalogue of model extensions: each a named physical term with one coefficient, turned
into `torchsoil.sim.Modifiers` for one window.

Every law is deliberately simple and monotone (one coefficient k, k = 0 is the paper's model;
linear in its covariate, but for passes); the world may follow another form (power law,
saturation): the diagnosis must still name the term.

| id | law | coefficient |
| --- | --- | --- |
| multi_pass_hardening | sinkage x (1 + n)^log2(1 + k), n earlier passes over the cell | k [-]: 2nd / 1st - 1 |
| speed_dependent_sinkage | sinkage x (1 + k * (v / v_mean - 1)), v_mean over the ground driven | k [-] |
| slip_sinkage | sinkage x (1 + k * (accel / g + sin(-pitch))) | k [-] |
| lateral_load_transfer | wheel sinkage x (1 + k * side * (a_lat / g + sin(roll))), side = -1 left, +1 right | k [-] |
| cohesive_walls | intact ground stands to tan(beta) * (1 + k), moved soil settles at beta | k >= 0 [-] |
| footprint_width | footprint radius x (1 + k) | k [-] |

The per-window base parameters (d_1..d_T, chi, beta) are still fitted; the sinkage factors
are normalised by nothing but their covariate, so d keeps its meaning at the covariate's
reference (first pass, mean speed, no traction demand, no lateral load).

Cohesive soil has two angles: ground that has not moved (native, or freshly cut by a wheel)
stands up to the intact angle, soil that has moved (the deposits, and whatever slid since)
settles at its loose angle, and a face flows beyond the loose angle only as far as it carries
loose soil (`sim.cohesive`). The fitted beta stays the loose angle, the angle deposited soil
settles at; the coefficient gives the intact one (`intact_angle`).

Passes follow a power law in the pass number (1 + n) rather than a line: a line through the
second pass's factor goes negative by the third pass of strong hardening, while soil hardens
by ever smaller steps (each pass compacts what the last one left). Under the dig order
"wheel" every wheel's pass counts (a rear wheel in its front wheel's rut runs the second),
under "robot" the robot's visits. Passes are counted cell by cell under each footprint: ground
hardens where a wheel pressed it, so a wheel that half overlaps an old rut sinks less over
that half only, and one that runs beside it (a lane change, the end of a loop) digs fresh soil.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from torchsoil.diagnosis.covariates import DriveSignals
from torchsoil.robot import Robot
from torchsoil.sim import Modifiers, ParamSpec

MAX_TAN = math.tan(math.radians(89.0))


@dataclass(frozen=True)
class Extension:
    """One catalogue term.

    id: docs/formats.md section 4 id. parameter: name of its coefficient. bounds: allowed range of
    the coefficient, of one sign where the physics has one (slip and load shifted onto a
    wheel deepen its rut, hardening makes later ruts shallower: a fit of the other sign would
    name physics the catalogue does not describe; `signs`). trials: coefficients tried when
    fitting besides 0 (the best is refined). covariate:
    the signal the term follows (None: a shape term). zone: cross-track zone where it shows.
    kind: which hook it uses: depth | radius | wall.
    """

    id: str
    parameter: str
    bounds: tuple[float, float]
    trials: tuple[float, ...]
    covariate: str | None
    zone: str
    kind: str
    description: str


CATALOGUE: dict[str, Extension] = {e.id: e for e in (
    Extension("multi_pass_hardening", "k_pass", (-0.9, 0.0), (-0.6, -0.3), "passes", "rut_floor", "depth",
              "each later pass over the same ground sinks less than the first"),
    Extension("speed_dependent_sinkage", "k_speed", (-0.9, 3.0), (-0.4, 0.4, 0.8), "speed", "rut_floor", "depth",
              "sinkage depends on travel speed"),
    Extension("slip_sinkage", "k_slip", (0.0, 20.0), (4.0, 8.0), "traction", "rut_floor", "depth",
              "sinkage grows with traction demand (acceleration, climbing)"),
    Extension("lateral_load_transfer", "k_lateral", (0.0, 8.0), (1.5, 3.0), "lateral_load", "rut_floor",
              "depth", "load, and so sinkage, shifts to the downhill or outer wheels with roll and turning"),
    Extension("cohesive_walls", "k_wall", (0.0, 20.0), (0.5, 1.5, 4.0), None, "rut_wall", "wall",
              "rut walls stand steeper than the angle at which deposited soil settles"),
    Extension("footprint_width", "k_width", (-0.4, 0.45), (-0.2, 0.15, 0.3), None, "rut_wall", "radius",
              "the contact patch is wider or narrower than the nominal wheel width"),
)}


def intact_angle(beta_deg: float, k_wall: float) -> float:
    """The intact angle [deg] of two-angle soil whose loose angle is beta_deg [deg] at the
    cohesive_walls coefficient k_wall: atan(tan(beta) * (1 + k)), within 89 deg."""
    if k_wall < 0 or not 0 < beta_deg < 90:
        raise ValueError(f"need k_wall >= 0 and 0 < beta < 90 deg, got k_wall {k_wall}, beta {beta_deg} deg")
    return math.degrees(math.atan(min(math.tan(math.radians(beta_deg)) * (1.0 + k_wall), MAX_TAN)))


def reported_parameters(ext: Extension, k: float, rows: list[dict]) -> dict[str, float]:
    """diagnosis.json's `extension_parameters` of a term at coefficient k: the coefficient,
    and for cohesive_walls both angles [deg], the loose one (the median of the windows' fitted
    beta, `rows` of the pass at k, beta in deg) and the intact one (`intact_angle`)."""
    out = {ext.parameter: round(float(k), 4)}
    if ext.id == "cohesive_walls":
        loose = float(np.nanmedian([r["beta"] for r in rows]))
        out |= {"beta_loose_deg": round(loose, 2), "beta_intact_deg": round(intact_angle(loose, k), 2)}
    return out


def signs(ext: Extension) -> int:
    """How many signs the term's coefficient may take: 2 where its bounds hold both (speed,
    footprint width: either way is physical), else 1. A two-signed term's sign is chosen per
    fold on the other fold's windows, which doubles its chance of a false alarm at a given z
    (`stats.level_z`)."""
    lo, hi = ext.bounds
    return 2 if lo < 0 < hi else 1


def get(ext_id: str) -> Extension:
    try:
        return CATALOGUE[ext_id]
    except KeyError:
        raise KeyError(f"unknown extension {ext_id!r}; catalogue: {sorted(CATALOGUE)}") from None


def ground_times(drive: DriveSignals, spacing: float = 0.02) -> np.ndarray:
    """(M,) times [s] at which the robot passes every `spacing` m of its path: a signal
    sampled there is weighted by the ground driven, not by the time spent (a robot standing
    still digs nothing). The recorded times when the robot never moves."""
    arc, t = drive.signals["arc_length"], drive.signals["t"]
    keep = np.concatenate([[True], np.diff(arc) > 0])
    s = np.arange(0.0, float(arc[-1]), spacing)
    return np.interp(s, arc[keep], t[keep]) if len(s) > 1 and keep.sum() > 1 else t


def references(drive: DriveSignals) -> dict[str, float]:
    """{signal: value} where a covariate term's factor is 1: the drive's mean speed [m/s]
    over the ground driven (time spent standing still does not lower it)."""
    return {"speed": float(np.mean(drive.at("speed", ground_times(drive))))}


def depth_factor(ext: Extension, drive: DriveSignals, robot: Robot, poses4: np.ndarray, k: float,
                 reference: dict[str, float]) -> np.ndarray:
    """(K, N) sinkage factor of a pose-driven depth term (speed, slip, lateral load) at (N, 4)
    resampled poses t, x, y, yaw; multi-pass hardening acts cell by cell (`entry_passes`).

    reference: {signal: value} where the factor is 1 (e.g. the drive's mean speed)."""
    K, N = len(robot.wheels), len(poses4)
    t = poses4[:, 0]
    if ext.id == "speed_dependent_sinkage":
        v0 = max(reference.get("speed", 1.0), 1e-3)
        x = np.broadcast_to(drive.at("speed", t) / v0 - 1.0, (K, N))
    elif ext.id == "slip_sinkage":
        x = np.broadcast_to(drive.at("traction", t), (K, N))
    elif ext.id == "lateral_load_transfer":
        side = -np.sign(robot.wheels[:, 1])[:, None]            # left -1, right +1
        x = side * drive.at("lateral_load", t)[None]
    else:
        raise ValueError(f"{ext.id} is not a sinkage term")
    return np.clip(1.0 + k * x, 0.05, 10.0)


def effect_size(ext: Extension, k: float, drive: DriveSignals, robot: Robot, quantile: float = 0.95) -> float:
    """How much the term at coefficient k changes the model [-], as a fraction: for the
    covariate terms (speed, slip, lateral load) the `quantile` of |sinkage factor - 1| over
    the ground driven and the wheels (`ground_times`: the change it makes on a twentieth of
    the drive at least); for the others |k|, the change of the second pass's sinkage
    (hardening), of the footprint radius, or of tan(beta) on intact ground. A term that changes the
    physics by a percent is not the cause of a mismatch, however steady its gain
    (DiagnosisConfig.effect_materiality)."""
    if ext.kind != "depth" or ext.id == "multi_pass_hardening":
        return abs(float(k))
    t = ground_times(drive)
    f = depth_factor(ext, drive, robot, np.pad(t[:, None], ((0, 0), (0, 3))), k, references(drive))
    return float(np.quantile(np.abs(f - 1.0), quantile))


def entry_passes(drive: DriveSignals, geom, grid, before: bool = False, by_wheel: bool = False) -> np.ndarray:
    """(E,) earlier passes over the cell of each entry of `geom` (WheelGeometry on `grid`: a
    cell near one wheel's path, at the wheel's nearest pose to it): soil hardens where a wheel
    pressed it, so an earlier wheel counts fully where its centre came within the footprint
    radius of the cell, and its share fades to none one cell beyond (`DriveSignals.passes`;
    before, by_wheel as there, at the arc of the entry's pose)."""
    Y = geom.shape[1]
    cell = geom.cell.cpu().numpy()
    xs, ys = grid.centers()
    pts = np.stack([xs[cell // Y], ys[cell % Y]], 1)
    arc = drive.at("arc_length", geom.poses[:, 0].cpu().numpy()[geom.pose.cpu().numpy()])
    wheel = geom.wheel.cpu().numpy() if by_wheel else None
    r = float(geom.radius)
    return drive.passes(pts, arc, before, wheel, reach=(r, r + float(geom.dx)))


def pass_factor(n: np.ndarray, k: float) -> np.ndarray:
    """Sinkage factor (1 + n)^log2(1 + k) after n earlier passes, clipped to [0.05, 10]."""
    return np.clip((1.0 + np.asarray(n, np.float64)) ** math.log2(1.0 + k), 0.05, 10.0)


class PassCounts:
    """Earlier passes (E,) per simulated visit of a window, kept for the hardening term's
    passes at other coefficients, up to `max_bytes` (then new counts are computed and not kept:
    the passes go over the windows in order, so the first ones kept are the ones read back)."""

    def __init__(self, max_bytes: int = 256 << 20):
        self.max_bytes, self.nbytes, self._n = max_bytes, 0, {}

    def get(self, key: tuple, count) -> np.ndarray:
        """The counts kept under `key`, else count() (kept while there is room)."""
        n = self._n.get(key)
        if n is None:
            n = np.asarray(count())
            if self.nbytes + n.nbytes <= self.max_bytes:
                self._n[key] = n
                self.nbytes += n.nbytes
        return n

    def of(self, drive: DriveSignals, wd, geom, before: bool, by_wheel: bool) -> np.ndarray:
        """`entry_passes` of the visit `geom` simulated for window data wd, kept by window,
        visit, view (before) and dig order (by_wheel)."""
        key = (visit_key(wd, geom), before, by_wheel)
        return self.get(key, lambda: entry_passes(drive, geom, wd.grid, before, by_wheel))


def visit_key(wd, geom) -> tuple:
    """Which window (wd: windows.WindowData) and which of its simulated visits (geom) a
    per-entry factor belongs to."""
    return (wd.spec.s0, wd.spec.s1, wd.crop, int(geom.poses.shape[0]), float(geom.poses[0, 0]))


class ExtensionModel:
    """An extension with a fixed coefficient, applied to the windows of one drive.

    `modifiers(wd, theta, geom)` returns the sim.Modifiers for window data wd
    (torchsoil.estimate.windows), full parameters theta (B, P) [m, -, rad] and the visit simulated
    (geom: wd.geom, the default, or one of wd.earlier); sinkage factors are cached per visit.

    view: what the pair's H_f holds on revisited ground (`windows.front_view`). With
    "first_view" every window simulates all the visits to its ground from untouched soil, so
    passes count the visits before each simulated pose's own (a loop's first lap digs fresh
    ground, although the drive comes back over it); with "last_visit" a window simulates the
    last visit only, and passes count all visits but the last (DriveSignals.passes).
    dig_order: the simulator's (SimConfig.dig_order); under "wheel" passes count every
    wheel's pass (a rear wheel in the front wheel's rut runs its second), under "robot"
    the robot's visits (its wheels dig as one).
    counts: a `PassCounts` shared by the models of one drive at other coefficients: the
    hardening term's pass counts do not depend on k, and counting them is most of the term's
    own cost (kept by window, visit, view and dig order)."""

    def __init__(self, ext: Extension, k: float, drive: DriveSignals, robot: Robot, view: str = "last_visit",
                 dig_order: str = "robot", counts: PassCounts | None = None):
        lo, hi = ext.bounds
        if not (lo <= k <= hi):
            raise ValueError(f"{ext.id}: coefficient {ext.parameter} = {k} outside [{lo}, {hi}]")
        if view not in ("first_view", "last_visit"):
            raise ValueError(f"view must be 'first_view' or 'last_visit', got {view!r}")
        self.ext, self.k, self.drive, self.robot, self.view = ext, float(k), drive, robot, view
        self.by_wheel = dig_order == "wheel"
        self.reference = references(drive)
        self._cache: dict[tuple, torch.Tensor] = {}
        self.counts = PassCounts() if counts is None else counts

    def modifiers(self, wd, theta: torch.Tensor, geom=None) -> Modifiers:
        B = theta.shape[0]
        kw = dict(device=theta.device, dtype=theta.dtype)
        geom = wd.geom if geom is None else geom
        if self.ext.kind == "depth":
            key = visit_key(wd, geom)
            if key not in self._cache:
                if self.ext.id == "multi_pass_hardening":       # (E,): cell by cell
                    n = self.counts.of(self.drive, wd, geom, self.view == "first_view", self.by_wheel)
                    f = pass_factor(n, self.k)
                else:                                           # (K, N): wheel by pose
                    f = depth_factor(self.ext, self.drive, self.robot, geom.poses.cpu().numpy(), self.k,
                                     self.reference)
                self._cache[key] = torch.as_tensor(f, **kw)
                if len(self._cache) > 64:          # the held-out offsets revisit windows up to 6 back
                    self._cache.pop(next(iter(self._cache)))
            f = self._cache[key]
            return Modifiers(depth_scale=f[None].expand(B, *f.shape))
        if self.ext.kind == "radius":
            return Modifiers(radius_scale=torch.full((B,), 1.0 + self.k, **kw))
        if self.ext.kind == "wall":                    # k = 0: one angle, the base model itself
            if self.k == 0:
                return Modifiers()
            beta = theta[:, ParamSpec.base(wd.geom.n_tracks).index("beta")]
            return Modifiers(tan_beta_intact=(torch.tan(beta) * (1.0 + self.k)).clamp(max=MAX_TAN))
        raise ValueError(f"unknown extension kind {self.ext.kind!r}")
