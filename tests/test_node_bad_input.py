"""semantic_mapper under bad input: every bad message is logged and counted by reason, the node keeps
running, and its state equals a run that never saw the bad messages."""

from __future__ import annotations

import copy

import cv2
import numpy as np
import pytest

import msg_adapters as ma
from monovoc_ros.core.evidence.palette import UNOBSERVED_ID
from monovoc_ros.core.map.camera import Intrinsics
from monovoc_ros.core.map_store import load_snapshot
from monovoc_ros.nodes.keyframe_publisher import KeyframePublisher, keyframe_messages
from monovoc_ros.nodes.qos import latched_qos
from monovoc_ros.ros_harness import (
    DiagnosticsMonitor,
    MessageCollector,
    call_service,
    wait_for_service,
    wait_for_subscribers,
    wait_until,
)
from tests.evidence import assert_same_evidence
from tests.node_scene import N_KEYFRAMES, assemble, mapper_with_client, offline_mapper, small_scene
from tests.rosutil import ros_environment

pytestmark = pytest.mark.ros

S = 1_000_000_000


def good_messages(scene) -> list[dict]:
    """Keyframe i stamped (i + 1) s: room between keyframes for bad messages far beyond the sync tolerance."""
    return [keyframe_messages(scene.keyframe(i), stamp_ns=(i + 1) * S) for i in range(len(scene))]


def bad_corpus(scene, base_ns: int) -> tuple[list[dict], dict[str, int]]:
    """Complete keyframe message sets, 70 ms apart after `base_ns`, each with one bad part; and the
    rejections they must cause."""
    kf = scene.keyframe(3)
    h, w = kf.mask.shape[:2]

    def variant(k: int, mutate) -> dict:
        msgs = keyframe_messages(kf, stamp_ns=base_ns + (k + 1) * 70_000_000)
        mutate(msgs, msgs["mask"].header.stamp)
        return msgs

    def set_(role, msg):
        return lambda m, stamp: (m.__setitem__(role, msg), setattr(m[role].header, "stamp", copy.copy(stamp)))

    def pose_value(attr, value):
        return lambda m, _: setattr(m["pose"].pose.orientation if attr == "w" else m["pose"].pose.position, attr, value)

    big = cv2.resize(kf.rgb, (10 * w, 10 * h), interpolation=cv2.INTER_NEAREST)
    white = np.full_like(kf.mask, 255)
    square = np.ascontiguousarray(cv2.resize(kf.mask, (100, 100), interpolation=cv2.INTER_NEAREST))
    wrong_info = ma.intrinsics_to_camera_info(Intrinsics(300.0, 300.0, 199.5, 149.5, 400, 300))
    zero_k = ma.intrinsics_to_camera_info(kf.intrinsics)
    zero_k.k = [0.0] * 9
    garbage = ma.numpy_to_compressed_image(kf.mask, "png")
    garbage.data = bytes(range(256)) * 4
    empty = ma.numpy_to_compressed_image(kf.mask, "png")
    empty.data = b""
    mutations = [
        (lambda m, _: setattr(m["image"], "format", "tiff"), "bad_image"),  # wrong encoding
        (lambda m, _: setattr(m["mask"], "format", "rgb8"), "bad_mask"),  # wrong encoding
        (set_("mask", garbage), "bad_mask"),  # undecodable
        (set_("mask", empty), "bad_mask"),  # empty
        (set_("mask", ma.numpy_to_compressed_image(white, "png")), "void_mask"),  # all void
        (set_("mask", ma.numpy_to_compressed_image(square, "png")), "size_mismatch"),  # mask vs camera_info
        (set_("image", ma.numpy_to_compressed_image(big, "jpeg")), "size_mismatch"),  # a 10x larger image
        (set_("camera_info", wrong_info), "size_mismatch"),  # camera_info vs image and mask
        (set_("camera_info", zero_k), "bad_camera_info"),  # uncalibrated
        (pose_value("x", float("nan")), "bad_pose"),  # NaN
        (pose_value("w", 7.0), "bad_pose"),  # not normalized
    ]
    expected: dict[str, int] = {}
    for _, reason in mutations:
        expected[reason] = expected.get(reason, 0) + 1
    return [variant(k, mutate) for k, (mutate, _) in enumerate(mutations)], expected


