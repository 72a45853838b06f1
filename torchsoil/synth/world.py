"""The world soil model: the base model's stages (torchsoil.sim) with spatially varying soil
and switchable extra physics (torchsoil.synth.effects), run along the true trajectory.

The path is simulated in short chunks of base_link arc length, each with the soil of its
own cells (sinkage d and angle of repose beta per cell, chi per chunk). The reference
height h~ of a cell is taken from the surface just before the robot's current visit to it,
so both wheels of a track dig to the same depth and a later pass digs from the rut the
earlier one left. A visit starts when a wheel comes near a cell after the robot has
travelled more than `revisit_gap` since it last did. Multi-pass hardening counts the visits
in which a footprint covered the cell (soil hardens where a wheel pressed it, not where the
robot only came near); when the axles dig in turn (world.dig_order "wheel") it counts wheel
passes instead, so a rear wheel in its front wheel's rut runs the second pass.

A drive may start on the ground an earlier one left (a later session of a season on the same
field): `simulate_world` then takes that drive's `WorldResult.end` (a `SoilState`: surface,
pass counts, loose soil) instead of a bare surface, so hardening counts the earlier sessions'
passes and a wheel on their ruts rests on them as on an earlier visit's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from torchsoil.grid import Grid
from torchsoil.robot import Robot
from torchsoil.settings import SECTIONS, WorldConfig, WorldSoil
from torchsoil.sim.cohesive import relax_two_angle
from torchsoil.sim.geometry import dig_order as wheel_turns
from torchsoil.sim.relaxation import relax
from torchsoil.sim.sinkage import reference_height, taper
from torchsoil.synth import effects as fx
from torchsoil.synth.terrain import as_world_soil, soil_at
from torchsoil.synth.trajectory import Trajectory

MAX_VISITS = 6


@dataclass
class SoilState:
    """The ground a drive leaves to the next (a later session on the same field), on the
    world's grid, all (X, Y): h, the surface, m; passes (int), the visits in which a wheel
    footprint covered the cell (multi-pass hardening's count under dig_order robot);
    wheel_passes (int), the wheels that dug it (the count under dig_order wheel); visits (int),
    all visits of the cell (module docstring); loose, moved soil lying on the intact ground
    (cohesive soil's state), m. Counts are over every drive so far."""

    h: np.ndarray
    passes: np.ndarray
    wheel_passes: np.ndarray
    visits: np.ndarray
    loose: np.ndarray

    @classmethod
    def fresh(cls, h: np.ndarray) -> SoilState:
        """Ground no wheel has touched, of surface h (X, Y) [m]."""
        h = np.asarray(h, dtype=np.float64)
        zero = np.zeros(h.shape, dtype=np.int64)
        return cls(h.copy(), zero, zero.copy(), zero.copy(), np.zeros(h.shape))


@dataclass
class WorldResult:
    """Truth of one drive on the corridor grid (all (X, Y) arrays, float64 unless noted).

    h_before: surface before the robot, m.          h_after: surface after the drive, m.
    states: (V+1, X, Y) surface after the cell's v-th visit (v = 0: before), m.
    visit_time: (V, X, Y) time the cell reached states[v+1], s (inf: no such visit).
    n_visits: (X, Y) int, visits per cell.     t_last_wheel: time a wheel last covered the cell, s (nan: never).
    soil: {d, chi, beta, moisture} per cell.
    pass_time: (V, X, Y) time base_link passed closest to the cell during visit v, s (nan: no
    such visit; a terrain pair's `visit_time`).
    end: the ground the drive left (SoilState: its surface h_after and the counts so far), the
    start of a later drive on the same field.
    """

    grid: Grid
    h_before: np.ndarray
    h_after: np.ndarray
    states: np.ndarray
    visit_time: np.ndarray
    n_visits: np.ndarray
    t_last_wheel: np.ndarray
    soil: dict
    pass_time: np.ndarray
    end: SoilState | None = None

    def surface_at(self, t: float) -> np.ndarray:
        """(X, Y) true surface at time t [s]: each cell in its state after the visits done by t."""
        done = (self.visit_time <= t).sum(0)
        return np.take_along_axis(self.states, done[None], 0)[0]


def _chunks(arc: np.ndarray, length: float) -> list[np.ndarray]:
    """Pose index ranges of consecutive chunks of `length` m of arc (1 pose overlap)."""
    edges = np.arange(0.0, arc[-1] + length, length)
    out = []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        idx = np.nonzero((arc >= a) & (arc < b))[0]
        if len(idx):
            hi = min(idx[-1] + 1, len(arc) - 1)
            out.append(np.arange(max(idx[0] - 1, 0), hi + 1))
    return out


def section_profile(q: np.ndarray, section: str = "taper", flat_fraction: float = 0.0) -> np.ndarray:
    """Share s(q) in [0, 1] of the sinkage across a tyre footprint, q = lateral offset /
    footprint radius (any shape; s = 0 for |q| >= 1).

    taper: the robot's (flat to |q| <= flat_fraction, cosine shoulder; what the estimator
    assumes); flat: a flat tread with narrow shoulders (taper with flat fraction 0.9);
    rounded: elliptic sqrt(1 - q^2); crowned: parabolic 1 - q^2."""
    q = np.abs(np.asarray(q, dtype=np.float64))
    if section in ("taper", "flat"):
        f = flat_fraction if section == "taper" else 0.9
        return taper(torch.from_numpy(q), f).numpy()
    inside = np.clip(1.0 - q * q, 0.0, 1.0)
    if section == "rounded":
        return np.sqrt(inside)
    if section == "crowned":
        return inside
    raise ValueError(f"tyre section must be one of {SECTIONS}, got {section!r}")


def simulate_world(grid: Grid, h0: np.ndarray | SoilState, traj: Trajectory, robot: Robot,
                   soil: WorldSoil | dict, effects: dict | None = None, config: WorldConfig | None = None,
                   revisit_gap: float | None = None, section: str = "taper",
                   width_scale: float = 1.0) -> WorldResult:
    """Drive the robot along `traj` over the surface h0 (X, Y) [m] on `grid`, or over the
    ground an earlier drive left (a SoilState, its `WorldResult.end`): then hardening counts
    the earlier drives' passes too, and a cell's first visit in this drive, where an earlier
    drive visited it, is a revisit (its reference height the footprint's, as below). Visits,
    states and times of the result are this drive's; `end` carries the counts over all.

    soil: scenario soil section (WorldSoil or a dict of it, see `terrain.soil_at`), with
    optional `track_scale` (T,) factors on d per track; effects: scenario effects section
    (see `effects.resolve`); config: the world's physics (settings.WorldConfig: the
    simulator's settings and chunk); revisit_gap: base_link travel [m] after which a wheel
    near a cell starts a new visit (default: twice the wheelbase plus a wheel width); section,
    width_scale: the tyre (`section_profile`; footprint width / the robot's). With
    config.dig_order "wheel" the axles dig in turn, each trailing wheel again from the rut
    ahead of it with the spoil of the wheels ahead beside it, resting where they dug on that
    surface's mean over its footprint (config.revisit_ref "footprint", as a wheel on the ruts
    of an earlier visit).
    """
    config = config or WorldConfig()
    soil = as_world_soil(soil)
    eff = fx.resolve(effects)
    start = h0 if isinstance(h0, SoilState) else SoilState.fresh(h0)
    h0 = start.h
    if h0.shape != grid.shape:
        raise ValueError(f"h0 must have the grid's shape {grid.shape}, got {h0.shape}")
    dx = grid.dx
    xs, ys = grid.centers()
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    sf = soil_at(soil, X, Y)
    track_scale = np.asarray(soil.track_scale if soil.track_scale is not None else [1.0] * robot.n_tracks,
                             dtype=np.float64)
    if track_scale.shape != (robot.n_tracks,):
        raise ValueError(f"soil.track_scale must have {robot.n_tracks} entries, got {track_scale.tolist()}")
    tan_beta = np.tan(sf["beta"])
    tan_intact = fx.intact_tan_beta(eff, tan_beta, sf["moisture"])
    cohesive = "cohesive_walls" in eff
    loose = start.loose.copy()          # thickness of moved soil on the intact ground, m (cohesive soil)
    track_width = float(np.ptp(robot.wheels[:, 1])) or 1.0
    gap = revisit_gap if revisit_gap is not None else 2.0 * float(np.ptp(robot.wheels[:, 0]) + robot.wheel_width)
    radius0 = robot.wheel_width * width_scale / 2
    # a wheel on ground wheels dug before (a later visit, a trailing axle) rests on it at the
    # mean over its footprint (revisit_ref "footprint"; sim.sinkage.contact_height)
    again_radius = radius0 if config.revisit_ref == "footprint" else config.ref_radius * radius0

    h = h0.copy()
    # the reference height of a first visit comes from the surface before the robot
    h_ref = reference_height(torch.from_numpy(h0)[None], config.ref_radius * robot.wheel_width * width_scale / 2,
                             dx)[0].numpy()
    # relaxation waits until the pass is over (or a revisit needs the settled surface): the
    # base model digs and deposits for every pose first, then relaxes once
    pending = np.zeros(grid.shape, dtype=bool)
    dug = np.zeros(grid.shape, dtype=bool)
    # deposits wait too (`held`): the wheels of a visit dig the surface without them, as the
    # simulator digs every pose of a path before it deposits, and none is dug again
    held = HeldDeposits()

    # dig_order "wheel": per turn r < R - 1, the surface the axles of turns <= r left in this visit
    # (no deposits), and per turn where its wheels dug in this visit; reset when the surface
    # settles. wheel_passes: how many wheels dug each cell in the visits before; dug_visits: in
    # how many visits before a footprint covered it (hardening counts wheel passes under
    # "wheel", the robot's visits under "robot": soil hardens where a wheel pressed it, not
    # where the robot only came near)
    n_axles = len(np.unique(np.round(robot.wheels[:, 0], 6)))
    lead = [h.copy() for _ in range(n_axles - 1)] if config.dig_order == "wheel" else []
    turn_dug = np.zeros((n_axles if lead else 0, *grid.shape), dtype=bool)
    # per turn r, the deposits of the wheels of turns <= r, laid on lead[r] once those wheels
    # have passed: a trailing wheel finds the spoil of the wheels ahead beside their ruts
    lead_held = [HeldDeposits() for _ in lead]
    wheel_passes = start.wheel_passes.copy()
    dug_visits = start.passes.copy()
    before = start.visits                   # visits of the drives before this one

    def settle(which: np.ndarray | None = None):
        """Relax the pending cells (those of `which`, default all) once, as one pass's digs."""
        sel = pending if which is None else pending & which
        if not sel.any():
            return
        laid = h.copy()
        held.lay(h, sel, dug)
        loose[:] += h - laid                # deposits are loose soil (cohesive soil's state)
        _forget(lead_held, sel, dug)        # laid on h above; the next visit's turns start from h
        # pass_loosening: the angle these digs relax to follows the visits before (not yet this one)
        _relax_box(h, loose, sel, fx.repose_tan_beta(eff, sf["beta"], tan_beta, dug_visits),
                   tan_intact if cohesive else None, dx, config)
        done = sel.copy()
        pending[done] = False
        dug_visits[done] += dug[done]
        dug[done] = False
        _start_visit(lead, turn_dug, wheel_passes, h, done)

    last_arc = np.full(grid.shape, -np.inf)
    n_visits = np.zeros(grid.shape, dtype=np.int64)
    states = np.repeat(h0[None], MAX_VISITS + 1, axis=0)
    visit_time = np.full((MAX_VISITS, *grid.shape), np.inf)
    pass_time = np.full((MAX_VISITS, *grid.shape), np.nan)
    pass_dist = np.full(grid.shape, np.inf)             # base_link's closest so far in the visit under way
    t_wheel = np.full(grid.shape, np.nan)
    reach = radius0 * 1.5 + (config.band_width + 1) * dx + config.relax_margin * robot.wheel_width + 2 * dx
    wxy = robot.wheels[:, :2]
    K = len(robot.wheels)
    tt = traj.poses[:, 0]
    w_all = _wheel_xy(traj.poses[:, [0, 1, 2, 6]], wxy)                   # (K, N, 2)
    wheel_arc = np.concatenate([np.zeros((K, 1)), np.cumsum(np.linalg.norm(np.diff(w_all, axis=1), axis=-1), 1)], 1)

    for idx in _chunks(traj.arc, config.chunk):
        p = traj.poses[idx]
        w = _wheel_xy(p[:, [0, 1, 2, 6]], wxy)
        lo = grid.index(w.reshape(-1, 2).min(0) - reach)
        hi = grid.index(w.reshape(-1, 2).max(0) + reach) + 1
        i0, j0 = max(lo[0], 0), max(lo[1], 0)
        i1, j1 = min(hi[0], grid.shape[0]), min(hi[1], grid.shape[1])
        if i1 - i0 < 2 or j1 - j0 < 2:
            continue
        win = (slice(i0, i1), slice(j0, j1))
        rscale = fx.radius_scale(eff, float(np.median(sf["d"][win])))
        geom = chunk_geometry(grid.crop(i0, i1, j0, j1), p[:, [0, 1, 2, 6]], wxy,
                              reach, config.pose_spacing * dx, wheel_arc[:, idx[0]])
        gp, dist, pidx = geom["poses"], geom["dist"], geom["pose"]
        t_pose = gp[:, 0][pidx]                                    # (K, X, Y)

        # visits: cells near a wheel now that the robot had left more than `gap` metres ago
        near_k = dist <= radius0 * rscale + config.relax_margin * robot.wheel_width
        near = near_k.any(0)
        new = near & (float(traj.arc[idx[0]]) - last_arc[win] > gap)
        if new.any():
            v = n_visits[win]
            if (new & (v >= 1) & pending[win]).any():
                # a revisit starts from the settled surface: the earlier visits' digs relax,
                # those of the visit under way (the robot left them less than `gap` ago) wait
                settle(float(traj.arc[idx[0]]) - last_arc > gap)
            hw = h[win]
            if v[new].max() >= MAX_VISITS:
                raise ValueError(f"a cell is visited more than {MAX_VISITS} times")
            for k in range(1, MAX_VISITS + 1):         # state after visit k, until overwritten
                sel = (new & (v == k))[None]
                states[k:, i0:i1, j0:j1] = np.where(sel, hw[None], states[k:, i0:i1, j0:j1])
            again = new & ((v >= 1) | (before[win] >= 1))
            if again.any():
                ref = reference_height(torch.from_numpy(hw)[None], again_radius, dx)[0].numpy()
                h_ref[win] = np.where(again, ref, h_ref[win])
            n_visits[win] = v + new
        last_arc[win] = np.where(near, float(traj.arc[idx[-1]]), last_arc[win])
        under_way = (n_visits[win] >= 1) & (float(traj.arc[idx[0]]) - last_arc[win] <= gap)
        _pass_times(pass_time, pass_dist, win, under_way, new, n_visits[win] - 1, gp, xs[i0:i1], ys[j0:j1])

        # sinkage per wheel and cell: soil d x track x pose-driven effects x pass effects (+ tread)
        sp, ac, yr = (np.interp(gp[:, 0], tt, a) for a in (traj.speed, traj.accel, traj.yaw_rate))
        ro, pi = (np.interp(gp[:, 0], tt, traj.poses[:, c]) for c in (4, 5))
        fpose = fx.pose_depth_factor(eff, sp, ac, pi, ro, yr, robot.wheels[:, 1], track_width)
        fcell = np.take_along_axis(fpose, pidx.reshape(K, -1), 1).reshape(pidx.shape)
        ref, turn = _turn_reference(h_ref[win], lead, turn_dug, win, gp, pidx, robot.wheels[:, 0],
                                    again_radius, dx)
        passes = _pass_index(dug_visits[win], turn, turn_dug[:, i0:i1, j0:j1], wheel_passes[win])
        depth = (sf["d"][win][None] * track_scale[robot.track][:, None, None] * fcell
                 * np.asarray(fx.pass_depth_factor(eff, passes)))
        if "tread" in eff:          # a lug marks the cell where the wheel's centre passes it
            depth = depth + fx.tread_depth(eff, geom["arc"])

        # speed_deposit: per wheel-cell, the share at the speed of the pose nearest it
        chi = fx.deposit_share(eff, sf["chi"][win], sp[pidx])
        h[win], deposits, covered, domain, targets = _step(h[win], ref, geom, radius0 * rscale, robot, depth,
                                                           chi, config, section, first=idx[0] == 0,
                                                           final=idx[-1] == len(traj.poses) - 1)
        _advance_turns(lead, win, turn, targets, turn_dug, covered)
        held.add(deposits, (i0, j0), grid.shape)
        loose[win][covered.any(0)] = 0.0               # a wheel's cut (or pressed) ground is intact
        _lead_deposits(lead, lead_held, deposits, turn, covered, turn_dug, (i0, j0))
        pending[win] |= domain
        dug[win] |= covered.any(0)
        t_cov = np.where(covered, t_pose, -np.inf).max(0)
        t_wheel[win] = np.where(covered.any(0), t_cov, t_wheel[win])
        t_near = np.where(near_k, t_pose, -np.inf).max(0)
        v = n_visits[win]
        for k in range(1, int(v.max()) + 1):
            sel = near & (v == k)
            cur = visit_time[k - 1, i0:i1, j0:j1]
            visit_time[k - 1, i0:i1, j0:j1] = np.where(sel, np.where(np.isfinite(cur), np.maximum(cur, t_near),
                                                                     t_near), cur)

    settle()
    V = int(n_visits.max())
    for k in range(1, V + 1):                               # the final state after the last visit
        states[k:] = np.where((n_visits == k)[None], h[None], states[k:])
    end = SoilState(h.copy(), dug_visits, wheel_passes, before + n_visits, loose)
    return WorldResult(grid, h0, h, states[: V + 1].copy(), visit_time[:V].copy(), n_visits, t_wheel, sf,
                       pass_time[:V].copy(), end)


def _relax_box(h: np.ndarray, loose: np.ndarray, sel: np.ndarray, tan_beta: np.ndarray,
               tan_intact: np.ndarray | None, dx: float, config: WorldConfig) -> None:
    """Relax h (X, Y) [m] in place over the bounding box of the (X, Y) bool `sel` cells, at the
    per-cell tan(beta); for cohesive soil (tan_intact (X, Y) given) with the two-angle
    relaxation, intact ground standing up to tan_intact and the loose thickness `loose` (X, Y)
    [m] updated in place."""
    ii, jj = np.nonzero(sel)
    box = (slice(ii.min(), ii.max() + 1), slice(jj.min(), jj.max() + 1))
    args = (dx, torch.from_numpy(sel[box].copy()), config.tau, config.max_iter, None, config.eps_scale)
    hb, tb = torch.from_numpy(h[box].copy())[None], torch.from_numpy(tan_beta[box])[None]
    if tan_intact is None:
        h[box] = relax(hb, tb, *args, config.backend).h[0].numpy()
        return
    rr = relax_two_angle(hb, torch.from_numpy(loose[box].copy())[None], tb, torch.from_numpy(tan_intact[box])[None],
                         *args, backend=config.backend)
    h[box], loose[box] = rr.h[0].numpy(), rr.loose[0].numpy()


def _pass_times(pass_time: np.ndarray, pass_dist: np.ndarray, win, under_way: np.ndarray, new: np.ndarray,
                visit: np.ndarray, poses: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> None:
    """Update in place, on window `win`, the time base_link passed closest to each cell in its
    visit under way (pass_time (V, X, Y) s, pass_dist (X, Y) that distance, m) from one chunk's
    (M, 4) poses t, x, y, yaw: on the window's (x, y) `under_way` cells (visited, the robot
    less than the revisit gap away), whose visit under way is `visit` ((x, y) int) and just
    started where `new`. xs, ys: the window's cell centres, m."""
    best = pass_dist[win]
    best[new] = np.inf
    cells = np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)
    d, k = cKDTree(poses[:, 1:3]).query(cells)
    d, t = d.reshape(under_way.shape), poses[k, 0].reshape(under_way.shape)
    ii, jj = np.nonzero(under_way & (d < best))
    pass_time[visit[ii, jj], ii + win[0].start, jj + win[1].start] = t[ii, jj]
    best[ii, jj] = d[ii, jj]


def _turn_reference(h_ref: np.ndarray, lead: list, turn_dug: np.ndarray, win, poses: np.ndarray,
                    pidx: np.ndarray, wheels_x: np.ndarray, radius: float, dx: float
                    ) -> tuple[np.ndarray, np.ndarray | None]:
    """Reference height of each wheel-cell [m] and the (K, X, Y) turn of each wheel at its
    nearest pose (`geometry.dig_order`; pidx (K, X, Y) into the chunk's (N, 4) poses): h_ref
    (X, Y) itself and None when the wheels dig all at once (`lead` empty). Under dig_order
    "wheel", (K, X, Y): a wheel of turn r >= 1 takes it from the surface the turns before it
    left (`lead`), smoothed over a disc of `radius` [m], where they dug in this visit
    (turn_dug (R, X, Y) on the whole grid)."""
    if not lead:
        return h_ref, None
    K = len(wheels_x)
    turn = np.take_along_axis(wheel_turns(poses, wheels_x), pidx.reshape(K, -1), 1).reshape(pidx.shape)
    ref = np.repeat(h_ref[None], K, 0)
    for r, surf in enumerate(lead, start=1):
        ahead = reference_height(torch.from_numpy(surf[win])[None], radius, dx)[0].numpy()
        dug = turn_dug[(slice(None, r), *win)].any(0)
        ref = np.where((turn == r) & dug[None], ahead[None], ref)
    return ref, turn


def _advance_turns(lead: list, win, turn: np.ndarray | None, targets: np.ndarray, turn_dug: np.ndarray,
                   covered: np.ndarray) -> None:
    """Update in place, on window `win`: `lead`, per turn r the surface the wheels of turns <= r
    left, from this chunk's (K, X, Y) targets [m]; and turn_dug (R, X, Y), where each turn's
    wheels dug in this visit, from their (K, X, Y) footprints `covered`."""
    for r, surf in enumerate(lead):
        surf[win] = np.fmin(surf[win], np.where(turn <= r, targets, np.inf).min(0))
    for r in range(len(turn_dug)):
        turn_dug[(slice(r, r + 1), *win)] |= (covered & (turn == r)).any(0)[None]


def _lead_deposits(lead: list, lead_held: list, deposits: list, turn: np.ndarray | None, covered: np.ndarray,
                   turn_dug: np.ndarray, corner: tuple[int, int]) -> None:
    """Under dig_order "wheel", in place: lay on each turn's surface `lead[r]` the deposits of
    the wheels of turns <= r (`lead_held[r]`, this chunk's `deposits` of `_step` added, the
    chunk's window starting at `corner`) over the bins those wheels have passed, outside the
    cells dug in this visit (turn_dug (R, X, Y)). A wheel's turn is its most common one over
    its footprint cells (covered, turn (K, X, Y))."""
    if not lead:
        return
    none = (np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64), (np.zeros(0, np.int64),) * 2)
    k_turn = [int(np.bincount(turn[k][covered[k]]).argmax()) if covered[k].any() else len(lead) + 1
              for k in range(len(deposits))]
    active = {k: int(dep[0].min()) for k, dep in enumerate(deposits) if len(dep[0])}
    shape = lead[0].shape
    dug = turn_dug.any(0)
    for r, (surf, lh) in enumerate(zip(lead, lead_held, strict=True)):
        lh.add([dep if k_turn[k] <= r else none for k, dep in enumerate(deposits)], corner, shape)
        lh.lay_passed(surf, active, dug)


def _forget(lead_held: list, settled: np.ndarray, dug: np.ndarray) -> None:
    """Drop from each turn's held deposits those whose band reaches the settled cells."""
    for lh in lead_held:
        lh.lay(np.zeros(settled.shape), settled, dug)


def _pass_index(dug_visits: np.ndarray, turn: np.ndarray | None, turn_dug: np.ndarray,
                wheel_passes: np.ndarray) -> np.ndarray:
    """The pass each wheel runs over each cell, 1 = first: (1, X, Y) one plus the robot's
    earlier visits whose footprints covered the cell (dug_visits) when the wheels dig all at
    once (turn None); else (K, X, Y) wheel passes: those of earlier visits
    (wheel_passes (X, Y)) plus the turns before the wheel's own (turn (K, X, Y)) that dug the
    cell in this visit (turn_dug (R, X, Y)), plus one."""
    if turn is None:
        return dug_visits[None] + 1
    ahead = np.cumsum(turn_dug, 0) - turn_dug
    return wheel_passes[None] + np.take_along_axis(ahead, turn, 0) + 1


class HeldDeposits:
    """The deposits of the visits under way, per wheel and arc bin (2 cells of the wheel's path
    length over the whole drive): the height its footprint lost times chi [m, summed over
    cells] and its band cells. They are laid when their cells settle, spread evenly over the
    band cells no wheel of the visit dug: the simulator's deposition over a whole path."""

    def __init__(self):
        self.volume: dict[tuple[int, int], float] = {}
        self.cells: dict[tuple[int, int], list[np.ndarray]] = {}

    def add(self, deposits: list, corner: tuple[int, int], shape: tuple[int, int]) -> None:
        """One chunk's digs (`_step`), per wheel k: (n,) arc bins and heights lost x chi [m] of
        its footprint cells, (m,) arc bins and (rows, cols) of its band cells on the chunk's
        window, whose first cell is `corner` on the grid of `shape`."""
        for k, (vol_bins, vol, band_bins, (rows, cols)) in enumerate(deposits):
            if len(vol_bins):
                ub, inv = np.unique(vol_bins, return_inverse=True)
                for b, v in zip(ub.tolist(), np.bincount(inv, vol).tolist(), strict=True):
                    self.volume[(k, b)] = self.volume.get((k, b), 0.0) + v
            if len(band_bins):
                flat = np.ravel_multi_index((rows + corner[0], cols + corner[1]), shape)
                order = np.argsort(band_bins, kind="stable")
                ub, start = np.unique(band_bins[order], return_index=True)
                for b, part in zip(ub.tolist(), np.split(flat[order], start[1:]), strict=True):
                    self.cells.setdefault((k, b), []).append(part)

    def lay(self, h: np.ndarray, settled: np.ndarray, dug: np.ndarray) -> None:
        """Add to h (X, Y) [m], in place, the deposits whose band reaches the (X, Y) bool
        `settled` cells, on their band cells outside the (X, Y) bool `dug` ones (on all their
        band cells where a wheel dug each). A bin with a volume but no band cell of its own
        gives it to the nearest bin of the same wheel that has some."""
        settled_f = settled.reshape(-1)
        self._lay(h, lambda key, c: bool(settled_f[c].any()), dug)

    def lay_passed(self, h: np.ndarray, active: dict, dug: np.ndarray) -> None:
        """As `lay`, the deposits of the bins each wheel has passed: those more than one bin
        before the first bin of wheel k in `active` {k: first arc bin its footprint dug in
        the chunk under way} (all of a wheel not in it)."""
        self._lay(h, lambda key, c: key[1] < active.get(key[0], np.inf) - 1, dug)

    def _lay(self, h: np.ndarray, ready, dug: np.ndarray) -> None:
        flat, dug_f = h.reshape(-1), dug.reshape(-1)
        cells = {key: np.unique(np.concatenate(parts)) for key, parts in self.cells.items()}
        for key in [key for key in self.volume if key not in cells]:
            near = [c for c in cells if c[0] == key[0]]
            if near:
                to = min(near, key=lambda c: abs(c[1] - key[1]))
                self.volume[to] = self.volume.get(to, 0.0) + self.volume.pop(key)
        for key in [key for key, c in cells.items() if ready(key, c)]:
            c = cells[key]
            use = c[~dug_f[c]] if (~dug_f[c]).any() else c
            flat[use] += self.volume.pop(key, 0.0) / len(use)
            del self.cells[key]


def _start_visit(lead: list, turn_dug: np.ndarray, wheel_passes: np.ndarray, h: np.ndarray,
                 cells: np.ndarray) -> None:
    """A new visit over the (X, Y) bool `cells` (where the surface h has settled), in place:
    every turn's surface becomes h there, the wheel passes of the visit that ended join
    wheel_passes, nothing is dug yet."""
    for surf in lead:
        surf[cells] = h[cells]
    wheel_passes[cells] += turn_dug[:, cells].sum(0)
    turn_dug[:, cells] = False


def _wheel_xy(gp: np.ndarray, wxy: np.ndarray) -> np.ndarray:
    """(N, 4) poses t, x, y, yaw -> (K, N, 2) wheel centres."""
    c, s = np.cos(gp[:, 3]), np.sin(gp[:, 3])
    x = gp[None, :, 1] + c[None] * wxy[:, :1] - s[None] * wxy[:, 1:]
    y = gp[None, :, 2] + s[None] * wxy[:, :1] + c[None] * wxy[:, 1:]
    return np.stack([x, y], -1)


def chunk_geometry(grid: Grid, poses: np.ndarray, wxy: np.ndarray, reach: float,
                   max_step: float, arc0: np.ndarray | None = None) -> dict:
    """Dense per-wheel geometry of one chunk on a small grid.

    poses: (N, 4) t, x, y, yaw; wxy: (K, 2) wheel offsets in base_link, m; reach: search
    radius, m; max_step: poses are resampled so no wheel moves more than this, m; arc0: (K,)
    each wheel's path length at the chunk's first pose, m (default 0), so that the arc bins
    of consecutive chunks line up.
    Returns {poses (M, 4), dist (K, X, Y) [m, inf beyond reach], lateral (K, X, Y) [m, left
    positive], pose (K, X, Y) int index of the nearest pose, arc (K, X, Y) the wheel's path
    length where its centre passes the cell [m] (the nearest pose's plus the cell's offset
    along the heading: cells behind the chunk's first pose come before it), bin (K, X, Y) int
    arc bin of 2 cells along the wheel's path}.
    """
    p = poses.copy()
    p[:, 3] = np.unwrap(p[:, 3])
    if len(p) > 1:
        w = _wheel_xy(p, wxy)
        step = np.linalg.norm(np.diff(w, axis=1), axis=-1).max(0)
        n = np.maximum(1, np.ceil(step / max_step).astype(np.int64))
        frac = np.concatenate([np.arange(m) / m for m in n])
        seg = np.repeat(np.arange(len(p) - 1), n)
        p = np.vstack([p[seg] + frac[:, None] * (p[seg + 1] - p[seg]), p[-1:]])
    w = _wheel_xy(p, wxy)                                          # (K, M, 2)
    xs, ys = grid.centers()
    K = len(wxy)
    shape = (K, *grid.shape)
    dist = np.full(shape, np.inf)
    lateral = np.zeros(shape)
    pose = np.zeros(shape, dtype=np.int64)
    bins = np.zeros(shape, dtype=np.int64)
    cell_arc = np.zeros(shape)
    ahead = np.zeros(shape, dtype=bool)
    behind = np.zeros(shape, dtype=bool)
    for k in range(K):
        lo = np.maximum(np.floor((w[k].min(0) - reach - grid.origin) / grid.dx).astype(int), 0)
        hi = np.minimum(np.ceil((w[k].max(0) + reach - grid.origin) / grid.dx).astype(int) + 1, grid.shape)
        if np.any(hi <= lo):
            continue
        cx, cy = np.meshgrid(xs[lo[0]:hi[0]], ys[lo[1]:hi[1]], indexing="ij")
        cells = np.column_stack([cx.ravel(), cy.ravel()])
        d = np.gradient(w[k], axis=0) if len(p) > 1 else np.zeros_like(w[k])
        moving = np.linalg.norm(d, axis=1) > 1e-9
        head = np.where(moving, np.arctan2(d[:, 1], d[:, 0]), p[:, 3])
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(w[k], axis=0), axis=1))])
        arc = arc + (0.0 if arc0 is None else float(arc0[k]))
        dd, ii = cKDTree(w[k]).query(cells, distance_upper_bound=reach)
        hit = np.isfinite(dd)
        ii = np.where(hit, ii, 0)
        rel = cells - w[k, ii]
        sub = (k, slice(lo[0], hi[0]), slice(lo[1], hi[1]))
        sh = cx.shape
        dist[sub] = dd.reshape(sh)
        lateral[sub] = np.where(hit, -np.sin(head[ii]) * rel[:, 0] + np.cos(head[ii]) * rel[:, 1], 0.0).reshape(sh)
        along = np.cos(head[ii]) * rel[:, 0] + np.sin(head[ii]) * rel[:, 1]
        ahead[sub] = (hit & (ii == len(p) - 1) & (along > 0)).reshape(sh)
        behind[sub] = (hit & (ii == 0) & (along < 0)).reshape(sh)
        pose[sub] = ii.reshape(sh)
        bins[sub] = np.floor(arc[ii] / (2 * grid.dx)).astype(np.int64).reshape(sh)
        cell_arc[sub] = np.where(hit, arc[ii] + along, 0.0).reshape(sh)
    return {"poses": p, "dist": dist, "lateral": lateral, "pose": pose, "arc": cell_arc, "bin": bins, "ahead": ahead,
            "behind": behind, "dx": grid.dx}


