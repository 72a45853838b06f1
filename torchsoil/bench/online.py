"""Online benchmark: the whole chain (streaming pipeline and window estimation) against the
recording's own length, window latency, and peak memory against the drive's length.

`online_realtime_factor`: wall time of `torchsoil.estimate.live.play` over the bench's 20 s `road`
recording (5 s when quick), from the first message to the last window, / recording length
(< 0.5: more than twice as fast as the robot drives). `online_latency_s_median` / `_max`: from
the arrival of the sweep that completes a window's ground to that window's row.
`online_peak_rss_mb_1min` / `_10min`: peak resident memory of `torchsoil estimate` (its own
process, started by a small launcher: `bench._memory`) on 1- and 10-minute synthetic straight
drives recorded with 16 beams x 512 columns (the 10-minute one is skipped when quick);
`online_estimate_s_1min` / `_10min`: that process's wall time, s (docs/memory.md).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path


def _long_drive(out: Path, minutes: float) -> Path:
    from torchsoil.synth.record import make_recording

    length = 60.0 * minutes
    scn = {"name": out.name, "trajectory": {"segments": [{"straight": length + 2.0, "speed": 1.0}]},
           "terrain": {"margin": 4.0}, "soil": {"base": {"d": 0.02, "chi": 0.3, "beta_deg": 30.0}},
           "landmarks": {"poles": int(length / 3), "trunks": int(length / 8), "shed": True, "fence": True},
           "lidar": {"columns": 512, "beams": 16}}
    make_recording(scn, out, seed=0, duration=length, progress=False)
    return out


def run(quick: bool = False) -> dict[str, float]:
    import numpy as np

    from torchsoil.bench._memory import peak_rss_mb
    from torchsoil.bench.pipeline import _recording
    from torchsoil.estimate.live import LiveEstimator, play
    from torchsoil.settings import load_settings

    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        bag, robot = _recording(Path(tmp) / "road", 5.0 if quick else 20.0)
        live = LiveEstimator(robot, load_settings(), spill_dir=tmp)
        t0 = time.perf_counter()
        latency = [w.done - w.ready for w in play(bag, live)]
        wall = time.perf_counter() - t0
        stamps = live.pipeline.trajectory()[0]
        duration = float(stamps[-1] - stamps[0]) + 0.1
        out.update(online_realtime_factor=wall / duration, online_wall_s=wall, online_recording_s=duration,
                   online_windows=len(latency), online_latency_s_median=float(np.median(latency)),
                   online_latency_s_max=float(np.max(latency)))
        out.update({f"online_{k}_s": v for k, v in live.pipeline.timings.items()})
        for minutes, key in ((1, "1min"), (10, "10min")):
            if quick and minutes > 1:
                continue
            drive = _long_drive(Path(tmp) / f"drive{minutes}", minutes)
            t0 = time.perf_counter()
            out[f"online_peak_rss_mb_{key}"] = peak_rss_mb(
                ["estimate", str(drive), "--robot", str(drive.parent / f"{drive.name}.robot.yaml"),
                 "--out", str(Path(tmp) / f"est{minutes}"), "--no-tensorboard"])
            out[f"online_estimate_s_{key}"] = time.perf_counter() - t0
    return out


if __name__ == "__main__":
    import json

    print(json.dumps(run(quick=True), indent=1))
