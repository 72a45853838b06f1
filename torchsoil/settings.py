"""The settings tree: every setting of torchsoil, its default (the paper's values), type and unit.

    settings = load_settings("my.yaml", overrides=["estimator.window=1.0", "sim.tau=0.005"])
    est = Estimator(pair, settings.estimator, settings.sim)

One frozen pydantic model per stage, combined in `Settings` (sections sim, estimator,
pipeline, diagnosis, env, synth, fleet). Defaults live here and nowhere else; YAML files and
`section.key=value` overrides only change them. Unknown keys and wrong types are refused
with the key named (`SettingsError`). Each stage receives its own section, never the tree.
`torchsoil settings` prints the effective tree as YAML, with units as comments.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Iterable
from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, NonNegativeFloat, ValidationError, field_validator, model_validator


class SettingsError(ValueError):
    """A setting that does not exist, or a value of the wrong type or range (the key is named)."""


class Section(BaseModel):
    """A settings section: frozen, unknown keys refused."""

    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)

    def replace(self, **changes):
        """A copy with some fields changed, validated like a YAML override (a mapping given
        for a nested section changes only the keys it names)."""
        plain = {k: v.model_dump() if isinstance(v, BaseModel) else v for k, v in changes.items()}
        return type(self).model_validate(merge(self.model_dump(), plain))


# ---------------------------------------------------------------------------- simulator
class SimConfig(Section):
    """Forward model (paper section IV-B). Lengths in metres, cells or wheel widths as named."""

    tau: float = Field(0.01, gt=0, description="relaxation stop: max |grad h| - tan(beta) < tau [-]")
    eps_scale: float = Field(4.0, gt=0, description="relaxation rate: epsilon = eps_scale / dx^2")
    max_iter: int = Field(2000, ge=1, description="relaxation iteration cap (flagged when hit)")
    fixed_iter: int | None = Field(None, ge=0, description="run exactly this many relaxation iterations "
                                                           "(capped relaxation); null: until tau")
    ref_radius: float = Field(0.5, ge=0, description="reference-height disc radius, fraction of half the "
                                                     "wheel width")
    revisit_ref: Literal["footprint", "disc"] = Field(
        "footprint", description="reference height on the cells earlier wheel passes went over (a visit after "
                                 "the first; a trailing wheel under dig_order wheel): footprint: the mean over "
                                 "the wheel's whole footprint, the level a wheel that spans the rut rests on "
                                 "(docs/visits.md); disc: the ref_radius disc of fresh ground")
    band_width: float = Field(1.0, gt=0, description="deposition band beside the rut, cells")
    relax_margin: float = Field(2.0, ge=0, description="relaxation domain: rut plus this many wheel widths "
                                                       "each side")
    pose_spacing: float = Field(0.5, gt=0, description="trajectory resampled so wheels move at most this "
                                                       "many cells per pose")
    backend: Literal["auto", "numba", "torch"] = Field("auto", description="relaxation kernel: auto (numba "
                                                                            "on CPU, torch on CUDA)")
    dig_order: Literal["robot", "wheel"] = Field(
        "robot", description="robot: every wheel digs from the surface before the robot (the paper); wheel: "
                             "the axles dig in the order they meet the ground, each trailing wheel again "
                             "from the surface the wheels before it left, their spoil included")


# ---------------------------------------------------------------------------- estimator
class PerKind(Section):
    """One value per kind of parameter: sinkage d (all tracks), chi, beta."""

    d: float = Field(gt=0, description="m")
    chi: float = Field(gt=0, description="-")
    beta: float = Field(gt=0, description="rad")


class InitialParams(Section):
    """Parameters the first window starts from."""

    d: float = Field(0.02, ge=0, description="sinkage, m")
    chi: float = Field(0.5, ge=0, description="displacement-compaction ratio, -")
    beta_deg: float = Field(30.0, gt=0, le=90, description="angle of repose, degrees")


class NuisanceConfig(Section):
    """Offset and tilt of H_b relative to H_f (torchsoil.estimate.nuisance), fitted on untouched ground
    (estimator.floor_inner wheel widths or more from every wheel path) and removed from H_b."""

    offset: bool = Field(True, description="fit and remove a vertical offset between the maps")
    tilt: bool = Field(True, description="and a tilt (a plane over the world)")
    knot_spacing: float = Field(5.0, ge=0, description="the offset may drift along the drive, "
                                                       "piecewise linear with knots this far apart, m "
                                                       "(0: constant)")
    min_cells: int = Field(200, ge=1, description="fewest untouched cells to fit on")


class OnlineConfig(Section):
    """Estimation while the robot drives (torchsoil.estimate.live): when a window's ground is complete."""

    lag: float = Field(2.0, ge=0, description="a window is fitted once the back lidar has rasterized the ground "
                                              "this far behind the rear wheels' margin past the window and the "
                                              "one ahead, m (more: denser H_b, later rows)")
    context: float = Field(4.0, ge=0, description="ground before a window also cut out with it (map offset fit, "
                                                  "smoothing at the crop edge), m")
    batch: int = Field(2, ge=1, description="windows fitted together on one stretch cut out of the tiles (more: "
                                            "less set-up per window, later rows)")
    worker: Literal["thread", "none"] = Field(
        "thread", description="windows fitted on a worker thread while the pipeline takes the next sweeps, "
                              "or none: in the caller's thread, between sweeps (the same rows either way)")
    max_pending: int = Field(8, ge=1, description="stretches queued for fitting at most; the pipeline waits "
                                                  "when the fits fall this far behind (bounded memory)")
    spill: bool = Field(True, description="heightmap tiles far from the robot written to OUT/tiles (bounded memory)")
    max_cells: int = Field(3_000_000, ge=1, description="a drive whose terrain pair would hold more cells is left "
                                                        "as tiles (no terrain_pair.npz, simulated.npz, fig6) and "
                                                        "written as terrain pairs of pieces of the drive")
    piece_length: float = Field(50.0, gt=0, description="a drive left as tiles: path length of each piece in "
                                                        "OUT/pieces/ (a terrain pair each, for export), m")


