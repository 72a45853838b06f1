"""torchsoil: measure how a field robot deforms soil from two lidars, and identify a
differentiable soil model online.

Importing torchsoil changes nothing process-wide (environment variables, thread counts,
matplotlib backends); the `torchsoil` command chooses those (manual: docs/getting-started.md, Threads).
"""

import sys

from torchsoil.grid import Grid
from torchsoil.robot import Robot, load_robot
from torchsoil.settings import Settings, load_settings

__version__ = "0.1.0"
__all__ = ["Grid", "Robot", "Settings", "load_robot", "load_settings"]

if "gymnasium" in sys.modules:  # gymnasium.make("torchsoil:torchsoil/SoilTraverse-v0") imports this module
    from envs.registration import register_envs

    register_envs()
