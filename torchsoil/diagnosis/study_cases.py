"""Short synthetic drives (10-15 m) for the diagnosis study and its tests: one per catalogue effect, a
null case (base physics, soil varying along the path), an out-of-catalogue effect no law
explains (tread) and the out-of-catalogue laws a learned modifier names (speed_deposit,
turn_scrub, pass_loosening: effects.LEARNED; expected id "learned") (STUDY_CASES); and a
randomized study (`randomized_cases`): random effect, law form and magnitude, drive shape
(revisits of every shape for hardening and loosening), soil, tyre and measurement nuisances,
plus null drives.

`world.chunk` is 0.1 m: what the recorder's world evaluates per chunk (the footprint width's
sinkage, the visits) changes in 0.1 m steps rather than its default 0.4 m.
"""

from __future__ import annotations

import copy

import numpy as np

from torchsoil.settings import REALISTIC
from torchsoil.synth import effects as fx

STRAIGHT = {"segments": [{"straight": 14.0, "speed": 1.0}]}


def _lane_change(side: int) -> list[dict]:
    """Two opposite 37 deg arcs of 1.25 m radius: 0.5 m sideways (half a track) over 1.5 m."""
    return [{"arc": 1.25, "angle_deg": 37 * side, "speed": 1.0}, {"arc": 1.25, "angle_deg": -37 * side, "speed": 1.0}]


# back along the first leg, on and off its tracks four times: pass-count changes are the only
# lever a per-window sinkage leaves a hardening term, and one revisit gives just two of them
WEAVE = [{"straight": 0.8, "speed": 1.0}]
for _side in (1, -1, 1, -1):
    WEAVE += _lane_change(_side) + [{"straight": 0.8, "speed": 1.0}]
WORLD = {"chunk": 0.1}