class EstimatorConfig(Section):
    """Sliding-window estimation (paper section IV-C)."""

    window: float = Field(0.8, gt=0, description="window length along the path, m")
    stride: float = Field(0.4, gt=0, description="advance between windows, m")
    corridor: float = Field(3.0, gt=0, description="ROI corridor width d_w around the path, m")
    front_smoothing: float = Field(1.0, ge=0, description="the simulation starts from H_f smoothed by a "
                                                          "Gaussian of this sigma, cells")
    after_blur: float = Field(0.0, ge=0, description="the simulated change is compared with H_b through a "
                                                     "Gaussian of this sigma, cells: the lidar raster's own "
                                                     "blur of a rut's walls (0: none; diagnose chooses it)")
    weight_width: float = Field(2.0, gt=0, description="cost weight 1 within this many wheel widths of "
                                                       "each wheel path")
    floor_inner: float = Field(2.5, ge=0, description="noise-floor zone starts this many wheel widths "
                                                      "from the wheel paths")
    floor_outer: float = Field(4.0, gt=0, description="noise-floor zone ends this many wheel widths from "
                                                      "the wheel paths")
    grad: Literal["autograd", "fd"] = Field("autograd", description="autograd, or fd (forward "
                                                                    "differences, the paper's)")
    fd_step: PerKind = Field(PerKind(d=0.0005, chi=0.01, beta=0.01),
                             description="forward-difference steps: m, -, rad")
    optimizer: Literal["rprop", "gd"] = Field("rprop", description="rprop (adaptive sign steps) or gd "
                                                                    "(the paper's fixed steps)")
    scale: PerKind = Field(PerKind(d=0.005, chi=0.1, beta=0.1),
                           description="the unit the optimizer steps in: m, -, rad")
    step: float = Field(0.25, gt=0, description="initial rprop step, in scale units")
    lr: PerKind = Field(PerKind(d=0.03, chi=10.0, beta=20.0),
                        description="gd only: alpha_i, parameter unit per m of cost gradient")
    max_iter: int = Field(40, ge=1, description="optimizer iteration cap per window")
    step_tol: float = Field(0.05, gt=0, description="stop when every step is below this, scale units")
    init: InitialParams = Field(InitialParams(), description="first window's starting parameters")
    merged_sinkage: bool = Field(False, description="ablation: one sinkage for all tracks")
    min_valid_fraction: float = Field(0.3, ge=0, le=1, description="of the weighted window cells, and "
                                                                   "of the footprint cells among them, "
                                                                   "measured; fewer: window flagged and skipped")
    stop_speed: float = Field(0.05, ge=0, description="slower than this for more than stop_time: window "
                                                      "flagged 'stopped', m/s")
    stop_time: float = Field(0.5, ge=0, description="s")
    image_every: int = Field(5, ge=0, description="TensorBoard image of measured vs simulated H_delta "
                                                  "every N windows (0: none)")
    device: str = Field("auto", description="auto (cuda when present), cpu, cuda, cuda:N")
    nuisance: NuisanceConfig = Field(NuisanceConfig(), description="map offset and tilt removed from H_b")
    front_view: Literal["auto", "last_visit", "first_view"] = Field(
        "auto", description="what H_f holds on ground driven over more than once: the surface before the "
                            "last visit (earlier ruts shown), the surface before the first (earlier visits "
                            "are then simulated too), or auto: told from the maps")
    online: OnlineConfig = Field(OnlineConfig(), description="estimation while the recording streams in")

    @model_validator(mode="after")
    def _floor_zone(self):
        if self.floor_outer <= self.floor_inner:
            raise ValueError(f"floor_outer ({self.floor_outer}) must exceed floor_inner ({self.floor_inner})")
        return self


# ---------------------------------------------------------------------------- pipeline
class TopicTime(Section):
    """How one lidar topic times its points (torchsoil.io.pointtime); 'auto' reads it from the values."""

    time_field: str = Field("auto", description="per-point time field: auto (t, time or timestamp), a name, "
                                                "or none (already de-skewed)")
    time_unit: Literal["auto", "s", "ms", "us", "ns"] = Field("auto", description="unit of the time field")
    time_base: Literal["auto", "stamp", "absolute"] = Field("auto", description="times relative to the header "
                                                                                "stamp, or absolute")
    stamp: Literal["auto", "start", "end"] = Field("auto", description="where the header stamp sits in the sweep")


class ReadConfig(Section):
    """Topics and frames of a recording."""

    front_topic: str = Field("/lidar_front/points", description="front lidar PointCloud2 topic")
    back_topic: str = Field("/lidar_back/points", description="back lidar PointCloud2 topic")
    tf_topic: str = Field("/tf_static", description="static transforms topic (/tf is read too)")
    imu_topic: str = Field("", description="sensor_msgs/msg/Imu topic levelling the world frame; empty: the "
                                           "bag's only Imu topic, if any; none: no IMU")
    base_frame: str = Field("base_link", description="robot body frame")
    extrinsics: dict[str, tuple[float, ...]] = Field(
        default_factory=dict, description="{frame or topic: [x, y, z, roll, pitch, yaw]} in base_frame (m, "
                                          "rad), overriding the recording's transforms")

    @field_validator("extrinsics")
    @classmethod
    def _six(cls, v):
        for frame, xyzrpy in v.items():
            if len(xyzrpy) != 6 or not all(math.isfinite(x) for x in xyzrpy):
                raise ValueError(f"{frame}: need 6 finite numbers [x, y, z, roll, pitch, yaw] (m, rad), "
                                 f"got {list(xyzrpy)}")
        return v

    times: dict[str, TopicTime] = Field(default_factory=dict, description="{topic: {time_field, time_unit, "
                                        "time_base, stamp}} per-point time convention (default: all auto)")


