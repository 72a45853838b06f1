"""Robot description: wheel contact points, track assignment and tyre shape (docs/formats.md section 2)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml


@dataclass(frozen=True)
class Robot:
    """A wheeled robot as the soil model sees it.

    Attributes:
        wheel_width: footprint diameter, m.
        wheels: (K, 3) float64, contact centres in base_link x, y [m] and track index.
        wheel_flat_fraction: tyre cross-section shape f in [0, 1): 0 rounded, near 1 flat.
        names: K wheel names.
        wheel_section_exponent: exponent e > 0 of the taper (sim.sinkage.taper; 1: the taper
            docs/formats.md describes; the diagnosis fits it with f as a nuisance).
    """

    wheel_width: float
    wheels: np.ndarray
    wheel_flat_fraction: float = 0.0
    names: tuple[str, ...] = ()
    wheel_section_exponent: float = 1.0

    def __post_init__(self):
        w = np.asarray(self.wheels, dtype=np.float64)
        if w.ndim != 2 or w.shape[1] != 3 or len(w) == 0:
            raise ValueError(f"wheels must be (K, 3) [x, y, track], got shape {w.shape}")
        if not np.all(np.isfinite(w)):
            raise ValueError("wheel positions must be finite")
        tracks = w[:, 2]
        if np.any(tracks != np.round(tracks)) or tracks.min() < 0:
            raise ValueError(f"track indices must be non-negative integers, got {tracks.tolist()}")
        used = sorted(set(tracks.astype(int).tolist()))
        if used != list(range(len(used))):
            raise ValueError(f"track indices must be 0..T-1 with none skipped, got {used}")
        if not (np.isfinite(self.wheel_width) and self.wheel_width > 0):
            raise ValueError(f"wheel_width must be a positive length in metres, got {self.wheel_width}")
        if not 0.0 <= self.wheel_flat_fraction < 1.0:
            raise ValueError(f"wheel_flat_fraction must be in [0, 1), got {self.wheel_flat_fraction}")
        if not (np.isfinite(self.wheel_section_exponent) and self.wheel_section_exponent > 0):
            raise ValueError(f"wheel_section_exponent must be positive, got {self.wheel_section_exponent}")
        object.__setattr__(self, "wheels", w)
        if not self.names:
            object.__setattr__(self, "names", tuple(f"wheel{i}" for i in range(len(w))))

    @property
    def n_tracks(self) -> int:
        return int(self.wheels[:, 2].max()) + 1

    @property
    def track(self) -> np.ndarray:
        """(K,) int64 track index per wheel."""
        return self.wheels[:, 2].astype(np.int64)

    @classmethod
    def from_yaml(cls, path: str | Path) -> Robot:
        """Read a robot YAML (docs/formats.md section 2)."""
        path = Path(path)
        try:
            doc = yaml.safe_load(path.read_text())
        except FileNotFoundError:
            raise FileNotFoundError(f"robot description not found: {path}") from None
        return cls.from_dict(doc, source=str(path))

    @classmethod
    def from_dict(cls, doc: dict, source: str = "robot description") -> Robot:
        try:
            wheels = [[float(w["x"]), float(w["y"]), int(w["track"])] for w in doc["wheels"]]
            names = tuple(str(w.get("name", f"wheel{i}")) for i, w in enumerate(doc["wheels"]))
            return cls(
                wheel_width=float(doc["wheel_width"]),
                wheels=np.array(wheels, dtype=np.float64),
                wheel_flat_fraction=float(doc.get("wheel_flat_fraction", 0.0) or 0.0),
                names=names,
                wheel_section_exponent=float(doc.get("wheel_section_exponent", 1.0) or 1.0),
            )
        except (KeyError, TypeError) as e:
            raise ValueError(f"{source}: missing or malformed key {e} "
                             "(see the manual, docs/formats.md section 2)") from None

    @classmethod
    def from_npz(cls, data) -> Robot:
        """Robot from a terrain-pair npz mapping (keys `wheels`, `wheel_width`, `wheel_flat_fraction`)."""
        flat = float(data["wheel_flat_fraction"]) if "wheel_flat_fraction" in data else 0.0
        e = float(data["wheel_section_exponent"]) if "wheel_section_exponent" in data else 1.0
        return cls(float(data["wheel_width"]), np.asarray(data["wheels"]), flat, wheel_section_exponent=e)

    def to_dict(self) -> dict:
        out = {
            "wheel_width": float(self.wheel_width),
            "wheel_flat_fraction": float(self.wheel_flat_fraction),
            "wheels": [
                {"name": n, "x": float(x), "y": float(y), "track": int(t)}
                for n, (x, y, t) in zip(self.names, self.wheels, strict=True)
            ],
        }
        if self.wheel_section_exponent != 1.0:
            out["wheel_section_exponent"] = float(self.wheel_section_exponent)
        return out


ROBOT_DIR = Path(__file__).resolve().parent / "configs" / "robot"


def available_robots() -> list[str]:
    """Names of the robot descriptions shipped with torchsoil."""
    return sorted(p.stem for p in ROBOT_DIR.glob("*.yaml"))


def robot_path(name_or_path: str | Path) -> Path:
    """A robot YAML path from a shipped name (`paper_platform`) or a path to a YAML file."""
    path = Path(name_or_path)
    if path.is_file():
        return path
    shipped = ROBOT_DIR / f"{name_or_path}.yaml"
    if path.suffix == "" and shipped.is_file():
        return shipped
    raise FileNotFoundError(f"robot description {str(name_or_path)!r} not found: neither a YAML file nor a "
                            f"shipped robot ({', '.join(available_robots())})")


def load_robot(name_or_path: str | Path) -> Robot:
    """Robot from a shipped name or a YAML path (docs/formats.md section 2)."""
    return Robot.from_yaml(robot_path(name_or_path))


def paper_platform() -> Robot:
    """The paper's robot: track 1.0 m, wheelbase 1.38 m, wheels 0.14 m wide."""
    return load_robot("paper_platform")
