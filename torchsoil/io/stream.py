"""One lidar topic's sweeps, read with that topic's time convention and stamped at the sweep start.

The convention (torchsoil.io.pointtime) is decided on the first `N_SAMPLE` sweeps of the
topic, or fixed by its `pipeline.read.times` setting; every sweep is then a Cloud whose
stamp is the sweep start and whose t are seconds after it, whatever the driver wrote, so
a start-stamped and an end-stamped lidar report the same quantity.
"""

from __future__ import annotations

import numpy as np

from torchsoil.io.pointcloud import LIVOX_CUSTOM, Cloud, RawCloud, decode_livox, decode_raw, to_cloud
from torchsoil.io.pointtime import Convention, PointTimeError, infer

N_SAMPLE = 5   # sweeps a topic's convention is decided on


class SweepStream:
    """Sweeps of one topic. `add` each message in bag order, then `finish`.

    topic: its name (for messages); setting: its torchsoil.settings.TopicTime (None: all auto).
    `take` hands out the sweeps decoded so far; after `finish`: convention (pointtime.Convention),
    period (s, from the header stamps of the first sweeps; None with one sweep), problems
    (one line per sweep skipped because of its times).
    """

    def __init__(self, topic: str, setting=None):
        self.topic = topic
        self.setting = setting
        self.pending: list[tuple[int, float, RawCloud]] = []
        self.convention: Convention | None = None
        self.period: float | None = None
        self.clouds: list[Cloud] = []
        self.problems: list[str] = []
        self.yielded = 0       # sweeps handed out by `take` and `finish`

    def add(self, msg, msgtype: str, index: int, when: float) -> None:
        """Decode message `index` (bag time `when`, s). Raises ValueError when it cannot be
        decoded, PointTimeError when the topic's times cannot be understood."""
        field = self.setting.time_field if self.setting is not None else "auto"
        raw = decode_livox(msg) if msgtype in LIVOX_CUSTOM else decode_raw(msg, field)
        if self.convention is not None:
            self._convert(index, when, raw)
            return
        self.pending.append((index, when, raw))
        if len(self.pending) >= N_SAMPLE:
            self._decide()

    def take(self) -> list[Cloud]:
        """The sweeps decoded since the last call, in arrival order (none before the convention is
        decided)."""
        out, self.clouds = self.clouds, []
        self.yielded += len(out)
        return out

    def finish(self) -> list[Cloud]:
        """The sweeps not taken yet, time-ordered (raises PointTimeError as `add`)."""
        if self.convention is None and self.pending:
            self._decide()
        self.clouds.sort(key=lambda c: c.stamp)
        return self.take()

    def note(self) -> str | None:
        """One line for the run's problems when the topic has no per-point time."""
        if self.convention is None or self.convention.field is not None:
            return None
        why = "time_field: none" if self.setting is not None and self.setting.time_field == "none" else \
            "no t, time or timestamp field, or all zero"
        return (f"{self.topic}: no per-point time ({why}); sweeps taken as already de-skewed, the header stamp "
                f"as the sweep {self.convention.stamp} (pipeline.read.times['{self.topic}'].stamp sets it)")

    def _decide(self) -> None:
        s = self.setting
        stamps = np.sort([r.times.sec + 1e-9 * r.times.nanosec for _, _, r in self.pending])
        steps = np.diff(stamps)
        self.period = float(np.median(steps)) if len(steps) and np.median(steps) > 0 else None
        auto = ("auto", "auto", "auto") if s is None else (s.time_unit, s.time_base, s.stamp)
        self.convention = infer(self.topic, [r.times for _, _, r in self.pending], self.period, *auto)
        for index, when, raw in self.pending:
            self._convert(index, when, raw)
        self.pending = []

    def _convert(self, index: int, when: float, raw: RawCloud) -> None:
        try:
            self.clouds.append(to_cloud(raw, self.convention, self.period))
        except PointTimeError as e:
            self.problems.append(f"{self.topic} sweep {index} at t={when:.3f} s skipped: {e}")
