"""The node's body, the same under ROS 1 and ROS 2: messages in (already deserialized, as
rosbags message objects), the soil estimate, the terrain near the robot and the node's health
out, through a `publish(name, msgtype, msg)` the transport gives.

    body = NodeBody(robot, settings, out_dir, publish, store)
    body.start()                                  # the processing thread
    body.receive("/lidar_front/points", "sensor_msgs/msg/PointCloud2", msg)   # from callbacks
    ...
    body.stop()                                   # at shutdown: the last windows, the run's outputs

Callbacks only queue (`receive` returns at once); one thread takes the queue in arrival
order through torchsoil.estimate.live.LiveEstimator (the pipeline, then the windows on its
fitting thread), writes each window's rows as `torchsoil estimate BAG` does (the same
torchsoil.jobs.estimate.LiveRun) and publishes it, and at `node.map_rate` the terrain near
the robot. Bounded everywhere: at most `node.queue` sweeps wait per lidar (the oldest is
dropped), at most `estimator.online.max_pending` stretches wait for fitting (later windows
are published as skipped, flag `skipped_behind`). A clock that jumps back (a bag played in a
loop) ends the drive: its outputs are written and a new drive begins in OUT/restart_NNN.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

import numpy as np

from torchsoil.estimate.live import CloudError
from torchsoil.node import messages as m
from torchsoil.robot import Robot
from torchsoil.settings import Settings

POINTCLOUD2 = "sensor_msgs/msg/PointCloud2"
TFMESSAGE = "tf2_msgs/msg/TFMessage"
IMU = "sensor_msgs/msg/Imu"

# name -> (message type, topic under the node's namespace, what it is): what the body publishes
OUTPUTS = {
    "soil": ("diagnostic_msgs/msg/DiagnosticArray", "~/soil", "each window's estimate as key-values"),
    "soil_values": ("std_msgs/msg/Float64MultiArray", "~/soil/values", "each window's numbers, labelled"),
    "terrain_cloud": (POINTCLOUD2, "~/terrain/cloud", "measured cells near the robot: x, y, z=H_b, h_delta, rut_depth"),
    "rut_grid": ("nav_msgs/msg/OccupancyGrid", "~/terrain/rut_depth", "rut depth near the robot, 100 = node.rut_full"),
    "grid_map": ("grid_map_msgs/msg/GridMap", "~/terrain/grid_map",
                 "the layers near the robot (ROS 2 with grid_map_msgs)"),
    "diagnostics": ("diagnostic_msgs/msg/DiagnosticArray", "/diagnostics", "the node's health"),
    "tf": (TFMESSAGE, "/tf", "the soil map frame under the robot's base frame"),
}
GRIDMAP_LAYERS = ("h_front", "h_back", "h_delta", "rut_depth", "passes")


def stamp_of(msg) -> float:
    """A message's header stamp, s."""
    st = msg.header.stamp
    return st.sec + 1e-9 * st.nanosec


class Health:
    """What /diagnostics says: per input topic its messages, rate over the last `span` s and
    age of the last; problems (the last few of each kind, counted)."""

    def __init__(self, span: float = 5.0):
        self.span = span
        self.arrivals: dict[str, deque] = {}
        self.dropped: dict[str, int] = {}
        self.count: dict[str, int] = {}
        self.problems: dict[str, list] = {}      # kind -> [count, last text, wall time]

    def arrived(self, topic: str, now: float) -> None:
        q = self.arrivals.setdefault(topic, deque())
        q.append(now)
        self.count[topic] = self.count.get(topic, 0) + 1
        while q and q[0] < now - self.span:
            q.popleft()

    def rate(self, topic: str, now: float) -> float:
        q = [t for t in self.arrivals.get(topic, ()) if t >= now - self.span]
        return len(q) / self.span

    def age(self, topic: str, now: float) -> float:
        q = self.arrivals.get(topic)
        return now - q[-1] if q else math.inf

    def problem(self, kind: str, text: str) -> None:
        entry = self.problems.setdefault(kind, [0, "", 0.0])
        entry[0] += 1
        entry[1], entry[2] = text, time.monotonic()


