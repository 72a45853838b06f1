"""A plain numpy forward model of the paper's Algorithm 1, written from the paper's text
(Tracking the ground, section IV-B), to make terrain pairs the estimator has never seen the
making of (torchsoil.sim is not used here).

For every pose and every wheel:

1. Footprint: the cells whose centre lies within r = w / 2 of the wheel's contact centre
   (a circle of diameter the wheel width w).
2. Reference height h~ of a cell: the mean of the surface BEFORE THE ROBOT over the cells
   whose centre lies within ref_radius * r of it (at ref_radius 0.5 and dx = 0.02 m, the
   3 x 3 block). Taking it from the untouched surface keeps ruts from compounding pose
   after pose (/work/shared/MEASURED.md, forward model).
3. Sinkage: h <- min(h, h~ - s d_k) over the footprint, with the centrality taper of
   docs/formats.md section 2 for the robot's tyre (flat fraction f, q = lateral offset / r):
   s = 1 for |q| <= f, then s = (1 + cos(pi (|q| - f) / (1 - f))) / 2, 0 at |q| = 1.
   For f = 0 (the paper's platform), s = (1 + cos(pi q)) / 2, a raised-cosine profile.
   "Lateral" is along the body's y axis (the drives made here are straight).
4. Deposition: the removed volume V = dx^2 * sum(removed heights) times chi, spread evenly
   over the one-cell-wide band beside the wheel: the cells with r < |lateral| <= r + dx
   and |longitudinal| <= r, left and right of the footprint.

On ground earlier wheels dug (`dug`: a visit after the first, in the first's ruts), the
reference of step 2 is instead the mean of the surface before the robot over the whole
footprint (the cells within r): a wheel spans a rut of its own width and rests on its walls.

With dig="wheel" the axles take turns instead (the leading axle first: the front one on a
drive forward, the rear one in reverse): each digs the whole drive in step 3 from the surface
the axles before it left (deposits included), so the trailing wheel digs again in the
leading one's rut; on the cells their footprints covered its reference is the mean of that
surface over its whole footprint, as on ground earlier wheels dug; `axle_scale` scales each
axle's d in that order (a soil whose every wheel pass sinks less than the one before).

Then, once every pose is done, Exner relaxation over the whole grid: forward-difference
gradients g = [h(i+1,j) - h(i,j), h(i,j+1) - h(i,j)] / dx (0 across the grid's outer
edge), flux phi = -max(|g| - tan(beta), 0) g / |g| leaving each cell through its +x and +y
faces, h(i,j) += -(phi_x(i,j) - phi_x(i-1,j) + phi_y(i,j) - phi_y(i,j-1)) / (eps dx) with
eps = 4 / dx^2, until max |g| - tan(beta) < tau (tau = 0.01).

Poses are interpolated linearly so that no wheel moves more than dx / 2 between two poses.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage


def taper(q: np.ndarray, flat: float = 0.0) -> np.ndarray:
    """Centrality factor s of docs/formats.md section 2 at q = lateral offset / half width."""
    a = np.abs(np.asarray(q, np.float64))
    s = 0.5 * (1.0 + np.cos(np.pi * np.clip((a - flat) / (1.0 - flat), 0.0, 1.0)))
    return np.where(a <= flat, 1.0, np.where(a >= 1.0, 0.0, s))


def disc_mean(h: np.ndarray, radius: float, dx: float) -> np.ndarray:
    """Mean of h over the cells whose centre lies within `radius` m of each cell (cells
    outside the grid left out)."""
    n = int(math.floor(radius / dx))
    acc = np.zeros_like(h)
    cnt = np.zeros_like(h)
    X, Y = h.shape
    for di in range(-n, n + 1):
        for dj in range(-n, n + 1):
            if (di * dx) ** 2 + (dj * dx) ** 2 > radius**2 + 1e-12:
                continue
            dst = (slice(max(0, -di), X - max(0, di)), slice(max(0, -dj), Y - max(0, dj)))
            src = (slice(max(0, di), X + min(0, di)), slice(max(0, dj), Y + min(0, dj)))
            acc[dst] += h[src]
            cnt[dst] += 1
    return acc / cnt


def dense_poses(poses: np.ndarray, wheels_xy: np.ndarray, step: float) -> np.ndarray:
    """(N, 7) FORMATS poses -> (M, 3) x, y, yaw, linearly interpolated so that no wheel moves
    more than `step` m between consecutive rows."""
    p = poses[:, [1, 2, 6]].copy()
    p[:, 2] = np.unwrap(p[:, 2])
    out = [p[:1]]
    for a, b in zip(p[:-1], p[1:], strict=True):
        def wheel(q):
            c, s = math.cos(q[2]), math.sin(q[2])
            return q[:2] + wheels_xy @ np.array([[c, s], [-s, c]])
        move = np.linalg.norm(wheel(b) - wheel(a), axis=1).max()
        n = max(1, int(math.ceil(move / step)))
        f = np.arange(1, n + 1)[:, None] / n
        out.append(a + f * (b - a))
    return np.vstack(out)


def relax(h: np.ndarray, dx: float, beta: float, tau: float = 0.01, eps_scale: float = 4.0,
          max_iter: int = 20000) -> tuple[np.ndarray, int]:
    """Exner relaxation (paper eqs. flux, height update, convergence); returns (h, iterations)."""
    h = h.copy()
    tan_b = math.tan(beta)
    eps = eps_scale / dx**2
    for it in range(max_iter):
        gx = np.zeros_like(h)
        gy = np.zeros_like(h)
        gx[:-1, :] = (h[1:, :] - h[:-1, :]) / dx
        gy[:, :-1] = (h[:, 1:] - h[:, :-1]) / dx
        g = np.hypot(gx, gy)
        if g.max() - tan_b < tau:
            return h, it
        excess = np.maximum(g - tan_b, 0.0)
        scale = np.divide(excess, g, out=np.zeros_like(g), where=g > 0)
        px, py = -scale * gx, -scale * gy               # flux out through the +x and +y faces
        div = px.copy()
        div[1:, :] -= px[:-1, :]
        div += py
        div[:, 1:] -= py[:, :-1]
        h -= div / (eps * dx)
    raise RuntimeError(f"relaxation did not converge in {max_iter} iterations")


def simulate(h0: np.ndarray, dx: float, origin, poses: np.ndarray, wheels: np.ndarray, wheel_width: float,
             d: tuple[float, ...], chi: float, beta: float, ref_radius: float = 0.5, flat: float = 0.0,
             tau: float = 0.01, dig: str = "robot", dug: np.ndarray | None = None,
             axle_scale: tuple[float, ...] | None = None) -> tuple[np.ndarray, dict]:
    """Algorithm 1 on the surface h0 (X, Y) [m]; d: sinkage per track [m]; beta [rad]; dig:
    "robot" (every wheel from the surface before the robot) or "wheel" (axle after axle);
    dug: (X, Y) bool cells earlier wheels dug (reference over the whole footprint there);
    axle_scale: with dig "wheel", a factor on d per axle in the order they dig.

    Returns the surface after the drive and {"removed": total removed volume m^3,
    "deposited": total deposited volume m^3, "iterations": relaxation iterations}."""
    h0 = np.asarray(h0, np.float64)
    h = h0.copy()
    r = wheel_width / 2
    h_ref = disc_mean(h0, ref_radius * r, dx)
    if dug is not None:
        h_ref = np.where(dug, disc_mean(h0, r, dx), h_ref)
    xs = origin[0] + dx * np.arange(h.shape[0])
    ys = origin[1] + dx * np.arange(h.shape[1])
    reach = int(math.ceil((r + 2 * dx) / dx))
    totals = [0.0, 0.0]
    dense = dense_poses(poses, wheels[:, :2], dx / 2)
    step = np.diff(dense[:, :2], axis=0)
    forward = float(np.sum(step[:, 0] * np.cos(dense[:-1, 2]) + step[:, 1] * np.sin(dense[:-1, 2]))) >= 0
    axles = [wheels] if dig == "robot" else [wheels[wheels[:, 0] == a]
                                             for a in sorted(set(wheels[:, 0]), reverse=forward)]
    scale = np.ones(len(axles)) if axle_scale is None else np.asarray(axle_scale, np.float64)
    covered = np.zeros(h.shape, bool)
    for n, axle in enumerate(axles):
        if n > 0:      # the next axle's turn: it rests on the surface the axles before left
            h_ref = np.where(covered, disc_mean(h, r, dx), h_ref)
        for x, y, yaw in dense:
            _dig(h, h_ref, xs, ys, origin, dx, r, reach, x, y, yaw, axle, np.asarray(d) * scale[n], chi, flat, totals,
                 covered)
    h, iterations = relax(h, dx, beta, tau)
    return h, {"removed": totals[0], "deposited": totals[1], "iterations": iterations}


def _dig(h, h_ref, xs, ys, origin, dx, r, reach, x, y, yaw, wheels, d, chi, flat, totals, covered):
    """Steps 1, 3 and 4 for the given wheels at one pose, in place on h; totals: [removed,
    deposited] volumes, m^3, added to; covered: (X, Y) bool, the footprint cells set."""
    X, Y = h.shape
    c, s = math.cos(yaw), math.sin(yaw)
    for wx, wy, track in wheels:
        cx, cy = x + c * wx - s * wy, y + s * wx + c * wy
        i0, j0 = int(round((cx - origin[0]) / dx)), int(round((cy - origin[1]) / dx))
        win = (slice(max(i0 - reach, 0), min(i0 + reach + 1, X)), slice(max(j0 - reach, 0), min(j0 + reach + 1, Y)))
        ex, ey = np.meshgrid(xs[win[0]] - cx, ys[win[1]] - cy, indexing="ij")
        along = ex * c + ey * s
        lat = -ex * s + ey * c
        foot = along**2 + lat**2 <= r**2
        covered[win] |= foot
        hw = h[win]
        target = h_ref[win] - taper(lat / r, flat) * d[int(track)]
        new = np.where(foot, np.minimum(hw, target), hw)
        volume = float((hw - new).sum()) * dx**2
        band = ~foot & (np.abs(lat) > r) & (np.abs(lat) <= r + dx) & (np.abs(along) <= r)
        if band.any() and volume > 0:
            new = new + band * (chi * volume / (band.sum() * dx**2))      # volume -> height
            totals[1] += chi * volume
        totals[0] += volume
        h[win] = new


def straight_drive_pair(d: tuple[float, float] = (0.03, 0.02), chi: float = 0.5, beta_deg: float = 30.0,
                        length: float = 4.0, speed: float = 1.0, dx: float = 0.02, relief: float = 0.004,
                        roughness: float = 0.001, noise: float = 0.0015, seed: int = 0,
                        wheels: np.ndarray | None = None, wheel_width: float = 0.14, flat: float = 0.0,
                        dig: str = "robot") -> tuple[dict, dict]:
    """Terrain pair (docs/formats.md section 3 keys) of a straight drive along +x from x = 0.

    The ground: smooth relief (std `relief` m, correlation ~3 cells) plus white roughness
    (`roughness` m per cell). h_front = ground + measurement noise, h_back = Algorithm 1's
    result + independent measurement noise (`noise` m per cell on each map). wheels: (K, 3)
    x, y, track (default: the paper's platform); flat: the tyre's flat fraction; dig: as in
    `simulate`. Returns (pair dict, truth dict with the
    noise-free surfaces and the model's bookkeeping)."""
    if wheels is None:
        wheels = np.array([[0.69, 0.5, 0], [0.69, -0.5, 1], [-0.69, 0.5, 0], [-0.69, -0.5, 1]], np.float64)
    rng = np.random.default_rng(seed)
    origin = np.array([-1.2, -1.6])
    X = int(round((length + 1.2 + 1.2) / dx)) + 1
    Y = int(round(3.2 / dx)) + 1
    smooth = ndimage.gaussian_filter(rng.normal(size=(X, Y)), 3.0)
    h0 = relief * smooth / smooth.std() + roughness * rng.normal(size=(X, Y))
    t = np.arange(0.0, length / speed + 1e-9, 0.05)
    poses = np.zeros((len(t), 7))
    poses[:, 0], poses[:, 1] = t, speed * t
    hb, info = simulate(h0, dx, origin, poses, wheels, wheel_width, d, chi, math.radians(beta_deg), flat=flat,
                        dig=dig)
    pair = {
        "dx": np.float64(dx), "origin": origin,
        "h_front": (h0 + rng.normal(0, noise, h0.shape)).astype(np.float32),
        "h_back": (hb + rng.normal(0, noise, h0.shape)).astype(np.float32),
        "poses": poses, "wheels": wheels.astype(np.float64), "wheel_width": np.float64(wheel_width),
        "wheel_flat_fraction": np.float64(flat),
    }
    return pair, {"h0": h0, "hb": hb, **info}
