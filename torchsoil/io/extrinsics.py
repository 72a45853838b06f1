"""Lidar (and IMU) extrinsics, in one place: the poses base_T_sensor from the recording's
/tf_static and /tf, the robot YAML's `lidars:` and the settings' `read.extrinsics`."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from torchsoil.settings import PipelineConfig, ReadConfig, Settings

if TYPE_CHECKING:
    from torchsoil.io.bag import Recording


def pipeline_settings(settings: Settings, robot_yaml: str | Path | None,
                      extrinsics: dict[str, list[float]] | None = None) -> PipelineConfig:
    """The pipeline section with the robot YAML's `lidars:` extrinsics added, then
    `extrinsics` ({frame or topic: [x, y, z, roll, pitch, yaw]}, m, rad); each overrides the
    ones before it for the frames or topics it names."""
    extra = {}
    if robot_yaml:
        from torchsoil.io.extrinsics import extrinsics_from_robot_yaml

        extra = extrinsics_from_robot_yaml(robot_yaml)
    extra.update(extrinsics or {})
    cfg = settings.pipeline
    return cfg.replace(read={"extrinsics": {**cfg.read.extrinsics, **extra}}) if extra else cfg


def extrinsics_for(rec: Recording, cfg: ReadConfig, streams: dict[str, str]) -> dict[str, np.ndarray]:
    """{topic: base_T_sensor (4, 4)} for streams {topic: frame_id}.

    Each topic's pose is, in this order: a cfg.extrinsics entry keyed by the topic, one keyed
    by its frame, the bag's transforms (/tf_static and /tf, chains composed). Topics and frames
    are compared without a leading slash. Raises ValueError naming the frame when no pose is
    known, and when two topics publish in one frame and are not both given per topic (the
    frame cannot tell them apart: one would silently get the other's pose).
    """
    given = {frame_name(k): xyzrpy_matrix(v) for k, v in cfg.extrinsics.items()}
    by_frame = {**rec.extrinsics, **given}
    out: dict[str, np.ndarray] = {}
    topic_of_frame: dict[str, str] = {}
    for topic, frame_id in streams.items():
        if frame_name(topic) in given:
            out[topic] = given[frame_name(topic)]
            continue
        frame = frame_name(frame_id)
        if frame in topic_of_frame:
            other = topic_of_frame[frame]
            raise ValueError(
                f"'{other}' and '{topic}' both publish in frame '{frame}', so the frame cannot tell "
                "their poses apart; give each topic its own extrinsic: in the robot YAML `lidars: "
                f"{{{other}: [x, y, z, roll, pitch, yaw], {topic}: [...]}}` ({cfg.base_frame}, m, rad) "
                "or `--extrinsic TOPIC X Y Z ROLL PITCH YAW`")
        topic_of_frame[frame] = topic
        if frame not in by_frame:
            raise ValueError(f"no extrinsic for frame '{frame}' of '{topic}': neither {cfg.tf_topic} nor /tf "
                             f"links it to '{cfg.base_frame}' (frames there: {sorted(rec.extrinsics)}) nor "
                             "does the configuration (read.extrinsics) or the robot YAML (lidars) give it "
                             "by frame or by topic")
        out[topic] = by_frame[frame]
    return out


def extrinsics_from_robot_yaml(path: str | Path) -> dict[str, list[float]]:
    """Optional `lidars: {frame or topic: [x, y, z, roll, pitch, yaw]}` (m, rad, in base_link)
    of a robot YAML (docs/formats.md section 2), for `ReadConfig.extrinsics`. A key naming a topic
    (`/lidar_back/points`) sets that topic's pose whatever its frame; the IMU's pose may be
    given the same way."""
    doc = yaml.safe_load(Path(path).read_text()) or {}
    out = {}
    for frame, v in (doc.get("lidars") or {}).items():
        try:
            out[str(frame)] = [float(x) for x in v]
            xyzrpy_matrix(out[str(frame)])
        except (TypeError, ValueError) as e:
            raise ValueError(f"{path}: lidars.{frame} must be [x, y, z, roll, pitch, yaw] "
                             f"in metres and radians ({e})") from None
    return out


def frame_name(frame_id: str) -> str:
    """A frame id as tf2 compares it: without a leading slash (`/os_sensor` = `os_sensor`)."""
    return str(frame_id).strip().lstrip("/")


def transform_matrix(translation, quaternion_xyzw) -> np.ndarray:
    """(3,) translation [m] and (4,) quaternion (x, y, z, w) -> (4, 4) homogeneous transform."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(np.asarray(quaternion_xyzw, dtype=np.float64)).as_matrix()
    T[:3, 3] = np.asarray(translation, dtype=np.float64)
    return T


def xyzrpy_matrix(xyzrpy) -> np.ndarray:
    """(6,) x, y, z [m], roll, pitch, yaw [rad] -> (4, 4) transform."""
    v = np.asarray(xyzrpy, dtype=np.float64)
    if v.shape != (6,) or not np.all(np.isfinite(v)):
        raise ValueError(f"extrinsic must be 6 finite numbers x y z roll pitch yaw, got {v}")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", v[3:]).as_matrix()
    T[:3, 3] = v[:3]
    return T


def resolve_frames(edges: dict[str, tuple[str, np.ndarray]], base_frame: str) -> dict:
    """Static transforms child -> (parent, parent_T_child) -> {frame: base_T_frame} (4, 4) for
    every frame whose chain of parents reaches `base_frame` (base_link -> os_sensor ->
    os_lidar composes to base_T_os_lidar)."""
    out = {base_frame: np.eye(4)}
    for frame in edges:
        T, f, seen = np.eye(4), frame, set()
        while f in edges and f != base_frame and f not in seen:
            seen.add(f)
            parent, P = edges[f]
            T = P @ T
            f = parent
        if f == base_frame:
            out[frame] = T
    return out


def tf_edges(msg) -> dict[str, tuple[str, np.ndarray]]:
    """TFMessage -> {child: (parent, parent_T_child)}, frame ids without leading slash."""
    out = {}
    for tr in msg.transforms:
        q, p = tr.transform.rotation, tr.transform.translation
        out[frame_name(tr.child_frame_id)] = (frame_name(tr.header.frame_id), transform_matrix(
            (p.x, p.y, p.z), (q.x, q.y, q.z, q.w)))
    return out
