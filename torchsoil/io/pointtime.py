"""Per-point capture times of the common lidar drivers: which field, which unit, relative to
what (docs/formats.md section 1).

    ouster-ros           t          uint32 ns after the header stamp (stamp: sweep start)
    velodyne_pointcloud  time       float32 s relative to the stamp, -0.1 .. 0 (stamp: last packet)
    Hesai, Robosense     timestamp  float64 absolute s (stamp: frame start, or first/last point)
    livox_ros_driver2    timestamp  float64 absolute ns (PointCloud2); offset_time uint32 ns
                                    after timebase (CustomMsg)

A field's name and type give its usual reading; the values decide: read in s, ms, us or ns,
relative to the header stamp or absolute, the times of one sweep must lie within a sweep of
the stamp and span about one sweep (1 / rate). `infer` picks the first reading the first
sweeps of a topic agree with (a reading other than the field's usual one only when the
sweep spans at least MIN_SPAN of a period) and raises `PointTimeError` (saying what was seen and which
setting fixes it) when none fits. Per topic, `pipeline.read.times` may fix the field, unit,
base and stamp position instead (torchsoil.settings.TopicTime).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
BASES = ("stamp", "absolute")
TIME_FIELDS = ("t", "time", "timestamp")   # looked for in this order when the field is "auto"
DEFAULT_PERIOD = 0.1                        # s, sweep period of a topic whose stamps do not tell it
SLOWEST = 0.2                               # s, the longest sweep accepted when the period is unknown (5 Hz)
WINDOW = 1.5                                # times within WINDOW periods of the stamp, spanning at most that
MIN_SPAN = 0.1                              # a plausible sweep spans at least this share of a period


class PointTimeError(ValueError):
    """Per-point times that cannot be understood; the message says what was seen and how to set it."""


class RawTimes(NamedTuple):
    """The time field of one sweep as stored. field: its name (None: the sweep has none);
    values: (N,) float64 raw values of the points kept; kind: numpy kind of the field ('u',
    'i' or 'f'); sec, nanosec: the header stamp; readings: (unit, base) pairs to try, in
    order (empty: by the field's name and kind, `usual_readings`)."""

    field: str | None
    values: np.ndarray
    kind: str
    sec: int
    nanosec: int
    readings: tuple = ()


class Convention(NamedTuple):
    """How a topic's point times are read. field: name (None: no per-point time); unit: key
    of UNITS; base: 'stamp' (relative to the header stamp) or 'absolute'; offset: s from the
    header stamp to the sweep start (added to stamps, subtracted from point times); stamp:
    where the header stamp sits in the sweep ('start', 'end' or 'mid')."""

    field: str | None
    unit: str = "s"
    base: str = "stamp"
    offset: float = 0.0
    stamp: str = "start"

    def describe(self) -> str:
        if self.field is None:
            return f"no per-point time; header stamp taken as the sweep {self.stamp}"
        ref = "after the header stamp" if self.base == "stamp" else "absolute"
        return (f"'{self.field}' in {self.unit} {ref}; header stamp at the sweep {self.stamp} "
                f"({self.offset * 1e3:+.1f} ms to the sweep start)")


def usual_readings(field: str, kind: str) -> list[tuple[str, str]]:
    """The drivers' readings of a time field, most usual first (the module docstring)."""
    if kind in "ui":
        return [("ns", "stamp")] if field != "timestamp" else [("ns", "absolute"), ("ns", "stamp")]
    if field == "timestamp":
        return [("s", "absolute"), ("ns", "absolute")]
    return [("s", "stamp")]


def relative(raw: RawTimes, unit: str, base: str) -> np.ndarray:
    """(N,) float64 s after the header stamp of `raw` read in `unit`, relative to `base`."""
    t = raw.values * UNITS[unit]
    if base == "absolute":
        t = (t - raw.sec) - raw.nanosec * 1e-9
    return t


def _fits(t: np.ndarray, period: float) -> bool:
    """Times (s after the stamp) that lie within a sweep of the stamp and span at most one."""
    if len(t) == 0:
        return True
    lo, hi = float(t.min()), float(t.max())
    return bool(np.isfinite(lo) and np.isfinite(hi) and -WINDOW * period <= lo and hi <= WINDOW * period
                and hi - lo <= WINDOW * period)


def _span(t: np.ndarray) -> float:
    return float(t.max() - t.min()) if len(t) else 0.0


def check(t: np.ndarray, period: float | None) -> None:
    """Raise PointTimeError when one sweep's times (s after the stamp) do not fit a sweep."""
    p = period or SLOWEST
    if not _fits(t, p):
        raise PointTimeError(f"point times {t.min():.6g} .. {t.max():.6g} s after the stamp do not fit "
                             f"a {p:.3f} s sweep")


def infer(topic: str, samples: list[RawTimes], period: float | None = None, unit: str = "auto",
          base: str = "auto", stamp: str = "auto") -> Convention:
    """The convention of a topic from the time fields of its first sweeps.

    samples: RawTimes of a few sweeps (all with the same field); period: sweep period of the
    topic, s (None: unknown, sweeps up to SLOWEST accepted); unit, base, stamp: the
    topic's settings ('auto' or a fixed value). Raises PointTimeError naming the
    topic and field when no reading fits a majority of the samples.
    """
    where = f"'{topic}'" if topic else "cloud"
    first = samples[0]
    if first.field is None or all(len(s.values) == 0 for s in samples):
        return _no_time(period, stamp)
    p = period or SLOWEST
    lo_span = MIN_SPAN * (period or DEFAULT_PERIOD)
    readings = list(first.readings) or usual_readings(first.field, first.kind)
    readings += [(u, b) for b in BASES for u in UNITS if (u, b) not in readings]
    readings = [(u, b) for u, b in readings if unit in ("auto", u) and base in ("auto", b)]
    if not readings:
        raise PointTimeError(_not_understood(where, first, samples, p, unit, base))
    fitting, plausible = [], []
    for u, b in readings:
        ts = [relative(s, u, b) for s in samples]
        if sum(_fits(t, p) for t in ts) * 2 > len(ts):
            fitting.append((u, b, ts))
            if np.median([_span(t) for t in ts]) >= lo_span:
                plausible.append((u, b, ts))
    # a reading other than the driver's usual one must also span a plausible sweep
    usual = [r for r in fitting if (r[0], r[1]) == readings[0]]
    if not plausible and not usual:
        raise PointTimeError(_not_understood(where, first, samples, p, unit, base))
    u, b, ts = (plausible or usual)[0]
    spans = [_span(t) for t in ts]
    if max(spans) == 0.0:           # a time field of zeros: already de-skewed
        return _no_time(period, stamp)
    span = float(np.median(spans))
    offset = float(np.median([t.min() for t in ts if len(t)]))
    label = ("start" if abs(offset) <= 0.25 * span else "end" if abs(offset + span) <= 0.25 * span
             else "mid")
    if stamp != "auto" and stamp != label:
        raise PointTimeError(f"{where}: the settings say the header stamp marks the sweep {stamp}, but the "
                             f"'{first.field}' times ({u}, {b}) run {offset:.4f} .. {offset + span:.4f} s after it "
                             f"(the sweep {label}); remove the stamp setting or fix time_unit / time_base")
    return Convention(first.field, u, b, offset, label)


def _no_time(period: float | None, stamp: str) -> Convention:
    end = stamp == "end"
    return Convention(None, offset=-(period or DEFAULT_PERIOD) if end else 0.0, stamp="end" if end else "start")


def _not_understood(where: str, first: RawTimes, samples: list[RawTimes], p: float, unit: str, base: str) -> str:
    v = np.concatenate([s.values for s in samples])
    stamp = first.sec + first.nanosec * 1e-9
    span = float(np.median([_span(s.values) for s in samples if len(s.values)]))
    kind = {"u": "unsigned integer", "i": "integer", "f": "float"}.get(first.kind, first.kind)
    msg = (f"{where}: per-point time field '{first.field}' ({kind}) cannot be understood: its values run "
           f"{v.min():.6g} .. {v.max():.6g} (a sweep spans {span:.6g}) with header stamps from {stamp:.6f} s; "
           f"read in s, ms, us or ns, relative to the header stamp or absolute"
           + (f" (limited to unit {unit}, base {base} by the settings)" if (unit, base) != ("auto", "auto") else "")
           + f", no reading puts a sweep within {WINDOW * p:.3f} s of its stamp.")
    clock = [u for u, k in UNITS.items() if MIN_SPAN * p <= span * k <= WINDOW * p]
    if clock:
        gap = float(np.median(v)) * UNITS[clock[0]] - stamp
        msg += (f" Read in {clock[0]} the sweep spans {span * UNITS[clock[0]]:.3f} s but sits {gap:.6g} s from "
                "the header stamp: the point times and the stamp come from different clocks (e.g. the lidar's "
                "internal clock and ROS time); make the driver stamp both from one clock (PTP or ROS time).")
    msg += (" If the field means something else, set pipeline.read.times: {'" + (where.strip("'") or "TOPIC")
            + "': {time_unit: s|ms|us|ns, time_base: stamp|absolute}} or {time_field: none} to ignore it.")
    return msg


def check_clock_domains(topics: dict[str, np.ndarray], slack: float = 1.0) -> None:
    """Raise PointTimeError when the sweep stamps of two streams ({topic: (S,) s}) do not
    overlap in time (within `slack` s): the lidars are stamped from different clocks."""
    spans = {k: (float(v.min()), float(v.max())) for k, v in topics.items() if len(v)}
    if len(spans) < 2:
        return
    lo, hi = max(s[0] for s in spans.values()), min(s[1] for s in spans.values())
    if lo - hi <= slack:
        return
    import datetime as _dt

    def when(x):
        return _dt.datetime.fromtimestamp(x, _dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3]

    seen = "; ".join(f"'{k}' stamps {when(a)} .. {when(b)} UTC" for k, (a, b) in spans.items())
    raise PointTimeError(f"the lidars are stamped in different clocks ({seen}, {lo - hi:.6g} s apart), so their "
                         "sweeps cannot be paired: one is probably on its internal clock (e.g. Ouster "
                         "timestamp_mode TIME_FROM_INTERNAL_OSC stamps from 1970). Record both lidars in one "
                         "clock domain (ROS time or PTP: ouster-ros timestamp_mode TIME_FROM_ROS_TIME or "
                         "TIME_FROM_PTP_1588).")