class MappingConfig(Section):
    """Reference map P_ref and trajectory T_ref by scan-to-map point-to-plane ICP."""

    voxel: float = Field(0.2, gt=0, description="scan and map voxel edge, m")
    map_radius: float = Field(30.0, gt=0, description="local map kept around the robot, m")
    normal_radius: float = Field(0.6, gt=0, description="normal estimation radius, m")
    max_dist: float = Field(0.5, gt=0, description="correspondence gate while tracking, m")
    startup_dist: float = Field(1.5, gt=0, description="correspondence gate of the first registration, m")
    max_iter: int = Field(30, ge=1, description="ICP iterations")
    degenerate_eigen: float = Field(2e-3, ge=0, description="normal-matrix eigenvalue below which a "
                                                            "direction counts as unconstrained")
    min_fitness: float = Field(0.3, ge=0, le=1, description="share of matched points below which a "
                                                            "registration fails")
    stationary_speed: float = Field(0.02, ge=0, description="below this the robot stands still, m/s")
    max_range: float = Field(40.0, gt=0, description="points farther from the robot are not used, m")
    velocity_window: float = Field(0.3, gt=0, description="baseline of the constant-velocity estimate, s")
    startup_baseline: float = Field(0.5, gt=0, description="time between the two sweeps that measure "
                                                           "the initial velocity, s")
    source_voxel: float = Field(0.2, gt=0, description="voxel of the registered sweep, m")
    max_points: int = Field(3000, ge=10, description="registered voxels per sweep at most (evenly thinned)")
    max_degenerate_share: float = Field(0.8, ge=0, le=1, description="above this share of degenerate "
                                                                     "sweeps the run stops")
    workers: int = Field(1, ge=1, description="threads for nearest-neighbour queries")
    ground_z: float | None = Field(0.97, description="normals with |n_z| above this count as ground "
                                                     "(see icp.register); null: off")
    one_sided: bool = Field(True, description="drop matches on steep faces turned away from the robot")
    use_gyro: bool = Field(True, description="the IMU's rate gyro (when the recording has one) predicts the "
                                             "rotation between sweeps")
    max_visit_shift: float = Field(0.04, gt=0, description="the ground between two visits, as the way out "
                                                           "left it and as the way back finds it, may lie this "
                                                           "far apart before the map counts as broken there, m")
    retry_turn: float = Field(1.0, gt=0, description="a registration that turns this far from the "
                                                     "constant-velocity prediction, or is weak or poor, is "
                                                     "tried again from other starts, degrees")
    max_yaw_rate: float = Field(45.0, gt=0, description="largest yaw rate the robot reaches; the other "
                                                        "starts span the yaw it can turn between two "
                                                        "sweeps either way, deg/s")
    retry_cost: float = Field(1.5, gt=1, description="... or whose truncated cost (icp.truncated_cost) "
                                                    "exceeds this multiple of the last ten sweeps' median")
    retry_step: float = Field(4.0, gt=0, description="yaw step between the other starts, degrees")
    retry_gain: float = Field(0.6, gt=0, le=1, description="another start replaces the first fit when its "
                                                           "truncated cost (icp.truncated_cost) is below "
                                                           "this share of the first's")


class ReregisterConfig(Section):
    """Re-registration of each stream onto P_ref (drift cancellation)."""

    enabled: bool = Field(True, description="false: rasterize with T_ref (the ablation)")
    voxel: float = Field(0.1, gt=0, description="source downsampling for ICP, m")
    max_dist: float = Field(0.3, gt=0, description="correspondence gate, m")
    max_iter: int = Field(20, ge=1, description="ICP iterations")
    min_fitness: float = Field(0.5, ge=0, le=1, description="share of matched points below which a sweep "
                                                            "is dropped")
    max_rmse: float = Field(0.05, gt=0, description="robust point-to-plane RMS above which a sweep is "
                                                    "dropped, m")
    max_shift: float = Field(0.3, gt=0, description="largest accepted translation from the seed, m")
    max_turn: float = Field(2.0, gt=0, description="largest accepted rotation from the seed, degrees")
    degenerate_eigen: float = Field(2e-3, ge=0, description="see mapping.degenerate_eigen")
    max_range: float = Field(30.0, gt=0, description="points used for ICP, m")
    max_points: int = Field(2500, ge=10, description="source voxels at most (evenly thinned)")
    one_sided: bool = Field(True, description="see mapping.one_sided")


class RasterConfig(Section):
    """Corridor extraction and rasterization into H_f, H_b."""

    dx: float = Field(0.02, gt=0, description="cell edge, m")
    corridor_width: float = Field(3.0, gt=0, description="d_w, width of the kept corridor, m")
    fill_radius: int = Field(2, ge=0, description="empty cells filled from measured cells up to this "
                                                  "many cells away")
    max_range: float = Field(12.0, gt=0, description="points farther from their lidar are not used, m")
    wheel_margin: float = Field(0.1, ge=0, description="front stream: points ahead of the front wheels' "
                                                       "footprint plus this; back stream: behind the rear "
                                                       "wheels' plus this, m")
    visit_margin: float = Field(2.0, ge=0, description="a cell is visited while base_link is within the outermost "
                                                      "wheel's |y| plus (0.5 + this) wheel widths of it (the "
                                                      "simulator's reach with its default sim.relax_margin), or "
                                                      "within a corner wheel's footprint's reach")
    visit_gap: float | None = Field(None, gt=0, description="base_link travel after which coming back over a cell "
                                                            "is a new visit, m (default: twice the wheelbase plus "
                                                            "a wheel width)")


