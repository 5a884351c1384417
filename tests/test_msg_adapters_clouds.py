"""Gaussian and semantic PointCloud2s, object MarkerArrays and SemanticObject messages."""

from __future__ import annotations

import array
import dataclasses
import time

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import PointCloud2, PointField
from visualization_msgs.msg import Marker, MarkerArray

from monovoc_interfaces.msg import SemanticObject
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.map.ply import SH_C0
from msg_adapters import (
    AdapterError,
    cloud_to_gaussian_map,
    gaussian_map_to_cloud,
    object_markers,
    point_cloud_from_cdr,
    semantic_cloud_from_arrays,
    semantic_cloud_to_arrays,
    semantic_object,
    semantic_object_to_dict,
    serialized_semantic_cloud,
    time_to_ns,
)
from msg_adapters.gaussian_cloud import COLOR_FIELDS, REQUIRED_FIELDS
from msg_adapters.point_cloud import points_offset

SCHEMA = ["x", "y", "z", "scale_0", "scale_1", "scale_2", "rot_w", "rot_x", "rot_y", "rot_z", "opacity",
          "f_dc_0", "f_dc_1", "f_dc_2", "id"]  # fmt: skip
_DATATYPES = {"f4": PointField.FLOAT32, "f8": PointField.FLOAT64, "u4": PointField.UINT32, "i4": PointField.INT32,
              "u1": PointField.UINT8, "i2": PointField.INT16}  # fmt: skip


def _wire(msg):
    return deserialize_message(serialize_message(msg), type(msg))


def _gaussians(n: int, seed: int = 0, *, colors: bool = True, ids: bool = True) -> GaussianMap:
    rng = np.random.default_rng(seed)
    return GaussianMap(
        means=rng.normal(size=(n, 3)) * 3,
        scales=rng.uniform(0.005, 0.2, (n, 3)),
        quats=rng.normal(size=(n, 4)),
        opacities=rng.uniform(0.0, 1.0, n),
        colors=rng.uniform(0.0, 1.0, (n, 3)) if colors else None,
        ids=rng.permutation(10 * n)[:n] if ids else None,
    )


def _cloud_from_structured(points: np.ndarray, *, height: int = 1, row_pad: int = 0) -> PointCloud2:
    """A PointCloud2 from a structured array as any publisher might lay it out (offsets, padding, endianness)."""
    dt = points.dtype
    fields = [
        PointField(name=name, offset=off, datatype=_DATATYPES[sub.str[1:]], count=1)
        for name, (sub, off) in dt.fields.items()
    ]
    width = points.size // height
    rows = points.view(np.uint8).reshape(height, width * dt.itemsize)
    if row_pad:
        rows = np.concatenate([rows, np.full((height, row_pad), 0xAB, np.uint8)], axis=1)
    msg = PointCloud2(height=height, width=width, fields=fields, point_step=dt.itemsize)
    msg.row_step = width * dt.itemsize + row_pad
    msg.is_bigendian = dt.fields["x"][0].byteorder == ">"
    msg.data = array.array("B", rows.tobytes())
    return msg


def _assert_maps_equal(a: GaussianMap, b: GaussianMap) -> None:
    np.testing.assert_array_equal(a.means, b.means)
    np.testing.assert_array_equal(a.scales, b.scales)
    np.testing.assert_array_equal(a.opacities, b.opacities)
    np.testing.assert_allclose(a.quats, b.quats, atol=1e-6)
    if a.colors is None:
        assert b.colors is None
    else:
        np.testing.assert_allclose(a.colors, b.colors, atol=1e-6)
    if a.ids is None:
        assert b.ids is None
    else:
        np.testing.assert_array_equal(a.ids, b.ids)


def test_gaussian_cloud_round_trip_with_the_documented_schema() -> None:
    gmap = _gaussians(1000)
    msg = gaussian_map_to_cloud(gmap, frame_id="map", stamp=123)
    assert [f.name for f in msg.fields] == SCHEMA
    assert [f.datatype for f in msg.fields] == [PointField.FLOAT32] * 14 + [PointField.UINT32]
    assert [f.offset for f in msg.fields] == list(range(0, 60, 4))
    assert (msg.point_step, msg.height, msg.width, msg.is_bigendian) == (60, 1, 1000, False)
    back = _wire(msg)
    assert back.header.frame_id == "map" and time_to_ns(back.header.stamp) == 123
    _assert_maps_equal(gmap, cloud_to_gaussian_map(back))
    assert cloud_to_gaussian_map(back).stamp_ns == 123  # the map's stamp: keyframes at or after it are in its frame
    stamped = dataclasses.replace(gmap, stamp_ns=456)
    assert cloud_to_gaussian_map(_wire(gaussian_map_to_cloud(stamped))).stamp_ns == 456
    # f_dc holds raw SH coefficients, as in the PLY.
    row = np.frombuffer(bytes(msg.data), np.float32, count=15)
    np.testing.assert_allclose(row[11:14], (gmap.colors[0] - 0.5) / SH_C0, rtol=1e-5)


