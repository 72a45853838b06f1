"""Soil parameters while the robot drives: the streaming lidar pipeline and the window
estimator in one object, fed message by message (what a ROS 2 node's callbacks call).

    live = LiveEstimator(robot, settings)
    live.add_transforms(tf_static_msg)                   # tf2_msgs/TFMessage, any time
    live.add_message("/lidar_front/points", msg)         # sensor_msgs/PointCloud2 (or Livox CustomMsg)
    live.add_imu(imu_msg)                                # sensor_msgs/Imu (optional)
    for w in live.poll():                                # windows whose ground is complete
        print(w.index, w.output.row["d1"], w.output.row["beta"])
    live.finish()                                        # the end: the last windows

A window is fitted as soon as the back lidar has rasterized its ground and the next
window's (for the prediction cost) `estimator.online.lag` m behind the rear wheels' margin.
Windows are taken `estimator.online.batch` at a time: cut out of the tiles with
`estimator.online.context` m of ground before them and fitted by `Estimator` on that stretch
(map offset included), each warm-started from the window before. The fitting runs on a worker
thread (`WindowFitter`), so the pipeline takes the next sweeps meanwhile (on two cores, both
busy); the rows are the same as when fitted in the caller's thread (`worker: none`).
"""

from __future__ import annotations

import math
import time
from concurrent.futures import Future, ThreadPoolExecutor, wait
from typing import NamedTuple

import numpy as np
import torch

from torchsoil.estimate.estimator import Estimator, WindowOutput
from torchsoil.estimate.windows import drive_windows, path_arc
from torchsoil.io.bag import ImuSample, Recording
from torchsoil.io.extrinsics import frame_name, resolve_frames, tf_edges
from torchsoil.io.stream import SweepStream
from torchsoil.pipeline.online import OnlinePipeline
from torchsoil.robot import Robot
from torchsoil.settings import Settings


class CloudError(ValueError):
    """A lidar message that cannot be decoded (its fields, layout or times); the message says why."""


class LiveWindow(NamedTuple):
    """index: the window's number along the whole drive; output: its estimator output (row
    with the drive's arc length `s`); pair: the stretch it was fitted on; ready: wall time
    (time.perf_counter) at which its ground was complete; done: when its row was ready; dist:
    (X, Y) over the window's crop, distance of each cell's arc length to the window centre, m."""

    index: int
    output: WindowOutput
    pair: object
    ready: float
    done: float
    dist: np.ndarray | None = None


