"""GNSS fixes of a recording: `sensor_msgs/msg/NavSatFix` messages and the antenna's place on
the robot (docs/formats.md section 1, optional topic; docs/export.md).

`read_fixes(bag)` returns every fix of the bag's NavSatFix topic (the only one, or the one
named) with its covariance and status, and the antenna's offset from base_link taken from
/tf_static (or /tf) by the fixes' `header.frame_id`. A bag without such a topic gives None.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from torchsoil.io.extrinsics import frame_name, resolve_frames, tf_edges

NAVSATFIX = "sensor_msgs/msg/NavSatFix"
# sensor_msgs/NavSatStatus and NavSatFix constants (REP 145 and the message definitions)
STATUS_NO_FIX, STATUS_FIX, STATUS_SBAS_FIX, STATUS_GBAS_FIX = -1, 0, 1, 2
COVARIANCE_TYPE_UNKNOWN = 0


@dataclass
class Fixes:
    """The fixes of one NavSatFix topic, in time order.

    t: (N,) header stamps, s; lat, lon: (N,) degrees (WGS 84); alt: (N,) ellipsoidal height, m;
    cov: (N, 3, 3) position covariance in the local ENU frame, m^2 (NaN where unknown);
    cov_type: (N,) the message's position_covariance_type; status: (N,) NavSatStatus.status
    (-1 no fix, 0 fix, 1 SBAS, 2 GBAS: RTK drivers report 2); frame: the antenna's frame;
    antenna: (3,) the antenna in base_link, m (zeros when the transforms do not say, with a
    note in `problems`, and antenna_known False); topic: where they were read; problems: notes
    on skipped messages.
    """

    t: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    alt: np.ndarray
    cov: np.ndarray
    cov_type: np.ndarray
    status: np.ndarray
    frame: str
    antenna: np.ndarray
    topic: str
    problems: list[str]
    antenna_known: bool = True

    def __len__(self) -> int:
        return len(self.t)

    def sigma_h(self) -> np.ndarray:
        """(N,) horizontal standard deviation sqrt((var_E + var_N) / 2), m; NaN where the
        covariance is unknown."""
        v = 0.5 * (self.cov[:, 0, 0] + self.cov[:, 1, 1])
        v = np.where(self.cov_type > COVARIANCE_TYPE_UNKNOWN, v, np.nan)
        return np.sqrt(np.where(v >= 0, v, np.nan))


def fix_topics(reader) -> list[str]:
    return sorted({c.topic for c in reader.connections if c.msgtype == NAVSATFIX})


def read_fixes(path: str | Path, topic: str = "", base_frame: str = "base_link") -> Fixes | None:
    """The NavSatFix fixes of the bag at `path` (topic "" : the bag's only NavSatFix topic;
    None when it has none). A named topic that is missing, or several topics with none named,
    raise BagError."""
    from torchsoil.io.bag import BagError, _check_topic, _open

    path = Path(path)
    reader = _open(path)
    try:
        if topic:
            conns = _check_topic(reader, path, topic, NAVSATFIX)
        else:
            topics = fix_topics(reader)
            if not topics:
                return None
            if len(topics) > 1:
                raise BagError(f"{path}: several NavSatFix topics {topics}; choose one with --gnss-topic")
            topic = topics[0]
            conns = [c for c in reader.connections if c.topic == topic]
        tf_conns = [c for c in reader.connections if c.topic in ("/tf_static", "/tf")]
        rows, problems, frame = [], [], ""
        edges: dict[str, dict] = {"/tf_static": {}, "/tf": {}}
        for conn, stamp, raw in reader.messages(connections=conns + tf_conns):
            try:
                msg = reader.deserialize(raw, conn.msgtype)
            except Exception as e:  # one undecodable message is skipped, not the topic
                problems.append(f"{conn.topic} message at t={stamp * 1e-9:.3f} s skipped: {e}")
                continue
            if conn.topic != topic:
                for child, edge in tf_edges(msg).items():
                    edges[conn.topic].setdefault(child, edge)
                continue
            frame = frame or frame_name(msg.header.frame_id)
            cov = np.asarray(msg.position_covariance, dtype=np.float64).reshape(3, 3)
            rows.append((msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec, msg.latitude, msg.longitude,
                         msg.altitude, cov, int(msg.position_covariance_type), int(msg.status.status)))
    finally:
        reader.close()
    rows.sort(key=lambda r: r[0])
    n = len(rows)
    col = (lambda k: np.array([r[k] for r in rows], dtype=np.float64)) if n else (lambda k: np.zeros(0))
    frames = resolve_frames({**edges["/tf"], **edges["/tf_static"]}, base_frame)
    antenna = np.zeros(3)
    if frame in frames:
        antenna = frames[frame][:3, 3].copy()
    elif n:
        problems.append(f"{topic}: no transform from {base_frame} to the antenna frame '{frame}' in /tf_static "
                        "or /tf; the antenna's offset is fitted with the map where the drive turns enough")
    return Fixes(col(0), col(1), col(2), col(3), np.stack([r[4] for r in rows]) if n else np.zeros((0, 3, 3)),
                 np.array([r[5] for r in rows], dtype=np.int64), np.array([r[6] for r in rows], dtype=np.int64),
                 frame, antenna, topic, problems, frame in frames or not n)
