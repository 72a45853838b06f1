"""Small env configs shared by the environment tests."""


def small_config(sim=None, **env):
    """A document of the env section: an 8 m x 5 m field, a wet patch at (4.5, 2.5), start at
    (2, 2.5) heading +x; keyword arguments override env keys, `sim` the env's physics."""
    return {
        "start": [2.0, 2.5, 0.0], "start_jitter": [0.1, 0.1, 3.0], "goal": [6.5, 2.5],
        "max_steps": 40, "obs_size": 8, "obs_dx": 0.2, **env,
        "sim": dict(sim or {}),
        "field": {"size": [8.0, 5.0], "dx": 0.05, "roughness": 0.002, "seed": 3,
                  "soil": {"d": 0.02, "chi": 0.6, "beta_deg": 30.0},
                  "patches": [{"center": [4.5, 2.5], "radius": 1.0, "d": 0.08, "chi": 0.3,
                               "beta_deg": 20.0}],
                  "lanes": [{"y": [4.0, 4.6], "d": 0.005}], "edge": 0.2},
    }
