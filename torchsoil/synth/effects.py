"""Physics the base model leaves out: the catalogue effects of docs/formats.md section 4 plus
out-of-catalogue ones, each a plausible law with its own parameters.

Every effect scales a base quantity by a factor 1 + k * phi(x) of a covariate x that is 0
under the base model's conditions, with a choosable functional form phi:

    linear:      phi(x) = x
    power:       phi(x) = sign(x) |x|^p
    saturating:  phi(x) = x_s * tanh(x / x_s)        (linear near 0, bounded by +-x_s)
    threshold:   phi(x) = sign(x) max(|x| - x_s, 0)  (no effect within +-x_s, linear beyond)

| id | covariate x | scaled quantity |
| --- | --- | --- |
| multi_pass_hardening | pass index - 1 (0 on the first; wheel passes if they dig in turn) | sinkage d (k < 0: harder) |
| speed_dependent_sinkage | v / v_ref - 1 | sinkage d |
| slip_sinkage | traction demand a / g + sin(grade) | sinkage d |
| lateral_load_transfer | per wheel -side * 2 h_cg / track * (a_lat / g + sin(roll)) | sinkage d of that wheel |
| cohesive_walls | c0 + soil moisture | tan(beta) where the ground has not moved (native, cut; moved soil: beta) |
| footprint_width | local d / d_ref | footprint radius |
| tread (out of catalogue) | wheel arc length s | extra floor depth amp (1 + cos(2 pi s / wavelength)) / 2 |
| speed_deposit (out of catalogue) | v / v_ref - 1 | deposit share chi, within [0, 1] |
| turn_scrub (out of catalogue) | abs(yaw rate) / r_ref | sinkage d |
| pass_loosening (out of catalogue) | passes before (0 on the first) | angle of repose beta, within 89 deg |

The last three are laws outside the catalogue that a learned modifier exp(f(covariate)) on one
model parameter can describe (LEARNED: the parameter and the covariate, in the learned stage's
names; its direction is the sign of k, phi rising with x): a correct diagnosis names them
`missing_physics: learned` with that parameter, covariate and direction (`expected`). tread
is not such a law (the verdict is `unexplained`). pass_loosening counts, like hardening under
dig order "robot", the visits before whose footprints covered the cell, and sets the angle the
visit's digs relax to (in cohesive soil the moved soil's; the intact ground keeps its own).
"""

from __future__ import annotations

import math

import numpy as np

CATALOGUE = ("multi_pass_hardening", "speed_dependent_sinkage", "slip_sinkage",
             "lateral_load_transfer", "cohesive_walls", "footprint_width")
# out-of-catalogue laws a learned modifier describes: (parameter, covariate) it acts on and follows
LEARNED: dict[str, tuple[str, str]] = {"speed_deposit": ("chi", "speed"), "turn_scrub": ("d", "turn_rate"),
                                       "pass_loosening": ("beta", "passes")}
OUT_OF_CATALOGUE = ("tread", *LEARNED)
EFFECTS = CATALOGUE + OUT_OF_CATALOGUE
FORMS = ("linear", "power", "saturating", "threshold")
# what a diagnosis should find for each effect (docs/formats.md section 4 `where`): the signal the
# mismatch follows and where across the track it shows
SIGNATURES: dict[str, dict] = {
    "multi_pass_hardening": {"covariate": "pass_count", "cross_track": "rut_floor"},
    "speed_dependent_sinkage": {"covariate": "speed", "cross_track": "rut_floor"},
    "slip_sinkage": {"covariate": "traction_demand", "cross_track": "rut_floor"},
    "lateral_load_transfer": {"covariate": "lateral_load", "cross_track": "rut_floor"},
    "cohesive_walls": {"covariate": None, "cross_track": "rut_wall"},
    "footprint_width": {"covariate": None, "cross_track": "rut_wall"},
    "tread": {"covariate": "along_track_period", "cross_track": "rut_floor"},
    "speed_deposit": {"covariate": "speed", "cross_track": "berm"},
    "turn_scrub": {"covariate": "turn_rate", "cross_track": "rut_floor"},
    "pass_loosening": {"covariate": "passes", "cross_track": "rut_wall"},
}
G = 9.81  # m/s^2