class LevelConfig(Section):
    """Levelling of the world frame (base_link at the first sweep) to gravity."""

    source: Literal["auto", "imu", "ground", "none"] = Field(
        "auto", description="auto: the IMU if the bag has one, else the ground; imu; ground: the mean ground "
                            "plane near the start; none: not levelled")
    window: float = Field(2.0, gt=0, description="IMU samples averaged from the first sweep on, s")
    bias_window: float = Field(60.0, ge=0, description="IMU samples of the first this many s also give the "
                                                       "accelerometer's bias, told from gravity by the robot's "
                                                       "turns; the map is then turned by the correction at that "
                                                       "time or at the end, s (0: off)")
    radius: float = Field(6.0, gt=0, description="ground within this distance of the start is fitted, m")


class PipelineConfig(Section):
    """The lidar pipeline (paper section III), one section per stage."""

    read: ReadConfig = ReadConfig()
    mapping: MappingConfig = MappingConfig()
    level: LevelConfig = LevelConfig()
    reregister: ReregisterConfig = ReregisterConfig()
    raster: RasterConfig = RasterConfig()
    checkpoint_s: float = Field(30.0, ge=0, description="process-bag: seconds between two checkpoints of the "
                                                        "pipeline's state (OUT/checkpoint; --resume goes on from "
                                                        "the last one)")


# ---------------------------------------------------------------------------- diagnosis
class DiagnosisConfig(Section):
    """Model-mismatch diagnosis: location tests, candidate fits, held-out acceptance."""

    n_fit: int = Field(4, ge=0, description="catalogue candidates fitted (the leading ones by location "
                                            "evidence)")
    alpha_accept: float = Field(0.05, gt=0, lt=1, description="family-wise one-sided level of the held-out "
                                                              "test, spent over the fitted candidates")
    lead_share: float = Field(0.6, gt=0, le=1, description="share of alpha_accept given to the leading "
                                                           "candidate(s) (fallback procedure)")
    alpha_locate: float = Field(0.01, gt=0, lt=1, description="family-wise level of the location tests")
    materiality: float = Field(0.1, ge=0, description="a located zone must exceed this fraction of the "
                                                      "measured noise floor")
    gain_materiality: float = Field(0.0, ge=0, description="an accepted term must lower the mean held-out "
                                                           "cost by at least this fraction of the base model's "
                                                           "(0: by anything; a real effect whose covariate varies "
                                                           "within windows gains little across them, and "
                                                           "effect_materiality keeps negligible coefficients out)")
    effect_materiality: float = Field(0.05, ge=0, description="an accepted term must change the physics by at "
                                                              "least this fraction at both folds' coefficients "
                                                              "(catalogue.effect_size: the sinkage on a twentieth "
                                                              "of the drive, the radius, the walls' slope)")
    own_fit_z: float = Field(0.0, ge=0, description="an accepted term must not make the windows' own fit worse: "
                                                   "the paired z of their residuals with it at least -own_fit_z "
                                                   "(a term that predicts neighbouring ground better but fits its "
                                                   "own worse stands in for soil that changes along the drive)")
    block_m: float = Field(2.4, gt=0, description="cross-validation block length, m")
    learned: bool = Field(True, description="also fit a learned modifier (diagnosis.learned: a parameter "
                                            "following a driving covariate, a curve fitted through the simulator) "
                                            "and name it where it predicts held-out ground better than the "
                                            "catalogue's term, or where the catalogue names none")
    checkpoint_s: float = Field(15.0, ge=0, description="seconds between two saves of a pass in progress "
                                                        "(OUT/passes; a killed run resumes after the last save; 0: "
                                                        "after every window)")
    refine_steps: int = Field(2, ge=0, description="parabolic refinements of a candidate's coefficient")
    offsets: tuple[int, ...] = Field((2, 4, 6), description="windows back (in strides) on whose ground "
                                                            "each fit is also scored")
    sections: tuple[tuple[float, float], ...] = Field(
        tuple([(f, 1.0) for f in (0.0, 0.15, 0.3, 0.5, 0.7, 0.85)]
              + [(f, e) for e in (0.5, 0.25) for f in (0.0, 0.15, 0.3)]),
        description="tyre sections (flat fraction f, taper exponent e; sim.sinkage.taper) tried besides the "
                    "robot's own; the best fit on the drive's windows is the base model's section, a nuisance "
                    "(a rounded or crowned tyre is not missing physics); (): the robot's as described, -")
    blurs: tuple[NonNegativeFloat, ...] = Field(
        (0.5, 0.75, 1.0, 1.5),
        description="raster blurs (estimator.after_blur, a Gaussian's sigma, cells) tried besides the estimator's "
                    "own; the best fit on the drive's windows is the base model's, a nuisance (a lidar map "
                    "spreads a rut's walls); (): the estimator's as set")
    dig_orders: tuple[Literal["robot", "wheel"], ...] = Field(
        ("robot", "wheel"), description="dig orders (sim.dig_order) tried, each at its best few sections; the "
                                        "one that fits the drive's windows best is the base model's, a nuisance "
                                        "like the section; (): sim.dig_order as set")
    footprint_sections: int = Field(3, ge=1, description="a footprint or wall term's passes choose their own section "
                                                         "among this many best for the base model and "
                                                         "the robot's own")
    min_spread: dict[str, float] = Field(
        default_factory=lambda: {"speed": 0.05, "traction": 0.004, "lateral_load": 0.004, "passes": 0.05},
        description="smallest spread (std over windows) of a covariate for its term to be testable, in "
                    "the covariate's unit")


