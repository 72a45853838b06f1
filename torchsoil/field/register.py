"""A session registered onto a field: the rigid transform from a recording's own map frame to
the field's, found from the ground both saw (ruts, relief) and the landmarks above it.

1. Initial guess: from GNSS when both the field and the session are tied to UTM (`geo.georef`),
   else a global search: masked normalised cross-correlation (Padfield 2012, by FFT) of two
   bird's-eye images per cloud, the ground's relief (height minus its 0.5 m mean) and the
   landmarks' height above the ground, over every shift and a ring of headings. The search
   also says how sure it is: the score of the best distinct second candidate (another lane,
   another heading) against the best one's.
2. Refinement: Gauss-Newton on heights (`refine`): the session's ground onto the field's
   heightmap over yaw, x, y, z and tilt, coarse to fine. On a field the ruts of earlier
   sessions are what fixes the placement across the rows; a point-to-plane ICP on the same
   points stalled half a rut wall away (its normals, estimated over 10 cm, blur 2 cm walls).
3. Checks: overlap (share of the session's ground on the field's after the fit) and the
   correlation of the two reliefs there, ambiguity (second / best score), and the
   disagreement with GNSS.

Pure functions on arrays: points (N, 3) in metres, transforms (4, 4) session -> field.
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass, field

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from torchsoil.pipeline import icp

IMAGE_RES = 0.1          # m per pixel of the search images
RELIEF_SIGMA = 0.5       # m: relief = height minus its Gaussian mean over this scale
LANDMARK_Z = 0.3         # m above the ground: a landmark (pole, trunk, wall), not ground
YAW_STEP_DEG = 2.0       # heading ring of the global search
DISTINCT = (0.5, 10.0)   # m, deg: a second candidate this far from the best is another solution


@dataclass
class Cloud:
    """What a session or the field offers to a registration, in its own frame.

    ground: (G, 3) ground surface points (heightmap cells), m; landmarks: (L, 3) map points
    standing above the ground, m (may be empty); heightmap: the ground as (h (X, Y) m, origin
    (2,) m, dx m), cell [i, j] centred at origin + (i, j) dx (what the refinement samples)."""

    ground: np.ndarray
    landmarks: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    heightmap: tuple | None = None

    def points(self) -> np.ndarray:
        return np.vstack([self.ground, self.landmarks])


@dataclass
class Registration:
    """transform: (4, 4) session -> field; method: "gnss+heights", "search+heights" or how the
    first session was placed; rmse_m: RMS height residual of the refinement, m; overlap:
    share of the session's ground the field's covers after the fit; relief: the correlation of
    the two grounds' relief there (`agreement`);
    ambiguity: best distinct second candidate's score / the best's (0: none; search only);
    score: the search's best score; gnss_m, gnss_deg: disagreement with the GNSS transform
    (None without GNSS); landmarks: landmark points used."""

    transform: np.ndarray
    method: str
    rmse_m: float = math.inf
    overlap: float = 0.0
    relief: float = 0.0
    ambiguity: float = 0.0
    score: float = 0.0
    gnss_m: float | None = None
    gnss_deg: float | None = None
    landmarks: int = 0

    def to_dict(self) -> dict:
        d = asdict(self)
        d["transform"] = np.asarray(self.transform).tolist()
        return d


def cloud_from_heightmap(h: np.ndarray, origin, dx: float, map_points: np.ndarray | None = None,
                         step: float = 0.04) -> Cloud:
    """A Cloud from a heightmap (X, Y) [m, NaN unknown] on the grid (origin of cell [0, 0], dx)
    and optionally a lidar map (M, 3): ground = the heightmap's cells every `step` m (and the
    heightmap so decimated), landmarks = map points more than LANDMARK_Z above the lowest map
    point of their 0.5 m column (the ground beside a pole, a trunk, a wall)."""
    k = max(1, int(round(step / dx)))
    hs = h[::k, ::k]
    ii, jj = np.nonzero(np.isfinite(hs))
    ground = np.stack([origin[0] + ii * k * dx, origin[1] + jj * k * dx, hs[ii, jj]], 1).astype(np.float64)
    lm = np.zeros((0, 3))
    if map_points is not None and len(map_points):
        p = np.asarray(map_points, np.float64)
        col = np.floor(p[:, :2] / 0.5).astype(np.int64)
        _, inv = np.unique(col, axis=0, return_inverse=True)
        floor = np.full(inv.max() + 1, np.inf)
        np.minimum.at(floor, inv.ravel(), p[:, 2])
        lm = p[p[:, 2] - floor[inv.ravel()] > LANDMARK_Z]
    return Cloud(ground, lm, (hs, np.asarray(origin, np.float64), k * dx))


# ---------------------------------------------------------------------------- global search
def _images(cloud: Cloud, lo: np.ndarray, shape: tuple[int, int]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Relief and landmark images (and their masks) of a cloud on the pixel grid from `lo`."""
    px = IMAGE_RES

    def raster(p, v, reduce):
        ij = np.floor((p[:, :2] - lo) / px).astype(np.int64)
        ok = (ij >= 0).all(1) & (ij[:, 0] < shape[0]) & (ij[:, 1] < shape[1])
        flat = ij[ok, 0] * shape[1] + ij[ok, 1]
        img = np.zeros(shape[0] * shape[1])
        n = np.bincount(flat, minlength=img.size).astype(np.float64)
        if reduce == "mean":
            img = np.bincount(flat, v[ok], minlength=img.size) / np.maximum(n, 1)
        else:
            np.maximum.at(img, flat, v[ok])
        return img.reshape(shape), (n > 0).reshape(shape)

    h, m = raster(cloud.ground, cloud.ground[:, 2], "mean")
    s = RELIEF_SIGMA / px
    mean = ndimage.gaussian_filter(h * m, s) / np.maximum(ndimage.gaussian_filter(m.astype(float), s), 1e-9)
    relief = np.where(m, h - mean, 0.0)
    # a pixel's blur: the ruts' pattern still lines up under a heading off by a search step
    relief = np.where(m, ndimage.gaussian_filter(relief, 1.0) / np.maximum(ndimage.gaussian_filter(m * 1.0, 1.0),
                                                                            1e-9), 0.0)
    imgs, masks = [relief], [m]
    if len(cloud.landmarks) >= 20:
        # landmark height above the ground's median, within 2 m of what the map covers
        z = cloud.landmarks[:, 2] - (np.median(cloud.ground[:, 2]) if len(cloud.ground) else 0.0)
        lm, lmask = raster(cloud.landmarks, np.clip(z, 0.0, 2.0), "max")
        cover = ndimage.binary_dilation(m | lmask, iterations=int(2 / px))
        imgs.append(lm)
        masks.append(cover)
    return imgs, masks


