"""What the node publishes, as rosbags message objects of a typestore (ROS 1 or ROS 2: only the
Header differs, `seq` in ROS 1), so that one body serves both transports.

- `soil_status`: a window's estimate as a diagnostic_msgs/DiagnosticArray of key-values (every
  params.csv column, the noise floor and deformation signal), what `rostopic echo`,
  `ros2 topic echo`, rqt and Foxglove show without building anything.
- `soil_values`: the same numbers as a std_msgs/Float64MultiArray, labelled: dim[0].label is
  the comma-separated column names (`SOIL_VALUES`), dim[0].size their number; plot one with
  PlotJuggler or `rqt_plot /torchsoil/soil/values/data[3]`.
- `terrain_cloud`: sensor_msgs/PointCloud2 of the measured cells near the robot, fields x, y,
  z (the surface after the wheels, H_b), h_delta and rut_depth (float32, metres).
- `rut_grid`: nav_msgs/OccupancyGrid of rut depth: 0 flat, 100 at `full` metres or deeper,
  -1 unmeasured or off the wheel tracks.
- `health`: /diagnostics statuses.
- `gridmap`: grid_map_msgs/msg/GridMap (ROS 2), layers of torchsoil.geo.layers.
"""

from __future__ import annotations

import math

import numpy as np

from torchsoil.grid import Grid

SOIL_VALUES = ("s", "visit", "passes_before", "d1", "d2", "chi", "beta", "residual", "prediction", "floor",
               "signal", "latency")
OK, WARN, ERROR, STALE = 0, 1, 2, 3   # diagnostic_msgs/DiagnosticStatus levels


def stamp(store, t: float):
    """builtin_interfaces/Time of t seconds."""
    ns = int(round(max(t, 0.0) * 1e9))
    return store.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def header(store, t: float, frame: str):
    """std_msgs/Header at t seconds in `frame` (seq 0 in ROS 1: the transport numbers messages)."""
    H = store.types["std_msgs/msg/Header"]
    kw = {"seq": 0} if "seq" in H.__dataclass_fields__ else {}
    return H(**kw, stamp=stamp(store, t), frame_id=frame)


def _text(v) -> str:
    if isinstance(v, float):
        return "nan" if math.isnan(v) else f"{v:.6g}"
    return str(v)


def status(store, name: str, level: int, message: str, values: dict, hardware_id: str = "torchsoil"):
    """diagnostic_msgs/DiagnosticStatus with key-values `values` (printed with 6 digits)."""
    T = store.types
    kv = [T["diagnostic_msgs/msg/KeyValue"](key=str(k), value=_text(v)) for k, v in values.items()]
    return T["diagnostic_msgs/msg/DiagnosticStatus"](level=int(level), name=name, message=message,
                                                     hardware_id=hardware_id, values=kv)


def diagnostic_array(store, t: float, statuses: list):
    return store.types["diagnostic_msgs/msg/DiagnosticArray"](header=header(store, t, ""), status=statuses)


def soil_status(store, t: float, frame: str, index: int, row: dict, reference: dict):
    """A window's estimate (params.csv row `row`, beta in degrees; reference: signal, floor, m)
    as a DiagnosticArray of one status named `torchsoil/soil`: level OK, WARN when flagged,
    STALE when skipped."""
    flags = str(row.get("flags", "") or "")
    level = STALE if "skipped" in flags else WARN if flags else OK
    msg = (f"window {index} s {row['s']:.2f} m: skipped ({flags})" if level == STALE else
           f"window {index} s {row['s']:.2f} m d1 {1e3 * row.get('d1', math.nan):.1f} mm "
           f"chi {row.get('chi', math.nan):.2f} beta {row.get('beta', math.nan):.1f} deg"
           + (f" [{flags}]" if flags else ""))
    values = {"window": index, **row, "signal": reference.get("signal", math.nan),
              "floor": reference.get("floor", math.nan)}
    return diagnostic_array(store, t, [status(store, "torchsoil/soil", level, msg, values)])


def soil_values(store, row: dict, reference: dict):
    """The window's numbers (SOIL_VALUES, NaN where absent) as a labelled Float64MultiArray."""
    T = store.types
    merged = {**row, **reference}
    data = np.array([float(merged.get(k, math.nan)) for k in SOIL_VALUES], np.float64)
    dim = T["std_msgs/msg/MultiArrayDimension"](label=",".join(SOIL_VALUES), size=len(SOIL_VALUES),
                                                 stride=len(SOIL_VALUES))
    return T["std_msgs/msg/Float64MultiArray"](layout=T["std_msgs/msg/MultiArrayLayout"](dim=[dim], data_offset=0),
                                               data=data)


def terrain_cloud(store, t: float, frame: str, grid: Grid, layers: dict[str, np.ndarray]):
    """PointCloud2 of the cells where H_f and H_b are measured: x, y (cell centres), z = H_b,
    h_delta, rut_depth (NaN off the wheel tracks); float32 fields, little-endian, dense."""
    T = store.types
    hb, hd = layers["h_back"], layers["h_delta"]
    ok = np.isfinite(hb) & np.isfinite(hd)
    xs, ys = grid.centers()
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    pts = np.column_stack([X[ok], Y[ok], hb[ok], hd[ok], layers["rut_depth"][ok]]).astype("<f4")
    names = ("x", "y", "z", "h_delta", "rut_depth")
    fields = [T["sensor_msgs/msg/PointField"](name=n, offset=4 * k, datatype=7, count=1) for k, n in enumerate(names)]
    return T["sensor_msgs/msg/PointCloud2"](header=header(store, t, frame), height=1, width=len(pts), fields=fields,
                                            is_bigendian=False, point_step=4 * len(names),
                                            row_step=4 * len(names) * len(pts),
                                            data=np.frombuffer(pts.tobytes(), np.uint8), is_dense=True)


def rut_grid(store, t: float, frame: str, grid: Grid, rut_depth: np.ndarray, full: float = 0.05):
    """OccupancyGrid of rut depth (X, Y) [m] on `grid`: round(100 * depth / full) clipped to
    0..100, -1 where NaN. Cell (i, j) is data[i + j * X] (x fastest), origin the corner of
    cell (0, 0)."""
    T = store.types
    X, Y = grid.shape
    occ = np.where(np.isfinite(rut_depth), np.clip(np.round(100.0 * np.nan_to_num(rut_depth) / full), 0, 100), -1)
    info = T["nav_msgs/msg/MapMetaData"](
        map_load_time=stamp(store, t), resolution=float(grid.dx), width=X, height=Y,
        origin=T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=grid.origin[0] - grid.dx / 2, y=grid.origin[1] - grid.dx / 2,
                                                  z=0.0),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0)))
    return T["nav_msgs/msg/OccupancyGrid"](header=header(store, t, frame), info=info,
                                           data=occ.T.ravel().astype(np.int8))


def transform(store, t: float, parent: str, child: str, T_pc: np.ndarray):
    """tf2_msgs/TFMessage of one transform: `child` in `parent` given as the (4, 4) pose of
    child in parent."""
    from scipy.spatial.transform import Rotation

    T = store.types
    q = Rotation.from_matrix(T_pc[:3, :3]).as_quat()
    tr = T["geometry_msgs/msg/Transform"](
        translation=T["geometry_msgs/msg/Vector3"](x=float(T_pc[0, 3]), y=float(T_pc[1, 3]), z=float(T_pc[2, 3])),
        rotation=T["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))
    ts = T["geometry_msgs/msg/TransformStamped"](header=header(store, t, parent), child_frame_id=child, transform=tr)
    return T["tf2_msgs/msg/TFMessage"](transforms=[ts])