# ---------------------------------------------------------------------------- environment
class SoilValues(Section):
    """Soil parameters of a field region: d (one value, or one per track) [m], chi [-], beta [deg]."""

    d: float | list[float] | None = None
    chi: float | None = None
    beta_deg: float | None = None


class Patch(SoilValues):
    """A disc of other soil (wet: deep sinkage)."""

    center: tuple[float, float]
    radius: float = Field(gt=0)


class Lane(SoilValues):
    """A band along x of other soil (packed: shallow sinkage); y: (ymin, ymax), m."""

    y: tuple[float, float]


class FieldConfig(Section):
    """The env's field: rough initial surface and soil maps."""

    size: tuple[float, float] = Field((20.0, 10.0), description="length along x, width along y, m")
    dx: float = Field(0.05, gt=0, description="cell edge, m")
    roughness: float = Field(0.003, ge=0, description="standard deviation of the initial surface, m")
    roughness_length: float = Field(0.3, gt=0, description="correlation length of the roughness, m")
    seed: int = Field(0, description="terrain noise seed")
    soil: SoilValues = Field(SoilValues(d=0.02, chi=0.6, beta_deg=30.0), description="background soil")
    patches: tuple[Patch, ...] = Field(
        (Patch(center=(10.0, 5.0), radius=2.0, d=0.08, chi=0.3, beta_deg=20.0),),
        description="wet discs: deep sinkage, little spill-over, low angle of repose")
    lanes: tuple[Lane, ...] = Field((Lane(y=(8.0, 9.5), d=0.005, chi=0.8, beta_deg=35.0),),
                                    description="packed lanes: shallow sinkage")
    edge: float = Field(0.5, ge=0, description="soft edge of the patches, m")


class RewardWeights(Section):
    """reward = progress * distance gained - damage - time (+ goal, - off_field)."""

    progress: float = Field(1.0, description="per m towards the goal")
    displaced: float = Field(40.0, description="per m^3 of soil dug")
    compacted: float = Field(40.0, description="per m^3 dug and not deposited")
    rut_depth: float = Field(1.0, description="per m of the deepest rut under the wheels this step")
    repeat_cells: float = Field(0.001, description="per cell entered again after an earlier pass")
    time: float = Field(0.01, description="per step")
    goal: float = Field(10.0, description="bonus on reaching the goal")
    off_field: float = Field(10.0, description="penalty for leaving the field")


class EnvConfig(Section):
    """SoilTraverse environment: episode, platform, field, physics, observation, reward."""

    dt: float = Field(0.2, gt=0, description="control period, s")
    speed: tuple[float, float] = Field((-0.5, 1.0), description="platform speed limits (min, max), m/s")
    curvature_max: float = Field(0.8, ge=0, description="symmetric dual steering limit, 1/m")
    start: tuple[float, float, float] = Field((2.0, 5.0, 0.0), description="x [m], y [m], yaw [deg]")
    start_jitter: tuple[float, float, float] = Field((0.2, 0.2, 5.0), description="uniform half-ranges of "
                                                                                 "the start, m, m, deg")
    goal: tuple[float, float] = Field((18.0, 5.0), description="m")
    goal_jitter: float = Field(0.0, ge=0, description="radius of a uniform disc around the goal, m")
    goal_radius: float = Field(0.5, gt=0, description="episode ends when base_link is this close, m")
    max_steps: int = Field(400, ge=1, description="truncation")
    obs_size: int = Field(24, ge=1, description="local observation patch, cells per side")
    obs_dx: float = Field(0.1, gt=0, description="spacing of the observation patch, m")
    soil_noise: float = Field(0.0, ge=0, description="relative std of observed soil parameters (0: true)")
    weights: RewardWeights = RewardWeights()
    sim: SimConfig = Field(SimConfig(fixed_iter=4, relax_margin=0.7),
                           description="the env's physics, relaxed every step (same meaning as section sim; "
                                       "pose_spacing unused: each wheel moves one segment a step)")
    field: FieldConfig = FieldConfig()
    robot: str = Field("paper_platform", description="robot name (shipped) or YAML path")
    params_csv: str | None = Field(None, description="replay the soil of an estimator run's params.csv")

    @model_validator(mode="after")
    def _limits(self):
        if self.speed[0] > self.speed[1]:
            raise ValueError(f"speed must be (min, max), got {self.speed}")
        if self.sim.dig_order != "robot":
            raise ValueError("sim.dig_order: the environment digs every wheel from the surface before the robot "
                             "('robot'); 'wheel' is for the estimator and the synthetic world")
        return self


# ---------------------------------------------------------------------------- synthetic world
class TrajectorySegment(Section):
    """A straight (length, m) or an arc (radius m, angle_deg) at a speed, m/s."""

    straight: float | None = Field(None, gt=0, description="m")
    arc: float | None = Field(None, gt=0, description="radius, m")
    angle_deg: float | None = Field(None, description="deg, left > 0")
    speed: float = Field(1.0, gt=0, description="m/s")

    @model_validator(mode="after")
    def _kind(self):
        if (self.straight is None) == (self.arc is None):
            raise ValueError("a segment is either {straight: m} or {arc: radius m, angle_deg: deg}")
        if self.arc is not None and self.angle_deg is None:
            raise ValueError("an arc segment needs angle_deg")
        return self


class TrajectoryConfig(Section):
    start: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="x [m], y [m], yaw [deg]")
    segments: tuple[TrajectorySegment, ...] = (TrajectorySegment(straight=20.0, speed=1.0),)
    accel_limit: float = Field(0.5, gt=0, description="m/s^2")