DEFAULTS: dict[str, dict] = {
    "multi_pass_hardening": {"form": "saturating", "k": -0.6, "p": 1.0, "x_s": 1.0},
    "speed_dependent_sinkage": {"form": "linear", "k": 0.6, "p": 1.0, "x_s": 0.5, "v_ref": 1.0},
    "slip_sinkage": {"form": "linear", "k": 6.0, "p": 1.0, "x_s": 0.1},
    "lateral_load_transfer": {"form": "linear", "k": 1.5, "p": 1.0, "x_s": 0.5, "h_cg": 0.6},
    "cohesive_walls": {"form": "linear", "k": 0.8, "p": 1.0, "x_s": 1.0, "c0": 1.0},
    "footprint_width": {"form": "linear", "k": 0.5, "p": 1.0, "x_s": 1.0, "d_ref": 0.05},
    "tread": {"amp": 0.007, "wavelength": 0.2},
    "speed_deposit": {"form": "linear", "k": 0.8, "p": 1.0, "x_s": 0.5, "v_ref": 1.0},
    "turn_scrub": {"form": "linear", "k": 0.6, "p": 1.0, "x_s": 1.0, "r_ref": 0.5},
    "pass_loosening": {"form": "linear", "k": -0.3, "p": 1.0, "x_s": 1.0},
}


def phi(x, form: str, p: float = 1.0, x_s: float = 1.0) -> np.ndarray:
    """The shape function of an effect law (see module docstring); x any array."""
    x = np.asarray(x, dtype=np.float64)
    if form == "linear":
        return x
    if form == "power":
        return np.sign(x) * np.abs(x) ** p
    if form == "saturating":
        return x_s * np.tanh(x / x_s)
    if form == "threshold":
        return np.sign(x) * np.maximum(np.abs(x) - x_s, 0.0)
    raise ValueError(f"effect form must be one of {FORMS}, got {form!r}")


def factor(x, params: dict, lo: float = 0.05, hi: float = 10.0) -> np.ndarray:
    """1 + k * phi(x), clipped to [lo, hi]."""
    f = 1.0 + params["k"] * phi(x, params["form"], params["p"], params["x_s"])
    return np.clip(f, lo, hi)


def resolve(effects: dict | None) -> dict[str, dict]:
    """Scenario `effects` section -> {id: full parameter dict} of the effects switched on.

    Accepts `{id: {param: value, enabled: bool}}` or `{id: true}`; unknown ids or parameters
    raise ValueError naming them."""
    out = {}
    for name, params in (effects or {}).items():
        if name not in EFFECTS:
            raise ValueError(f"unknown effect {name!r}; known: {EFFECTS}")
        if params is False or params is None:
            continue
        params = {} if params is True else dict(params)
        if not params.pop("enabled", True):
            continue
        unknown = set(params) - set(DEFAULTS[name])
        if unknown:
            raise ValueError(f"effect {name}: unknown parameters {sorted(unknown)}; "
                             f"known: {sorted(DEFAULTS[name])}")
        full = DEFAULTS[name] | params
        if "form" in full and full["form"] not in FORMS:
            raise ValueError(f"effect {name}: form must be one of {FORMS}, got {full['form']!r}")
        out[name] = full
    return out


def pose_depth_factor(effects: dict[str, dict], speed, accel, pitch, roll, yaw_rate,
                      wheels_y: np.ndarray, track_width: float) -> np.ndarray:
    """Per-wheel, per-pose sinkage factor of the pose-driven effects.

    speed, accel [m/s, m/s^2], pitch, roll [rad], yaw_rate [rad/s]: (N,) at the poses;
    wheels_y: (K,) lateral wheel offsets, m. Returns (K, N) factors (1 without effects).
    """
    N, K = len(speed), len(wheels_y)
    f = np.ones((K, N))
    if "speed_dependent_sinkage" in effects:
        e = effects["speed_dependent_sinkage"]
        f = f * factor(np.asarray(speed) / e["v_ref"] - 1.0, e)[None]
    if "slip_sinkage" in effects:
        e = effects["slip_sinkage"]
        demand = np.asarray(accel) / G + np.sin(-np.asarray(pitch))   # climbing: pitch < 0
        f = f * factor(demand, e)[None]
    if "lateral_load_transfer" in effects:
        e = effects["lateral_load_transfer"]
        a_lat = np.asarray(speed) * np.asarray(yaw_rate)             # towards the turn centre
        side = np.sign(wheels_y)[:, None]                            # +1 left, -1 right
        shift = 2 * e["h_cg"] / track_width * (a_lat / G + np.sin(np.asarray(roll)))[None]
        f = f * factor(-side * shift, e)
    if "turn_scrub" in effects:
        e = effects["turn_scrub"]
        f = f * factor(np.abs(np.asarray(yaw_rate)) / e["r_ref"], e)[None]
    return f


