"""Synthetic recorder benchmark: terrain pair of a 20 m drive, and a full dual-lidar rosbag2
recording of the `watered` scenario (20 s at 1 m/s, 1024 columns; quick: 3 s, 512 columns)."""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path


def run(quick: bool = False) -> dict[str, float]:
    """Figures: synth.pair_20m_s (make_terrain_pair, dx 0.02), synth.record_s (truth + lidars +
    bag), synth.record_realtime_x (drive time / generation time), synth.bag_mb, synth.points_per_s."""
    from torchsoil.synth.record import make_recording
    from torchsoil.synth.scenario import make_terrain_pair

    make_terrain_pair("watered", seed=0)          # warm up imports and numba caches
    t0 = time.perf_counter()
    make_terrain_pair("watered", seed=1)
    pair_s = time.perf_counter() - t0
    tmp = Path(tempfile.mkdtemp(prefix="torchsoil_bench_synth_"))
    try:
        stats = make_recording("watered", tmp / "rec", seed=0, duration=3.0 if quick else None,
                               columns=512 if quick else None)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {
        "synth.pair_20m_s": pair_s,
        "synth.record_s": stats["total_s"],
        "synth.record_drive_s": stats["drive_s"],
        "synth.record_realtime_x": stats["drive_s"] / stats["total_s"],
        "synth.bag_mb": stats["bag_mb"],
        "synth.points_per_s": stats["points"] / stats["lidar_s"],
    }


if __name__ == "__main__":
    import json

    print(json.dumps(run(), indent=1))