class NodeBody:
    """The running node (module docstring). robot; settings (the tree: `node`, `estimator`,
    `pipeline` with the extrinsics of the robot YAML); out: the run folder (params.csv ...);
    publish(name, msgtype, msg): the transport's, name a key of OUTPUTS; store: the rosbags
    typestore the transport serializes with; resume: continue out's params.csv (the same
    messages replayed: the windows written are not fitted again); gridmap: publish
    grid_map_msgs/GridMap (the transport knows whether the type is available)."""

    def __init__(self, robot: Robot, settings: Settings, out: str | Path, publish: Callable, store,
                 resume: bool = False, gridmap: bool = False, log: Callable[[str], None] = print):
        self.robot, self.settings, self.publish, self.store = robot, settings, publish, store
        self.out = Path(out)
        self.resume, self.gridmap, self.log = resume, gridmap, log
        r = settings.pipeline.read
        self.lidars = (r.front_topic, r.back_topic)
        self.imu_topic = {"": "/imu/data", "none": None}.get(r.imu_topic, r.imu_topic)   # a live graph: the usual name
        self.cfg = settings.node
        self.queue: deque = deque()
        self.waiting = {t: 0 for t in self.lidars}  # sweeps of each lidar in the queue
        self.keep_every = 1                  # lidar sweeps kept: one per keep_every periods (`_admit`)
        self.changed = -math.inf             # when keep_every last changed (perf_counter)
        self.slot: dict[str, int | None] = {}
        self.last_t: dict[str, float] = {}
        self.steps: dict[str, deque] = {}
        self.cond = threading.Condition()
        self.health = Health()
        self.thread: threading.Thread | None = None
        self.running = False
        self.drive = 0
        self.run = None                      # torchsoil.jobs.estimate.LiveRun of the current drive
        self.last_stamp: dict[str, float] = {}   # each stamped topic's latest, s
        self.arrival = time.perf_counter()   # arrival of the message being processed
        self.windows = 0
        self.skipped = 0
        self.latency: deque = deque(maxlen=200)
        self.recent: deque = deque(maxlen=64)  # the last rows, for the terrain's parameter layers
        self.next_map = 0.0
        self.next_health = 0.0
        self.error: BaseException | None = None

    # ------------------------------------------------------------------ input
    def receive(self, topic: str, msgtype: str, msg) -> None:
        """A message from a callback (any thread): queued, returns at once. When the pipeline
        falls behind, the lidars are thinned together (`_admit`), and a lidar's oldest queued
        sweep is dropped when `node.queue` of its sweeps still wait."""
        now = time.perf_counter()
        with self.cond:
            self.health.arrived(topic, time.monotonic())
            if topic in self.waiting:
                if not self._admit(topic, stamp_of(msg), now):
                    self.health.dropped[topic] = self.health.dropped.get(topic, 0) + 1
                    return
                if self.waiting[topic] >= self.cfg.queue:
                    for k, item in enumerate(self.queue):
                        if item[0] == topic:
                            del self.queue[k]
                            break
                    self.waiting[topic] -= 1
                    self.health.dropped[topic] = self.health.dropped.get(topic, 0) + 1
                self.waiting[topic] += 1
            elif len(self.queue) > 20 * self.cfg.queue + 1000:
                return     # the processing thread has stopped: keep memory bounded
            self.queue.append((topic, msgtype, msg, now))
            self.cond.notify()

    def _admit(self, topic: str, t: float, now: float) -> bool:
        """Whether a lidar sweep stamped t [s] is queued: one per `keep_every` sweep periods of
        each lidar, on the same slots for both (so that the sweeps kept still pair up and come
        at a steady rate, which the mapper needs). keep_every doubles (up to 8, at most every
        0.5 s) while `node.queue` - 1 sweeps of a lidar wait, and halves after 5 s with at most
        one waiting."""
        steps = self.steps.setdefault(topic, deque(maxlen=10))
        if topic in self.last_t and t > self.last_t[topic]:
            steps.append(t - self.last_t[topic])
        self.last_t[topic] = t
        backlog = max(self.waiting.values())
        if backlog >= self.cfg.queue - 1 and self.keep_every < 8 and now - self.changed > 0.5:
            self.keep_every, self.changed = 2 * self.keep_every, now
        elif backlog <= 1 and self.keep_every > 1 and now - self.changed > 5.0:
            self.keep_every, self.changed = self.keep_every // 2, now
        if self.keep_every == 1:
            self.slot[topic] = None
            return True
        period = float(np.median(steps)) if steps else 0.1
        slot = math.floor((t + period / 2) / (self.keep_every * period))
        if slot == self.slot.get(topic):
            return False
        self.slot[topic] = slot
        return True

    # ----------------------------------------------------------------- thread
    def start(self) -> None:
        """Open the run folder and start the processing thread."""
        self._open_drive()
        self.running = True
        self.thread = threading.Thread(target=self._loop, name="torchsoil-node", daemon=True)
        self.thread.start()

    def stop(self) -> None:
        """Shutdown: the queued messages are processed, the last windows fitted and published,
        the run's outputs written."""
        with self.cond:
            self.running = False
            self.cond.notify()
        if self.thread is not None:
            self.thread.join()
        self._end_drive()
        self.publish("diagnostics", OUTPUTS["diagnostics"][0], self.diagnostics())   # the final count
        h = self.health
        self.log("torchsoil node: " + ", ".join(f"{t}: {h.count.get(t, 0)} messages, {h.dropped.get(t, 0)} dropped"
                                                 for t in sorted(h.count)) +
                 f"; {self.windows} windows, {self.skipped} skipped")

    def _loop(self) -> None:
        while True:
            with self.cond:
                if not self.queue and self.running:
                    self.cond.wait(timeout=0.05)
                if not self.queue and not self.running:
                    return
                item = self.queue.popleft() if self.queue else None
                if item is not None and item[0] in self.waiting:
                    self.waiting[item[0]] -= 1
            try:
                if item is not None:
                    self._handle(*item)
                self._timers()
            except Exception as e:   # said on /diagnostics and the log; the node goes on
                import traceback

                self.health.problem("error", f"{type(e).__name__}: {e}")
                self.log(f"torchsoil node: {type(e).__name__}: {e}\n{traceback.format_exc(limit=-3)}")

    def _timers(self) -> None:
        now = time.perf_counter()
        if now >= self.next_health:
            self.next_health = now + 1.0 / self.cfg.diagnostics_rate
            self.publish("diagnostics", OUTPUTS["diagnostics"][0], self.diagnostics())
        if self.cfg.map_rate > 0 and now >= self.next_map:
            self.next_map = now + 1.0 / self.cfg.map_rate
            self.publish_terrain()

    # -------------------------------------------------------------- messages
    def _handle(self, topic: str, msgtype: str, msg, arrival: float) -> None:
        self.arrival = arrival
        if msgtype != TFMESSAGE:
            self._check_clock(topic, stamp_of(msg))
        live = self.run.live
        if msgtype == TFMESSAGE:
            if any(t.child_frame_id.lstrip("/") != self.cfg.map_frame for t in msg.transforms):
                live.add_transforms(msg)      # not the node's own soil_map frame
        elif msgtype == IMU:
            live.add_imu(msg)
        elif topic in self.lidars:
            self._lidar(topic, msgtype, msg)
        for w in live.poll():
            self._window(w)

    def _check_clock(self, topic: str, t: float) -> None:
        """A stamp `node.clock_jump` s before the last of its topic ends the drive and begins a
        new one (the transforms known go on: /tf_static comes once)."""
        last = self.last_stamp.get(topic, -math.inf)
        if t < last - self.cfg.clock_jump:
            self.health.problem("clock", f"{topic}: the clock jumped back {last - t:.1f} s (a bag played again?): "
                                         f"drive {self.drive} ended, a new one begins")
            known = dict(self.run.live.edges)
            self._end_drive()
            self._open_drive(new=True, edges=known)
            last = -math.inf
        self.last_stamp[topic] = max(last, t)

    def _lidar(self, topic: str, msgtype: str, msg) -> None:
        t = stamp_of(msg)
        live = self.run.live
        live.pipeline.keep_every = self.keep_every
        try:
            live.add_message(topic, msg, msgtype)
            pipe = live.pipeline
            if pipe.ext is None and pipe.held:
                frames = ", ".join(sorted(set(pipe.frames.values())))
                self.health.problem("tf", f"{len(pipe.held)} sweeps wait for the transforms of {frames} to "
                                          f"{self.settings.pipeline.read.base_frame} (is /tf_static published?)")
        except CloudError as e:
            self.health.problem("cloud", f"sweep at t={t:.3f} s skipped: {e}")
        except ValueError as e:
            pipe = live.pipeline
            if pipe.ext is not None:
                raise
            del pipe.held[:-50]          # waiting for the transforms: the last 50 sweeps kept
            self.health.problem("tf", f"{topic}: no transform to its frame yet ({e})")

    def _window(self, w) -> None:
        """A fitted (or skipped) window: rows written, published."""
        self.run.add(w)
        row = self.run.params.rows[-1]
        ref = w.output.reference
        lat = time.perf_counter() - w.ready
        self.windows += 1
        if "skipped" in str(row.get("flags", "")):
            self.skipped += 1
        else:
            self.latency.append(lat)
            self.recent.append(row)
        t = row["t"] if math.isfinite(row.get("t", math.nan)) else self._now_stamp()
        self.publish("soil", OUTPUTS["soil"][0], m.soil_status(self.store, t, self.cfg.map_frame, w.index, row, ref))
        self.publish("soil_values", OUTPUTS["soil_values"][0],
                     m.soil_values(self.store, row | {"latency": lat}, ref))

    def _now_stamp(self) -> float:
        stamps = [self.last_stamp[t] for t in self.lidars if t in self.last_stamp]
        return max(stamps) if stamps else 0.0

    # ----------------------------------------------------------------- drives
    def _open_drive(self, new: bool = False, edges: dict | None = None) -> None:
        """A drive's run folder and LiveRun (OUT, then OUT/restart_NNN); edges: the transforms
        known so far (frame -> edge, LiveEstimator.edges)."""
        from torchsoil.jobs.estimate import LiveRun

        self.drive += 1
        out = self.out if self.drive == 1 else self.out / f"restart_{self.drive - 1:03d}"
        out.mkdir(parents=True, exist_ok=True)
        self.run = LiveRun(out, self.robot, self.settings, self.resume and not new, tensorboard=self.cfg.tensorboard)
        self.run.live.clock = lambda: self.arrival
        self.run.live.when_behind = "skip"
        if edges:
            self.run.live.add_edges(edges)
        self.last_stamp = {}
        self.recent.clear()

    def _end_drive(self) -> None:
        """The drive's last windows fitted, published and written, then its outputs."""
        run = self.run
        if run is None:
            return
        self.run = None
        live = run.live
        try:
            if not live.pipeline.ok_stamps and live.pipeline.mapper is None:
                self.log(f"torchsoil node: drive {self.drive}: no sweep mapped, nothing to finish")
                run.close()
                return
            self.run = run
            for w in live.finish():
                self._window(w)
            run.close()
            run.finish("ros")
            self.log(f"torchsoil node: drive {self.drive}: {len(run.params.rows)} windows written to {run.out}")
        except Exception as e:
            run.close()
            self.health.problem("finish", f"drive {self.drive}: {type(e).__name__}: {e}")
            import traceback

            self.log(f"torchsoil node: drive {self.drive}: its outputs could not be finished: {type(e).__name__}: {e}"
                     f"\n{traceback.format_exc(limit=-4)}")
        finally:
            self.run = None

    # ------------------------------------------------------------------ views
    def terrain_layers(self):
        """(grid, layers) of the ground near the robot: the last `node.map_length` m of the
        path, layers as torchsoil.geo.layers (the recent windows' parameters painted on their
        ground); None before there is any."""
        from torchsoil.estimate.windows import path_arc
        from torchsoil.geo.layers import Run, raster_layers

        pipe = self.run.live.pipeline if self.run is not None else None
        if pipe is None or pipe.mapper is None or len(pipe.ok_stamps) < 2:
            return None
        stamps, poses = pipe.trajectory()
        if len(stamps) < 2:
            return None
        arc = path_arc(np.column_stack([stamps, poses[:, :3, 3], np.zeros((len(stamps), 3))]))
        k0 = int(np.searchsorted(arc, arc[-1] - self.cfg.map_length))
        k0 = min(k0, len(stamps) - 2)
        pair = pipe.terrain(stamps[k0], stamps[-1])
        e = self.settings.estimator
        rows = list(self.recent)
        run = Run(pair, self.out, rows=rows, names=list(self.run.names) if rows else [], window=e.window,
                  corridor=e.corridor, arc0=float(arc[k0]))
        return pair.grid, raster_layers(run)

    def publish_terrain(self) -> None:
        """The terrain near the robot: PointCloud2, OccupancyGrid of rut depth, GridMap, and the
        soil map frame in TF (under the robot's base frame)."""
        got = self.terrain_layers()
        if got is None:
            return
        grid, layers = got
        stamps, poses = self.run.live.pipeline.trajectory()
        t, frame = float(stamps[-1]), self.cfg.map_frame
        self.publish("terrain_cloud", POINTCLOUD2, m.terrain_cloud(self.store, t, frame, grid, layers))
        self.publish("rut_grid", OUTPUTS["rut_grid"][0],
                     m.rut_grid(self.store, t, frame, grid, layers["rut_depth"], self.cfg.rut_full))
        if self.gridmap:
            from torchsoil.geo.gridmap import gridmap_message

            names = [n for n in (*GRIDMAP_LAYERS, *self.run.names) if n in layers]
            self.publish("grid_map", OUTPUTS["grid_map"][0],
                         gridmap_message(self.store, grid, {n: layers[n] for n in names}, frame, int(t * 1e9)))
        if self.cfg.publish_tf:
            base = self.settings.pipeline.read.base_frame
            self.publish("tf", TFMESSAGE, m.transform(self.store, t, base, frame, np.linalg.inv(poses[-1])))

    def diagnostics(self):
        """/diagnostics: inputs (rate, age, dropped), estimator (windows, skipped, latency,
        backlog), problems."""
        now, st = time.monotonic(), self.store
        h, cfg = self.health, self.cfg
        statuses = []
        r = self.settings.pipeline.read
        for topic in (*self.lidars, self.imu_topic or "", r.tf_topic):
            if not topic:
                continue
            age, rate = h.age(topic, now), h.rate(topic, now)
            lidar = topic in self.lidars
            level = m.OK
            msg = f"{rate:.1f} Hz"
            if lidar and age > cfg.silence:
                level = m.WARN if math.isfinite(age) else m.ERROR
                msg = f"silent for {age:.1f} s" if math.isfinite(age) else "no message yet"
            elif lidar and h.dropped.get(topic):
                level, msg = m.WARN, f"{rate:.1f} Hz, {h.dropped[topic]} sweeps dropped (the pipeline behind)"
            statuses.append(m.status(st, f"torchsoil: input {topic}", level if lidar else m.OK, msg,
                                     {"messages": h.count.get(topic, 0), "rate_hz": rate, "last_message_age_s": age,
                                      "dropped": h.dropped.get(topic, 0)}))
        lat = np.asarray(self.latency) if self.latency else np.zeros(1)
        live = self.run.live if self.run is not None else None
        backlog = sum(self.waiting.values())
        pending = len(live.pending) if live is not None else 0
        behind = self.skipped or pending >= self.settings.estimator.online.max_pending or self.keep_every > 1
        thinned = f", lidars thinned to 1 sweep in {self.keep_every} (behind)" if self.keep_every > 1 else ""
        statuses.append(m.status(st, "torchsoil: estimator", m.WARN if behind else m.OK,
                                 f"{self.windows} windows, {self.skipped} skipped, latency median "
                                 f"{np.nanmedian(lat):.2f} s{thinned}",
                                 {"drive": self.drive, "windows": self.windows, "skipped": self.skipped,
                                  "latency_median_s": float(np.nanmedian(lat)), "latency_max_s": float(np.nanmax(lat)),
                                  "queued_sweeps": backlog, "pending_stretches": pending,
                                  "keep_every": self.keep_every}))
        fresh = {k: v for k, v in h.problems.items() if now - v[2] < 30.0}
        level = m.ERROR if "error" in fresh else m.WARN if fresh else m.OK
        text = "; ".join(f"{k}: {v[1]}" for k, v in fresh.items()) or "none"
        statuses.append(m.status(st, "torchsoil: problems", level, text[:500],
                                 {f"{k}_count": v[0] for k, v in h.problems.items()}))
        return m.diagnostic_array(st, self._now_stamp(), statuses)