class LiveEstimator:
    """The running estimate. Args: robot; settings (torchsoil.settings.Settings); spill_dir:
    where far heightmap tiles go (None: kept in memory). `pipeline` is the OnlinePipeline."""

    def __init__(self, robot: Robot, settings: Settings | None = None, spill_dir=None, rec: Recording | None = None):
        self.settings = settings = settings or Settings()
        self.robot = robot
        self.rec = rec if rec is not None else Recording([], [])
        self.pipeline = OnlinePipeline(robot, settings.pipeline, self.rec, spill_dir)
        self.pipeline.on_ground = self._advance
        self.next = 0                      # next window index
        self.skip = 0                      # windows before this one were written by an interrupted run
        self.polled = -np.inf              # pipeline.ground_stamp at the last poll
        self.ready_at: dict[int, float] = {}
        self.edges: dict[str, tuple] = {}
        r = settings.pipeline.read
        self.streams = {r.front_topic: ("front", SweepStream(r.front_topic, r.times.get(r.front_topic))),
                        r.back_topic: ("back", SweepStream(r.back_topic, r.times.get(r.back_topic)))}
        e = settings.estimator
        self.behind = abs(float(robot.wheels[:, 0].min())) + robot.wheel_width / 2 \
            + settings.pipeline.raster.wheel_margin + e.online.lag
        self.reach = np.abs(robot.wheels[:, 0]).max() + robot.wheel_width
        self.last_row: dict | None = None  # warm start of a resumed run (a params.csv row)
        self.fitter = WindowFitter(settings)
        self.pending: list[tuple] = []     # (future, pair) of the stretches queued or being fitted, in order
        self.worker: ThreadPoolExecutor | None = None   # with estimator.online.worker=thread
        self.clock = time.perf_counter     # when a window became ready (a node: the sweep's arrival)
        self.when_behind = "wait"          # fits max_pending behind: "wait" for them, or "skip" the new windows

    # ---------------------------------------------------------------- input
    def add_message(self, topic: str, msg, msgtype: str = "sensor_msgs/msg/PointCloud2") -> None:
        """A lidar message of the front or back topic (PointCloud2 or Livox CustomMsg); CloudError
        when it cannot be decoded (nothing of it is kept)."""
        name, stream = self.streams[topic]
        try:
            stream.add(msg, msgtype, stream.yielded + len(stream.clouds), 0.0)
        except ValueError as e:   # PointTimeError included
            raise CloudError(f"{topic}: {e}") from e
        for cloud in stream.take():
            self.pipeline.add_cloud(name, cloud)

    def add_cloud(self, name: str, cloud) -> None:
        """A decoded sweep (torchsoil.io.pointcloud.Cloud, stamped at its start) of "front" or "back"."""
        self.pipeline.add_cloud(name, cloud)

    def add_transforms(self, msg) -> None:
        """A tf2_msgs/TFMessage (/tf_static or /tf): lidar and IMU extrinsics."""
        self.add_edges(tf_edges(msg))

    def add_edges(self, edges: dict[str, tuple]) -> None:
        """Transforms {child frame: (parent frame, (4, 4) parent_T_child)}, as tf_edges gives
        them (the first of each frame is kept)."""
        for child, edge in edges.items():
            self.edges.setdefault(child, edge)
        self.rec.extrinsics = resolve_frames(self.edges, frame_name(self.settings.pipeline.read.base_frame))

    def add_imu(self, msg) -> None:
        """A sensor_msgs/Imu message (or an ImuSample)."""
        if not isinstance(msg, ImuSample):
            msg = ImuSample(msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec,
                            (msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z),
                            (msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z),
                            frame_name(msg.header.frame_id), "/imu")
        self.pipeline.add_imu(msg)

    # --------------------------------------------------------------- output
    def poll(self, final: bool = False) -> list[LiveWindow]:
        """Windows fitted since the last call, in order. Each time the pipeline rasterizes new
        ground, the windows whose ground it completed are cut out and queued for fitting (at the
        pipeline's own step, so that the rows do not depend on how the sweeps were grouped or
        interleaved on arrival); with `final` all that are left. With `estimator.online.worker`
        = thread (the default) the fitting runs on a worker thread while the caller feeds the
        next sweeps, and its windows come out of a later call (`finish` waits for them all)."""
        if final:
            self._advance(final=True)
        out = self._collect(final)
        now = time.perf_counter()
        return [w._replace(done=now) for w in out]

    def _advance(self, final: bool = False) -> None:
        """Queue the windows whose ground became complete (called by the pipeline each time it
        rasterizes ground, `OnlinePipeline.on_ground`): cut out and fitted, or, with the fits
        `max_pending` stretches behind and `when_behind` = skip, queued as skipped."""
        fitting = sum(1 for f, pair in self.pending if pair is not None and not f.done())
        full = fitting >= self.settings.estimator.online.max_pending
        skip = full and self.when_behind == "skip" and not final
        job = self._job(final, skip)
        if job is None:
            return
        done = Future()
        if skip:
            done.set_result(self._skipped(job[5]))
            self.pending.append((done, None))
        elif self.settings.estimator.online.worker == "none":
            done.set_result(self.fitter(*job))
            self.pending.append((done, job[0]))
        else:
            if full:   # bounded queue: wait for the oldest stretch being fitted
                wait([f for f, pair in self.pending if pair is not None and not f.done()][:1])
            if self.worker is None:
                self.worker = ThreadPoolExecutor(1, thread_name_prefix="torchsoil-fit")
            self.pending.append((self.worker.submit(self.fitter, *job), job[0]))

    def _collect(self, final: bool) -> list[LiveWindow]:
        """The windows of the stretches fitted so far, in order (with `final`: all, waiting)."""
        out = []
        while self.pending and (final or self.pending[0][0].done()):
            future, pair = self.pending.pop(0)
            out += [w._replace(pair=pair) for w in future.result()]   # a failed fit raises here
        return out

    def _job(self, final: bool, skip: bool = False) -> tuple | None:
        """The WindowFitter arguments of the windows whose ground became complete (the stretch cut
        out of the tiles, its first pose's arc length along the drive, the indices along the drive
        of its windows, the first and last to fit, when each became ready, the warm start of a
        resumed run); None when there are none. With `skip`, nothing is cut out: only the
        windows' ready times (argument 5) count, the rest is None."""
        pipe, e = self.pipeline, self.settings.estimator
        if pipe.L is None or pipe.mapper is None or (not final and pipe.ground_stamp == self.polled):
            return None   # no new ground since the last call: nothing can have become ready
        self.polled = pipe.ground_stamp
        stamps, poses = pipe.trajectory()
        if len(stamps) < 2:
            return None
        arc = path_arc(np.column_stack([stamps, poses[:, :3, 3], np.zeros((len(stamps), 3))]))
        if final:
            last = int(math.floor((arc[-1] - e.window) / e.stride + 1e-9))
        else:
            done_arc = float(np.interp(pipe.ground_stamp, stamps, arc)) - self.behind
            last = int(math.floor((done_arc - 2 * e.window) / e.stride + 1e-9))
        if last < self.next:
            return None
        now = self.clock()
        for k in range(self.next, last + 1):
            self.ready_at.setdefault(k, now)
        if not final and last - self.next + 1 < e.online.batch:
            return None   # wait for a few: each stretch cut out and indexed costs as much as a fit
        if skip:
            ready = {k: self.ready_at.pop(k, now) for k in range(self.next, last + 1) if k >= self.skip}
            self.next = last + 1
            return (None, None, None, None, None, ready, None) if ready else None
        a0 = max(0.0, self.next * e.stride - e.online.context)
        a1 = min(arc[-1], (last * e.stride + 2 * e.window) + self.reach + 0.5)   # + poses past it
        t0, t1 = np.interp([a0, a1], arc, stamps)
        pair = pipe.terrain(t0, t1)
        arc0 = float(arc[np.searchsorted(stamps, t0)])
        specs = drive_windows(float(path_arc(pair.poses)[-1]), e.window, e.stride, arc0)   # as Estimator places them
        index = [int(round((w.s0 + arc0) / e.stride)) for w in specs]
        take = [k for k in index if self.next <= k <= last]
        if final:   # the drive ends here: no later window can be fitted
            self.next = max(self.next, last + 1)
        if not take:
            return None
        self.next = max(self.next, take[-1] + 1)
        ready = {k: self.ready_at.pop(k, now) for k in take}
        take = [k for k in take if k >= self.skip]
        if not take:
            return None
        return pair, arc0, index, take[0], take[-1], {k: ready[k] for k in take}, self.last_row

    def _skipped(self, ready: dict[int, float]) -> list[LiveWindow]:
        """Windows `ready` (index -> when its ground was complete) as skipped (no fit: the fits
        are max_pending stretches behind): rows with NaN parameters, flag `skipped_behind`. The
        next fitted window starts from the last fit, as after any gap."""
        e = self.settings.estimator
        now = time.perf_counter()
        out = []
        for k in sorted(ready):
            row = {"s": k * e.stride + e.window / 2, "visit": 0, "flags": "skipped_behind", "iterations": 0}
            out.append(LiveWindow(k, WindowOutput(row, {"signal": math.nan, "floor": math.nan}, None, None, None),
                                  None, ready[k], now))
        return out

    def resume(self, rows: list[dict]) -> None:
        """Continue after the windows of `rows` (params.csv rows of an interrupted run, in order):
        they are not fitted again, and the last fitted one warm-starts the next. The stretches are
        cut where the interrupted run cut them (a window's H_b and map offset depend on the stretch
        it comes with: the back lidar keeps filling its ground in), those written skipped."""
        self.skip = len(rows)
        fitted = [r for r in rows if not math.isnan(float(r["d1"]))]
        self.last_row = fitted[-1] if fitted else None

    def finish(self) -> list[LiveWindow]:
        """The end of the recording: the pipeline flushed, the last windows fitted, every queued
        window returned and the worker thread stopped."""
        self.pipeline.finish()
        out = self.poll(final=True)
        self.close()
        return out

    def close(self) -> None:
        """Stop the worker thread (queued fits are dropped)."""
        if self.worker is not None:
            for future, _ in self.pending:
                future.cancel()
            self.worker.shutdown(wait=True)
            self.worker = None