SCENARIOS: dict[str, dict] = {
    "speed_dependent_sinkage": {
        "trajectory": {"accel_limit": 1.0, "segments": [
            {"straight": 2.0, "speed": 1.0}, {"straight": 2.0, "speed": 0.5}, {"straight": 2.0, "speed": 1.5},
            {"straight": 2.0, "speed": 0.6}, {"straight": 2.0, "speed": 1.4}, {"straight": 2.0, "speed": 0.5},
            {"straight": 2.0, "speed": 1.5}]},
        "soil": {"base": {"d": 0.025, "chi": 0.2, "beta_deg": 30.0}},
        "effects": {"speed_dependent_sinkage": {"form": "linear", "k": 0.6}}},
    "slip_sinkage": {
        "trajectory": {"accel_limit": 0.4, "segments": [
            {"straight": 2.5, "speed": 0.6}, {"straight": 2.5, "speed": 1.4}, {"straight": 2.5, "speed": 0.6},
            {"straight": 2.5, "speed": 1.4}, {"straight": 2.5, "speed": 0.6}, {"straight": 2.5, "speed": 1.4}]},
        "terrain": {"relief": {"amplitude": 0.02, "slope_x": 0.06}},
        "soil": {"base": {"d": 0.025, "chi": 0.2, "beta_deg": 30.0}},
        "effects": {"slip_sinkage": {"form": "linear", "k": 6.0}}},
    "lateral_load_transfer": {
        "trajectory": {"segments": [
            {"straight": 1.0, "speed": 1.0}, {"arc": 3.0, "angle_deg": 40, "speed": 1.0},
            {"arc": 3.0, "angle_deg": -80, "speed": 1.0}, {"arc": 3.0, "angle_deg": 40, "speed": 1.0},
            {"straight": 1.0, "speed": 1.0}]},
        "terrain": {"relief": {"amplitude": 0.02, "slope_y": 0.08}},
        "soil": {"base": {"d": 0.025, "chi": 0.2, "beta_deg": 30.0}},
        "effects": {"lateral_load_transfer": {"form": "linear", "k": 1.5}}},
    "multi_pass_hardening": {
        "trajectory": {"segments": [
            {"straight": 10.0, "speed": 1.0}, {"arc": 1.5, "angle_deg": 180, "speed": 0.8},
            {"straight": 10.0, "speed": 1.0}, {"arc": 1.5, "angle_deg": 180, "speed": 0.8}] + WEAVE},
        "soil": {"base": {"d": 0.025, "chi": 0.25, "beta_deg": 28.0, "moisture": 0.3}},
        "effects": {"multi_pass_hardening": {"form": "saturating", "k": -0.6}}},
    "cohesive_walls": {
        "trajectory": STRAIGHT,
        "soil": {"base": {"d": 0.04, "chi": 0.3, "beta_deg": 22.0, "moisture": 0.5}},
        "effects": {"cohesive_walls": {"form": "saturating", "k": 1.0, "c0": 0.5}}},
    "footprint_width": {
        "trajectory": STRAIGHT,
        "soil": {"base": {"d": 0.02, "chi": 0.2, "beta_deg": 28.0},
                 "patches": [{"kind": "band_x", "center": 7.0, "sigma": 2.0, "delta": {"d": 0.02}}]},
        "effects": {"footprint_width": {"form": "linear", "k": 0.6}}},
    "watered": {
        "trajectory": STRAIGHT,
        "soil": {"base": {"d": 0.015, "chi": 0.05, "beta_deg": 25.0, "moisture": 0.2},
                 "patches": [{"kind": "band_x", "center": 7.0, "sigma": 2.0,
                              "delta": {"d": 0.035, "beta_deg": 15.0, "moisture": 0.7, "chi": 0.15}}],
                 "track_scale": [1.0, 1.1]}},
    "tread": {
        "trajectory": STRAIGHT,
        "soil": {"base": {"d": 0.025, "chi": 0.2, "beta_deg": 30.0}},
        "effects": {"tread": {"amp": 0.007, "wavelength": 0.2}}},
    # out of catalogue, learned: chi follows the speed; d follows |turn rate|; beta follows the passes
    "speed_deposit": {
        "trajectory": {"accel_limit": 1.0, "segments": [
            {"straight": 2.0, "speed": 1.0}, {"straight": 2.0, "speed": 0.5}, {"straight": 2.0, "speed": 1.5},
            {"straight": 2.0, "speed": 0.6}, {"straight": 2.0, "speed": 1.4}, {"straight": 2.0, "speed": 0.5},
            {"straight": 2.0, "speed": 1.5}]},
        "soil": {"base": {"d": 0.03, "chi": 0.25, "beta_deg": 30.0}},
        "effects": {"speed_deposit": {"form": "linear", "k": 0.8}}},
    "turn_scrub": {
        "trajectory": {"segments": [
            {"straight": 1.5, "speed": 1.0}, {"arc": 1.5, "angle_deg": 90, "speed": 1.0},
            {"straight": 1.5, "speed": 1.0}, {"arc": 4.0, "angle_deg": -60, "speed": 1.0},
            {"straight": 1.5, "speed": 1.0}, {"arc": 2.0, "angle_deg": -90, "speed": 1.0},
            {"straight": 1.5, "speed": 1.0}]},
        "soil": {"base": {"d": 0.025, "chi": 0.2, "beta_deg": 30.0}},
        "effects": {"turn_scrub": {"form": "linear", "k": 0.6, "r_ref": 0.5}}},
    "pass_loosening": {
        "trajectory": {"segments": [
            {"straight": 10.0, "speed": 1.0}, {"arc": 1.5, "angle_deg": 180, "speed": 0.8},
            {"straight": 10.0, "speed": 1.0}, {"arc": 1.5, "angle_deg": 180, "speed": 0.8}] + WEAVE},
        "soil": {"base": {"d": 0.04, "chi": 0.25, "beta_deg": 30.0, "moisture": 0.3}},
        "effects": {"pass_loosening": {"form": "linear", "k": -0.3}}},
}

# the extension coefficient that matches each world law near its operating point
TRUTH = {"speed_dependent_sinkage": ("k_speed", 0.6), "slip_sinkage": ("k_slip", 6.0),
         "lateral_load_transfer": ("k_lateral", 1.8), "multi_pass_hardening": ("k_pass", -0.457),
         "cohesive_walls": ("k_wall", 0.76), "footprint_width": ("k_width", 0.3)}


