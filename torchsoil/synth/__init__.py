"""Synthetic field recordings with known truth: terrain, world soil model with switchable
effects, trajectory, dual simulated lidars and rosbag2 output.

    from torchsoil.synth import make_terrain_pair, make_recording, load_truth
"""

from torchsoil.synth.scenario import available, build_truth, load_scenario, make_terrain_pair


def make_recording(*args, **kwargs):
    """See `torchsoil.synth.record.make_recording` (imported lazily: numba, rosbags)."""
    from torchsoil.synth.record import make_recording as _mk

    return _mk(*args, **kwargs)


def load_truth(*args, **kwargs):
    """See `torchsoil.synth.truthfile.load_truth`."""
    from torchsoil.synth.truthfile import load_truth as _load

    return _load(*args, **kwargs)


__all__ = ["available", "build_truth", "load_scenario", "load_truth", "make_recording", "make_terrain_pair"]