class WindowFitter:
    """Fits the windows of the stretches LiveEstimator cuts out, one stretch after the other,
    each window warm-started from the one before (state: `theta`, the last fitted parameters)."""

    def __init__(self, settings: Settings):
        self.settings = settings
        self.theta: torch.Tensor | None = None

    def __call__(self, pair, arc0: float, index: list[int], first: int, last: int, ready: dict,
                 last_row: dict | None = None) -> list[LiveWindow]:
        """Windows `first`..`last` (indices along the drive; `index`: of every window the estimator
        places on the stretch `pair`, whose first pose lies at arc length arc0 [m] along the drive);
        ready: wall time at which each became ready; last_row: a params.csv row to start from
        when nothing was fitted yet (a resumed run). The windows come without their pair."""
        e = self.settings.estimator
        est = Estimator(pair, e, self.settings.sim, arc0=arc0)
        if self.theta is None and last_row is not None:
            self.theta = est.free_from_row(last_row)
        out = []
        j0, j1 = index.index(first), index.index(last) + 1
        for j, o in enumerate(est.run(start=j0, theta=self.theta, stop=j1), start=j0):
            if o.fit is not None:
                self.theta = o.fit.theta
            dist = None
            if o.data is not None:
                i0, i1, c0, c1 = o.data.crop
                dist = np.abs(est.index.s[i0:i1, c0:c1] - o.data.spec.centre)
            out.append(LiveWindow(index[j], o, None, ready[index[j]], time.perf_counter(), dist))
        return out


def play(bag, live: LiveEstimator, realtime: bool = False, progress=None):
    """Feed a recording to `live` in bag order and yield each LiveWindow as it is fitted; with
    `realtime`, at the recording's own pace (sweeps held until their time has come on the
    wall clock). progress: optional callable(n) per message."""
    from torchsoil.io.bag import stream_recording

    r = live.settings.pipeline.read
    start = None
    for name, item in stream_recording(bag, live.rec, r.front_topic, r.back_topic, r.tf_topic, r.base_frame,
                                       progress=progress, times=r.times, imu_topic=r.imu_topic):
        if name == "imu":
            live.add_imu(item)
            continue
        if realtime:
            if start is None:
                start = (time.perf_counter(), item.stamp)
            wait = (item.stamp - start[1]) - (time.perf_counter() - start[0])
            if wait > 0:
                time.sleep(wait)
        live.add_cloud(name, item)
        yield from live.poll()
    yield from live.finish()
