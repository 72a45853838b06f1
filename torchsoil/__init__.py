"""torchsoil: measure how a field robot deforms soil from two lidars, and identify a
differentiable soil model online."""

from torchsoil.grid import Grid
from torchsoil.registration import register_envs
from torchsoil.robot import Robot

__version__ = "0.1.0"
__all__ = ["Grid", "Robot", "register_envs"]

register_envs()  # gymnasium.make("torchsoil:torchsoil/SoilTraverse-v0") imports this module