class SessionConfig(TrajectoryConfig):
    """A later session on the same field: another day's drive over the ground the sessions
    before it left (their ruts, their passes), from its own start, after a clock gap."""

    start: tuple[float, float, float] = Field(description="x [m], y [m], yaw [deg] in the world (the first "
                                                          "session's trajectory frame)")
    segments: tuple[TrajectorySegment, ...] = Field(min_length=1)
    gap: float = Field(86400.0, ge=0, description="clock from the end of the session before to this one's "
                                                  "start, s")
    gnss: bool = Field(True, description="the session's bag holds the RTK fixes (the recorder's --no-gnss "
                                         "leaves them out of every session)")


class ReliefConfig(Section):
    amplitude: float = Field(0.05, ge=0, description="m")
    wavelength: float = Field(25.0, gt=0, description="m")
    slope_x: float = Field(0.0, description="m/m")
    slope_y: float = Field(0.0, description="m/m")


class MicroConfig(Section):
    rms: float = Field(0.007, ge=0, description="m")
    corr_length: float = Field(0.07, gt=0, description="m")


class TerrainConfig(Section):
    relief: ReliefConfig = ReliefConfig()
    micro: MicroConfig = MicroConfig()
    margin: float = Field(10.0, ge=0, description="field around the path, m")


class WorldSoil(Section):
    """Soil of the synthetic world: base values, patches (free-form, see synth.terrain), a
    per-track scale."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    base: dict[str, float] = Field(default_factory=lambda: {"d": 0.03, "chi": 0.2, "beta_deg": 30.0,
                                                            "moisture": 0.0})
    patches: list[dict] = Field(default_factory=list)
    track_scale: list[float] | None = None

    @field_validator("base")
    @classmethod
    def _base_keys(cls, v):
        unknown = set(v) - {"d", "chi", "beta_deg", "moisture"}
        if unknown:
            raise ValueError(f"unknown keys {sorted(unknown)}; known: d, chi, beta_deg, moisture")
        return {"d": 0.03, "chi": 0.2, "beta_deg": 30.0, "moisture": 0.0, **v}


class LandmarkConfig(Section):
    poles: int = Field(10, ge=0)
    trunks: int = Field(6, ge=0)
    shed: bool = True
    fence: bool = True


class LidarConfig(Section):
    columns: Literal[512, 1024, 2048] = 1024
    beams: int = Field(32, ge=1, le=128, description="rings (fewer: smaller bags for long drives)")
    rate_hz: float = Field(10.0, gt=0, description="Hz")
    range_noise: float = Field(0.01, ge=0, description="m")
    dropout: float = Field(0.02, ge=0, le=1, description="fraction of returns dropped")
    organized: bool = Field(False, description="full beams x columns clouds, NaN where nothing returned")
    tilt_deg: float = Field(30.0, ge=0, le=60, description="each lidar tilted down towards its own side, deg "
                                                          "(less: it sees farther, more landmarks)")


class WorldConfig(SimConfig):
    """The world's physics: the simulator's settings and chunk, the arc length of trajectory
    dug and deposited per step, m (relaxation runs once a pass)."""

    chunk: float = Field(0.4, gt=0, description="m")


SECTIONS = ("taper", "flat", "rounded", "crowned")


class TyreConfig(Section):
    """The world's tyre, drawn per drive from the seed (the terrain pair and the estimator keep
    the robot's nominal width and taper): one section of `sections`, a footprint width of the
    robot's wheel_width times a factor drawn uniformly in `width_scale`, and (when set) one
    dig order of `dig_orders`, which then overrides world.dig_order."""

    sections: tuple[Literal["taper", "flat", "rounded", "crowned"], ...] = Field(
        ("taper",), min_length=1, description="cross-sections to draw from: taper (the robot's), flat, rounded "
                                              "(elliptic), crowned (parabolic) (synth.world.section_profile)")
    width_scale: tuple[float, float] = Field((1.0, 1.0), description="range of footprint width / robot "
                                                                     "wheel_width, -")
    dig_orders: tuple[Literal["robot", "wheel"], ...] | None = Field(
        None, min_length=1, description="how the wheels dig, drawn per drive (sim.dig_order: robot, every wheel "
                                        "from the surface before the robot; wheel, axle after axle); null: "
                                        "world.dig_order")

    @field_validator("width_scale")
    @classmethod
    def _positive(cls, v):
        if not 0 < v[0] <= v[1]:
            raise ValueError(f"need 0 < low <= high, got {list(v)}")
        return v


class MeasurementConfig(Section):
    """Nuisances of the terrain pair's maps, drawn per drive from the seed within these
    ranges (synth.measurement.apply_measurement). Defaults: Gaussian noise only (all others off)."""

    noise: float = Field(0.003, ge=0, description="per-cell noise standard deviation, m")
    noise_dof: tuple[float, float] | None = Field(None, description="Student-t degrees of freedom drawn in "
                                                                    "this range (> 2; scaled to `noise` std); "
                                                                    "null: Gaussian")
    offset: float = Field(0.0, ge=0, description="H_b - H_f vertical offset drawn uniformly in +-offset, m")
    tilt_deg: float = Field(0.0, ge=0, description="H_b tilt about x and about y, each drawn uniformly in "
                                                   "+-tilt_deg (pivot: grid centre), deg")
    dropout: tuple[float, float] = Field((0.0, 0.0), description="range of the fraction of single cells "
                                                                 "lost in each map, -")
    blobs: float = Field(0.0, ge=0, description="lost discs per m^2 of grid in each map, 1/m^2")
    blob_radius: tuple[float, float] = Field((0.02, 0.06), description="range of the blob radius, m")
    streaks: float = Field(0.0, ge=0, description="occlusion streaks (thin lost lines along the heading, "
                                                  "behind the robot) per m of path in each map, 1/m")
    streak_length: tuple[float, float] = Field((0.2, 0.8), description="range of the streak length, m")
    first_view: float = Field(0.0, ge=0, le=1, description="probability that H_f holds the first view of "
                                                          "revisited ground (a pipeline keeping each cell's "
                                                          "oldest height), not the one before the last visit")

    @field_validator("dropout", "blob_radius", "streak_length")
    @classmethod
    def _range(cls, v):
        if not 0 <= v[0] <= v[1]:
            raise ValueError(f"need a range 0 <= low <= high, got {list(v)}")
        return v

    @field_validator("noise_dof")
    @classmethod
    def _dof(cls, v):
        if v is not None and not 2 < v[0] <= v[1]:
            raise ValueError(f"need 2 < low <= high (finite variance), got {list(v)}")
        return v


# what real before/after maps have (issue 12): lidar extrinsic and re-registration residuals
# (offset, tilt), occlusions, blobs, dropouts, heavy-tailed noise, tyre sections unlike the
# model's. Not a footprint wider or narrower than the robot's wheel_width: that is the
# catalogue's footprint_width effect, and a drive with it is not a null drive.
REALISTIC = {
    "measurement": {"noise_dof": (3.0, 5.0), "offset": 0.002, "tilt_deg": 0.05, "dropout": (0.005, 0.015),
                    "blobs": 1.0, "streaks": 2.0, "first_view": 0.5},
    "tyre": {"sections": SECTIONS, "dig_orders": ("robot", "wheel")},
}


class SynthConfig(Section):
    """A synthetic scenario (configs/scenarios/NAME.yaml are documents of this section).

    `realistic()`: the same scenario with the measurement nuisances and tyre draws of real
    data on (settings.REALISTIC)."""

    name: str = "custom"
    description: str = ""
    trajectory: TrajectoryConfig = TrajectoryConfig()
    later_sessions: tuple[SessionConfig, ...] = Field(
        (), description="later sessions of the same field, in order (a season; the first session is "
                        "`trajectory`, at clock 0): {gap: s, start: [x, y, yaw_deg], segments, accel_limit, gnss}")
    terrain: TerrainConfig = TerrainConfig()
    soil: WorldSoil = WorldSoil()
    effects: dict[str, dict | bool] = Field(default_factory=dict, description="{id: {form, k, ...}} or {id: "
                                                                             "true} (synth.effects)")
    landmarks: LandmarkConfig = LandmarkConfig()
    lidar: LidarConfig = LidarConfig()
    world: WorldConfig = WorldConfig()
    robot: str = Field("paper_platform", description="robot name (shipped) or YAML path")
    tyre: TyreConfig = TyreConfig()
    measurement: MeasurementConfig = MeasurementConfig()

    def realistic(self) -> SynthConfig:
        """A copy with settings.REALISTIC's measurement nuisances and tyre draws."""
        return self.replace(**REALISTIC)


