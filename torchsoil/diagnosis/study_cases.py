"""Short synthetic drives (10-15 m) for the diagnosis study and its tests: one per catalogue effect, a
null case (base physics, soil varying along the path) and an out-of-catalogue effect.

`world.chunk` is 0.1 m: the recorder's world relaxes chunk by chunk and its default 0.4 m
chunks leave a faint periodic pattern on deep rut floors that a tread test would see too.
"""

from __future__ import annotations

import copy

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
]
