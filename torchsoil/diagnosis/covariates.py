"""Signals taken from the recorded poses alone, per pose and per window.

Everything here reads the trajectory (docs/formats.md (N, 7) rows t, x, y, z, roll, pitch, yaw)
and the robot's wheel layout, never the soil. The signals are what a missing physical term
could follow:

| name | unit | meaning |
| --- | --- | --- |
| arc_length | m | distance travelled by base_link |
| speed | m/s | ground speed (unsigned) |
| accel | m/s^2 | acceleration along the body x axis (reversing and speeding up: < 0) |
| pitch, roll | rad | chassis attitude |
| yaw_rate | rad/s | turn rate |
| lateral_accel | m/s^2 | signed forward speed * yaw_rate (along body y: left > 0) |
| traction | - | traction demand accel / g + sin(-pitch) (climbing: pitch < 0) |
| lateral_load | - | lateral_accel / g + sin(roll): load shift to the right wheels when > 0 |
| passes | - | passes of the wheels over the ground under a wheel before the last one |
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from torchsoil.robot import Robot
from torchsoil.sim.geometry import resample_poses, wheel_positions

G = 9.81  # m/s^2
POSE_SIGNALS = ("arc_length", "speed", "accel", "pitch", "roll", "yaw_rate", "lateral_accel",
                "traction", "lateral_load")
SIGNALS = POSE_SIGNALS + ("passes",)


def side_arc(poses: np.ndarray, lateral: float) -> np.ndarray:
    """(N,) distance travelled by the point `lateral` m left of base_link (a wheel's track)
    at each (N, 7) pose, m. On a turn of radius R the inner track covers (R - lateral) / R of
    base_link's arc: a tyre prints its lugs at fixed distances along its own track, so a
    tread's wavelength is steady in this arc length and not in base_link's."""
    p = check_poses(poses)
    x = p[:, 1] - lateral * np.sin(p[:, 6])
    y = p[:, 2] + lateral * np.cos(p[:, 6])
    return np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])


def check_poses(poses) -> np.ndarray:
    """Validate (N, 7) docs/formats.md poses; returns a float64 copy. Raises ValueError naming the fault."""
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 7:
        raise ValueError(f"poses must be (N, 7) rows t, x, y, z, roll, pitch, yaw; got shape {p.shape}")
    if len(p) < 3:
        raise ValueError(f"poses: need at least 3 poses to take derivatives, got {len(p)}")
    bad = ~np.isfinite(p).all(1)
    if bad.any():
        raise ValueError(f"poses: row {int(np.flatnonzero(bad)[0])} holds NaN or inf")
    dt = np.diff(p[:, 0])
    if (dt <= 0).any():
        raise ValueError(f"poses: time must increase strictly; row {int(np.flatnonzero(dt <= 0)[0]) + 1} "
                         "does not")
    return p


def pose_signals(poses, smooth_s: float = 0.2) -> dict[str, np.ndarray]:
    """Per-pose signals (table in the module docstring) from (N, 7) poses.

    Derivatives are taken after Gaussian smoothing over `smooth_s` seconds (odometry is noisy).
    Returns {name: (N,) array}."""
    p = check_poses(poses)
    t = p[:, 0]
    dt = float(np.median(np.diff(t)))
    sigma = max(smooth_s / dt, 0.0)

    def smooth(x):
        return ndimage.gaussian_filter1d(x, sigma, mode="nearest") if sigma > 0 else x

    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p[:, 1:3], axis=0), axis=1))])
    speed = smooth(np.gradient(arc, t))
    # the sign of the velocity along the heading: accelerations are along the body axes, so a
    # robot speeding up in reverse pushes backwards, and a reversing turn loads the other side
    along = smooth(np.gradient(p[:, 1], t) * np.cos(p[:, 6]) + np.gradient(p[:, 2], t) * np.sin(p[:, 6]))
    forward = speed * np.where(along < 0, -1.0, 1.0)
    accel = np.gradient(forward, t)
    yaw_rate = smooth(np.gradient(np.unwrap(p[:, 6]), t))
    pitch, roll = smooth(p[:, 5]), smooth(p[:, 4])
    lat = forward * yaw_rate
    return {"t": t, "arc_length": arc, "speed": speed, "accel": accel, "pitch": pitch, "roll": roll,
            "yaw_rate": yaw_rate, "lateral_accel": lat, "traction": accel / G + np.sin(-pitch),
            "lateral_load": lat / G + np.sin(roll)}


@dataclass
class DriveSignals:
    """Pose signals of one drive plus the wheel-path index needed to count earlier passes.

    signals: {name: (N,)} at the recorded poses; poses4: (N, 4) t, x, y, unwrapped yaw.
    wheel_points: (M, 2) every wheel centre along
    the drive, resampled every `spacing` m; wheel_arc: (M,) base_link arc length there, m.
    inner, radius: an earlier wheel passing within `inner` m of a point (its footprint)
    counts as a full pass there, one passing `radius` m away or farther not at all, and in
    between the share falls linearly. For the `passes` covariate (where a window's poses run
    near old tracks, for the location evidence) the share fades over about two wheel widths:
    a path that joins an old track at an angle comes near it before its wheels meet the old
    ruts. The hardening law itself counts the passes over each cell under a footprint
    (`passes(reach=...)`, `catalogue.entry_passes`). gap: base_link
    travel [m] after which coming back counts as a new pass. wheel_of: (M,) index of the wheel
    each wheel point belongs to (needed to count wheel passes, `passes(wheel=...)`); lag:
    base_link travel [m] by which another wheel's pass must precede a wheel's own to count
    before it (half the shortest spacing of the robot's axles). prior: (layer (X, Y), origin
    (2,) m, dx m), the wheel passes each cell had before the recording (a field's earlier
    sessions, `passes_prior` of torchsoil.field), added to every count of `passes`.
    """

    signals: dict[str, np.ndarray]
    poses4: np.ndarray
    wheel_points: np.ndarray
    wheel_arc: np.ndarray
    radius: float
    gap: float
    inner: float = 0.0
    wheel_of: np.ndarray | None = None
    lag: float = 0.0
    prior: tuple | None = None
    _tree: cKDTree | None = field(default=None, repr=False, compare=False)

    @classmethod
    def from_pair(cls, pair, spacing: float = 0.02) -> DriveSignals:
        """The signals of a terrain pair's drive, with its `passes_prior` layer when it has one."""
        prior = pair.extras.get("passes_prior")
        return cls.from_poses(pair.poses, pair.robot, spacing,
                              None if prior is None else (np.asarray(prior, np.float64), pair.origin, pair.dx))

    @classmethod
    def from_poses(cls, poses, robot: Robot, spacing: float = 0.02, prior: tuple | None = None) -> DriveSignals:
        p = check_poses(poses)
        sig = pose_signals(p)
        dense = resample_poses(p[:, [0, 1, 2, 6]], robot.wheels[:, :2], spacing)
        arc = np.interp(dense[:, 0], sig["t"], sig["arc_length"])
        w = wheel_positions(dense, robot.wheels[:, :2])                     # (K, M, 2)
        gap = 2.0 * float(np.ptp(robot.wheels[:, 0]) + robot.wheel_width)
        r = robot.wheel_width / 2
        axles = np.diff(np.unique(np.round(robot.wheels[:, 0], 6)))
        lag = float(axles.min()) / 2 if len(axles) else gap / 2
        return cls(sig, dense_src(p), w.reshape(-1, 2), np.tile(arc, len(w)), r + 2 * robot.wheel_width, gap, r,
                   np.repeat(np.arange(len(w)), w.shape[1]), lag, prior)

    def at(self, name: str, t) -> np.ndarray:
        """Signal `name` interpolated at times t [s] (any shape)."""
        if name not in self.signals:
            raise KeyError(f"unknown signal {name!r}; known: {sorted(self.signals)}")
        return np.interp(np.asarray(t, np.float64), self.signals["t"], self.signals[name])

    def passes(self, points: np.ndarray, arc: np.ndarray, before: bool = False,
               wheel: np.ndarray | None = None, reach: tuple[float, float] | None = None) -> np.ndarray:
        """Passes before the last one over the ground at `points` (..., 2) [m]: distinct visits
        (separated by more than `gap` of base_link travel) of any wheel within `radius`, each
        weighted by its closest wheel's distance (1 within `inner`, falling linearly to 0 at
        `radius`), all but the last. A terrain pair holds the surface just before the last
        visit to each cell, so the deformation it shows there is that of the last pass, whose
        earlier passes these are, whichever pass the pose itself belongs to. arc: (...)
        base_link arc length [m] of the pose at each point; before: count only the visits that
        ended more than `gap` / 2 of travel before it (the passes before the pose's own, for a
        simulation that drives every visit). Returns a float array of arc's shape (whole
        numbers where old tracks are driven exactly), plus the `prior` passes of each point's cell.

        wheel: (...) int, the wheel whose centre each point is. Given, every wheel's pass (a
        run of its hits, broken where it travelled more than `radius` away) counts on its own
        (the multi-pass count of wheels digging in turn, where a rear wheel runs on the ground
        its front wheel has just passed): the passes whose centre (the share-weighted mean arc
        of a wheel's hits) lies more than `lag` of travel before that wheel's own pass (the
        pose's with `before`, else its last over the point).

        reach: (inner, radius) [m] in place of the drive's (`inner`, `radius`): how near an
        earlier wheel's centre must have come to count fully, and to count at all."""
        pts = np.asarray(points, np.float64).reshape(-1, 2)
        inner, radius = (self.inner, self.radius) if reach is None else reach
        if self._tree is None:
            self._tree = cKDTree(self.wheel_points)
        hits = self._tree.query_ball_point(pts, radius)
        n_hits = np.fromiter((len(h) for h in hits), np.int64, len(hits))
        out = np.zeros(len(pts))
        if n_hits.sum() == 0:
            return (out + self._prior(pts)).reshape(np.shape(points)[:-1])
        i = np.repeat(np.arange(len(pts)), n_hits)                       # one row per (point, hit)
        j = np.concatenate([np.asarray(h, np.int64) for h in hits if len(h)])
        a = self.wheel_arc[j]
        by_wheel = wheel is not None
        if by_wheel and self.wheel_of is None:
            raise ValueError("counting wheel passes needs DriveSignals.wheel_of")
        kw = self.wheel_of[j] if by_wheel else np.zeros_like(j)
        order = np.lexsort((a, kw, i))
        i, j, a, kw = i[order], j[order], a[order], kw[order]
        dist = np.linalg.norm(self.wheel_points[j] - pts[i], axis=1)
        share = np.clip((radius - dist) / max(radius - inner, 1e-9), 0.0, 1.0)
        split = radius if by_wheel else self.gap                  # a wheel that left the disc came back
        first = np.flatnonzero(np.r_[True, (i[1:] != i[:-1]) | (kw[1:] != kw[:-1]) | (np.diff(a) > split)])
        best = np.maximum.reduceat(share, first)                         # closest wheel of each visit
        owner = i[first]
        if by_wheel:
            w_sum = np.add.reduceat(share, first)
            centre = np.where(w_sum > 0, np.add.reduceat(share * a, first) / np.maximum(w_sum, 1e-12),
                              np.minimum.reduceat(a, first))
            own = np.asarray(arc, np.float64).reshape(-1).copy()
            if not before:
                mine = kw[first] == np.asarray(wheel).reshape(-1)[owner]
                last = np.full(len(pts), -np.inf)
                np.maximum.at(last, owner[mine], centre[mine])
                own = np.where(np.isfinite(last), last, own)
            earlier = centre < own[owner] - self.lag
        elif before:
            ends = np.maximum.reduceat(a, first)
            earlier = ends < np.asarray(arc, np.float64).reshape(-1)[owner] - self.gap / 2
        else:
            earlier = np.r_[owner[1:] == owner[:-1], False]              # every visit but a point's last
        out += np.bincount(owner, weights=best * earlier, minlength=len(pts))
        return (out + self._prior(pts)).reshape(np.shape(points)[:-1])

    def _prior(self, pts: np.ndarray) -> np.ndarray | float:
        """(P,) `prior` passes at the cells of points (P, 2) [m]; 0 outside or without one."""
        if self.prior is None:
            return 0.0
        layer, origin, dx = self.prior
        i = np.rint((pts[:, 0] - origin[0]) / dx).astype(np.int64)
        j = np.rint((pts[:, 1] - origin[1]) / dx).astype(np.int64)
        ok = (i >= 0) & (j >= 0) & (i < layer.shape[0]) & (j < layer.shape[1])
        out = np.zeros(len(pts))
        out[ok] = layer[i[ok], j[ok]]
        return out

    def pose_passes(self, poses4: np.ndarray, robot: Robot, before: bool = False,
                    by_wheel: bool = False) -> np.ndarray:
        """(N, 4) poses t, x, y, yaw -> (K, N) earlier passes under each wheel (float); before:
        see `passes`; by_wheel: count every wheel's pass (`passes(wheel=...)`), not visits."""
        w = wheel_positions(np.asarray(poses4, np.float64), robot.wheels[:, :2])
        arc = self.at("arc_length", poses4[:, 0])
        wheel = np.broadcast_to(np.arange(len(w))[:, None], w.shape[:2]) if by_wheel else None
        return self.passes(w, np.broadcast_to(arc, w.shape[:2]), before, wheel)


def window_signals(drive: DriveSignals, spans: list[tuple[float, float]], robot: Robot) -> dict[str, np.ndarray]:
    """Mean of every signal over the poses whose arc length lies in each span [s0, s1) m.

    Returns {name: (W,)}; `passes` is the mean over wheels and poses; spans without poses get
    the signal at the span centre."""
    sig = drive.signals
    out = {n: np.zeros(len(spans)) for n in SIGNALS}
    for w, (s0, s1) in enumerate(spans):
        sel = (sig["arc_length"] >= s0) & (sig["arc_length"] < s1)
        if sel.sum() == 0:
            sel = np.zeros(len(sig["t"]), bool)
            sel[np.argmin(np.abs(sig["arc_length"] - 0.5 * (s0 + s1)))] = True
        for n in POSE_SIGNALS:
            out[n][w] = sig[n][sel].mean()
        out["passes"][w] = drive.pose_passes(drive.poses4[sel], robot).mean()
    return out


def dense_src(p: np.ndarray) -> np.ndarray:
    """(N, 7) poses -> (N, 4) t, x, y, unwrapped yaw."""
    q = p[:, [0, 1, 2, 6]].copy()
    q[:, 3] = np.unwrap(q[:, 3])
    return q