def test_gaussian_cloud_without_colors_or_ids() -> None:
    gmap = _gaussians(50, colors=False, ids=False)
    msg = gaussian_map_to_cloud(gmap)
    assert [f.name for f in msg.fields] == SCHEMA[:11] and msg.point_step == 44
    _assert_maps_equal(gmap, cloud_to_gaussian_map(_wire(msg)))
    with_ids = _gaussians(50)
    dropped = gaussian_map_to_cloud(with_ids, include_ids=False)
    assert "id" not in [f.name for f in dropped.fields]
    assert cloud_to_gaussian_map(dropped).ids is None
    empty = cloud_to_gaussian_map(gaussian_map_to_cloud(_gaussians(0)))
    assert len(empty) == 0 and empty.ids is not None


@pytest.mark.parametrize("byteorder", ["<", ">"])
def test_gaussian_cloud_any_layout(byteorder: str) -> None:
    """Shuffled field order, unrelated fields, point_step padding, float64, int32 ids, row padding."""
    gmap = _gaussians(24, seed=3)
    rng = np.random.default_rng(1)
    names = list(SCHEMA) + ["intensity"]
    rng.shuffle(names)
    formats = {name: byteorder + ("i4" if name == "id" else "f8" if name in ("x", "opacity", "rot_y") else "f4")
               for name in names}  # fmt: skip
    offsets, off = {}, 2
    for name in names:
        offsets[name] = off
        off += int(formats[name][-1]) + 1  # one byte of padding between fields
    dt = np.dtype({"names": names, "formats": [formats[n] for n in names], "offsets": [offsets[n] for n in names],
                   "itemsize": off + 5})  # fmt: skip
    points = np.zeros(24, dtype=dt)
    f_dc = (gmap.colors - 0.5) / SH_C0
    columns = {"x": gmap.means[:, 0], "y": gmap.means[:, 1], "z": gmap.means[:, 2], "opacity": gmap.opacities,
               "id": gmap.ids, "intensity": np.ones(24)}  # fmt: skip
    columns.update({f"scale_{i}": gmap.scales[:, i] for i in range(3)})
    columns.update({f"rot_{c}": gmap.quats[:, i] for i, c in enumerate("wxyz")})
    columns.update({f"f_dc_{i}": f_dc[:, i] for i in range(3)})
    for name in names:
        points[name] = columns[name]
    for height, row_pad in ((1, 0), (4, 0), (3, 16)):
        msg = _wire(_cloud_from_structured(points, height=height, row_pad=row_pad))
        assert msg.is_bigendian == (byteorder == ">")
        _assert_maps_equal(gmap, cloud_to_gaussian_map(msg))


