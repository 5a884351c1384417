"""BagWriter / iter_messages / bag_info: round trips, schemas, metadata, and other readers (rosbags, mcap_ros2)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.serialization import serialize_message
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Reader as RosbagsReader
from rosbags.typesys import Stores, get_typestore
from std_msgs.msg import String

from monovoc_interfaces.msg import SemanticObjectArray
from monovoc_ros.bags import BagError, BagWriter, bag_info, bag_metadata, iter_messages
from monovoc_ros.bags.qos import OfferedQos
from monovoc_ros.bags.schemas import UnknownTypeError, canonical_cdr, message_definition, normalize_type_name
from monovoc_ros.core.map.camera import Intrinsics, quat_wxyz_to_matrix
from monovoc_ros.core.map.gaussians import GaussianMap
from msg_adapters import (
    camera_info_to_intrinsics,
    cloud_to_gaussian_map,
    compressed_image_to_numpy,
    gaussian_map_to_cloud,
    header_stamp_ns,
    image_to_numpy,
    intrinsics_to_camera_info,
    make_header,
    matrix_to_pose_stamped,
    numpy_to_compressed_image,
    numpy_to_image,
    pose_stamped_to_matrix,
    semantic_object,
    semantic_object_to_dict,
)

RNG = np.random.default_rng(5)
MASK = RNG.integers(0, 4, (30, 40, 3), dtype=np.uint8) * 80
RGB = RNG.integers(0, 256, (30, 40, 3), dtype=np.uint8)
CAM = Intrinsics(40.0, 41.0, 19.5, 14.5, 40, 30)
POSE = np.eye(4)
POSE[:3, :3] = quat_wxyz_to_matrix(np.array([0.7, -0.2, 0.4, 0.1]))
POSE[:3, 3] = (0.5, -1.5, 2.0)
GMAP = GaussianMap(
    means=RNG.normal(size=(300, 3)),
    scales=RNG.uniform(0.01, 0.1, (300, 3)),
    quats=RNG.normal(size=(300, 4)),
    opacities=RNG.uniform(0, 1, 300),
    colors=RNG.uniform(0, 1, (300, 3)),
    ids=np.arange(300) * 7 + 3,
)
T0 = 1_700_000_000_000_000_000


def _objects(stamp: int) -> SemanticObjectArray:
    msg = SemanticObjectArray(header=make_header("map", stamp))
    msg.objects = [semantic_object(0x11AA33, centroid=(1, 2, 3), bbox_min=(0, 1, 2), bbox_max=(2, 3, 4), label="sofa")]
    return msg


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("io") / "round_trip.mcap"
    with BagWriter(path) as w:
        w.add_json_metadata("monovoc_labels", [{"color": [240, 0, 0], "class_name": "sofa"}])
        w.add_metadata("plain", {"a": "1"})
        latched = OfferedQos(transient_local=True, depth=1)
        w.write("/map", gaussian_map_to_cloud(GMAP, stamp=T0 - 1), T0 - 1, qos=latched)
        for k in range(3):
            t = T0 + k * 100_000_000
            w.write("/mask", numpy_to_compressed_image(MASK, "png", frame_id="cam", stamp=t), t)
            w.write("/rgb", numpy_to_image(RGB, "rgb8", frame_id="cam", stamp=t), t)
            w.write("/info", intrinsics_to_camera_info(CAM, frame_id="cam", stamp=t), t)
            w.write("/pose", matrix_to_pose_stamped(POSE, stamp=t), t)
        w.write("/objects", _objects(T0 + 50), T0 + 50)  # logged after later messages: read back in log order
        w.write("/raw", serialize_message(String(data="hello")), T0 + 10, type_name="std_msgs/String")
        w.write("/raw", serialize_message(String(data="again")), T0 + 20)
    return path


def test_bag_info(bag: Path) -> None:
    info = bag_info(bag)
    assert info.profile == "ros2" and info.compression == ["zstd"]
    types = {t.name: (t.type_name, t.count) for t in info.topics.values()}
    assert types == {
        "/map": ("sensor_msgs/msg/PointCloud2", 1),
        "/mask": ("sensor_msgs/msg/CompressedImage", 3),
        "/rgb": ("sensor_msgs/msg/Image", 3),
        "/info": ("sensor_msgs/msg/CameraInfo", 3),
        "/pose": ("geometry_msgs/msg/PoseStamped", 3),
        "/objects": ("monovoc_interfaces/msg/SemanticObjectArray", 1),
        "/raw": ("std_msgs/msg/String", 2),
    }
    assert info.message_count == 16
    assert (info.start_ns, info.end_ns) == (T0 - 1, T0 + 200_000_000)
    assert info.topics["/map"].transient_local and not info.topics["/mask"].transient_local
    assert info.metadata["plain"] == {"a": "1"}
    assert bag_metadata(bag, "monovoc_labels") == [{"class_name": "sofa", "color": [240, 0, 0]}]
    assert bag_metadata(bag, "missing") is None
    json.dumps(info.as_dict())


def test_iter_messages_order_filter_and_decode(bag: Path) -> None:
    messages = list(iter_messages(bag))
    times = [m.log_time_ns for m in messages]
    assert times == sorted(times) and len(messages) == 16
    topic, type_name, log_time, data = messages[0]
    assert (topic, type_name, log_time) == ("/map", "sensor_msgs/msg/PointCloud2", T0 - 1)
    assert isinstance(data, bytes) and data[:2] == b"\x00\x01"  # CDR little-endian encapsulation
    # Ties keep file order: the four messages of stamp T0 come in the order they were written.
    assert [m.topic for m in messages[1:4]] == ["/mask", "/rgb", "/info"]
    assert [m.topic for m in messages if T0 < m.log_time_ns < T0 + 100] == ["/raw", "/raw", "/objects"]
    for m in messages:
        if m.topic != "/raw":
            assert header_stamp_ns(m.decode()) == m.log_time_ns == m.publish_time_ns
    assert [m.decode().data for m in iter_messages(bag, topics=["/raw"])] == ["hello", "again"]
    window = list(iter_messages(bag, topics=["/mask"], start_ns=T0 + 1, end_ns=T0 + 200_000_000))
    assert [m.log_time_ns for m in window] == [T0 + 100_000_000]


def _check_arrays(decoded: dict[str, list]) -> None:
    for msg in decoded["/mask"]:
        np.testing.assert_array_equal(compressed_image_to_numpy(msg), MASK)
    for msg in decoded["/rgb"]:
        np.testing.assert_array_equal(image_to_numpy(msg), RGB)
    for msg in decoded["/info"]:
        assert camera_info_to_intrinsics(msg) == CAM
    for msg in decoded["/pose"]:
        np.testing.assert_allclose(pose_stamped_to_matrix(msg), POSE, atol=1e-12)
    gmap = cloud_to_gaussian_map(decoded["/map"][0])
    for name in ("means", "scales", "opacities", "ids"):
        np.testing.assert_array_equal(getattr(gmap, name), getattr(GMAP, name))
    np.testing.assert_allclose(gmap.quats, GMAP.quats, atol=1e-7)
    np.testing.assert_allclose(gmap.colors, GMAP.colors, atol=1e-6)
    objects = [semantic_object_to_dict(o) for o in decoded["/objects"][0].objects]
    assert objects[0]["label"] == "sofa" and objects[0]["id"] == 0x11AA33 and objects[0]["extent"] == [2.0, 2.0, 2.0]


def test_decoded_by_our_reader(bag: Path) -> None:
    decoded: dict[str, list] = {}
    for m in iter_messages(bag):
        decoded.setdefault(m.topic, []).append(m.decode())
    _check_arrays(decoded)


def test_readable_by_mcap_ros2_decoder(bag: Path) -> None:
    decoded: dict[str, list] = {}
    with open(bag, "rb") as f:
        for _, channel, _, msg in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            decoded.setdefault(channel.topic, []).append(msg)
    _check_arrays(decoded)


def test_readable_by_rosbags(bag: Path) -> None:
    # An EMPTY default typestore: every type (custom ones too) must come from the bag's own schemas.
    decoded: dict[str, list] = {}
    with AnyReader([bag], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        assert reader.message_count == 16
        for connection, timestamp, raw in reader.messages():
            msg = reader.deserialize(raw, connection.msgtype)
            if connection.topic != "/raw":
                assert header_stamp_ns(msg) == timestamp
            decoded.setdefault(connection.topic, []).append(msg)
    _check_arrays(decoded)
    with RosbagsReader(bag) as reader:
        qos = {c.topic: c.ext.offered_qos_profiles for c in reader.connections}
        assert qos["/map"][0].durability.name == "TRANSIENT_LOCAL" and qos["/map"][0].depth == 1
        assert qos["/mask"][0].reliability.name == "RELIABLE"


def test_schemas() -> None:
    text = message_definition("monovoc_interfaces/msg/SemanticObjectArray")
    for dep in ("MSG: monovoc_interfaces/SemanticObject", "MSG: std_msgs/ColorRGBA", "MSG: geometry_msgs/Point"):
        assert dep in text
    assert message_definition("sensor_msgs/CompressedImage").startswith("std_msgs/Header header\nstring format")
    assert normalize_type_name("nav_msgs.msg.Odometry") == "nav_msgs/msg/Odometry"
    with pytest.raises(UnknownTypeError, match="no_such_pkg"):
        message_definition("no_such_pkg/msg/Thing")


def test_canonical_cdr_makes_serialization_reproducible() -> None:
    # rclpy leaves padding bytes uninitialized; rosbags' re-serialization zeroes them.
    msg = gaussian_map_to_cloud(GMAP, stamp=T0)
    variants = {canonical_cdr(serialize_message(msg), "sensor_msgs/msg/PointCloud2") for _ in range(10)}
    assert len(variants) == 1


def test_errors(tmp_path: Path) -> None:
    not_a_bag = tmp_path / "x.mcap"
    not_a_bag.write_bytes(b"definitely not an mcap file")
    with pytest.raises(BagError, match="x.mcap"):
        bag_info(not_a_bag)
    with pytest.raises(BagError, match="x.mcap"):
        list(iter_messages(not_a_bag))
    with pytest.raises(BagError, match="no such bag"):
        bag_info(tmp_path / "missing.mcap")
    with BagWriter(tmp_path / "w.mcap") as w:
        with pytest.raises(ValueError, match="type_name"):
            w.write("/raw", b"\x00\x01\x00\x00", 1)
        w.write("/s", String(data="a"), 1)
        with pytest.raises(ValueError, match="already registered"):
            w.write("/s", make_header("x", 1), 2)
        with pytest.raises(ValueError, match="negative"):
            w.write("/s", String(data="b"), -5)
    assert bag_info(tmp_path / "w.mcap").message_count == 1


def test_unfinished_bag_is_read_up_to_its_last_complete_chunk(tmp_path: Path) -> None:
    """A recorder killed hard leaves no summary or footer: the complete chunks are still readable."""
    path = tmp_path / "killed.mcap"
    with BagWriter(path, chunk_size=1) as w:  # one message per chunk
        for k in range(20):
            w.write("/mask", numpy_to_compressed_image(MASK, "png", stamp=T0 + k), T0 + k)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: int(path.stat().st_size * 0.6)])
    info = bag_info(cut)
    assert not info.finished and bag_info(path).finished
    assert 5 <= info.message_count < 20 and info.start_ns == T0
    messages = list(iter_messages(cut))
    assert [m.log_time_ns for m in messages] == [T0 + k for k in range(info.message_count)]
    np.testing.assert_array_equal(compressed_image_to_numpy(messages[-1].decode()), MASK)


@pytest.mark.parametrize("cut_bytes", [1, 9, 30, 38, 100])
def test_a_bag_cut_a_few_bytes_short_is_read_as_unfinished(tmp_path: Path, cut_bytes: int) -> None:
    """Cut inside the footer or summary records, mcap's reader ran out of bytes in `struct` (a traceback in every
    command); such a bag is an unfinished one: every complete message is read."""
    path = tmp_path / "whole.mcap"
    with BagWriter(path, chunk_size=1) as w:
        for k in range(6):
            w.write("/mask", numpy_to_compressed_image(MASK, "png", stamp=T0 + k), T0 + k)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:-cut_bytes])
    info = bag_info(cut)
    assert not info.finished and info.message_count == 6
    assert [m.log_time_ns for m in iter_messages(cut)] == [T0 + k for k in range(6)]