# ---------------------------------------------------------------------------- many recordings
class FleetConfig(Section):
    """What each task of a many-recordings run (torchsoil.jobs.fleet) asks of a machine: one task per
    recording (or per study drive). A Ray cluster schedules tasks by these requests; the local
    engine starts at most as many workers as the cores and available memory hold."""

    cpus_per_task: int = Field(1, ge=1, description="CPU cores per task, also its torch and numba threads, cores")
    memory_mb_per_task: int = Field(2000, ge=0, description="memory reserved per task (Ray's `memory` resource; "
                                                            "local workers <= available memory / this), MiB; "
                                                            "0: no reservation")
    retries: int = Field(0, ge=0, description="times a task whose worker process died is started again (an "
                                              "error raised by the task is not retried; rerun the command), -")


# ---------------------------------------------------------------------------- on the robot
class NodeConfig(Section):
    """The live ROS node (torchsoil.node): what it publishes and how it stays bounded."""

    queue: int = Field(10, ge=1, description="sweeps of each lidar waiting to be processed at most; the oldest is "
                                            "dropped (and said on /diagnostics) when the pipeline falls behind")
    map_rate: float = Field(1.0, ge=0, description="terrain near the robot published this often, Hz (0: never)")
    map_length: float = Field(6.0, gt=0, description="path behind the robot the published terrain covers, m")
    map_frame: str = Field("soil_map", description="frame of the published soil and terrain (the pipeline's map)")
    publish_tf: bool = Field(True, description="publish map_frame on /tf as a child of pipeline.read.base_frame")
    rut_full: float = Field(0.05, gt=0, description="rut depth shown as 100 in the OccupancyGrid, m")
    gridmap: Literal["auto", "on", "off"] = Field(
        "auto", description="publish grid_map_msgs/GridMap: auto where the ROS 2 package is installed")
    diagnostics_rate: float = Field(1.0, gt=0, description="/diagnostics published this often, Hz")
    silence: float = Field(1.0, gt=0, description="a lidar silent this long is a warning on /diagnostics, s")
    clock_jump: float = Field(1.0, gt=0, description="a lidar stamp this far before the last ends the drive "
                                                     "(a bag played again) and begins a new one, s")
    tensorboard: bool = Field(True, description="TensorBoard logs in the run folder, as `estimate`")
    reliable: bool = Field(False, description="ROS 2: lidars and IMU subscribed reliable (no sample lost; only "
                                              "reliable publishers match) instead of best-effort (matches both)")