def test_gaussian_cloud_rejects_bad_input() -> None:
    gmap = _gaussians(10)
    good = gaussian_map_to_cloud(gmap)

    def without(*names: str) -> PointCloud2:
        msg = _wire(good)
        msg.fields = [f for f in msg.fields if f.name not in names]
        return msg

    def with_field(name: str, **changes) -> PointCloud2:
        msg = _wire(good)
        for f in msg.fields:
            if f.name == name:
                for k, v in changes.items():
                    setattr(f, k, v)
        return msg

    def with_value(column: int, value: float) -> PointCloud2:
        data = np.frombuffer(bytes(good.data), np.float32).reshape(10, 15).copy()
        data[3, column] = value
        msg = _wire(good)
        msg.data = array.array("B", data.tobytes())
        return msg

    with pytest.raises(AdapterError, match=r"missing required fields \['scale_1', 'rot_w'\]"):
        cloud_to_gaussian_map(without("scale_1", "rot_w"))
    with pytest.raises(AdapterError, match="field 'opacity' has datatype UINT8, expected FLOAT32 or FLOAT64"):
        cloud_to_gaussian_map(with_field("opacity", datatype=PointField.UINT8))
    with pytest.raises(AdapterError, match="field 'id' has datatype FLOAT32"):
        cloud_to_gaussian_map(with_field("id", datatype=PointField.FLOAT32))
    with pytest.raises(AdapterError, match="field 'x' has unknown datatype 42"):
        cloud_to_gaussian_map(with_field("x", datatype=42))
    with pytest.raises(AdapterError, match="field 'rot_z' has count 3"):
        cloud_to_gaussian_map(with_field("rot_z", count=3))
    with pytest.raises(AdapterError, match="field 'id' at offset 58 does not fit point_step 60"):
        cloud_to_gaussian_map(with_field("id", offset=58))
    with pytest.raises(AdapterError, match="color fields must come as a group; missing \\['f_dc_2'\\]"):
        cloud_to_gaussian_map(without("f_dc_2"))
    with pytest.raises(AdapterError, match=r"NaN/inf values in position fields \['y'\] \(first at point 3\)"):
        cloud_to_gaussian_map(with_value(1, np.nan))
    with pytest.raises(AdapterError, match="log-scales sent"):
        cloud_to_gaussian_map(with_value(4, -4.5))
    with pytest.raises(AdapterError, match="logits sent"):
        cloud_to_gaussian_map(with_value(10, 2.5))
    short = _wire(good)
    short.data = array.array("B", bytes(good.data)[:-1])
    with pytest.raises(AdapterError, match="data has 599 bytes, 10x1 points need 600"):
        cloud_to_gaussian_map(short)
    # Names are names, not payloads: an error quotes them, and the map reader sends its errors in one message.
    extra = _wire(good)
    extra.fields = list(extra.fields) + [PointField(name="n" * 1025, offset=0, datatype=PointField.UINT8, count=1)]
    with pytest.raises(AdapterError, match="a field name of 1025 characters \\(at most 1024\\)"):
        cloud_to_gaussian_map(extra)
    extra.fields[-1].name = "n" * 1024  # at the limit: an extra field like any other
    assert len(cloud_to_gaussian_map(extra)) == 10
    many = without("x")
    many.fields = list(many.fields) + [
        PointField(name=f"{k:05d}" + "m" * 1000, offset=0, datatype=PointField.UINT8, count=1) for k in range(20000)
    ]
    with pytest.raises(AdapterError, match="missing required fields \\['x'\\]") as refused:
        cloud_to_gaussian_map(many)
    assert "and 19998 more" in str(refused.value) and len(str(refused.value)) < 2000
    dup = _wire(good)
    dup.fields = list(dup.fields) + [PointField(name="x", offset=4, datatype=PointField.FLOAT32, count=1)]
    with pytest.raises(AdapterError, match="field 'x' appears more than once"):
        cloud_to_gaussian_map(dup)
    zero_q = np.frombuffer(bytes(good.data), np.float32).reshape(10, 15).copy()
    zero_q[5, 6:10] = 0
    bad = _wire(good)
    bad.data = array.array("B", zero_q.tobytes())
    with pytest.raises(AdapterError, match=r"1 zero quaternions \(first at point 5\)"):
        cloud_to_gaussian_map(bad)
    same_ids = np.frombuffer(bytes(good.data), np.uint32).reshape(10, 15).copy()
    same_ids[:, 14] = 7
    bad.data = array.array("B", same_ids.tobytes())
    with pytest.raises(AdapterError, match="ids must be unique"):
        cloud_to_gaussian_map(bad)
    big_ids = GaussianMap(gmap.means, gmap.scales, gmap.quats, gmap.opacities, ids=np.arange(10) + 2**32)
    with pytest.raises(AdapterError, match="ids must fit uint32"):
        gaussian_map_to_cloud(big_ids)


