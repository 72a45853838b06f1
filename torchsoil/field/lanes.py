"""Lanes of a field: the wheel tracks of the straight legs of every session's drive (rows,
not headland turns), those of different rows or sessions on one line grouped as one lane (a
rut: in controlled traffic the next row's wheels on one side run in the last row's rut). Pure
functions on arrays (field frame, metres, radians)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class Leg:
    """A straight stretch of one session's drive: session index, start and end (2,) of
    base_link in the field frame [m], times [s]."""

    session: int
    start: np.ndarray
    end: np.ndarray
    t0: float
    t1: float

    @property
    def direction(self) -> np.ndarray:
        d = self.end - self.start
        return d / max(float(np.linalg.norm(d)), 1e-12)

    @property
    def length(self) -> float:
        return float(np.linalg.norm(self.end - self.start))


def legs(poses: np.ndarray, session: int, min_length: float = 3.0, max_turn_deg: float = 5.0) -> list[Leg]:
    """The straight legs of a drive: (N, 7) poses t, x, y, z, roll, pitch, yaw [s, m, rad], cut
    where the heading leaves the leg's own by more than max_turn_deg; legs shorter than
    min_length [m] (turns, manoeuvres) are left out."""
    out: list[Leg] = []
    if len(poses) < 2:
        return out
    yaw = np.unwrap(poses[:, 6])
    a = 0
    while a < len(poses) - 1:
        b = a + 1
        ref = yaw[a]
        while b < len(poses) and abs(yaw[b] - ref) <= math.radians(max_turn_deg):
            # the leg's heading: its own mean so far, so a slow drift does not end it
            ref = float(np.mean(yaw[a:b + 1]))
            b += 1
        p, q = poses[a, 1:3], poses[b - 1, 1:3]
        if np.linalg.norm(q - p) >= min_length:
            out.append(Leg(session, p.copy(), q.copy(), float(poses[a, 0]), float(poses[b - 1, 0])))
        a = b
    return out


@dataclass
class Lane:
    """Legs on one line: a point on it and its unit direction (2,) [m], and the legs."""

    origin: np.ndarray
    direction: np.ndarray
    legs: list[Leg]

    def offset(self, xy: np.ndarray) -> np.ndarray:
        """Signed lateral distance [m] of points (..., 2) from the lane's line (left positive)."""
        n = np.array([-self.direction[1], self.direction[0]])
        return (np.asarray(xy) - self.origin) @ n

    def along(self, xy: np.ndarray) -> np.ndarray:
        return (np.asarray(xy) - self.origin) @ self.direction


def wheel_tracks(leg: Leg, track_offsets) -> list[Leg]:
    """The lines of a leg's wheel tracks: the leg shifted sideways by each offset [m] (base_link
    y of a track's wheels, left positive)."""
    n = np.array([-leg.direction[1], leg.direction[0]])
    return [Leg(leg.session, leg.start + o * n, leg.end + o * n, leg.t0, leg.t1) for o in track_offsets]


def group_lanes(all_legs: list[Leg], lateral: float = 0.1, max_angle_deg: float = 5.0) -> list[Lane]:
    """Lines on one line (parallel or opposite within max_angle_deg, within `lateral` m of each
    other at the new one's middle, overlapping along it) make one lane, in the order first met."""
    lanes: list[Lane] = []
    for leg in all_legs:
        for lane in lanes:
            cos = abs(float(lane.direction @ leg.direction))
            mid = 0.5 * (leg.start + leg.end)
            if cos < math.cos(math.radians(max_angle_deg)) or abs(float(lane.offset(mid))) > lateral:
                continue
            s = sorted(float(lane.along(p)) for p in (leg.start, leg.end))
            span = [(min(lane.along(g.start), lane.along(g.end)), max(lane.along(g.start), lane.along(g.end)))
                    for g in lane.legs]
            if any(s[0] < b and s[1] > a for a, b in span):
                lane.legs.append(leg)
                break
        else:
            lanes.append(Lane(leg.start.copy(), leg.direction.copy(), [leg]))
    return lanes


def track_mask(lane: Lane, xs: np.ndarray, ys: np.ndarray, half_width: float, margin: float = 0.5) -> np.ndarray:
    """(X, Y) cells of the grid (centres xs (X,), ys (Y,)) within half_width [m] of the lane's
    line, within its lines' extent along it less `margin` [m] at each end (where rows meet the
    headland turns)."""
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    xy = np.stack([gx, gy], -1)
    off, s = lane.offset(xy), lane.along(xy)
    ends = [sorted((float(lane.along(g.start)), float(lane.along(g.end)))) for g in lane.legs]
    lo, hi = min(e[0] for e in ends) + margin, max(e[1] for e in ends) - margin
    return (np.abs(off) <= half_width) & (s >= lo) & (s <= hi)
