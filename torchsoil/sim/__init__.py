"""The paper's soil-deformation model as batched, differentiable tensor ops.

Stages: `sinkage` (wheels dig), `deposition` (a share chi goes beside the rut),
`relaxation` (Exner flow to the angle of repose); `geometry` precomputes the wheel paths;
`simulate` runs them in order.
"""

from torchsoil.settings import SimConfig
from torchsoil.sim.geometry import WheelGeometry, wheel_geometry
from torchsoil.sim.params import ParamSpec
from torchsoil.sim.relaxation import relax
from torchsoil.sim.simulate import Modifiers, SimResult, simulate, simulate_path

__all__ = ["Modifiers", "ParamSpec", "SimConfig", "SimResult", "WheelGeometry", "relax",
           "simulate", "simulate_path", "wheel_geometry"]