@pytest.mark.parametrize("ids", [True, False])
def test_gaussian_cloud_from_serialized_bytes_equals_rclpy_s(ids: bool) -> None:
    """A raw subscription's bytes decoded without rclpy: the same map, bit for bit, from arrays of their own (not views
    of the message's buffer, which the map would otherwise keep alive)."""
    gmap = _gaussians(500, ids=ids)
    data = serialize_message(gaussian_map_to_cloud(gmap, frame_id="odom", stamp=12_500_000_000))
    msg = point_cloud_from_cdr(data)
    assert str(msg.header.frame_id) == "odom" and time_to_ns(msg.header.stamp) == 12_500_000_000
    got, want = cloud_to_gaussian_map(msg), cloud_to_gaussian_map(deserialize_message(data, PointCloud2))
    for name in ("means", "scales", "quats", "opacities", "colors", "ids"):
        a, b = getattr(got, name), getattr(want, name)
        assert (a is None) == (b is None) and (a is None or (a.dtype == b.dtype and np.array_equal(a, b))), name
        assert a is None or a.base is None or not np.shares_memory(a, np.frombuffer(data, np.uint8)), name
    assert got.stamp_ns == want.stamp_ns == 12_500_000_000


def test_gaussian_map_from_serialized_bytes_in_either_byte_order() -> None:
    """What the node, its map reader and offline mapping read: the map and the frame; big-endian CDR (a publisher on
    a big-endian machine) gives the same map; a frame_id that is no UTF-8 or too long refuses the message (rclpy
    replaced such bytes: docs/robustness.md)."""
    from rosbags.typesys import Stores, get_typestore

    from msg_adapters import gaussian_map_from_cdr

    gmap = _gaussians(300)
    data = serialize_message(gaussian_map_to_cloud(gmap, frame_id="odom", stamp=3))
    got, frame = gaussian_map_from_cdr(data)
    assert frame == "odom" and got.stamp_ns == 3
    store = get_typestore(Stores.ROS2_JAZZY)
    big = bytes(store.serialize_cdr(point_cloud_from_cdr(data), "sensor_msgs/msg/PointCloud2", little_endian=False))
    assert big[:2] == b"\x00\x00"
    got_big, frame_big = gaussian_map_from_cdr(big)
    assert frame_big == "odom"
    for name in ("means", "scales", "quats", "opacities", "colors", "ids"):
        np.testing.assert_array_equal(getattr(got_big, name), getattr(got, name))
    at = data.index(b"odom")
    with pytest.raises(AdapterError, match="not a serialized PointCloud2"):
        gaussian_map_from_cdr(data[:at] + b"\xff\xfedm" + data[at + 4 :])
    with pytest.raises(AdapterError, match="frame_id of 2000 characters"):
        gaussian_map_from_cdr(serialize_message(gaussian_map_to_cloud(gmap, frame_id="f" * 2000)))


def test_serialized_bytes_that_are_no_point_cloud_are_refused() -> None:
    from std_msgs.msg import String

    data = serialize_message(gaussian_map_to_cloud(_gaussians(50)))
    for bad in (data[:-1], data[:1500], data[:40], b"\x07", b"", b"\x00\x01\x00\x00" + bytes(range(256)),
                serialize_message(String(data="not a cloud"))):  # fmt: skip
        with pytest.raises(AdapterError, match="PointCloud2: not a serialized PointCloud2"):
            point_cloud_from_cdr(bad)


def test_gaussian_cloud_speed_600k() -> None:
    gmap = _gaussians(600_000, ids=False)
    start = time.perf_counter()
    msg = gaussian_map_to_cloud(gmap)
    to_cloud = time.perf_counter() - start
    start = time.perf_counter()
    back = cloud_to_gaussian_map(msg)
    from_cloud = time.perf_counter() - start
    print(f"600k Gaussians: map->cloud {to_cloud * 1e3:.0f} ms, cloud->map {from_cloud * 1e3:.0f} ms")
    assert len(back) == 600_000
    # Tens of ms on an idle machine; the bound leaves room for a loaded shared CI host.
    assert to_cloud < 1.5 and from_cloud < 1.5


