"""Static parameters of the soil-traverse environment, derived once from its settings.

`env_config` reads the settings (`torchsoil.settings.EnvConfig`: the env section of the
settings tree) from None, an `EnvConfig`, a dict or a YAML path; `make_params` builds from
them, the field and the robot everything the pure functions of `envs.core` need and that
never changes during an episode (`TraverseParams`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from envs import dynamics as dyn
from envs.field import SoilField, field_from_params_csv, make_field
from torchsoil.grid import Grid
from torchsoil.robot import Robot, load_robot
from torchsoil.settings import EnvConfig, Settings, SettingsError, merge, read_yaml, validate
from torchsoil.sim.params import BETA_BOUNDS, CHI_BOUNDS, D_BOUNDS
from torchsoil.sim.simulate import MAX_TAN_BETA
from torchsoil.sim.stencil import numba_ok


def env_config(config: EnvConfig | dict | str | Path | None = None) -> EnvConfig:
    """The env's settings from None (the defaults), an `EnvConfig` (as it is), or a document
    (a dict or a YAML path) of the env section (keys dt, speed, ..., field, sim, robot,
    params_csv) or of the full settings tree (its `env:` section is used). A document is
    merged onto the defaults (mappings merge, lists replace); unknown keys and wrong values
    raise `SettingsError` naming the key (`env.field.size`)."""
    if config is None:
        return EnvConfig()
    if isinstance(config, EnvConfig):
        return config
    if isinstance(config, (str, Path)):
        doc, source = read_yaml(config), str(config)
    elif isinstance(config, dict):
        doc, source = config, "env config"
    else:
        raise SettingsError(f"env config must be None, an EnvConfig, a dict or a YAML path, got "
                            f"{type(config).__name__}")
    if "env" in doc:                                   # a document of the full settings tree
        unknown = sorted(set(doc) - set(Settings.model_fields))
        if unknown:
            raise SettingsError(f"{source}: unknown settings section(s) {', '.join(map(repr, unknown))} "
                                f"(known: {', '.join(Settings.model_fields)})")
        doc = doc["env"] if doc["env"] is not None else {}
        if not isinstance(doc, dict):
            raise SettingsError(f"{source}: section `env` must be a mapping, got {type(doc).__name__}")
    return validate(EnvConfig, merge(EnvConfig().model_dump(), doc), source, prefix="env.")


def relax_margin_cells(relax_margin: float, wheel_width: float, dx: float) -> int:
    """Relaxation room around each wheel's footprint and bands, in cells, from `sim.relax_margin`
    in wheel widths: ceil(relax_margin * wheel_width / dx), 1e-9 cells of rounding forgiven."""
    return max(0, int(math.ceil(relax_margin * wheel_width / dx - 1e-9)))


def visit_length(robot: Robot, curvature_max: float, step: float) -> float:
    """Distance [m] base_link drives while one visit of a cell lasts: from the first wheel
    touching it to the last wheel of the same track leaving it, straight or on the tightest
    arc, plus one step. Within it the rear wheels reuse the front wheels' reference height."""
    w, r = robot.wheels, robot.wheel_width / 2
    longest = 0.0
    for t in range(robot.n_tracks):
        wx, wy = w[w[:, 2] == t, 0], w[w[:, 2] == t, 1]
        longest = max(longest, wx.max() - wx.min() + 2 * r)
        for k in (curvature_max, -curvature_max):
            if k == 0:
                continue
            R = 1.0 / k
            phi = np.arctan2(wx * np.sign(R), np.abs(R - wy))       # angle of each wheel about the ICR
            rho = np.hypot(wx, R - wy).min()
            longest = max(longest, abs(R) * (phi.max() - phi.min() + 2 * r / rho))
    return float(longest + step + 0.1)


