"""Adapters on messages decoded from an MCAP bag: mcap_ros2's dynamic classes and rosbags' dataclasses.

The bag is written in the test: rclpy-serialized CDR (what a recorder stores) with ros2msg schemas.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_ros2.decoder import DecoderFactory
from nav_msgs.msg import Odometry
from rclpy.serialization import serialize_message
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from monovoc_interfaces.msg import SemanticObjectArray
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
    matrix_to_transform_stamped,
    numpy_to_compressed_image,
    numpy_to_image,
    odometry_to_matrix,
    pose_stamped_to_matrix,
    semantic_cloud_from_arrays,
    semantic_cloud_to_arrays,
    semantic_object,
    semantic_object_to_dict,
    transform_stamped_to_matrix,
)

INTERFACES = Path(__file__).resolve().parents[1] / "monovoc_interfaces" / "msg"
RNG = np.random.default_rng(11)
RGB = RNG.integers(0, 256, (24, 32, 3), dtype=np.uint8)
MASK = RNG.integers(0, 4, (24, 32), dtype=np.uint8) * 60
DEPTH = RNG.integers(0, 65536, (24, 32), dtype=np.uint16)
CAM = Intrinsics(300.0, 301.0, 15.5, 11.5, 32, 24)
POSE = np.eye(4)
POSE[:3, :3] = quat_wxyz_to_matrix(np.array([0.9, 0.1, -0.3, 0.2]))
POSE[:3, 3] = (1.0, -2.0, 0.5)
GMAP = GaussianMap(
    means=RNG.normal(size=(200, 3)),
    scales=RNG.uniform(0.01, 0.1, (200, 3)),
    quats=RNG.normal(size=(200, 4)),
    opacities=RNG.uniform(0, 1, 200),
    colors=RNG.uniform(0, 1, (200, 3)),
    ids=np.arange(200) * 3,
)
SEM_POINTS = RNG.normal(size=(50, 3)).astype(np.float32)
SEM_RGB = RNG.integers(0, 256, (50, 3), dtype=np.uint8)
SEM_IDS = RNG.integers(0, 0xFFFFFF, 50).astype(np.uint32)
SEM_CONF = RNG.uniform(0, 1, 50).astype(np.float32)
STAMP = 1_700_000_000_250_000_000


def _messages() -> dict[str, object]:
    odom = Odometry(header=make_header("map", STAMP), child_frame_id="cam_optical")
    odom.pose.pose = matrix_to_pose_stamped(POSE).pose
    objects = SemanticObjectArray(header=make_header("map", STAMP))
    objects.objects = [
        semantic_object(0xAA5500, centroid=(1, 2, 3), bbox_min=(0, 1, 2), bbox_max=(2, 3, 4), label="chair", score=0.5),
        semantic_object(0x0055AA, centroid=(0, 0, 0), bbox_min=(0, 0, 0), bbox_max=(0, 0, 0), label="lamp"),
    ]
    return {
        "/camera/image": numpy_to_image(RGB, "bgr8", frame_id="cam_optical", stamp=STAMP),
        "/camera/depth": numpy_to_image(DEPTH, "mono16", frame_id="cam_optical", stamp=STAMP),
        "/camera/mask": numpy_to_compressed_image(MASK, "png", frame_id="cam_optical", stamp=STAMP),
        "/camera/color_png": numpy_to_compressed_image(RGB, "png", frame_id="cam_optical", stamp=STAMP),
        "/camera/info": intrinsics_to_camera_info(CAM, frame_id="cam_optical", stamp=STAMP),
        "/slam/pose": matrix_to_pose_stamped(POSE, frame_id="map", stamp=STAMP),
        "/slam/tf": matrix_to_transform_stamped(POSE, frame_id="map", child_frame_id="cam_optical", stamp=STAMP),
        "/slam/odom": odom,
        "/slam/gaussians": gaussian_map_to_cloud(GMAP, frame_id="map", stamp=STAMP),
        "/monovoc/semantic_cloud": semantic_cloud_from_arrays(SEM_POINTS, SEM_RGB, SEM_IDS, SEM_CONF, stamp=STAMP),
        "/monovoc/objects": objects,
    }


def _type_name(msg: object) -> str:
    module = type(msg).__module__.split(".")  # e.g. sensor_msgs.msg._image
    return f"{module[0]}/msg/{type(msg).__name__}"


@pytest.fixture(scope="module")
def typestore():
    store = get_typestore(Stores.ROS2_JAZZY)
    for name in ("SemanticObject", "SemanticObjectArray"):
        store.register(get_types_from_msg((INTERFACES / f"{name}.msg").read_text(), f"monovoc_interfaces/msg/{name}"))
    return store


@pytest.fixture(scope="module")
def bag(tmp_path_factory, typestore) -> Path:
    path = tmp_path_factory.mktemp("bag") / "tiny.mcap"
    with open(path, "wb") as f:
        writer = Writer(f)
        writer.start(profile="ros2", library="monovoc-tests")
        schemas: dict[str, int] = {}
        for i, (topic, msg) in enumerate(_messages().items()):
            name = _type_name(msg)
            if name not in schemas:
                msgdef, _ = typestore.generate_msgdef(name, ros_version=2)
                schemas[name] = writer.register_schema(name=name, encoding="ros2msg", data=msgdef.encode())
            channel = writer.register_channel(topic=topic, message_encoding="cdr", schema_id=schemas[name])
            writer.add_message(channel, log_time=STAMP + i, publish_time=STAMP + i, data=serialize_message(msg))
        writer.finish()
    return path


def _decoded_mcap_ros2(path: Path) -> dict[str, object]:
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return {channel.topic: decoded for _, channel, _, decoded in reader.iter_decoded_messages()}


def _decoded_rosbags(path: Path, typestore) -> dict[str, object]:
    with open(path, "rb") as f:
        reader = make_reader(f)
        return {
            channel.topic: typestore.deserialize_cdr(message.data, schema.name)
            for schema, channel, message in reader.iter_messages()
        }


@pytest.fixture(scope="module", params=["mcap_ros2", "rosbags"])
def decoded(request, bag, typestore) -> dict[str, object]:
    if request.param == "mcap_ros2":
        return _decoded_mcap_ros2(bag)
    return _decoded_rosbags(bag, typestore)


def test_every_topic_was_decoded(decoded) -> None:
    assert sorted(decoded) == sorted(_messages())
    for msg in decoded.values():
        assert header_stamp_ns(msg) == STAMP


def test_payload_types_differ_by_decoder(decoded, request) -> None:
    image_data = decoded["/camera/image"].data
    if "mcap_ros2" in request.node.callspec.id:
        assert isinstance(image_data, bytes)
    else:
        assert isinstance(image_data, np.ndarray) and image_data.dtype == np.uint8


def test_images(decoded) -> None:
    np.testing.assert_array_equal(image_to_numpy(decoded["/camera/image"]), RGB)
    np.testing.assert_array_equal(image_to_numpy(decoded["/camera/depth"]), DEPTH)
    np.testing.assert_array_equal(compressed_image_to_numpy(decoded["/camera/mask"]), MASK)
    np.testing.assert_array_equal(compressed_image_to_numpy(decoded["/camera/color_png"]), RGB)


def test_camera_info(decoded) -> None:
    info = decoded["/camera/info"]
    assert camera_info_to_intrinsics(info) == CAM
    assert camera_info_to_intrinsics(info, 16, 12) == CAM.scaled_to(16, 12)


def test_poses(decoded) -> None:
    np.testing.assert_allclose(pose_stamped_to_matrix(decoded["/slam/pose"]), POSE, atol=1e-12)
    np.testing.assert_allclose(transform_stamped_to_matrix(decoded["/slam/tf"]), POSE, atol=1e-12)
    np.testing.assert_allclose(odometry_to_matrix(decoded["/slam/odom"]), POSE, atol=1e-12)
    assert decoded["/slam/tf"].child_frame_id == "cam_optical"


def test_clouds(decoded) -> None:
    gmap = cloud_to_gaussian_map(decoded["/slam/gaussians"])
    np.testing.assert_array_equal(gmap.means, GMAP.means)
    np.testing.assert_array_equal(gmap.ids, GMAP.ids)
    np.testing.assert_allclose(gmap.colors, GMAP.colors, atol=1e-6)
    np.testing.assert_allclose(gmap.quats, GMAP.quats, atol=1e-6)
    sem = semantic_cloud_to_arrays(decoded["/monovoc/semantic_cloud"])
    np.testing.assert_array_equal(sem.points, SEM_POINTS)
    np.testing.assert_array_equal(sem.rgb, SEM_RGB)
    np.testing.assert_array_equal(sem.object_ids, SEM_IDS)
    np.testing.assert_array_equal(sem.confidence, SEM_CONF)


def test_semantic_objects(decoded) -> None:
    objects = [semantic_object_to_dict(o) for o in decoded["/monovoc/objects"].objects]
    assert [o["label"] for o in objects] == ["chair", "lamp"]
    assert objects[0]["id"] == 0xAA5500 and objects[0]["extent"] == [2.0, 2.0, 2.0]
    assert objects[0]["score"] == 0.5 and objects[1]["centroid"] == [0.0, 0.0, 0.0]
