"""Terrain pair: before/after heightmaps on one grid, with the trajectory and the robot
(docs/formats.md section 3).

`TerrainPair.load(path)` / `pair.save(path)` read and write the `.npz`; every key is checked
for presence, shape, dtype and finiteness with an error that names the file and the key.
Extra keys (valid masks, counts, variances, per-scan registration quality) travel in
`extras` and are written back unchanged. The optional per-visit layers (`visit_front`,
`visit_back`, `visit_time`, (V, X, Y)) come all three or not at all.
"""

from __future__ import annotations

import os
import tempfile
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from torchsoil.grid import Grid
from torchsoil.robot import Robot

REQUIRED = ("dx", "origin", "h_front", "h_back", "poses", "wheels", "wheel_width")
VISITS = ("visit_front", "visit_back", "visit_time")  # optional, all or none (docs/formats.md v1.1)
KNOWN = (*REQUIRED, "wheel_flat_fraction", "wheel_section_exponent", *VISITS)


@dataclass
class TerrainPair:
    """Heightmaps before (front lidar) and after (back lidar) the wheels on one grid.

    Attributes:
        dx: cell edge, m.
        origin: (2,) world (x, y) of the centre of cell [0, 0], m.
        h_front: (X, Y) float32 surface height before the wheels, m; NaN where unmeasured.
        h_back: (X, Y) float32 surface height after the wheels, m; NaN where unmeasured.
        poses: (N, 7) float64 base_link in world: t [s], x, y, z [m], roll, pitch, yaw [rad].
        wheels: (K, 3) float64 wheel contact centres in base_link x, y [m] and track index.
        wheel_width: m.
        wheel_flat_fraction: tyre taper f in [0, 1).
        wheel_section_exponent: exponent e > 0 of the taper (Robot; 1 unless fitted).
        extras: other arrays stored alongside (name -> array).
        visit_front: (V, X, Y) float32 surface just before each cell's visit v, m; NaN where the
            cell has fewer than v + 1 visits or no measurement. None: one visit per cell.
        visit_back: (V, X, Y) float32 surface just after each cell's visit v, m; NaN likewise.
        visit_time: (V, X, Y) float32 or float64 time (poses clock) base_link passed closest to
            the cell during visit v, s; NaN where no such visit. A float64 one stays float64 (at
            a bag's clock, about 1.7e9 s, float32 resolves only 128 s).
    """

    dx: float
    origin: np.ndarray
    h_front: np.ndarray
    h_back: np.ndarray
    poses: np.ndarray
    wheels: np.ndarray
    wheel_width: float
    wheel_flat_fraction: float = 0.0
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    wheel_section_exponent: float = 1.0
    visit_front: np.ndarray | None = None
    visit_back: np.ndarray | None = None
    visit_time: np.ndarray | None = None

    def __post_init__(self):
        self.validate()

    # ------------------------------------------------------------------ checks
    def validate(self, source: str = "terrain pair") -> None:
        """Check keys, shapes, dtypes and values; raise ValueError naming `source` and the key."""

        def fail(key: str, msg: str):
            raise ValueError(f"{source}: key '{key}' {msg} (see the manual, docs/formats.md section 3)")

        dx = float(np.asarray(self.dx))
        if not (np.isfinite(dx) and dx > 0):
            fail("dx", f"must be a positive cell edge in metres, got {self.dx!r}")
        self.dx = dx
        origin = np.asarray(self.origin, dtype=np.float64)
        if origin.shape != (2,) or not np.all(np.isfinite(origin)):
            fail("origin", f"must be 2 finite numbers (x, y) in metres, got shape {origin.shape}")
        self.origin = origin
        for key in ("h_front", "h_back"):
            h = np.asarray(getattr(self, key))
            if h.ndim != 2 or min(h.shape) < 1:
                fail(key, f"must be a 2-D (X, Y) heightmap, got shape {h.shape}")
            if not np.issubdtype(h.dtype, np.floating):
                fail(key, f"must hold floating-point heights in metres, got dtype {h.dtype}")
            if np.any(np.isinf(h)):
                fail(key, "holds infinite values (use NaN for unmeasured cells)")
            setattr(self, key, h.astype(np.float32, copy=False))
        if self.h_front.shape != self.h_back.shape:
            fail("h_back", f"shape {self.h_back.shape} differs from h_front {self.h_front.shape}")
        poses = np.asarray(self.poses, dtype=np.float64)
        if poses.ndim != 2 or poses.shape[1] != 7 or len(poses) == 0:
            fail("poses", f"must be (N, 7) [t, x, y, z, roll, pitch, yaw], got shape {poses.shape}")
        if not np.all(np.isfinite(poses)):
            bad = int(np.flatnonzero(~np.all(np.isfinite(poses), axis=1))[0])
            fail("poses", f"holds a non-finite value in row {bad}")
        if np.any(np.diff(poses[:, 0]) < 0):
            bad = int(np.flatnonzero(np.diff(poses[:, 0]) < 0)[0]) + 1
            fail("poses", f"must be time-ordered; time goes backwards at row {bad}")
        self.poses = poses
        try:
            robot = Robot(float(np.asarray(self.wheel_width)), np.asarray(self.wheels),
                          float(np.asarray(self.wheel_flat_fraction)),
                          wheel_section_exponent=float(np.asarray(self.wheel_section_exponent)))
        except ValueError as e:
            fail("wheels/wheel_width/wheel_flat_fraction", str(e))
        self.wheels = robot.wheels
        self.wheel_width = robot.wheel_width
        self.wheel_flat_fraction = robot.wheel_flat_fraction
        self.wheel_section_exponent = robot.wheel_section_exponent
        self._validate_visits(fail)
        for key, value in self.extras.items():
            if key in KNOWN:
                fail(key, "is a standard key and cannot also be an extra")
            self.extras[key] = np.asarray(value)

    def _validate_visits(self, fail) -> None:
        given = [k for k in VISITS if getattr(self, k, None) is not None]
        if not given:
            return
        if len(given) < len(VISITS):
            missing = [k for k in VISITS if k not in given]
            fail(missing[0], f"is missing while {given} are given: the visit layers come all together")
        shape = None
        for key in VISITS:
            v = np.asarray(getattr(self, key))
            if v.ndim != 3 or v.shape[0] < 1 or v.shape[1:] != self.h_front.shape:
                fail(key, f"must be (V, X, Y) with (X, Y) = h_front's {self.h_front.shape}, got shape {v.shape}")
            if shape is not None and v.shape != shape:
                fail(key, f"shape {v.shape} differs from visit_front's {shape}")
            shape = v.shape
            if not np.issubdtype(v.dtype, np.floating):
                fail(key, f"must hold floating-point values, got dtype {v.dtype}")
            if np.any(np.isinf(v)):
                fail(key, "holds infinite values (use NaN where a cell has no such visit)")
            dtype = np.promote_types(v.dtype, np.float32) if key == "visit_time" else np.float32
            setattr(self, key, v.astype(dtype, copy=False))

    # ----------------------------------------------------------------- derived
    @property
    def n_visits(self) -> int:
        """V, the most visits of any cell (1 for a pair without visit layers)."""
        return 1 if self.visit_front is None else int(self.visit_front.shape[0])

    @property
    def grid(self) -> Grid:
        return Grid(self.dx, (float(self.origin[0]), float(self.origin[1])), self.h_front.shape)

    @property
    def robot(self) -> Robot:
        return Robot(self.wheel_width, self.wheels, self.wheel_flat_fraction,
                     wheel_section_exponent=self.wheel_section_exponent)

    @property
    def h_delta(self) -> np.ndarray:
        """(X, Y) float32 displacement map H_back - H_front, m (NaN where either is NaN)."""
        return self.h_back - self.h_front

    # -------------------------------------------------------------------- I/O
    def to_dict(self) -> dict[str, np.ndarray]:
        out = {
            "dx": np.float64(self.dx),
            "origin": self.origin.astype(np.float64),
            "h_front": self.h_front.astype(np.float32),
            "h_back": self.h_back.astype(np.float32),
            "poses": self.poses.astype(np.float64),
            "wheels": self.wheels.astype(np.float64),
            "wheel_width": np.float64(self.wheel_width),
            "wheel_flat_fraction": np.float64(self.wheel_flat_fraction),
        }
        if self.wheel_section_exponent != 1.0:
            out["wheel_section_exponent"] = np.float64(self.wheel_section_exponent)
        if self.visit_front is not None:
            out.update({k: getattr(self, k) for k in VISITS})
        out.update(self.extras)
        return out

    def save(self, path: str | Path) -> Path:
        """Write the `.npz` atomically (a temporary file renamed into place): a failed write
        never leaves a partial file behind."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(suffix=".npz", dir=path.parent)
        os.close(fd)
        try:
            np.savez_compressed(tmp, **self.to_dict())
            os.chmod(tmp, 0o644)
            os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
        return path

    @classmethod
    def from_mapping(cls, data, source: str = "terrain pair") -> TerrainPair:
        """Build from any mapping of the docs/formats.md section 3 keys (an open npz, a dict)."""
        missing = [k for k in REQUIRED if k not in data]
        if missing:
            raise ValueError(f"{source}: missing key(s) {missing} (see the manual, docs/formats.md section 3); "
                             f"present: {sorted(data.keys())}")
        flat = data["wheel_flat_fraction"] if "wheel_flat_fraction" in data else 0.0
        extras = {k: np.asarray(data[k]) for k in data.keys() if k not in KNOWN}
        pair = cls.__new__(cls)
        pair.dx, pair.origin = data["dx"], data["origin"]
        pair.h_front, pair.h_back = data["h_front"], data["h_back"]
        pair.poses, pair.wheels = data["poses"], data["wheels"]
        pair.wheel_width, pair.wheel_flat_fraction = data["wheel_width"], flat
        pair.wheel_section_exponent = data["wheel_section_exponent"] if "wheel_section_exponent" in data else 1.0
        pair.extras = extras
        for key in VISITS:
            setattr(pair, key, data[key] if key in data else None)
        pair.validate(source)
        return pair

    @classmethod
    def load(cls, path: str | Path) -> TerrainPair:
        """Read a terrain-pair `.npz`; errors name the file and the offending key."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"terrain pair not found: {path}")
        try:
            with np.load(path, allow_pickle=False) as data:
                return cls.from_mapping({k: data[k] for k in data.files}, source=str(path))
        except (OSError, EOFError, ValueError, zipfile.BadZipFile) as e:
            if str(path) in str(e):
                raise
            raise ValueError(f"{path}: not a readable .npz terrain pair ({e})") from None