def test_semantic_cloud_round_trip_and_rviz_rgb_bits() -> None:
    rng = np.random.default_rng(4)
    n = 500
    points = rng.normal(size=(n, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, (n, 3), dtype=np.uint8)
    rgb[0], rgb[1], rgb[2] = (255, 255, 255), (0, 0, 1), (0, 0, 0)  # extremes, incl. denormal float bits
    packed = (rgb[:, 0].astype(np.uint32) << 16) | (rgb[:, 1].astype(np.uint32) << 8) | rgb[:, 2]
    conf = rng.uniform(0, 1, n).astype(np.float32)
    for colors in (rgb, rgb / 255.0, packed):
        msg = _wire(semantic_cloud_from_arrays(points, colors, packed, conf, frame_id="map", stamp=9))
        assert [(f.name, f.offset, f.datatype) for f in msg.fields] == [
            ("x", 0, PointField.FLOAT32), ("y", 4, PointField.FLOAT32), ("z", 8, PointField.FLOAT32),
            ("rgb", 12, PointField.FLOAT32), ("object_id", 16, PointField.UINT32),
            ("confidence", 20, PointField.FLOAT32),
        ]  # fmt: skip
        assert msg.point_step == 24 and msg.is_dense
        raw = np.frombuffer(bytes(msg.data), np.uint32).reshape(n, 6)
        np.testing.assert_array_equal(raw[:, 3], packed)  # RViz reads these bits as 0x00RRGGBB
        back = semantic_cloud_to_arrays(msg)
        np.testing.assert_array_equal(back.points, points)
        np.testing.assert_array_equal(back.rgb, rgb)
        np.testing.assert_array_equal(back.object_ids, packed)
        np.testing.assert_array_equal(back.confidence, conf)


def test_semantic_cloud_other_publishers_layouts() -> None:
    n = 6
    dt = np.dtype([("confidence", ">f8"), ("object_id", ">u4"), ("rgb", ">u4"), ("z", ">f4"), ("y", ">f4"),
                   ("x", ">f4")])  # fmt: skip
    points = np.zeros(n, dt)
    points["x"], points["y"], points["z"] = np.arange(n), -np.arange(n), 0.5
    points["rgb"] = 0xFF000000 | np.arange(n) * 0x010203  # rgba-style alpha bits are ignored
    points["object_id"], points["confidence"] = np.arange(n) + 10, 0.25
    back = semantic_cloud_to_arrays(_cloud_from_structured(points))
    np.testing.assert_array_equal(back.points[:, 0], np.arange(n))
    np.testing.assert_array_equal(back.rgb[:, 2], 3 * np.arange(n))
    np.testing.assert_array_equal(back.object_ids, np.arange(n) + 10)


def test_semantic_cloud_rejects_bad_input() -> None:
    p, ids, conf = np.zeros((3, 3)), np.array([1, 2, 3]), np.ones(3)
    rgb = np.zeros((3, 3), np.uint8)
    with pytest.raises(AdapterError, match="NaN"):
        semantic_cloud_from_arrays(np.full((3, 3), np.nan), rgb, ids, conf)
    with pytest.raises(AdapterError, match=r"points must be \(N, 3\)"):
        semantic_cloud_from_arrays(np.zeros((3, 2)), rgb, ids, conf)
    with pytest.raises(AdapterError, match=r"confidence must have shape \(3,\)"):
        semantic_cloud_from_arrays(p, rgb, ids, np.ones(4))
    with pytest.raises(AdapterError, match="object_ids must be integers"):
        semantic_cloud_from_arrays(p, rgb, np.array([-1, 2, 3]), conf)
    with pytest.raises(AdapterError, match=r"float colors must be finite and in \[0, 1\]"):
        semantic_cloud_from_arrays(p, np.full((3, 3), 2.0), ids, conf)
    with pytest.raises(AdapterError, match="packed colors must be integers"):
        semantic_cloud_from_arrays(p, np.array([1, 2, 0x1000000]), ids, conf)
    msg = semantic_cloud_from_arrays(p, rgb, ids, conf)
    msg.fields = [f for f in msg.fields if f.name != "confidence"]
    with pytest.raises(AdapterError, match=r"SemanticCloud: missing required fields \['confidence'\]"):
        semantic_cloud_to_arrays(msg)


def test_object_markers() -> None:
    ids = np.array([0xFF0000, 0x00FF80, 0x123456])
    centroids = np.array([[1.0, 2.0, 0.5], [0.0, -1.0, 1.0], [3.0, 3.0, 3.0]])
    extents = np.array([[0.4, 0.6, 1.0], [2.0, 0.5, 0.0], [0.1, 0.1, 0.1]])
    labels = ["chair", "", "lamp"]
    msg = _wire(object_markers(ids, labels, centroids, extents, ids, frame_id="map", stamp=5, text_height=0.2))
    assert isinstance(msg, MarkerArray) and len(msg.markers) == 1 + 2 * 3
    first = msg.markers[0]
    assert first.action == Marker.DELETEALL and first.ns == ""
    boxes = [m for m in msg.markers if m.type == Marker.CUBE]
    texts = [m for m in msg.markers if m.type == Marker.TEXT_VIEW_FACING]
    assert [m.id for m in boxes] == ids.tolist() and [m.id for m in texts] == ids.tolist()
    assert all(m.header.frame_id == "map" and time_to_ns(m.header.stamp) == 5 for m in msg.markers)
    chair = boxes[0]
    assert (chair.pose.position.x, chair.pose.position.y, chair.pose.position.z) == (1.0, 2.0, 0.5)
    assert (chair.scale.x, chair.scale.y, chair.scale.z) == pytest.approx((0.4, 0.6, 1.0))
    assert (chair.color.r, chair.color.g, chair.color.b, chair.color.a) == pytest.approx((1.0, 0.0, 0.0, 0.4))
    assert boxes[1].scale.z == pytest.approx(0.01)  # flat extent clamped so RViz draws it
    assert boxes[1].color.g == pytest.approx(1.0) and boxes[1].color.b == pytest.approx(128 / 255)
    assert [m.text for m in texts] == ["chair", "#00ff80", "lamp"]
    assert texts[0].pose.position.z == pytest.approx(0.5 + 0.5 + 0.75 * 0.2)  # above the box
    assert texts[0].pose.position.x == 1.0 and texts[0].scale.z == pytest.approx(0.2)

    # Ids stay with their objects whatever the order; y-down maps put labels at lower y.
    order = [2, 0, 1]
    again = object_markers(ids[order], [labels[i] for i in order], centroids[order], extents[order], ids[order],
                           up=(0, -1, 0))  # fmt: skip
    by_id = {m.id: m for m in again.markers if m.type == Marker.CUBE}
    assert by_id[0xFF0000].pose.position.x == 1.0
    label_y = {m.id: m.pose.position.y for m in again.markers if m.type == Marker.TEXT_VIEW_FACING}
    assert label_y[0xFF0000] == pytest.approx(2.0 - 0.3 - 0.75 * 0.12)
    assert len(object_markers([], [], [], [], []).markers) == 1


def test_object_markers_reuse_the_markers_of_unchanged_objects() -> None:
    """With a cache, an object whose values are the same as last time keeps its markers (restamped); a changed
    one gets new markers; an object gone is forgotten; what is sent equals markers built afresh."""
    from msg_adapters import MessageCache

    ids = np.array([0xFF0000, 0x00FF80, 0x123456])
    centroids = np.array([[1.0, 2.0, 0.5], [0.0, -1.0, 1.0], [3.0, 3.0, 3.0]])
    extents = np.array([[0.4, 0.6, 1.0], [2.0, 0.5, 0.1], [0.1, 0.1, 0.1]])
    labels = ["chair", "", "lamp"]
    cache = MessageCache()
    first = object_markers(ids, labels, centroids, extents, ids, stamp=5, cache=cache)
    assert cache.built == 3
    moved = centroids.copy()
    moved[1, 0] += 0.25
    relabelled = ["chair", "", "desk lamp"]
    second = object_markers(ids, relabelled, moved, extents, ids, stamp=9, cache=cache)
    assert cache.built == 5  # the second and third objects changed
    assert second.markers[1] is first.markers[1] and second.markers[2] is first.markers[2]
    assert second.markers[3] is not first.markers[3] and second.markers[5] is not first.markers[5]
    assert all(time_to_ns(m.header.stamp) == 9 for m in second.markers)
    fresh = object_markers(ids, relabelled, moved, extents, ids, stamp=9)
    assert _wire(second) == _wire(fresh)
    object_markers(ids[:1], labels[:1], centroids[:1], extents[:1], ids[:1], stamp=10, cache=cache)
    object_markers(ids, relabelled, moved, extents, ids, stamp=11, cache=cache)
    assert cache.built == 7  # the objects gone for one publication are built again


def test_object_markers_reject_bad_input() -> None:
    one = ([7], ["x"], [[0, 0, 0]], [[1, 1, 1]], [[1, 2, 3]])
    with pytest.raises(AdapterError, match="labels has 2 entries for 1 ids"):
        object_markers(one[0], ["a", "b"], *one[2:])
    with pytest.raises(AdapterError, match="ids must be unique"):
        object_markers([7, 7], ["a", "b"], [[0, 0, 0]] * 2, [[1, 1, 1]] * 2, [[1, 2, 3]] * 2)
    with pytest.raises(AdapterError, match="must be finite"):
        object_markers(one[0], one[1], [[np.nan, 0, 0]], *one[3:])
    with pytest.raises(AdapterError, match="extents must be non-negative"):
        object_markers(one[0], one[1], one[2], [[-1, 1, 1]], one[4])
    with pytest.raises(AdapterError, match="ids must be a 1-D integer array"):
        object_markers([0.5], *one[1:])
    with pytest.raises(AdapterError, match=r"integer colors must be in \[0, 255\]"):
        object_markers(*one[:4], [[0, 256, 0]])


def test_semantic_object_messages() -> None:
    box = {"centroid": (1, 2, 3), "bbox_min": (0.5, 1.5, 2.0), "bbox_max": (1.5, 2.25, 4.0)}
    obj = semantic_object(0x2080FF, **box, label="sofa", description="grey sofa", score=0.5, num_gaussians=12,
                          num_observations=3)  # fmt: skip
    assert isinstance(obj, SemanticObject)
    d = semantic_object_to_dict(_wire(obj))
    assert d["id"] == 0x2080FF and d["hex"] == "#2080ff" and d["label"] == "sofa"
    assert d["extent"] == [1.0, 0.75, 2.0] and d["centroid"] == [1.0, 2.0, 3.0]
    assert d["color"] == pytest.approx([0x20 / 255, 0x80 / 255, 1.0, 1.0])
    assert (d["score"], d["num_gaussians"], d["num_observations"]) == (0.5, 12, 3)
    with pytest.raises(AdapterError, match="not a packed 0x00RRGGBB color"):
        semantic_object(1 << 24, centroid=(0, 0, 0), bbox_min=(0, 0, 0), bbox_max=(0, 0, 0))
    with pytest.raises(AdapterError, match="is below bbox_min"):
        semantic_object(1, centroid=(0, 0, 0), bbox_min=(1, 0, 0), bbox_max=(0, 0, 0))
    with pytest.raises(AdapterError, match="score nan is not finite"):
        semantic_object(1, centroid=(0, 0, 0), bbox_min=(0, 0, 0), bbox_max=(0, 0, 0), score=float("nan"))


def test_required_field_names_match_the_schema() -> None:
    assert list(REQUIRED_FIELDS) == SCHEMA[:11] and list(COLOR_FIELDS) == SCHEMA[11:14]


@pytest.mark.parametrize("n", [0, 1, 7, 1000])
@pytest.mark.parametrize("frame_id", ["", "m", "map", "odom_", "a/longer/frame_id"])
def test_serialized_semantic_cloud_is_rclpy_s_serialization_of_the_message(n: int, frame_id: str) -> None:
    rng = np.random.default_rng(n)
    arrays = (
        rng.normal(size=(n, 3)).astype(np.float32),
        rng.integers(0, 256, (n, 3), dtype=np.uint8),
        rng.integers(0, 2**32, n, dtype=np.uint32),
        rng.uniform(0, 1, n).astype(np.float32),
    )
    stamp = 1_700_000_000_123_456_789
    data = serialized_semantic_cloud(*arrays, frame_id=frame_id, stamp=stamp)
    reference = semantic_cloud_from_arrays(*arrays, frame_id=frame_id, stamp=stamp)
    assert data.dtype == np.uint8 and data.ndim == 1
    # Same length and the same message; the bytes differ only where rclpy leaves its alignment padding unset.
    assert data.size == len(serialize_message(reference))
    assert deserialize_message(data.tobytes(), PointCloud2) == reference


def test_serialized_semantic_cloud_checks_its_input_and_the_serialized_head() -> None:
    with pytest.raises(AdapterError, match="NaN"):
        serialized_semantic_cloud(
            np.full((2, 3), np.nan), np.zeros((2, 3), np.uint8), np.ones(2, np.uint32), np.ones(2)
        )
    empty = (np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, np.uint32), np.zeros(0))
    head = serialize_message(semantic_cloud_from_arrays(*empty))
    assert points_offset(head) == len(head) - 1
    # Written otherwise (padding recorded in the encapsulation options, a length that is not 0, no is_dense byte
    # last): not spliced, the whole message is serialized by rclpy instead.
    assert points_offset(head[:2] + b"\0\3" + head[4:]) is None
    assert points_offset(head[:-5] + b"\0\0\0\1" + head[-1:]) is None
    assert points_offset(head + b"\0") is None
    assert points_offset(head[:8]) is None