def scenario(name: str, **effect_overrides) -> dict:
    """A copy of SCENARIOS[name] with world chunk 0.1 m and the effect's law overridden."""
    sc = copy.deepcopy(SCENARIOS[name])
    sc["name"] = name
    sc["world"] = dict(WORLD)
    if effect_overrides:
        (eid, law), = sc["effects"].items()
        sc["effects"] = {eid: {**law, **effect_overrides}}
    return sc


# (case name, scenario, seed, expected verdict, expected id): the confusion-table study
STUDY_CASES: list[tuple[str, dict, int, str, str | None]] = [
    ("speed linear", scenario("speed_dependent_sinkage"), 1, "missing_physics", "speed_dependent_sinkage"),
    ("speed power 0.5", scenario("speed_dependent_sinkage", form="power", p=0.5), 2, "missing_physics",
     "speed_dependent_sinkage"),
    ("speed saturating", scenario("speed_dependent_sinkage", form="saturating", k=0.8, x_s=0.3), 3,
     "missing_physics", "speed_dependent_sinkage"),
    ("slip linear", scenario("slip_sinkage"), 1, "missing_physics", "slip_sinkage"),
    ("slip saturating", scenario("slip_sinkage", form="saturating", k=8.0, x_s=0.03), 2, "missing_physics",
     "slip_sinkage"),
    ("slip power 1.5", scenario("slip_sinkage", form="power", p=1.5, k=40.0), 3, "missing_physics", "slip_sinkage"),
    ("lateral linear", scenario("lateral_load_transfer"), 1, "missing_physics", "lateral_load_transfer"),
    ("lateral saturating", scenario("lateral_load_transfer", form="saturating", k=2.0, x_s=0.1), 2,
     "missing_physics", "lateral_load_transfer"),
    ("lateral power 0.7", scenario("lateral_load_transfer", form="power", p=0.7, k=1.0), 3, "missing_physics",
     "lateral_load_transfer"),
    ("passes saturating", scenario("multi_pass_hardening"), 1, "missing_physics", "multi_pass_hardening"),
    ("passes linear", scenario("multi_pass_hardening", form="linear", k=-0.4), 2, "missing_physics",
     "multi_pass_hardening"),
    ("passes power 2", scenario("multi_pass_hardening", form="power", p=2.0, k=-0.5), 3, "missing_physics",
     "multi_pass_hardening"),
    ("walls saturating", scenario("cohesive_walls"), 1, "missing_physics", "cohesive_walls"),
    ("walls linear", scenario("cohesive_walls", form="linear", k=0.8), 2, "missing_physics", "cohesive_walls"),
    ("width linear", scenario("footprint_width"), 1, "missing_physics", "footprint_width"),
    ("width saturating", scenario("footprint_width", form="saturating", k=0.8, x_s=0.8), 2, "missing_physics",
     "footprint_width"),
    ("watered seed 1", scenario("watered"), 1, "adequate", None),
    ("watered seed 2", scenario("watered"), 2, "adequate", None),
    ("watered seed 3", scenario("watered"), 3, "adequate", None),
    ("tread seed 1", scenario("tread"), 1, "unexplained", None),
    ("tread seed 2", scenario("tread", wavelength=0.3), 2, "unexplained", None),
    # out of catalogue, a learned modifier names them: parameter, covariate and direction come
    # from the law (effects.expected), the study scores them (study.learned_match)
    ("deposit linear", scenario("speed_deposit"), 1, "missing_physics", "learned"),
    ("deposit saturating falling", scenario("speed_deposit", form="saturating", k=-1.0, x_s=0.4), 2,
     "missing_physics", "learned"),
    ("scrub linear", scenario("turn_scrub"), 1, "missing_physics", "learned"),
    ("scrub threshold", scenario("turn_scrub", form="threshold", k=1.2, x_s=0.5), 2, "missing_physics", "learned"),
    ("loosening linear", scenario("pass_loosening"), 1, "missing_physics", "learned"),
    ("loosening saturating rising", scenario("pass_loosening", form="saturating", k=0.4, x_s=0.8), 2,
     "missing_physics", "learned"),
]


