"""The soil parameter vector theta (B, P) and its bounds.

Base layout (the paper's): d_1..d_T sinkage per track [m], chi displacement-compaction
ratio [-], beta angle of repose [rad]. Model extensions append their own named parameters
after the base ones, so a parameter set is always addressed by name, never by a fixed index.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch

D_BOUNDS = (0.0, 0.30)
CHI_BOUNDS = (0.0, 2.0)
BETA_BOUNDS = (math.radians(2.0), math.radians(90.0))


@dataclass(frozen=True)
class ParamSpec:
    """Names, bounds (and units) of the entries of theta.

    Attributes:
        names: P parameter names, e.g. ("d1", "d2", "chi", "beta", ...).
        lower, upper: P bounds in the parameter's own unit.
        units: P unit strings ("m", "-", "rad").
    """

    names: tuple[str, ...]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    units: tuple[str, ...]

    @classmethod
    def base(cls, n_tracks: int) -> ParamSpec:
        """The paper's parameters for a robot with n_tracks ruts."""
        if n_tracks < 1:
            raise ValueError("a robot needs at least one track")
        names = tuple(f"d{k + 1}" for k in range(n_tracks)) + ("chi", "beta")
        lower = (D_BOUNDS[0],) * n_tracks + (CHI_BOUNDS[0], BETA_BOUNDS[0])
        upper = (D_BOUNDS[1],) * n_tracks + (CHI_BOUNDS[1], BETA_BOUNDS[1])
        units = ("m",) * n_tracks + ("-", "rad")
        return cls(names, lower, upper, units)

    def extend(self, names, lower, upper, units) -> ParamSpec:
        """A spec with extra named parameters appended (model extensions)."""
        clash = set(names) & set(self.names)
        if clash:
            raise ValueError(f"parameter names already used: {sorted(clash)}")
        return ParamSpec(self.names + tuple(names), self.lower + tuple(lower),
                         self.upper + tuple(upper), self.units + tuple(units))

    @property
    def n_tracks(self) -> int:
        return sum(1 for n in self.names if n.startswith("d") and n[1:].isdigit())

    def __len__(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no parameter {name!r} in {self.names}") from None

    def bounds(self, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(P,) lower and upper bounds on the device/dtype of `like` (shared: do not modify)."""
        return _bounds(self.lower, self.upper, like.dtype, like.device)

    def clamp(self, theta: torch.Tensor) -> torch.Tensor:
        """Project theta (B, P) onto the bounds."""
        lo, hi = self.bounds(theta)
        return torch.maximum(torch.minimum(theta, hi), lo)

    def check(self, theta: torch.Tensor, tol: float = 1e-9) -> torch.Tensor:
        """Validate theta; returns it as (B, P). Raises ValueError naming the bad entry."""
        if theta.ndim == 1:
            theta = theta[None]
        if theta.ndim != 2 or theta.shape[1] != len(self):
            raise ValueError(f"theta must be (B, {len(self)}) for {self.names}, got {tuple(theta.shape)}")
        t = theta.detach()
        if not torch.isfinite(t).all():
            b, p = torch.nonzero(~torch.isfinite(t))[0].tolist()
            raise ValueError(f"parameter {self.names[p]} of batch element {b} is not finite")
        lo, hi = self.bounds(t)
        bad = (t < lo - tol) | (t > hi + tol)
        if bad.any():
            b, p = torch.nonzero(bad)[0].tolist()
            raise ValueError(
                f"parameter {self.names[p]} = {t[b, p].item():.6g} {self.units[p]} of batch element {b} "
                f"is outside its bounds [{self.lower[p]:.6g}, {self.upper[p]:.6g}]"
            )
        return theta

    def make(self, batch: int = 1, device=None, dtype=torch.float64, **values) -> torch.Tensor:
        """theta (batch, P) from named values (beta in radians); unnamed ones at their lower bound."""
        unknown = set(values) - set(self.names)
        if unknown:
            raise KeyError(f"unknown parameters {sorted(unknown)}; known: {self.names}")
        row = [float(values.get(n, lo)) for n, lo in zip(self.names, self.lower, strict=True)]
        return torch.tensor([row] * batch, device=device, dtype=dtype)


@functools.lru_cache(maxsize=256)
def _bounds(lower: tuple[float, ...], upper: tuple[float, ...], dtype, device) -> tuple[torch.Tensor, torch.Tensor]:
    """The bounds as tensors, made once per layout, dtype and device (simulate checks theta on
    every call)."""
    return torch.tensor(lower, dtype=dtype, device=device), torch.tensor(upper, dtype=dtype, device=device)