def _step(h, h_ref, geom: dict, radius: float, robot: Robot, depth, chi, config: WorldConfig,
          section: str = "taper", first: bool = True, final: bool = True):
    """Sinkage and deposition of one chunk on window arrays (X, Y) [m]; h_ref (X, Y) or per
    wheel (K, X, Y) [m]; depth (K, X, Y) [m], chi (X, Y), or per wheel (K, X, Y), the soil's
    displacement-compaction ratio where the soil is dug.

    Sinkage h <- min(h, h_ref - s * depth) over each footprint; the height removed under
    each wheel goes, times the local chi, to the band of width config.band_width cells
    beside its footprint in the same 2-cell arc bin, once the visit is over, as relaxation.
    The ground beyond the chunk's last pose (before its first) is the next (the last) chunk's,
    unless this one is the drive's `final` (`first`) one: a footprint or band there would
    give a cell to two chunks and its volume to the wrong arc bin.
    Returns the dug surface (X, Y), per wheel the deposits to make (the arc bins of its
    footprint cells and the height each lost times chi [m], the arc bins and (rows, cols) of
    its band cells; `HeldDeposits.add`), the (K, X, Y) bool footprint cover, the (X, Y) bool
    relaxation domain of the chunk and the (K, X, Y) targets h_ref - s * depth [m] (inf off
    the footprint)."""
    dist, lateral = geom["dist"], geom["lateral"]
    covered = (dist <= radius) & (True if final else ~geom["ahead"])
    s = np.zeros_like(dist)
    s[covered] = section_profile(lateral[covered] / radius, section, robot.wheel_flat_fraction)
    targets = np.where(covered, (h_ref if h_ref.ndim == 3 else h_ref[None]) - s * depth, np.inf)
    h_dug = np.minimum(h, targets.min(0))
    removed = (h - h_dug) * chi
    covered_any = covered.any(0)
    owner = covered & (np.arange(len(dist))[:, None, None] == np.where(covered, s + 1, 0).argmax(0)[None])
    beyond = (geom["ahead"] if not final else False) | (geom["behind"] if not first else False)
    band = (dist > radius) & (dist <= radius + config.band_width * geom["dx"]) & ~covered_any & ~beyond
    deposits = [(geom["bin"][k][owner[k]], (removed[k] if removed.ndim == 3 else removed)[owner[k]],
                 geom["bin"][k][band[k]], np.nonzero(band[k]))
                for k in range(len(dist))]
    domain = dist.min(0) <= radius + config.relax_margin * robot.wheel_width
    return h_dug, deposits, covered, domain, targets
