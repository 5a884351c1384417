"""sequence_to_bag and bag_events: a converted bag holds exactly the sequence, offline keyframes equal it,
corrupted messages become rejections; Replica office_0 and the bundled bag; the `monovoc bag` commands."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped

import msg_adapters as ma
from monovoc_ros.bags import (
    BagWriter,
    bag_events,
    bag_info,
    bag_labels,
    bag_metadata,
    iter_messages,
    sequence_to_bag,
    topic_names,
)
from monovoc_ros.bags.bundled import BUNDLED_DIR, SYNTHETIC_BAG, SYNTHETIC_LABELS, bundled_bag, write_labels_file
from monovoc_ros.bags.convert import MIN_START_NS
from monovoc_ros.bags.schemas import deserialize_rosbags, type_hash
from monovoc_ros.cli import main as monovoc
from monovoc_ros.core.evaluation.datasets import open_sequence
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.ingest import IngestConfig, KeyframeAssembler, Rejection
from monovoc_ros.synthetic import SceneConfig, generate_scene

TOPICS = topic_names()
N_KF = 6


def small_scene():
    """A small synthetic scene. The bags only need some scene: optional map refinements of the generator
    (slow at this size, and being reworked) are turned off when the config has them."""
    names = {f.name for f in dataclasses.fields(SceneConfig)}
    extra = {k: False for k in ("observed_only", "edge_adaptive") if k in names}
    return generate_scene(SceneConfig.at_resolution(160, 90, n_keyframes=N_KF, n_gaussians=3000, **extra))


def moved(gmap: GaussianMap, offset=(0.5, 0.0, -0.25)) -> GaussianMap:
    return GaussianMap(gmap.means + np.float32(offset), gmap.scales, gmap.quats, gmap.opacities, gmap.colors, gmap.ids)


@pytest.fixture(scope="module")
def scene():
    return small_scene()


@pytest.fixture(scope="module")
def bag(scene, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("convert") / "scene.mcap"
    report = sequence_to_bag(scene, path, map_updates={3: moved(scene.gaussians)})
    assert report.keyframes == N_KF and report.map_messages == 2 and report.time_offset_ns == MIN_START_NS
    return path


def assert_same_map(a: GaussianMap, b: GaussianMap) -> None:
    for name in ("means", "scales", "opacities", "ids"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    np.testing.assert_allclose(a.quats, b.quats, atol=1e-7)
    np.testing.assert_allclose(a.colors, b.colors, atol=1e-6)


def assert_same_keyframe(got: Keyframe, ref: Keyframe, offset: int, *, rgb_exact: bool) -> None:
    assert got.stamp_ns == ref.stamp_ns + offset
    np.testing.assert_array_equal(got.mask, ref.mask)
    np.testing.assert_allclose(got.cam_to_world, ref.cam_to_world, atol=1e-12)
    assert got.intrinsics == ref.intrinsics
    if rgb_exact:
        np.testing.assert_array_equal(got.rgb, ref.rgb)
    else:  # JPEG q95
        assert got.rgb.shape == ref.rgb.shape
        assert np.abs(got.rgb.astype(int) - ref.rgb).mean() < 4.0


def test_bag_layout(scene, bag: Path) -> None:
    info = bag_info(bag)
    counts = {t.name: (t.type_name, t.count) for t in info.topics.values()}
    assert counts == {
        TOPICS["gaussians"]: ("sensor_msgs/msg/PointCloud2", 2),
        TOPICS["pose"]: ("geometry_msgs/msg/PoseStamped", N_KF),
        TOPICS["camera_info"]: ("sensor_msgs/msg/CameraInfo", N_KF),
        TOPICS["image"]: ("sensor_msgs/msg/CompressedImage", N_KF),
        TOPICS["mask"]: ("sensor_msgs/msg/CompressedImage", N_KF),
    }
    assert info.topics[TOPICS["gaussians"]].transient_local
    stamps = scene.stamps_ns + MIN_START_NS
    messages = list(iter_messages(bag))
    # The map 1 ms before keyframe 0, the update 1 ms before keyframe 3; log time = publish time = header stamp.
    assert messages[0].topic == TOPICS["gaussians"] and messages[0].log_time_ns == stamps[0] - 1_000_000
    maps = [m for m in messages if m.topic == TOPICS["gaussians"]]
    assert [m.log_time_ns for m in maps] == [stamps[0] - 1_000_000, stamps[3] - 1_000_000]
    frames = {"gaussians": "map", "pose": "map", "camera_info": "camera_optical_frame"}
    for m in messages:
        msg = m.decode()
        assert ma.header_stamp_ns(msg) == m.log_time_ns == m.publish_time_ns
        role = m.topic.rsplit("/", 1)[1]
        assert msg.header.frame_id == frames.get(role, "camera_optical_frame")
    for role in ("pose", "camera_info", "image", "mask"):
        assert [m.log_time_ns for m in messages if m.topic == TOPICS[role]] == stamps.tolist()
    assert bag_labels(bag) == scene.labels() and len(scene.labels()) > 5
    source = bag_metadata(bag, "monovoc_source")
    assert source["time_offset_ns"] == MIN_START_NS and source["map_updates"] == [3]


@pytest.mark.parametrize("decoder", ["mcap_ros2", "rosbags"])
def test_every_message_converts_back(scene, bag: Path, decoder: str) -> None:
    decoded: dict[str, list] = {}
    for m in iter_messages(bag):
        msg = m.decode() if decoder == "mcap_ros2" else deserialize_rosbags(m.data, m.type_name)
        decoded.setdefault(m.topic.rsplit("/", 1)[1], []).append(msg)
    assert_same_map(ma.cloud_to_gaussian_map(decoded["gaussians"][0]), scene.gaussians)
    assert_same_map(ma.cloud_to_gaussian_map(decoded["gaussians"][1]), moved(scene.gaussians))
    for i in range(N_KF):
        ref = scene.keyframe(i)
        np.testing.assert_array_equal(ma.compressed_image_to_numpy(decoded["mask"][i]), ref.mask)
        np.testing.assert_allclose(ma.pose_stamped_to_matrix(decoded["pose"][i]), ref.cam_to_world, atol=1e-12)
        assert ma.camera_info_to_intrinsics(decoded["camera_info"][i]) == ref.intrinsics
        assert not ma.has_distortion(decoded["camera_info"][i])
        rgb = ma.compressed_image_to_numpy(decoded["image"][i])
        assert decoded["image"][i].format.endswith("jpeg compressed bgr8")
        assert np.abs(rgb.astype(int) - ref.rgb).mean() < 4.0


def test_bag_events_equal_the_sequence(scene, bag: Path) -> None:
    assembler = KeyframeAssembler()
    events = list(bag_events(bag, assembler=assembler))
    kinds = [type(e).__name__ for e in events]
    assert kinds == ["GaussianMap"] + ["Keyframe"] * 3 + ["GaussianMap"] + ["Keyframe"] * 3
    assert_same_map(events[0], scene.gaussians)
    assert_same_map(events[4], moved(scene.gaussians))
    keyframes = [e for e in events if isinstance(e, Keyframe)]
    for i, kf in enumerate(keyframes):
        assert kf.index == i
        assert_same_keyframe(kf, scene.keyframe(i), MIN_START_NS, rgb_exact=False)
    assert not assembler.rejected and assembler.sync.stats.matched == N_KF


def test_a_camera_only_bag_has_no_masks_for_the_segmenter_to_make(scene, tmp_path: Path) -> None:
    out = tmp_path / "camera.mcap"
    assert monovoc(["bag", "convert", "synthetic", "-o", str(out), "--mask-format", "none", "--max-keyframes", "3",
                    "--quiet"]) == 0  # fmt: skip
    topics = bag_info(out).topics
    assert TOPICS["mask"] not in topics and TOPICS["segments"] not in topics
    assert topics[TOPICS["image"]].count == topics[TOPICS["pose"]].count == topics[TOPICS["camera_info"]].count == 3
    assert topics[TOPICS["gaussians"]].count == 1


def test_raw_and_png_formats_are_exact(scene, tmp_path: Path) -> None:
    raw = tmp_path / "raw.mcap"
    sequence_to_bag(scene, raw, rgb_format="raw", mask_format="raw", max_keyframes=2, time_offset_ns=5_000_000)
    info = bag_info(raw)
    assert info.topics[TOPICS["image"]].type_name == info.topics[TOPICS["mask"]].type_name == "sensor_msgs/msg/Image"
    assert info.topics[TOPICS["mask"]].count == 2
    keyframes = [e for e in bag_events(raw) if isinstance(e, Keyframe)]
    assert len(keyframes) == 2
    for i, kf in enumerate(keyframes):
        assert_same_keyframe(kf, scene.keyframe(i), 5_000_000, rgb_exact=True)
    png = tmp_path / "png.mcap"
    sequence_to_bag(scene, png, rgb_format="png", max_keyframes=1, include_map=False)
    assert TOPICS["gaussians"] not in bag_info(png).topics
    (kf,) = [e for e in bag_events(png) if isinstance(e, Keyframe)]
    assert_same_keyframe(kf, scene.keyframe(0), MIN_START_NS, rgb_exact=True)


def test_conversion_is_deterministic(scene, bag: Path, tmp_path: Path) -> None:
    again = tmp_path / "again.mcap"
    sequence_to_bag(scene, again, map_updates=[(3, moved(scene.gaussians))])
    assert again.read_bytes() == bag.read_bytes()


def test_bad_options(scene, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="rgb_format"):
        sequence_to_bag(scene, tmp_path / "x.mcap", rgb_format="bmp")
    with pytest.raises(ValueError, match="map update before keyframe 6"):
        sequence_to_bag(scene, tmp_path / "x.mcap", map_updates={6: scene.gaussians})
    assert not list(tmp_path.iterdir())  # nothing half-written is left behind


def test_corrupted_messages_are_rejected_and_the_stream_continues(scene, bag: Path, tmp_path: Path) -> None:
    """Keyframe 1's mask PNG truncated, keyframe 3's pose NaN, keyframe 4's camera_info undecodable CDR,
    and the map update replaced by a cloud without the Gaussian fields."""
    stamps = scene.stamps_ns + MIN_START_NS
    bad = tmp_path / "corrupt.mcap"
    with BagWriter(bad) as w:
        for m in iter_messages(bag):
            role = m.topic.rsplit("/", 1)[1]
            data: object = m.data
            if role == "mask" and m.log_time_ns == stamps[1]:
                msg = ma.numpy_to_compressed_image(scene.keyframe(1).mask, "png", frame_id="c", stamp=m.log_time_ns)
                msg.data = msg.data[: len(msg.data) // 2]
                data = msg
            elif role == "pose" and m.log_time_ns == stamps[3]:
                msg = PoseStamped(header=ma.make_header("map", m.log_time_ns))
                msg.pose.position.x = float("nan")
                data = msg
            elif role == "camera_info" and m.log_time_ns == stamps[4]:
                data = m.data[:40]
            elif role == "gaussians" and m.log_time_ns == stamps[3] - 1_000_000:
                zeros = np.zeros((4, 3), np.float32)
                ids, confidence = np.zeros(4, np.uint32), np.ones(4, np.float32)
                rgb = zeros.astype(np.uint8)
                data = ma.semantic_cloud_from_arrays(zeros, rgb, ids, confidence, stamp=m.log_time_ns)
            w.write(m.topic, data, m.log_time_ns, type_name=m.type_name)
    events = list(bag_events(bad, IngestConfig()))
    rejections = [(e.reason, e.role) for e in events if isinstance(e, Rejection)]
    assert rejections == [
        ("bad_mask", "mask"),
        ("bad_gaussians", "gaussians"),
        ("bad_pose", "pose"),
        ("bad_camera_info", "camera_info"),
    ]
    keyframes = [e for e in events if isinstance(e, Keyframe)]
    assert [kf.stamp_ns for kf in keyframes] == [stamps[i] for i in (0, 2, 5)]
    assert_same_keyframe(keyframes[-1], scene.keyframe(5), MIN_START_NS, rgb_exact=False)
    assert sum(isinstance(e, GaussianMap) for e in events) == 1


def test_map_messages_that_are_no_gaussian_cloud_are_rejected(scene, tmp_path: Path) -> None:
    """The map topic is read from its bytes as the live node reads them (msg_adapters.point_cloud_from_cdr): a cut
    message and one of another type are rejected as bad_gaussians, and the next map is read."""
    from std_msgs.msg import String

    good = ma.gaussian_map_to_cloud(scene.gaussians, stamp=MIN_START_NS + 2)
    path = tmp_path / "maps.mcap"
    cut = _serialized(good)[:3000]
    with BagWriter(path) as w:
        w.write(TOPICS["gaussians"], cut, MIN_START_NS + 1, type_name="sensor_msgs/msg/PointCloud2")
        w.write(TOPICS["gaussians"], good, MIN_START_NS + 2)
    events = list(bag_events(path, IngestConfig()))
    assert isinstance(events[0], Rejection) and events[0].reason == "bad_gaussians"
    assert "not a serialized PointCloud2" in events[0].detail and events[0].stamp_ns == MIN_START_NS + 1
    assert_same_map(events[1], scene.gaussians)
    other = tmp_path / "string.mcap"
    with BagWriter(other) as w:
        w.write(TOPICS["gaussians"], String(data="a map"), MIN_START_NS)
    (event,) = bag_events(other, IngestConfig())
    assert isinstance(event, Rejection) and event.reason == "bad_gaussians"
    assert event.detail == "std_msgs/msg/String in 'cdr', not a CDR PointCloud2"


def _serialized(msg) -> bytes:
    from rclpy.serialization import serialize_message

    return serialize_message(msg)


def test_replica_office0_through_the_cli(replica_office0: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "replica.mcap"
    assert monovoc(["bag", "convert", str(replica_office0), "-o", str(out), "--max-keyframes", "3", "--quiet"]) == 0
    assert json.loads(capsys.readouterr().out)["keyframes"] == 3
    assert monovoc(["bag", "info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["topics"][TOPICS["mask"]]["count"] == 3 and info["topics"][TOPICS["gaussians"]]["count"] == 1
    assert monovoc(["bag", "info", str(out)]) == 0
    assert "monovoc_labels" in capsys.readouterr().out
    sequence = open_sequence(replica_office0)
    assert bag_labels(out) == sequence.labels()
    events = list(bag_events(out))
    assert_same_map(events[0], sequence.load_gaussians())
    keyframes = [e for e in events if isinstance(e, Keyframe)]
    assert len(keyframes) == 3
    for i, kf in enumerate(keyframes):
        assert_same_keyframe(kf, sequence.keyframe(i), MIN_START_NS, rgb_exact=False)


def test_cli_errors(tmp_path: Path, capsys) -> None:
    assert monovoc(["bag", "info", str(tmp_path / "none.mcap")]) == 1
    assert monovoc(["bag", "convert", str(tmp_path), "-o", str(tmp_path / "x.mcap"), "--quiet"]) == 1
    assert "monovoc bag convert:" in capsys.readouterr().err


def test_bundled_synthetic_bag() -> None:
    """The committed bag: the default synthetic scene, every keyframe, under 15 MB, clean through ingest."""
    path = bundled_bag(SYNTHETIC_BAG)
    info = bag_info(path)
    assert info.size_bytes < 15e6
    n = SceneConfig().n_keyframes
    assert {t.name: t.count for t in info.topics.values()} == {
        TOPICS["gaussians"]: 1,
        **{TOPICS[r]: n for r in ("pose", "camera_info", "image", "mask")},
    }
    assert len(bag_labels(path)) > 5
    # Channels carry rosbag2 Jazzy's RIHS01 type hash (regenerate the bag if this fails after a change).
    assert all(t.type_hash == type_hash(t.type_name) for t in info.topics.values())
    assembler = KeyframeAssembler()
    events = list(bag_events(path, assembler=assembler))
    assert isinstance(events[0], GaussianMap) and len(events[0]) > 1000
    assert sum(isinstance(e, Keyframe) for e in events) == n and not assembler.rejected


def test_bundled_labels_file_is_the_bags_labels(tmp_path: Path) -> None:
    """bags/synthetic_room.labels.json, the labels_file to launch the node on the bundled bag with (README),
    is what `monovoc bag make-bundled` writes from the bag's labels."""
    committed = BUNDLED_DIR / SYNTHETIC_LABELS
    made = write_labels_file(bundled_bag(SYNTHETIC_BAG), tmp_path / SYNTHETIC_LABELS)
    assert committed.read_bytes() == made.read_bytes()
    assert json.loads(committed.read_text()) == bag_labels(bundled_bag(SYNTHETIC_BAG))


def test_convert_with_mask_noise_renumbers_every_mask(tmp_path: Path) -> None:
    from monovoc_ros.core.evidence.palette import pack_rgb

    out = tmp_path / "pf.mcap"
    args = [
        "bag",
        "convert",
        "synthetic",
        "-o",
        str(out),
        "--quiet",
        "--max-keyframes",
        "3",
        "--mask-noise",
        "shuffled",
    ]
    assert monovoc(args) == 0
    scene = generate_scene(SceneConfig())
    keyframes = [e for e in bag_events(out) if isinstance(e, Keyframe)]
    assert len(keyframes) == 3
    for i, kf in enumerate(keyframes):
        clean, noisy = pack_rgb(scene.keyframe(i).mask), pack_rgb(kf.mask)
        pairs = np.unique(np.stack([clean.ravel(), noisy.ravel()]), axis=1)
        # the same segments (a bijection of colors), none of them keeping its global color but void
        assert len(set(pairs[0])) == len(set(pairs[1])) == pairs.shape[1]
        assert all((a == b) == (a == 0xFFFFFF) for a, b in pairs.T.tolist())
