"""The job behind `torchsoil record`: a synthetic recording (a bag and its truth) of a shipped
scenario or a scenario YAML, or only its terrain pair."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from torchsoil.synth.record import make_recording
from torchsoil.synth.scenario import load_scenario, make_terrain_pair


def record(scenario: str | Path, out: str | Path, seed: int = 0, dx: float = 0.02, pair_only: bool = False,
           realistic: bool = False, **bag_options) -> str:
    """Write the recording of `scenario` (seed; terrain cell edge dx [m]) to `out`; returns what
    was written, a line. pair_only: only the terrain pair, as OUT.npz (`realistic`: with the
    measurement nuisances and tyre draws of real data, settings.REALISTIC). Otherwise a bag
    directory and its truth, bag_options going to `synth.record.make_recording` (storage,
    compress, duration, columns, organized, convention, imu, gnss); the line holds its statistics."""
    if realistic and not pair_only:
        raise ValueError("--realistic applies to --pair-only (the recorder's lidars have their own noise model)")
    out = Path(out)
    if pair_only:
        out = out if out.suffix == ".npz" else out.with_name(out.name + ".npz")
        out.parent.mkdir(parents=True, exist_ok=True)
        scn = load_scenario(scenario)
        np.savez_compressed(out, **make_terrain_pair(scn.realistic() if realistic else scn, seed, dx, visits=True))
        return f"wrote {out}"
    stats = make_recording(scenario, out, seed, dx, progress=True, **bag_options)
    return json.dumps({k: round(v, 3) for k, v in stats.items()})