def _masked_ncc(f: np.ndarray, mf: np.ndarray, g: np.ndarray, mg: np.ndarray, min_overlap: float,
                cache: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Masked normalised cross-correlation of the moving image g (mask mg) against the fixed f
    (mask mf) for every integer shift (FFT, full size): out[u] compares f(x + u) with g(x).
    Shifts whose overlap is below min_overlap pixels score -1. Returns (scores, overlap in
    pixels), both of the full size. cache: a dict kept across calls with the same f, mf and
    g's shape (the fixed image's spectra)."""
    from scipy import fft

    shape = [a + b - 1 for a, b in zip(f.shape, g.shape, strict=True)]
    size = [fft.next_fast_len(n, real=True) for n in shape]
    workers = os.cpu_count() or 1
    F = lambda a: fft.rfft2(a, size, workers=workers)  # noqa: E731
    inv = lambda a: fft.irfft2(a, size, workers=workers)[: shape[0], : shape[1]]  # noqa: E731
    key = tuple(size)
    if cache is None or key not in cache:
        fm = f * mf
        spectra = F(fm), F(fm * fm), F(mf.astype(float))
        if cache is not None:
            cache[key] = spectra
    else:
        spectra = cache[key]
    Ff, Ff2, Fmf = spectra
    gr = (g * mg)[::-1, ::-1]
    Fg, Fg2, Fmg = F(gr), F(gr * gr), F(mg[::-1, ::-1].astype(float))
    n = np.round(inv(Fmf * Fmg))
    sf, sg = inv(Ff * Fmg), inv(Fmf * Fg)
    num = inv(Ff * Fg) - sf * sg / np.maximum(n, 1)
    vf = inv(Ff2 * Fmg) - sf**2 / np.maximum(n, 1)
    vg = inv(Fmf * Fg2) - sg**2 / np.maximum(n, 1)
    den = np.sqrt(np.maximum(vf, 0) * np.maximum(vg, 0))
    out = np.where((n >= min_overlap) & (den > 1e-12 * np.maximum(n, 1)), num / np.maximum(den, 1e-300), -1.0)
    return out, n


def search(session: Cloud, fixed: Cloud, yaw_step_deg: float = YAW_STEP_DEG, min_overlap: float = 0.3
           ) -> list[tuple[float, float, float, float]]:
    """Global search: candidates (score, yaw rad, tx m, ty m), best first, each the best of
    its heading; T = translation (tx, ty) after rotation by yaw about the session frame's
    origin. Headings every 2 yaw steps first, then every step around the eight best.
    The score: the channels' mean normalised correlation times the square root of the share
    of the session's ground the field covers there (a small overlap correlates by chance).
    min_overlap: that share's least."""
    pts_f = fixed.points()[:, :2]
    lo_f = pts_f.min(0) - 1.0
    shape_f = tuple(int(v) for v in np.ceil((pts_f.max(0) + 1.0 - lo_f) / IMAGE_RES))
    imgs_f, masks_f = _images(fixed, lo_f, shape_f)
    pts = session.points()
    c = pts[:, :2].mean(0)
    r = float(np.linalg.norm(pts[:, :2] - c, axis=1).max()) + 1.0
    lo_s = np.array([-r, -r])
    shape_s = (int(2 * r / IMAGE_RES) + 1,) * 2
    caches: list[dict] = [{}, {}]

    def at(yaw: float) -> tuple[float, float, float, float]:
        R = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
        rot = Cloud(np.c_[(session.ground[:, :2] - c) @ R.T, session.ground[:, 2]],
                    np.c_[(session.landmarks[:, :2] - c) @ R.T, session.landmarks[:, 2]])
        imgs_s, masks_s = _images(rot, lo_s, shape_s)
        n_ground = max(int(masks_s[0].sum()), 1)
        ncc, n = _masked_ncc(imgs_f[0], masks_f[0], imgs_s[0], masks_s[0], min_overlap * n_ground, caches[0])
        if len(imgs_f) > 1 and len(imgs_s) > 1:
            ncc = 0.5 * (ncc + _masked_ncc(imgs_f[1], masks_f[1], imgs_s[1], masks_s[1], 50, caches[1])[0])
        scores = np.where(ncc > 0, ncc * np.sqrt(np.minimum(n / n_ground, 1.0)), ncc)
        u = np.unravel_index(int(np.argmax(scores)), scores.shape)
        # scores[u]: f(x + u - (shape_s - 1)) matches g(x): session pixel x -> field pixel x + u - shape_s + 1
        shift = (np.array(u) - (np.array(shape_s) - 1)) * IMAGE_RES + lo_f - lo_s
        t = shift - R @ c   # session xy p -> R (p - c) + shift = R p + (shift - R c)
        return float(scores[u]), float(yaw), float(t[0]), float(t[1])

    step = math.radians(yaw_step_deg)
    out = {round(y / step) % round(2 * math.pi / step): at(y) for y in np.arange(0.0, 2 * math.pi - 1e-9, 2 * step)}
    for k in sorted(out, key=lambda k: -out[k][0])[:8]:
        for j in (k - 1, k + 1):
            j %= round(2 * math.pi / step)
            if j not in out:
                out[j] = at(j * step)
    return sorted(out.values(), key=lambda x: -x[0])