def deposit_share(effects: dict[str, dict], chi, speed):
    """The deposit share where the soil is dug at travel speed `speed` [m/s] (arrays that
    broadcast): chi x factor(v / v_ref - 1) within [0, 1] under speed_deposit; chi itself
    (the same object) without it."""
    if "speed_deposit" not in effects:
        return chi
    e = effects["speed_deposit"]
    return np.clip(np.asarray(chi) * factor(np.asarray(speed) / e["v_ref"] - 1.0, e), 0.0, 1.0)


def repose_tan_beta(effects: dict[str, dict], beta: np.ndarray, tan_beta: np.ndarray, passes_before
                    ) -> np.ndarray:
    """tan of the angle of repose the digs of a visit relax to, for cells whose footprints
    covered them in `passes_before` earlier visits: tan(beta x factor(passes before)), beta
    [rad] within 89 deg, under pass_loosening; tan_beta itself (the same object) without it."""
    if "pass_loosening" not in effects:
        return tan_beta
    e = effects["pass_loosening"]
    b = np.asarray(beta) * factor(np.asarray(passes_before, dtype=np.float64), e)
    return np.tan(np.minimum(b, math.radians(89.0)))


def expected(effects: dict[str, dict]) -> dict:
    """What a correct diagnosis says of a world with these effects (`resolve`d), in the shape
    of a foreign truth's `expected` (docs/formats.md section 4): verdict, missing_physics,
    cross_track and covariate (SIGNATURES); for a learned law (LEARNED) missing_physics
    "learned" and also the parameter and the direction ("+" where the parameter grows with the
    covariate: k >= 0). With several effects the first catalogue one, else the first learned."""
    none = {"verdict": "adequate", "missing_physics": None, "cross_track": None, "covariate": None}
    cat = [e for e in effects if e in CATALOGUE]
    if cat:
        return {"verdict": "missing_physics", "missing_physics": cat[0], **SIGNATURES[cat[0]]}
    learned = [e for e in effects if e in LEARNED]
    if learned:
        eid = learned[0]
        return {"verdict": "missing_physics", "missing_physics": "learned", **SIGNATURES[eid],
                "parameter": LEARNED[eid][0], "direction": "-" if effects[eid]["k"] < 0 else "+"}
    return {**none, "verdict": "unexplained"} if effects else none


def pass_depth_factor(effects: dict[str, dict], pass_index: np.ndarray) -> np.ndarray | float:
    """Sinkage factor for cells visited for the pass_index-th time (1 = first)."""
    if "multi_pass_hardening" not in effects:
        return 1.0
    return factor(np.asarray(pass_index, dtype=np.float64) - 1.0, effects["multi_pass_hardening"])


def intact_tan_beta(effects: dict[str, dict], tan_beta: np.ndarray, moisture: np.ndarray) -> np.ndarray:
    """tan of the angle ground that has not moved (native, or cut by a wheel) stands up to:
    tan(beta) x factor(c0 + moisture), within 89 deg, in cohesive soil (whose moved soil settles
    at beta); tan(beta) without the effect."""
    if "cohesive_walls" not in effects:
        return tan_beta
    e = effects["cohesive_walls"]
    return np.minimum(tan_beta * factor(e["c0"] + moisture, e, lo=1.0),
                      math.tan(math.radians(89.0)))


def radius_scale(effects: dict[str, dict], d: float) -> float:
    """Footprint radius factor for local sinkage d [m], within [0.5, 1.5]."""
    if "footprint_width" not in effects:
        return 1.0
    e = effects["footprint_width"]
    return float(np.clip(factor(d / e["d_ref"], e), 0.5, 1.5))


def tread_depth(effects: dict[str, dict], arc: np.ndarray) -> np.ndarray | float:
    """Extra floor depth of a lugged tyre at wheel arc length `arc` [m] (0 without tread)."""
    if "tread" not in effects:
        return 0.0
    e = effects["tread"]
    return e["amp"] * 0.5 * (1.0 + np.cos(2 * math.pi * np.asarray(arc) / e["wavelength"]))