# ---------------------------------------------------------------------------- the tree
class Settings(Section):
    """All of torchsoil's settings, one section per part."""

    sim: SimConfig = SimConfig()
    estimator: EstimatorConfig = EstimatorConfig()
    pipeline: PipelineConfig = PipelineConfig()
    diagnosis: DiagnosisConfig = DiagnosisConfig()
    env: EnvConfig = EnvConfig()
    synth: SynthConfig = SynthConfig()
    fleet: FleetConfig = Field(FleetConfig(), description="per task of a many-recordings run: cpus_per_task "
                                                          "cores, memory_mb_per_task MiB, retries")
    node: NodeConfig = Field(NodeConfig(), description="the live ROS node: queues, published terrain, diagnostics")

    def to_yaml(self, sections: Iterable[str] | None = None) -> str:
        """The settings as YAML, each leaf with its description (unit) as a comment."""
        return dump_yaml(self, sections)

    def fingerprint(self) -> dict:
        """JSON-ready dict of every value (for run.json)."""
        return self.model_dump(mode="json")


def merge(base: dict, top: dict) -> dict:
    """Mappings merged key by key (recursively); anything else in `top` replaces."""
    out = copy.deepcopy(base)
    for key, value in (top or {}).items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def parse_override(text: str) -> dict:
    """'estimator.window=1.0' -> {'estimator': {'window': 1.0}} (the value parsed as YAML)."""
    if "=" not in text:
        raise SettingsError(f"override {text!r} must look like section.key=value")
    path, value = text.split("=", 1)
    keys = [k for k in path.strip().split(".")]
    if not all(keys):
        raise SettingsError(f"override {text!r}: empty key in {path!r}")
    try:
        node: object = yaml.safe_load(value)
    except yaml.YAMLError as e:
        raise SettingsError(f"override {text!r}: value is not valid YAML ({e})") from None
    for k in reversed(keys):
        node = {k: node}
    return node  # type: ignore[return-value]


def read_yaml(path: str | Path) -> dict:
    """A YAML file as a mapping (empty file: {}); clear errors for a missing or bad file."""
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"settings file not found: {path}") from None
    except yaml.YAMLError as e:
        raise SettingsError(f"{path}: not valid YAML ({e})") from None
    if doc is None:
        return {}
    if not isinstance(doc, dict):
        raise SettingsError(f"{path}: must be a mapping of sections, got {type(doc).__name__}")
    return doc


def validate(model: type[Section], doc: dict, source: str = "settings", prefix: str = ""):
    """model.model_validate(doc) with errors that name the key and the source."""
    try:
        return model.model_validate(doc)
    except ValidationError as e:
        raise SettingsError(f"{source}: " + "; ".join(_describe(model, err, prefix) for err in e.errors())) \
            from None


def load_settings(*sources: str | Path | dict | None, overrides: Iterable[str] = ()) -> Settings:
    """Defaults, then each YAML path or dict in `sources` (in order), then `overrides`
    ('section.key=value', repeatable). Unknown keys and wrong types raise SettingsError."""
    doc: dict = Settings().model_dump()
    names = []
    for src in sources:
        if src is None:
            continue
        if isinstance(src, dict):
            doc, name = merge(doc, src), "settings dict"
        else:
            doc, name = merge(doc, read_yaml(src)), str(src)
        names.append(name)
    for text in overrides:
        doc = merge(doc, parse_override(text))
        names.append(f"--set {text}")
    return validate(Settings, doc, " + ".join(names) or "settings")


def _describe(model: type[BaseModel], err: dict, prefix: str) -> str:
    loc = [str(p) for p in err["loc"]]
    key = prefix + ".".join(loc)
    if err["type"] == "extra_forbidden":
        known = _known_keys(model, err["loc"][:-1])
        return f"unknown setting `{key}`" + (f" (known here: {', '.join(known)})" if known else "")
    value = err.get("input")
    shown = repr(value) if not isinstance(value, dict) else "a mapping"
    return f"`{key}` = {shown}: {err['msg']}"


def _known_keys(model: type[BaseModel], loc) -> list[str]:
    """Field names of the section at `loc` inside `model` (empty when it is not a section)."""
    node = model
    for part in loc:
        field = node.model_fields.get(str(part)) if isinstance(node, type) and issubclass(node, BaseModel) \
            else None
        if field is None:
            return []
        node = field.annotation
    if isinstance(node, type) and issubclass(node, BaseModel):
        return list(node.model_fields)
    return []


def dump_yaml(model: BaseModel, sections: Iterable[str] | None = None, indent: int = 0) -> str:
    """YAML of a settings model with each field's description as a comment."""
    lines: list[str] = []
    names = list(sections) if sections is not None else list(type(model).model_fields)
    for name in names:
        if name not in type(model).model_fields:
            raise SettingsError(f"no settings section `{name}`; known: {', '.join(type(model).model_fields)}")
        info = type(model).model_fields[name]
        value = getattr(model, name)
        pad = " " * indent
        comment = f"  # {info.description}" if info.description else ""
        if isinstance(value, BaseModel) and not _is_small(value):
            lines.append(f"{pad}{name}:{comment}")
            lines.append(dump_yaml(value, indent=indent + 2).rstrip("\n"))
        else:
            plain = value.model_dump(mode="json") if isinstance(value, BaseModel) else _jsonable(value)
            text = yaml.safe_dump(plain, default_flow_style=True, width=10_000, sort_keys=False).strip()
            if text.endswith("\n...") or text.endswith("..."):
                text = text.rsplit("\n", 1)[0].strip()
            lines.append(f"{pad}{name}: {text}{comment}")
    return "\n".join(lines) + "\n"


def _is_small(value: BaseModel) -> bool:
    """Sections of a few plain numbers print on one line ({d: .., chi: .., beta: ..})."""
    fields = type(value).model_fields
    return len(fields) <= 4 and all(not isinstance(getattr(value, f), (BaseModel, dict, list, tuple))
                                    for f in fields)


def _jsonable(value):
    if isinstance(value, BaseModel):
        return value.model_dump(mode="json")
    if isinstance(value, (tuple, list)):
        return [_jsonable(v) for v in value]
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, float) and math.isinf(value):
        return ".inf"
    return value
