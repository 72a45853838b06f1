"""The node's messages against the conventions of ROS's own message definitions, by hand: an
OccupancyGrid is row-major with x fastest and its origin at the corner of cell (0, 0); a
PointCloud2's fields sit at their offsets; a DiagnosticStatus level is OK/WARN/STALE as the
row says; the ROS 1 and ROS 2 encodings round-trip."""

from __future__ import annotations

import math

import numpy as np
import pytest

from torchsoil.geo.gridmap import typestore as ros2_store
from torchsoil.grid import Grid
from torchsoil.node import messages as m
from torchsoil.node.ros1 import typestore as ros1_store


@pytest.fixture(params=["ros1", "ros2"])
def store(request):
    return ros1_store() if request.param == "ros1" else ros2_store()


def _roundtrip(store, msg, typename):
    if "seq" in store.types["std_msgs/msg/Header"].__dataclass_fields__:
        return store.deserialize_ros1(store.serialize_ros1(msg, typename), typename)
    return store.deserialize_cdr(store.serialize_cdr(msg, typename), typename)


def test_occupancy_grid_is_x_fastest_with_its_origin_at_the_first_cell_corner(store):
    grid = Grid(0.1, (2.0, -1.0), (3, 2))
    depth = np.array([[0.0, 0.05], [0.01, np.nan], [0.2, 0.025]])     # (X=3, Y=2)
    msg = _roundtrip(store, m.rut_grid(store, 12.5, "soil_map", grid, depth, full=0.05), "nav_msgs/msg/OccupancyGrid")
    assert (msg.info.width, msg.info.height) == (3, 2)
    assert msg.info.origin.position.x == pytest.approx(1.95) and msg.info.origin.position.y == pytest.approx(-1.05)
    # data[i + j * width]: the first row of the message is y = -1.0 (j = 0), x running along it
    assert list(msg.data) == [0, 20, 100, 100, -1, 50]
    assert msg.header.frame_id == "soil_map" and msg.header.stamp.sec == 12 and msg.header.stamp.nanosec == 500_000_000


def test_terrain_cloud_fields_read_back_at_their_offsets(store):
    grid = Grid(0.5, (0.0, 0.0), (2, 2))
    hb = np.array([[1.0, np.nan], [2.0, 3.0]])
    hf = np.array([[1.5, 0.0], [2.0, 2.5]])
    layers = {"h_back": hb, "h_delta": hb - hf, "rut_depth": np.maximum(hf - hb, 0.0)}
    msg = _roundtrip(store, m.terrain_cloud(store, 1.0, "soil_map", grid, layers), "sensor_msgs/msg/PointCloud2")
    assert msg.width == 3 and msg.point_step == 20 and msg.row_step == 60 and not msg.is_bigendian
    offsets = {f.name: f.offset for f in msg.fields}
    assert [f.datatype for f in msg.fields] == [7] * 5          # FLOAT32
    raw = np.asarray(msg.data, np.uint8).tobytes()
    pts = {name: np.frombuffer(raw, "<f4")[offsets[name] // 4::5] for name in offsets}
    assert pts["x"].tolist() == [0.0, 0.5, 0.5] and pts["y"].tolist() == [0.0, 0.0, 0.5]
    assert pts["z"].tolist() == [1.0, 2.0, 3.0]
    assert pts["h_delta"].tolist() == pytest.approx([-0.5, 0.0, 0.5])
    assert pts["rut_depth"].tolist() == pytest.approx([0.5, 0.0, 0.0])


def test_soil_status_levels_and_values(store):
    row = {"s": 2.4, "visit": 0, "d1": 0.012, "d2": 0.01, "chi": 0.3, "beta": 30.0, "flags": ""}
    ok = _roundtrip(store, m.soil_status(store, 5.0, "soil_map", 5, row, {"floor": 0.001}),
                    "diagnostic_msgs/msg/DiagnosticArray").status[0]
    assert ok.level == m.OK and "d1 12.0 mm" in ok.message
    values = {kv.key: kv.value for kv in ok.values}
    assert values["window"] == "5" and float(values["d1"]) == 0.012 and float(values["floor"]) == 0.001
    flagged = m.soil_status(store, 5.0, "soil_map", 5, row | {"flags": "few_valid"}, {}).status[0]
    skipped = m.soil_status(store, 5.0, "soil_map", 6, {"s": 2.8, "flags": "skipped_behind"}, {}).status[0]
    assert flagged.level == m.WARN and skipped.level == m.STALE and "skipped" in skipped.message


def test_soil_values_are_labelled_one_name_per_number(store):
    msg = _roundtrip(store, m.soil_values(store, {"s": 1.2, "d1": 0.02, "beta": 31.0}, {"floor": 0.002}),
                     "std_msgs/msg/Float64MultiArray")
    names = msg.layout.dim[0].label.split(",")
    assert len(names) == msg.layout.dim[0].size == len(msg.data)
    got = dict(zip(names, msg.data, strict=True))
    assert got["s"] == 1.2 and got["d1"] == 0.02 and got["beta"] == 31.0 and got["floor"] == 0.002
    assert math.isnan(got["chi"])


def test_transform_is_the_child_pose_in_the_parent(store):
    yaw = math.radians(90)
    T = np.eye(4)
    T[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    T[:3, 3] = [1.0, 2.0, 0.5]
    tf = _roundtrip(store, m.transform(store, 3.0, "base_link", "soil_map", T), "tf2_msgs/msg/TFMessage").transforms[0]
    assert tf.header.frame_id == "base_link" and tf.child_frame_id == "soil_map"
    assert (tf.transform.translation.x, tf.transform.translation.y, tf.transform.translation.z) == (1.0, 2.0, 0.5)
    q = tf.transform.rotation
    assert (q.z, q.w) == pytest.approx((math.sin(yaw / 2), math.cos(yaw / 2)))