def bad_clouds(gaussians):
    missing = ma.gaussian_map_to_cloud(gaussians)
    missing.fields = [f for f in missing.fields if f.name != "opacity"]
    nan_map = ma.gaussian_map_to_cloud(gaussians)
    data = np.frombuffer(bytes(nan_map.data), np.uint8).copy()
    data[0:4] = np.frombuffer(np.float32(np.nan).tobytes(), np.uint8)  # x of the first point
    nan_map.data = data.tobytes()
    from rclpy.serialization import serialize_message

    # Published serialized, as a rogue or broken publisher can: the node takes the map topic's bytes itself.
    cut = serialize_message(ma.gaussian_map_to_cloud(gaussians))[:2000]
    return [missing, nan_map, cut, b"\x00\x01\x00\x00" + bytes(range(256))]


def test_bad_messages_are_counted_and_change_nothing(tmp_path):
    from sensor_msgs.msg import PointCloud2

    from monovoc_interfaces.srv import SaveMap

    scene = small_scene()
    good = good_messages(scene)
    corpus, expected = bad_corpus(scene, base_ns=4 * S)  # between good keyframes 3 and 4
    out_of_order = keyframe_messages(scene.keyframe(5), stamp_ns=2 * S + S // 2)  # older than the last
    expected.update(duplicate_stamp=4, stamp_out_of_order=4, bad_gaussians=4)

    keyframes = assemble(good)
    reference = offline_mapper(scene.gaussians, keyframes)
    env = ros_environment(tmp_path)
    params = {"publish_rate_hz": 0.0, "diagnostics_period_s": 0.2}
    with mapper_with_client(env, params) as (node, client):
        clouds = MessageCollector()
        client.node.create_subscription(PointCloud2, "/monovoc/semantic_cloud", clouds, latched_qos())
        diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
        publisher = KeyframePublisher(client.node)
        for pub in publisher.all_publishers():
            wait_for_subscribers(pub, timeout=20.0, process=node)
        publisher.publish_map(scene.gaussians)
        for msgs in good[:4]:
            publisher.publish_messages(msgs)
        publisher.publish_messages(good[3])  # duplicate stamps on all four topics
        for msgs in corpus:
            publisher.publish_messages(msgs)
        publisher.publish_messages(out_of_order)
        diagnostics.wait_for(lambda v: v["keyframes_processed"] == "4", 20.0, process=node)
        for count, cloud in enumerate(bad_clouds(scene.gaussians), 1):
            # One at a time: the latched map topic keeps only the newest message (depth 1).
            publisher.gaussians.publish(cloud)
            diagnostics.wait_for(lambda v, n=count: v["rejected.bad_gaussians"] == str(n), 10.0, process=node)
        for msgs in good[4:]:
            publisher.publish_messages(msgs)

        done = diagnostics.wait_for(lambda v: v["keyframes_processed"] == str(N_KEYFRAMES)
                                    and v["rejected.bad_gaussians"] == "4", 30.0, process=node)  # fmt: skip
        got = {k.split(".", 1)[1]: int(v) for k, v in done.items() if k.startswith("rejected.") and v != "0"}
        assert got == expected
        assert done["keyframes_received"] == str(N_KEYFRAMES) and done["map_updates"] == "0"
        assert done["gaussians"] == str(len(scene.gaussians))

        save = client.node.create_client(SaveMap, "/monovoc/save_map")
        wait_for_service(save, process=node)
        response = call_service(save, SaveMap.Request(directory=str(tmp_path / "saved")), process=node)
        assert response.success, response.message
        last = keyframes[-1].stamp_ns
        wait_until(lambda: any(ma.header_stamp_ns(m) == last for m in clouds.messages), 10.0, "the final cloud")
        cloud = ma.semantic_cloud_to_arrays(next(m for m in clouds.messages if ma.header_stamp_ns(m) == last))
        node.check_running()
        log = node.output()

    for reason in expected:
        assert f"rejected ({reason})" in log, reason
    saved = load_snapshot(tmp_path / "saved")
    np.testing.assert_array_equal(saved.state.stamps_ns, [kf.stamp_ns for kf in keyframes])
    assert_same_evidence(saved.state, reference.state, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(saved.palette_builder.ids, reference.palette_builder.ids)
    expected_ids = reference.result().object_ids
    np.testing.assert_array_equal(cloud.object_ids, expected_ids[expected_ids != UNOBSERVED_ID])