# ---------------------------------------------------------------------------- randomized study
# typical covariate size |x0| of each effect on the drives below, and the range of the linear
# coefficient k_lin: a law of any form is scaled so that k phi(x0) = k_lin x0 (the same effect
# at the typical covariate, other shapes around it)
LAWS = {"speed_dependent_sinkage": (0.5, (0.3, 0.8)), "slip_sinkage": (0.08, (4.0, 8.0)),
        "lateral_load_transfer": (0.14, (1.0, 2.0)), "multi_pass_hardening": (1.0, (-0.6, -0.3)),
        "cohesive_walls": (1.0, (0.5, 1.0)), "footprint_width": (0.6, (0.4, 0.8))}
KINDS = (*LAWS, "tread")
# the out-of-catalogue laws a learned modifier names (effects.LEARNED), the same way: typical
# |x0| and the range of k_lin, whose sign flips for half the laws that may go either way
LEARNED_LAWS = {"speed_deposit": (0.5, (0.5, 1.0)), "turn_scrub": (1.0, (0.3, 0.8)),
                "pass_loosening": (1.0, (-0.4, -0.2))}
EITHER_WAY = ("speed_deposit", "pass_loosening")
LEARNED_KINDS = tuple(LEARNED_LAWS)
REVISITS = ("out_and_back", "loop", "stadium", "lane_changes")


def random_law(rng: np.random.Generator, eid: str) -> dict:
    """An effect law of a random form (effects.FORMS) and magnitude for effect `eid`."""
    if eid == "tread":
        return {"amp": float(rng.uniform(0.004, 0.008)), "wavelength": float(rng.uniform(0.06, 0.3))}
    x0, k_range = LAWS[eid] if eid in LAWS else LEARNED_LAWS[eid]
    form = str(rng.choice(fx.FORMS))
    law = {"form": form, "p": float(rng.uniform(0.5, 2.0)) if form == "power" else 1.0,
           "x_s": float(x0 * (rng.uniform(0.5, 1.5) if form == "saturating" else rng.uniform(0.2, 0.5)))}
    law["k"] = float(rng.uniform(*k_range) * x0 / fx.phi(x0, form, law["p"], law["x_s"]))
    if eid == "cohesive_walls":
        law["c0"] = float(rng.uniform(0.3, 1.0))
    if eid in EITHER_WAY and rng.random() < 0.5:
        law["k"] = -law["k"]
    return law