@dataclass(frozen=True, eq=False)
class TraverseParams:
    """Everything static about N soil-traverse episodes on one device.

    Attributes:
        config: the env's settings.
        robot: the platform (wheel layout, wheel width, tyre taper).
        field: initial surface h0 (X, Y) [m] and soil layers (T + 2, X, Y) on `device`.
        device: where the state lives.
        cell_table: (X*Y, T + 4) per field cell: tan(beta) (capped), h0 [m], d_1..d_T [m],
            chi [-], beta [rad] (one gather per use).
        track: (K,) int64 track of each wheel.  wheels: (K, 2) wheel centres in base_link, m.
        radius: footprint radius (half the wheel width), m.
        relax_margin: relaxation room around each wheel's footprint and bands, cells.
        window: W, cells per side of every wheel's window, from the fastest wheel on the
            tightest arc (so an episode's result does not depend on the rest of the batch).
        visit_length: m driven while a visit of a cell lasts (`visit_length`).
        lo, hi: (2,) bounds of the wheel centres on the field, m.
        obs_offsets: (S*S, 2) body-frame points of the observation patch, m.
        soil_lo, soil_hi: (T + 2,) float32 bounds of the soil layers.
        weights: reward weights by name.
        fused: step the soil and sample the observation in the fused CPU kernels of
            `envs._step_numba` (on the CPU with numba, sim.backend auto or numba); else in
            torch ops (CUDA, or sim.backend torch).
    """

    config: EnvConfig
    robot: Robot
    field: SoilField
    device: torch.device
    cell_table: torch.Tensor
    track: torch.Tensor
    wheels: torch.Tensor
    radius: float
    relax_margin: int
    window: int
    visit_length: float
    lo: torch.Tensor
    hi: torch.Tensor
    obs_offsets: torch.Tensor
    soil_lo: np.ndarray
    soil_hi: np.ndarray
    weights: dict[str, float]
    fused: bool = False

    @property
    def grid(self) -> Grid:
        return self.field.grid

    @property
    def n_tracks(self) -> int:
        return self.field.n_tracks


def build_field(config: EnvConfig, robot: Robot) -> SoilField:
    """The field of `config`: from `params_csv` if set, else from `config.field`."""
    if config.params_csv:
        soil_field = field_from_params_csv(config.params_csv, config.field)
    else:
        soil_field = make_field(config.field, robot.n_tracks)
    if soil_field.n_tracks != robot.n_tracks:
        raise ValueError(f"field has {soil_field.n_tracks} sinkage tracks, robot uses {robot.n_tracks}")
    return soil_field


def make_params(config: EnvConfig | dict | str | Path | None = None,
                device: str | torch.device = "cpu") -> TraverseParams:
    """Parameters of the env from its settings (anything `env_config` reads)."""
    cfg = env_config(config)
    robot = load_robot(cfg.robot)
    soil_field = build_field(cfg, robot)
    device = torch.device(device)
    fld = soil_field.to(device)
    g = fld.grid
    X, Y = g.shape
    radius = robot.wheel_width / 2
    step_max = max(abs(cfg.speed[0]), abs(cfg.speed[1])) * cfg.dt
    S = cfg.obs_size
    ar = (torch.arange(S, dtype=torch.float32) - (S - 1) / 2) * cfg.obs_dx
    obs_offsets = torch.stack(torch.meshgrid(ar, ar, indexing="ij"), -1).reshape(-1, 2).to(device)
    T = fld.n_tracks
    tan_beta = torch.tan(fld.soil[T + 1]).clamp(max=MAX_TAN_BETA)
    cell_table = torch.cat([tan_beta[None], fld.h0[None], fld.soil]).reshape(T + 4, -1).T.contiguous()
    margin = relax_margin_cells(cfg.sim.relax_margin, robot.wheel_width, g.dx)
    reach = float(np.hypot(robot.wheels[:, 0], robot.wheels[:, 1]).max())
    wheel_step = step_max * (1 + cfg.curvature_max * reach)
    window = dyn.window_size(torch.zeros(1, 2), torch.tensor([[wheel_step, 0.0]]), radius,
                             cfg.sim.band_width * g.dx, margin, g.dx)
    if window > min(X, Y):
        raise ValueError(f"the field ({X} x {Y} cells) is smaller than a wheel window of {window} cells")
    return TraverseParams(
        config=cfg, robot=robot, field=fld, device=device, cell_table=cell_table,
        track=torch.as_tensor(robot.track, device=device),
        wheels=torch.as_tensor(robot.wheels[:, :2], dtype=torch.float32, device=device),
        radius=radius, relax_margin=margin, window=window,
        visit_length=visit_length(robot, cfg.curvature_max, step_max),
        lo=torch.tensor([g.origin[0] + radius, g.origin[1] + radius], device=device),
        hi=torch.tensor([g.origin[0] + (X - 1) * g.dx - radius, g.origin[1] + (Y - 1) * g.dx - radius],
                        device=device),
        obs_offsets=obs_offsets,
        soil_lo=np.array([D_BOUNDS[0]] * T + [CHI_BOUNDS[0], BETA_BOUNDS[0]], np.float32),
        soil_hi=np.array([D_BOUNDS[1]] * T + [CHI_BOUNDS[1], BETA_BOUNDS[1]], np.float32),
        weights=cfg.weights.model_dump(),
        fused=device.type == "cpu" and cfg.sim.backend != "torch" and numba_ok())
