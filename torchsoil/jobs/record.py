"""The job behind `torchsoil record`: a synthetic recording (a bag and its truth) of a shipped
scenario or a scenario YAML, or only its terrain pair."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from torchsoil.synth.record import make_recording, make_season
from torchsoil.synth.scenario import load_scenario, make_terrain_pair


def record(scenario: str | Path, out: str | Path, seed: int = 0, dx: float = 0.02, pair_only: bool = False,
           realistic: bool = False, sessions: list[int] | None = None, **bag_options) -> str:
    """Write the recording of `scenario` (seed; terrain cell edge dx [m]) to `out`; returns what
    was written, a line. pair_only: only the terrain pair, as OUT.npz (`realistic`: with the
    measurement nuisances and tyre draws of real data, settings.REALISTIC). Otherwise a bag
    directory and its truth, bag_options going to `synth.record.make_recording` (storage,
    compress, duration, columns, organized, convention, imu, gnss); the line holds its statistics.

    A season (a scenario with later_sessions) goes into the directory `out`, one recording (or
    with pair_only one pair and truth) per session, or those of `sessions` (1-based):
    `synth.record.make_season`."""
    if realistic and not pair_only:
        raise ValueError("--realistic applies to --pair-only (the recorder's lidars have their own noise model)")
    out = Path(out)
    scn = load_scenario(scenario)
    if scn.later_sessions:
        if out.suffix == ".npz":
            raise ValueError(f"scenario {scn.name!r} is a season of {1 + len(scn.later_sessions)} sessions: --out "
                             f"is the directory they go into, not {out}")
        stats = make_season(scn, out, seed, dx, sessions, pair_only=pair_only, realistic=realistic,
                            progress=not pair_only, **bag_options)
        return json.dumps(_rounded(stats))
    if sessions not in (None, [1]):
        raise ValueError(f"scenario {scn.name!r} has one session (no later_sessions), not {sessions}")
    if pair_only:
        out = out if out.suffix == ".npz" else out.with_name(out.name + ".npz")
        out.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(out, **make_terrain_pair(scn.realistic() if realistic else scn, seed, dx, visits=True))
        return f"wrote {out}"
    stats = make_recording(scn, out, seed, dx, progress=True, **bag_options)
    return json.dumps(_rounded(stats))


def _rounded(stats: dict) -> dict:
    return {k: _rounded(v) if isinstance(v, dict) else round(v, 3) for k, v in stats.items()}