def random_path(rng: np.random.Generator, kind: str) -> dict:
    """`trajectory` and `terrain.relief` of a random drive of one kind (lengths in m, speeds
    m/s, angles deg): speed_steps, slope_speed (climbing with speed changes), s_turns (on a
    side slope), the revisits out_and_back (light-bulb turn back onto the same ruts), loop (round
    and over the start again), stadium (a stadium loop driven twice: all its ground twice),
    lane_changes (back along the first leg, on and off its ruts), turns (level ground, straights
    between turns of 1.5 to 4 m radius either way: the turn rate changes, the roll does not),
    or plain (straight or a gentle curve at one speed)."""
    u = rng.uniform
    relief = {"amplitude": float(u(0.01, 0.05))}
    if kind == "speed_steps":
        speeds = [float(u(0.4, 0.7)) if i % 2 else float(u(1.2, 1.6)) for i in range(int(rng.integers(6, 9)))]
        segs, accel = [{"straight": float(u(1.8, 2.5)), "speed": v} for v in speeds], 1.0
    elif kind == "slope_speed":
        speeds = [float(u(0.5, 0.7)) if i % 2 else float(u(1.3, 1.5)) for i in range(6)]
        segs, accel = [{"straight": 2.5, "speed": v} for v in speeds], 0.4
        relief["slope_x"] = float(rng.choice([-1, 1]) * u(0.04, 0.08))
    elif kind == "s_turns":
        r, a = float(u(2.5, 4.0)), float(u(30.0, 45.0) * rng.choice([-1, 1]))
        segs = [{"straight": 1.0}, {"arc": r, "angle_deg": a}, {"arc": r, "angle_deg": -2 * a},
                {"arc": r, "angle_deg": 2 * a}, {"arc": r, "angle_deg": -a}, {"straight": 1.0}]
        segs, accel = [{**s, "speed": 1.0} for s in segs], 0.5
        relief["slope_y"] = float(rng.choice([-1, 1]) * u(0.05, 0.1))
    elif kind == "out_and_back":
        # a light-bulb turn (60 deg one way, 300 deg the other, 60 deg, one radius) ends on the
        # line it left, heading back: both tracks return on the ruts (left and right swapped)
        r, side, leg = float(u(1.5, 2.0)), int(rng.choice([-1, 1])), float(u(6.0, 8.0))
        segs = [{"straight": leg}, {"arc": r, "angle_deg": -60 * side}, {"arc": r, "angle_deg": 300 * side},
                {"arc": r, "angle_deg": -60 * side}, {"straight": leg}]
        segs, accel = [{**s, "speed": float(u(0.8, 1.0))} for s in segs], 0.5
    elif kind == "loop":
        r, leg = float(u(1.5, 2.5)), float(u(5.0, 7.0))
        segs = [{"straight": leg}, {"arc": r, "angle_deg": 180}, {"straight": leg}, {"arc": r, "angle_deg": 180},
                {"straight": float(u(3.0, leg))}]
        segs, accel = [{**s, "speed": float(u(0.8, 1.0))} for s in segs], 0.5
    elif kind == "stadium":
        r, leg = float(u(1.5, 2.0)), float(u(3.0, 4.0))
        lap = [{"straight": leg}, {"arc": r, "angle_deg": 180}, {"straight": leg}, {"arc": r, "angle_deg": 180}]
        segs, accel = [{**s, "speed": float(u(0.8, 1.0))} for s in lap + lap], 0.5
    elif kind == "lane_changes":
        leg = float(u(5.0, 7.0))
        segs = [{"straight": leg, "speed": 1.0}, {"arc": 1.5, "angle_deg": 180, "speed": 0.8},
                {"straight": leg, "speed": 1.0}, {"arc": 1.5, "angle_deg": 180, "speed": 0.8}] + WEAVE
        accel = 0.5
    elif kind == "turns":
        segs = [{"straight": float(u(1.0, 2.0))}]
        for side in rng.permutation([1, -1, 1, -1]):
            segs += [{"arc": float(u(1.5, 4.0)), "angle_deg": float(side * u(45.0, 100.0))},
                     {"straight": float(u(1.0, 2.0))}]
        segs, accel = [{**s, "speed": float(u(0.8, 1.0))} for s in segs], 0.5
        relief = {"amplitude": float(u(0.005, 0.02))}
    elif kind == "plain":
        v = float(u(0.7, 1.3))
        segs = [{"straight": float(u(12.0, 16.0)), "speed": v}] if rng.random() < 0.5 else [
            {"straight": 2.0, "speed": v}, {"arc": float(u(10.0, 20.0)), "angle_deg": float(u(-40, 40)), "speed": v},
            {"straight": 4.0, "speed": v}]
        accel = 0.5
    else:
        raise ValueError(f"unknown path kind {kind!r}")
    return {"trajectory": {"segments": segs, "accel_limit": accel}, "relief": relief}


# soil of a random drive (d m, chi -, beta_deg deg, moisture -), and where an effect needs
# other soil to show at all: walls only stand steeper than the angle of repose where the dug
# slope exceeds it (at most d pi / wheel_width for the cosine taper: 0.015 m ruts under the
# 0.14 m wheel slope by 19 deg, nothing to slump at 30 deg; 0.035 m ones by 38 deg)
SOIL = {"d": (0.015, 0.035), "chi": (0.1, 0.35), "beta_deg": (24.0, 34.0), "moisture": (0.0, 0.5)}
# (the same for an angle of repose that changes with the passes, and a deposit share that
# has room to change)
SOIL_FOR = {"cohesive_walls": {"d": (0.035, 0.05), "beta_deg": (20.0, 28.0)},
            "pass_loosening": {"d": (0.03, 0.045), "beta_deg": (24.0, 32.0)},
            "speed_deposit": {"chi": (0.2, 0.4)}}
