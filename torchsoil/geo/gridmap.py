"""The run's layers as `grid_map_msgs/msg/GridMap` messages (ROS 2) in an MCAP rosbag2, which
Foxglove and `ros2 bag play` read: the message definitions are registered with rosbags and
written into the file's schemas.

grid_map's conventions (grid_map_core, GridMapRosConverter): the map's pose is its centre;
matrix row r runs along -x and column c along -y from the cell of largest x and y (so
M[r, c] = A[X - 1 - r, Y - 1 - c] of a run's (X, Y) array); each layer is a
Float32MultiArray in Eigen's column-major order, dim[0] "column_index" (size Y, stride X*Y)
and dim[1] "row_index" (size X, stride X); start indices 0. NaN is grid_map's "no data".
A grid larger than `tile` cells a side goes out as tiles, one message each, stamped with the
time the robot passed the tile.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np

from torchsoil.grid import Grid

GRIDMAP = "grid_map_msgs/msg/GridMap"
GRIDMAP_MSG = """\
std_msgs/Header header
grid_map_msgs/GridMapInfo info
string[] layers
string[] basic_layers
std_msgs/Float32MultiArray[] data
uint16 outer_start_index
uint16 inner_start_index
"""
GRIDMAPINFO_MSG = """\
float64 resolution
float64 length_x
float64 length_y
geometry_msgs/Pose pose
"""
TILE = 512   # cells a side of one message


def typestore():
    """A ROS 2 typestore that knows grid_map_msgs/msg/GridMap and GridMapInfo."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    types = {}
    types.update(get_types_from_msg(GRIDMAPINFO_MSG, "grid_map_msgs/msg/GridMapInfo"))
    types.update(get_types_from_msg(GRIDMAP_MSG, GRIDMAP))
    store.register(types)
    return store


def to_gridmap_matrix(a: np.ndarray) -> np.ndarray:
    """(X, Y) run array (i along x) -> grid_map's (X, Y) matrix (row 0 at the largest x, column
    0 at the largest y)."""
    return a[::-1, ::-1]


def gridmap_message(store, grid: Grid, layers: dict[str, np.ndarray], frame: str, t_ns: int):
    """One GridMap of `layers` ({name: (X, Y) array on grid}) in `frame` at time t_ns."""
    T = store.types
    X, Y = grid.shape
    cx = grid.origin[0] + (X - 1) * grid.dx / 2
    cy = grid.origin[1] + (Y - 1) * grid.dx / 2
    dims = [T["std_msgs/msg/MultiArrayDimension"](label="column_index", size=Y, stride=X * Y),
            T["std_msgs/msg/MultiArrayDimension"](label="row_index", size=X, stride=X)]
    layout = T["std_msgs/msg/MultiArrayLayout"](dim=dims, data_offset=0)
    data = [T["std_msgs/msg/Float32MultiArray"](
        layout=layout, data=np.asarray(to_gridmap_matrix(a), np.float32).ravel(order="F"))
        for a in layers.values()]
    pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=cx, y=cy, z=0.0),
                                       orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
    info = T["grid_map_msgs/msg/GridMapInfo"](resolution=grid.dx, length_x=X * grid.dx, length_y=Y * grid.dx,
                                              pose=pose)
    header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=int(t_ns // 10**9),
                                                                             nanosec=int(t_ns % 10**9)),
                                      frame_id=frame)
    return T[GRIDMAP](header=header, info=info, layers=list(layers), basic_layers=[], data=data,
                      outer_start_index=0, inner_start_index=0)


def write_gridmap_bag(path: str | Path, grid: Grid, names: list[str],
                      block: Callable[[int, int, int, int], dict[str, np.ndarray]], poses: np.ndarray,
                      topic: str = "/soil/grid_map", frame: str = "map", tile: int = TILE) -> Path:
    """Write the rosbag2 directory `path` (storage mcap) with the grid as GridMap messages on
    `topic`: layers `names` from `block(i0, i1, j0, j1)`, one message per tile of `tile` cells a
    side, stamped with the time of the pose (N, 7) nearest the tile's centre. Returns the path
    of the .mcap file inside."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    path = Path(path)
    if path.exists():
        shutil.rmtree(path)
    store = typestore()
    X, Y = grid.shape
    pieces = []
    for i0 in range(0, X, tile):
        for j0 in range(0, Y, tile):
            i1, j1 = min(i0 + tile, X), min(j0 + tile, Y)
            sub = grid.crop(i0, i1, j0, j1)
            c = np.asarray(sub.origin) + (np.asarray(sub.shape) - 1) * sub.dx / 2
            t = float(poses[np.argmin(np.linalg.norm(poses[:, 1:3] - c, axis=1)), 0])
            pieces.append((t, i0, i1, j0, j1, sub))
    pieces.sort(key=lambda p: p[0])
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection(topic, GRIDMAP, typestore=store)
        last = -1
        for t, i0, i1, j0, j1, sub in pieces:
            t_ns = max(int(round(t * 1e9)), last + 1)   # strictly increasing stamps
            last = t_ns
            arrays = block(i0, i1, j0, j1)
            if not any(np.any(np.nan_to_num(a)) for a in arrays.values()):
                continue          # ground the drive never saw
            msg = gridmap_message(store, sub, {n: arrays[n] for n in names}, frame, t_ns)
            writer.write(conn, t_ns, store.serialize_cdr(msg, GRIDMAP))
    return next(path.glob("*.mcap"))