def ambiguity(cands: list[tuple[float, float, float, float]]) -> float:
    """Best distinct second candidate's score over the best's (DISTINCT apart), 0 when none."""
    best = cands[0]
    if best[0] <= 0:
        return 1.0
    for s, yaw, tx, ty in cands[1:]:
        dyaw = abs((math.degrees(yaw - best[1]) + 180) % 360 - 180)
        if dyaw > DISTINCT[1] or math.hypot(tx - best[2], ty - best[3]) > DISTINCT[0]:
            return max(s, 0.0) / best[0]
    return 0.0


def planar(yaw: float, tx: float, ty: float, tz: float = 0.0) -> np.ndarray:
    """(4, 4) rotation by yaw [rad] about z, then translation (tx, ty, tz) [m]."""
    T = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = (tx, ty, tz)
    return T


# ---------------------------------------------------------------------------- refinement
def refine(session: Cloud, fixed: Cloud, init: np.ndarray, sigmas=(0.12, 0.06, 0.03, 0.0), iters: int = 15,
           huber: float = 0.005) -> tuple[np.ndarray, float]:
    """Gauss-Newton on heights (2.5-D Lucas-Kanade): the session's ground points p placed by T
    onto the field's heightmap H, residual H(T p) - (T p)_z, over yaw, x, y, z and the tilt
    (z a plane in x, y), from `init`, on H smoothed by each of `sigmas` [m] in turn (wide
    basin first, the ruts' walls last). Huber weights at `huber` m. Returns (T (4, 4), RMS of
    the final residuals [m], inf when the grounds did not meet)."""
    h, origin, dx = fixed.heightmap
    finite = np.isfinite(h)
    T = np.array(init, np.float64)
    T[2, 3] += _height_offset(session, fixed, T)
    p = session.ground
    rms = math.inf
    for sigma in sigmas:
        s = sigma / dx
        if s > 0:
            w = ndimage.gaussian_filter(finite.astype(float), s)
            H = np.where(w > 0.5, ndimage.gaussian_filter(np.where(finite, h, 0.0), s) / np.maximum(w, 1e-9), np.nan)
        else:
            H = np.where(finite, h, np.nan)
        gx, gy = np.gradient(H, dx)
        for _ in range(iters):
            q = icp.apply(T, p)
            u, v = (q[:, 0] - origin[0]) / dx, (q[:, 1] - origin[1]) / dx
            hv = ndimage.map_coordinates(H, [u, v], order=1, cval=np.nan)
            ok = np.isfinite(hv)
            if ok.sum() < 50:
                return T, math.inf
            du = ndimage.map_coordinates(np.nan_to_num(gx), [u[ok], v[ok]], order=1)
            dv = ndimage.map_coordinates(np.nan_to_num(gy), [u[ok], v[ok]], order=1)
            qo = q[ok]
            c = qo[:, :2].mean(0)
            r = hv[ok] - qo[:, 2]
            # d(residual)/d(x, y, yaw about c, z, tilt x, tilt y)
            J = np.stack([du, dv, du * -(qo[:, 1] - c[1]) + dv * (qo[:, 0] - c[0]), -np.ones(len(r)),
                          -(qo[:, 0] - c[0]), -(qo[:, 1] - c[1])], 1)
            wgt = np.minimum(1.0, huber / np.maximum(np.abs(r), 1e-12))
            A = (J * wgt[:, None]).T @ J + 1e-9 * np.eye(6)
            step = -np.linalg.solve(A, (J * wgt[:, None]).T @ r)
            T = _compose(step, c) @ T
            rms = float(np.sqrt(np.mean(r**2)))
            if np.abs(step[:3]).max() < 1e-5 and abs(step[3]) < 1e-5:
                break
    return T, rms