PATH_FOR = {"speed_dependent_sinkage": ("speed_steps",), "slip_sinkage": ("slope_speed",),
            "lateral_load_transfer": ("s_turns",), "multi_pass_hardening": REVISITS,
            "speed_deposit": ("speed_steps",), "turn_scrub": ("turns",), "pass_loosening": REVISITS}
PATHS = ("speed_steps", "slope_speed", "s_turns", *REVISITS, "plain")   # null drives' (turns: not, to keep their draws)


def random_case(seed: int, kind: str | None) -> tuple[str, dict, int, str, str | None]:
    """One randomized study case (name, scenario dict, seed, expected verdict, expected id):
    effect `kind` (an id of KINDS; None: no missing physics) with a random law, on a random
    drive that lets it show (nulls: any drive), random soil with a patch of other soil, and
    the measurement nuisances and tyre draws of real data (settings.REALISTIC) on."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 12]))
    paths = PATH_FOR.get(kind, ("plain",)) if kind is not None else PATHS
    path_kind = str(rng.choice(paths))
    path = random_path(rng, path_kind)
    ranges = {**SOIL, **SOIL_FOR.get(kind, {})}
    base = {key: float(rng.uniform(*ranges[key])) for key in ("d", "chi", "beta_deg", "moisture")}
    patch = {"kind": "band_x", "center": float(rng.uniform(3.0, 10.0)), "sigma": float(rng.uniform(1.0, 3.0)),
             "delta": {"d": float(rng.uniform(0.005, 0.02) if kind == "footprint_width" else rng.uniform(-0.005, 0.02)),
                       "beta_deg": float(rng.uniform(-5.0, 5.0))}}
    sc = {"name": f"r{seed:04d}", "trajectory": path["trajectory"], "terrain": {"relief": path["relief"]},
          "soil": {"base": base, "patches": [patch]}, "world": dict(WORLD), **copy.deepcopy(REALISTIC)}
    if kind is not None:
        law = random_law(rng, kind)
        sc["effects"] = {kind: law}
        form = law.get("form", "tread")
        verdict, eid = (("unexplained", None) if kind == "tread" else ("missing_physics", "learned")
                        if kind in fx.LEARNED else ("missing_physics", kind))
    else:
        form, verdict, eid = "-", "adequate", None
    return f"r{seed:04d} {kind or 'null'} {form} {path_kind}", sc, int(seed), verdict, eid


def randomized_cases(n: int, n_null: int = 20, seed: int = 0, n_learned: int = 0
                     ) -> list[tuple[str, dict, int, str, str | None]]:
    """n drives with an effect (the KINDS in turn: every catalogue id and the out-of-catalogue
    tread come up once n >= 7), n_learned drives with an out-of-catalogue law a learned
    modifier names (the LEARNED_KINDS in turn: each comes up once n_learned >= 3; expected id
    "learned") and n_null drives without, in that order. Effect case i has seed
    1000 * seed + i, learned case j 1000 * seed + 499 - j (counting down, so that neither list
    moves the other: n + n_learned <= 500), null case j 1000 * seed + 500 + j: a longer study
    extends a shorter one, and the cases of a study without learned drives are those of one
    with them."""
    if not (0 <= n and 0 <= n_learned and n + n_learned <= 500 and 0 <= n_null <= 500):
        raise ValueError(f"at most 500 effect (with the learned) and 500 null drives per study seed, got {n} "
                         f"(and {n_learned} learned) and {n_null}")
    return ([random_case(1000 * seed + i, KINDS[i % len(KINDS)]) for i in range(n)]
            + [random_case(1000 * seed + 499 - j, LEARNED_KINDS[j % len(LEARNED_KINDS)]) for j in range(n_learned)]
            + [random_case(1000 * seed + 500 + j, None) for j in range(n_null)])


def revisit_cases(cases: list[tuple]) -> list[tuple]:
    """The cases (`randomized_cases`) whose drive comes back over its own ruts (REVISITS): every
    hardening and loosening drive and the null drives of those shapes."""
    return [c for c in cases if c[0].rsplit(" ", 1)[-1] in REVISITS]
