"""Read a recording (docs/formats.md section 1) with `rosbags`: ROS 2 (sqlite3, mcap) or ROS 1.

`read_recording(path, ...)` returns the front and back sweeps decoded to numpy, the IMU
samples (if the bag has a `sensor_msgs/msg/Imu` topic) and the transforms of `/tf_static`
and `/tf` merged (ROS 1 `static_transform_publisher` publishes on `/tf`), chains composed
to `base_link`, frame ids without their leading slash. A missing topic, a wrong message type or a bag that
cannot be opened or read to its end raises `BagError` naming the bag and the topic; a
single message that cannot be decoded is skipped and reported in `Recording.problems`
(its sweep index and time), so the run continues with that span flagged.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from torchsoil.io.extrinsics import frame_name, resolve_frames, tf_edges
from torchsoil.io.pointcloud import LIVOX_CUSTOM, Cloud, parse_livox, register_livox
from torchsoil.io.pointtime import PointTimeError, check_clock_domains
from torchsoil.io.stream import SweepStream

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
TFMESSAGE = "tf2_msgs/msg/TFMessage"
IMU = "sensor_msgs/msg/Imu"
TF_DYNAMIC = "/tf"


class BagError(ValueError):
    """A recording that cannot be used; the message names the bag and the topic."""


@dataclass
class ImuData:
    """Samples of one sensor_msgs/msg/Imu topic, in time order.

    t: (N,) header stamps, s; acc: (N, 3) linear acceleration (specific force, gravity
    included), m/s^2; gyro: (N, 3) angular velocity, rad/s; both in the IMU's frame
    `frame` (leading slash removed); topic: where they were read.
    """

    t: np.ndarray
    acc: np.ndarray
    gyro: np.ndarray
    frame: str
    topic: str


@dataclass
class Recording:
    """Decoded sweeps of both lidars.

    front, back: time-ordered sweeps (sensor frame), one Cloud each.
    extrinsics: frame name (no leading slash) -> (4, 4) float64 pose of that frame in
        `base_frame`, from /tf_static and /tf.
    imu: the IMU samples, or None when the bag has no IMU topic (or it was not asked for).
    problems: human-readable notes on skipped or suspicious messages (topic, index, time).
    start, end: first and last message time in the bag, s.
    conventions: topic -> how its point times and stamps were read (sweep stamps are moved
    to the sweep start, torchsoil.io.stream).
    """

    front: list[Cloud]
    back: list[Cloud]
    extrinsics: dict[str, np.ndarray] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    imu: ImuData | None = None
    start: float = 0.0
    end: float = 0.0
    conventions: dict[str, str] = field(default_factory=dict)

    @property
    def duration(self) -> float:
        return self.end - self.start


def _open(path: Path):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    if not path.exists():
        raise FileNotFoundError(f"recording not found: {path}")
    typestore = get_typestore(Stores.ROS2_HUMBLE)
    register_livox(typestore)
    reader = AnyReader([path], default_typestore=typestore)
    try:
        reader.open()
    except Exception as e:  # rosbags raises several reader-specific errors
        raise BagError(f"{path}: cannot open the bag ({type(e).__name__}: {e}); "
                       "is it truncated or corrupt?") from None
    return reader


def _check_topic(reader, path: Path, topic: str, msgtype: str | tuple[str, ...]):
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        have = sorted({f"{c.topic} [{c.msgtype}]" for c in reader.connections})
        raise BagError(f"{path}: topic '{topic}' not found; the bag holds: {have}")
    ok = (msgtype,) if isinstance(msgtype, str) else msgtype
    wrong = [c.msgtype for c in conns if c.msgtype not in ok]
    if wrong:
        raise BagError(f"{path}: topic '{topic}' has type {wrong[0]}, expected {' or '.join(ok)}")
    return conns


def _imu_connections(reader, path: Path, imu_topic: str | None) -> list:
    """Connections of the IMU topic: `imu_topic` (must exist), or with "" the bag's only
    sensor_msgs/msg/Imu topic (none: no IMU), or none at all for None / "none"."""
    if imu_topic is None or imu_topic.lower() == "none":
        return []
    if imu_topic:
        return _check_topic(reader, path, imu_topic, IMU)
    topics = sorted({c.topic for c in reader.connections if c.msgtype == IMU})
    if len(topics) > 1:
        raise BagError(f"{path}: several IMU topics {topics}; choose one with pipeline.read.imu_topic "
                       "(--imu-topic) or none with imu_topic=none")
    return [c for c in reader.connections if topics and c.topic == topics[0]]


class ImuSample(NamedTuple):
    """One IMU message: t [s], acc (3,) specific force [m/s^2], gyro (3,) [rad/s], its frame and topic."""

    t: float
    acc: tuple
    gyro: tuple
    frame: str
    topic: str


def imu_data(samples: list[ImuSample]) -> ImuData:
    """IMU samples -> ImuData sorted by stamp."""
    t = np.array([m.t for m in samples])
    acc = np.array([m.acc for m in samples], dtype=np.float64).reshape(-1, 3)
    gyro = np.array([m.gyro for m in samples], dtype=np.float64).reshape(-1, 3)
    order = np.argsort(t, kind="stable")
    return ImuData(t[order], acc[order], gyro[order], samples[0].frame, samples[0].topic)


def read_recording(path: str | Path, front_topic: str = "/lidar_front/points",
                   back_topic: str = "/lidar_back/points", tf_topic: str = "/tf_static",
                   base_frame: str = "base_link", require_tf: bool = False,
                   progress: Callable[[int], None] | None = None, times: dict | None = None,
                   imu_topic: str | None = "") -> Recording:
    """Read both lidar streams, the IMU and the extrinsics of a bag.

    Args:
        path: ROS 2 bag directory (sqlite3 or mcap) or ROS 1 `.bag` file.
        front_topic, back_topic: PointCloud2 (or Livox CustomMsg) topics.
        tf_topic: TFMessage topic with the static extrinsics; `/tf` is read as well (its first
            transform of each frame; /tf_static wins where both name a frame). Both may be
            absent unless `require_tf` (the caller then supplies extrinsics itself).
        base_frame: frame the extrinsics are expressed in.
        progress: called with the number of messages read since the last call.
        imu_topic: sensor_msgs/msg/Imu topic; "" the bag's only Imu topic if it has one;
            None or "none": no IMU.
        times: {topic: torchsoil.settings.TopicTime} per-point time conventions (default auto).
    """
    rec = Recording([], [])
    imu: list = []
    for name, item in stream_recording(path, rec, front_topic, back_topic, tf_topic, base_frame, require_tf,
                                       progress, times, imu_topic):
        (imu if name == "imu" else getattr(rec, name)).append(item)
    if imu:
        rec.imu = imu_data(imu)
    for name in ("front", "back"):
        getattr(rec, name).sort(key=lambda c: c.stamp)
    return rec


def stream_recording(path: str | Path, rec: Recording, front_topic: str = "/lidar_front/points",
                     back_topic: str = "/lidar_back/points", tf_topic: str = "/tf_static",
                     base_frame: str = "base_link", require_tf: bool = False,
                     progress: Callable[[int], None] | None = None, times: dict | None = None,
                     imu_topic: str | None = ""):
    """The messages of a bag as they come: yields ("front" | "back", Cloud) once the topic's
    time convention is known (after its first few sweeps, torchsoil.io.stream) and ("imu",
    ImuSample) per IMU message, in bag order. `rec` (an empty Recording) is filled meanwhile:
    start, end, extrinsics (updated as transforms arrive), problems, and at the end
    conventions. Arguments and errors as `read_recording`."""
    path = Path(path)
    base_frame = frame_name(base_frame)
    reader = _open(path)
    try:
        conns = {name: _check_topic(reader, path, topic, (POINTCLOUD2, *LIVOX_CUSTOM))
                 for name, topic in (("front", front_topic), ("back", back_topic))}
        present = {c.topic for c in reader.connections}
        tf_conns = [c for t in dict.fromkeys((tf_topic, TF_DYNAMIC)) if t in present
                    for c in _check_topic(reader, path, t, TFMESSAGE)]
        if not tf_conns and require_tf:
            raise BagError(f"{path}: neither '{tf_topic}' nor '{TF_DYNAMIC}' found and no extrinsics given")
        imu_conns = _imu_connections(reader, path, imu_topic)
        rec.start, rec.end = reader.start_time * 1e-9, reader.end_time * 1e-9
        stream_of = {c.id: name for name, cs in conns.items() for c in cs}
        topic_of = {"front": front_topic, "back": back_topic}
        tf_ids = {c.id: c.topic for c in tf_conns}
        imu_ids = {c.id for c in imu_conns}
        edges: dict[str, dict] = {tf_topic: {}, TF_DYNAMIC: {}}
        counts = {"front": 0, "back": 0}
        streams = {name: SweepStream(topic, (times or {}).get(topic)) for name, topic in topic_of.items()}
        clock = ClockCheck(path)
        wanted = [c for cs in conns.values() for c in cs] + list(tf_conns) + list(imu_conns)
        it = reader.messages(connections=wanted)
        while True:
            try:
                conn, stamp, raw = next(it)
            except StopIteration:
                break
            except Exception as e:
                done = ", ".join(f"{k}: {v} sweeps" for k, v in counts.items())
                raise BagError(f"{path}: reading stopped with {type(e).__name__}: {e} after "
                               f"{done}; the bag is truncated or corrupt") from None
            if progress is not None:
                progress(1)
            if conn.id in tf_ids or conn.id in imu_ids:
                sample = _take_aux(reader, conn, raw, stamp, conn.id in imu_ids, edges, rec)
                if sample is not None:
                    yield "imu", sample
                elif conn.id in tf_ids:
                    rec.extrinsics = resolve_frames({**edges[TF_DYNAMIC], **edges[tf_topic]}, base_frame)
                continue
            name = stream_of[conn.id]
            index = counts[name]
            counts[name] += 1
            try:
                msg = parse_livox(raw, not reader.is2) if conn.msgtype in LIVOX_CUSTOM else \
                    reader.deserialize(raw, conn.msgtype)
                streams[name].add(msg, conn.msgtype, index, stamp * 1e-9)
            except PointTimeError as e:
                raise BagError(f"{path}: {e}") from None
            except Exception as e:
                rec.problems.append(f"{topic_of[name]} sweep {index} at t={stamp * 1e-9:.3f} s "
                                    f"skipped: cannot decode ({type(e).__name__}: {e})")
            for cloud in streams[name].take():
                clock.check(streams[name].topic, cloud.stamp)
                yield name, cloud
        yield from _drain(streams, rec, clock, path)
    finally:
        reader.close()
    for name in ("front", "back"):
        if counts[name] == 0:
            raise BagError(f"{path}: topic '{topic_of[name]}' holds no messages")
        if not streams[name].yielded:
            raise BagError(f"{path}: none of the {counts[name]} sweeps on '{topic_of[name]}' "
                           f"could be decoded; first problem: {rec.problems[0]}")


def _drain(streams: dict[str, SweepStream], rec: Recording, clock, path: Path):
    """The sweeps the streams still hold at the end of the bag; their conventions and notes
    into `rec`."""
    for name, s in streams.items():
        try:
            clouds = s.finish()
        except PointTimeError as e:
            raise BagError(f"{path}: {e}") from None
        rec.problems += s.problems + [n for n in [s.note()] if n]
        if s.convention is not None:
            rec.conventions[s.topic] = s.convention.describe()
        for cloud in clouds:
            clock.check(s.topic, cloud.stamp)
            yield name, cloud


class ClockCheck:
    """Refuses two lidar streams stamped in different clock domains, from their first sweeps
    on (pointtime.check_clock_domains on the stamps seen so far, once both streams have one)."""

    def __init__(self, path: Path):
        self.path = path
        self.spans: dict[str, list[float]] = {}
        self.done = False

    def check(self, topic: str, stamp: float) -> None:
        if self.done:
            return
        lo, hi = self.spans.get(topic, [stamp, stamp])
        self.spans[topic] = [min(lo, stamp), max(hi, stamp)]
        if len(self.spans) < 2:
            return
        try:
            check_clock_domains({k: np.array(v) for k, v in self.spans.items()})
        except PointTimeError as e:
            raise BagError(f"{self.path}: {e}") from None
        self.done = True


def _take_aux(reader, conn, raw, stamp: int, is_imu: bool, edges: dict, rec: Recording):
    """One /tf(_static) or IMU message: transforms into edges[topic] (the first of each frame
    wins); an IMU message is returned as an ImuSample; a message that cannot be decoded is
    noted in rec.problems (and None returned)."""
    try:
        msg = reader.deserialize(raw, conn.msgtype)
        if is_imu:
            return ImuSample(msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec,
                             (msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z),
                             (msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z),
                             frame_name(msg.header.frame_id), conn.topic)
        for child, edge in tf_edges(msg).items():
            edges[conn.topic].setdefault(child, edge)
    except Exception as e:
        rec.problems.append(f"{conn.topic} message at t={stamp * 1e-9:.3f} s skipped: {e}")
    return None


def count_messages(path: str | Path, topics: list[str]) -> int:
    """Number of messages on `topics` (for progress bars)."""
    reader = _open(Path(path))
    try:
        return sum(c.msgcount for c in reader.connections if c.topic in topics)
    finally:
        reader.close()