def _compose(step: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(4, 4) small motion: yaw step[2] about (c, 0), shift step[0:2], lift step[3] and the
    tilts step[4:6] (z += a (x - cx) + b (y - cy), a rotation to first order)."""
    dxy, yaw, dz, a, b = step[:2], step[2], step[3], step[4], step[5]
    D = planar(yaw, 0.0, 0.0)
    D[:2, 3] = c - D[:2, :2] @ c + dxy
    D[2, 0], D[2, 1], D[0, 2], D[1, 2] = a, b, -a, -b
    D[2, 3] = dz - a * c[0] - b * c[1]
    U, _, Vt = np.linalg.svd(D[:3, :3])
    D[:3, :3] = U @ Vt            # keep it a rotation
    return D


def _height_offset(session: Cloud, fixed: Cloud, T: np.ndarray) -> float:
    """Median vertical gap between the field's ground and the session's placed by T, m."""
    p = icp.apply(T, session.ground)
    d, i = cKDTree(fixed.ground[:, :2]).query(p[:, :2], distance_upper_bound=0.05)
    ok = np.isfinite(d)
    return float(np.median(fixed.ground[i[ok], 2] - p[ok, 2])) if ok.any() else 0.0


def agreement(session: Cloud, fixed: Cloud, T: np.ndarray) -> tuple[float, float]:
    """(overlap, relief correlation) of the session placed by T on the field: the share of the
    session's ground pixels (IMAGE_RES) that the field's ground covers, and the correlation of
    the two reliefs there (1: the same ground; ~0: another field, even as flat)."""
    placed = Cloud(icp.apply(T, session.ground), icp.apply(T, session.landmarks) if len(session.landmarks)
                   else session.landmarks)
    both = np.vstack([fixed.ground[:, :2], placed.ground[:, :2]])
    lo = both.min(0) - 1.0
    shape = tuple(int(v) for v in np.ceil((both.max(0) + 1.0 - lo) / IMAGE_RES))
    (rf, *_), (mf, *_) = _images(Cloud(fixed.ground), lo, shape)
    (rs, *_), (ms, *_) = _images(Cloud(placed.ground), lo, shape)
    m = mf & ms
    share = float(m.sum() / max(ms.sum(), 1))
    if m.sum() < 10:
        return share, 0.0
    a, b = rf[m] - rf[m].mean(), rs[m] - rs[m].mean()
    den = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return share, float((a * b).sum() / den) if den > 0 else 0.0


def transform_error(A: np.ndarray, B: np.ndarray, at: np.ndarray) -> tuple[float, float]:
    """(metres, degrees) between two (4, 4) transforms: the largest horizontal distance between
    where they put the points `at` (N, 3), and the heading difference."""
    d = np.linalg.norm((icp.apply(A, at) - icp.apply(B, at))[:, :2], axis=1).max() if len(at) else 0.0
    yaw = math.atan2(A[1, 0], A[0, 0]) - math.atan2(B[1, 0], B[0, 0])
    return float(d), float(abs(math.degrees((yaw + math.pi) % (2 * math.pi) - math.pi)))


def register_session(session: Cloud, fixed: Cloud, guess: np.ndarray | None = None) -> Registration:
    """Register a session onto the field (module docstring). guess: (4, 4) session -> field
    from GNSS, or None for the global search."""
    if guess is not None:
        T, rms = refine(session, fixed, guess)
        method, amb, score = "gnss+heights", 0.0, 0.0
    else:
        cands = search(session, fixed)
        amb, score = ambiguity(cands), cands[0][0]
        T, rms = refine(session, fixed, planar(*cands[0][1:]))
        method = "search+heights"
    share, relief = agreement(session, fixed, T)
    reg = Registration(T, method, rms, share, relief, float(amb), float(score), landmarks=len(session.landmarks))
    if guess is not None:
        reg.gnss_m, reg.gnss_deg = transform_error(T, guess, session.ground)
    return reg
