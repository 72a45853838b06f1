"""torchsoil: measure how a field robot deforms soil from two lidars, and identify a
differentiable soil model online."""

import os

# torch's and numba's OpenMP pools share the cores: threads that spin while waiting starve
# the other pool (3-10x slower on 2 busy cores). Effective when torchsoil is imported first.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import sys  # noqa: E402

from torchsoil.grid import Grid  # noqa: E402
from torchsoil.robot import Robot  # noqa: E402

__version__ = "0.1.0"
__all__ = ["Grid", "Robot"]

if "gymnasium" in sys.modules:  # gymnasium.make("torchsoil:torchsoil/SoilTraverse-v0") imports this module
    from envs import register_envs

    register_envs()
