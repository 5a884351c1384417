"""semantic_mapper end to end: a synthetic scene published into the live node (a separate process).

The offline reference runs the very same message objects through a KeyframeAssembler and a SemanticMapper
in this process: same keyframes through the same code, so the node's labels must be identical.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

import msg_adapters as ma
from monovoc_ros.core.evaluation.evaluation import SegmentationEvaluator, render_point_labels
from monovoc_ros.core.evidence.palette import UNOBSERVED_ID, pack_rgb
from monovoc_ros.nodes.keyframe_publisher import KeyframePublisher
from monovoc_ros.nodes.qos import latched_qos
from monovoc_ros.ros_harness import (
    DiagnosticsMonitor,
    MessageCollector,
    call_service,
    wait_for_service,
    wait_for_subscribers,
    wait_until,
)
from tests.node_scene import (
    N_KEYFRAMES,
    assemble,
    mapper_with_client,
    offline_mapper,
    scene_messages,
    small_scene,
)
from tests.rosutil import ros_environment

pytestmark = pytest.mark.ros


@pytest.fixture(scope="module")
def scene():
    return small_scene()


def miou(scene, points, labels):
    ev = SegmentationEvaluator()
    for i in range(len(scene)):
        kf = scene.keyframe(i)
        ev.update(render_point_labels(points, labels, kf.intrinsics, kf.cam_to_world), pack_rgb(scene.clean_mask(i)))
    return ev.result()["miou"]


def gaussian_truth(scene) -> np.ndarray:
    """(N,) packed color of the object each Gaussian lies on (void for floaters and unlabelled surfaces)."""
    colors = np.array([pack_rgb(o.palette_rgb) for o in scene.objects] + [0xFFFFFF], np.uint32)
    index = np.where(scene.gaussian_object >= 0, scene.gaussian_object, len(scene.objects))
    return colors[index]


def test_live_node_matches_offline_mapping(tmp_path, scene):
    from sensor_msgs.msg import PointCloud2
    from std_srvs.srv import Trigger
    from visualization_msgs.msg import MarkerArray

    from monovoc_interfaces.msg import SemanticObjectArray

    messages = scene_messages()
    keyframes = assemble(messages)
    reference = offline_mapper(scene.gaussians, keyframes)
    assert len(keyframes) == N_KEYFRAMES
    expected = reference.result()
    labels_file = tmp_path / "labels.json"
    labels_file.write_text(json.dumps(scene.labels()))
    names = {int(pack_rgb(np.array(d["color"], np.uint8))): d["class_name"] for d in scene.labels()}

    env = ros_environment(tmp_path)
    params = {"publish_rate_hz": 0.0, "labels_file": str(labels_file), "diagnostics_period_s": 0.2}
    with mapper_with_client(env, params) as (node, client):
        clouds, objects, markers = MessageCollector(), MessageCollector(), MessageCollector()
        client.node.create_subscription(PointCloud2, "/monovoc/semantic_cloud", clouds, latched_qos())
        client.node.create_subscription(SemanticObjectArray, "/monovoc/objects", objects, latched_qos())
        client.node.create_subscription(MarkerArray, "/monovoc/objects/markers", markers, latched_qos())
        diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
        publisher = KeyframePublisher(client.node)
        for pub in publisher.all_publishers():
            wait_for_subscribers(pub, timeout=20.0, process=node)
        # Keyframes first: those that arrive before any map wait for it in the worker queue.
        for msgs in messages[:3]:
            publisher.publish_messages(msgs)
        diagnostics.wait_for(lambda v: v["queue_length"] == "3" and v["has_map"] == "false", 10.0, process=node)
        publisher.publish_map(scene.gaussians)
        for msgs in messages[3:]:
            publisher.publish_messages(msgs)

        last = keyframes[-1].stamp_ns
        done = diagnostics.wait_for(lambda v: v["keyframes_processed"] == str(N_KEYFRAMES), 30.0, process=node)
        assert done["keyframes_received"] == str(N_KEYFRAMES)
        assert done["keyframes_dropped"] == "0" and done["rejected_total"] == "0"
        wait_until(lambda: any(ma.header_stamp_ns(m) == last for m in clouds.messages), 10.0, "the final cloud",
                   process=node)  # fmt: skip
        cloud = next(m for m in clouds.messages if ma.header_stamp_ns(m) == last)

        # The publish service re-sends the same map on demand.
        trigger = client.node.create_client(Trigger, "/monovoc/publish")
        wait_for_service(trigger, process=node)
        count = len(clouds.messages)
        response = call_service(trigger, Trigger.Request(), process=node)
        assert response.success, response.message
        clouds.wait_for(count + 1, process=node)
        wait_until(lambda: objects.messages and ma.header_stamp_ns(objects.messages[-1]) == last, 10.0, "objects")
        wait_until(lambda: markers.messages and markers.messages[-1].markers[0].header.stamp.sec == last // 10**9,
                   10.0, "markers")  # fmt: skip

    # (b) identical labels: observed Gaussians only, in map order
    known = expected.object_ids != UNOBSERVED_ID
    got = ma.semantic_cloud_to_arrays(cloud)
    assert cloud.header.frame_id == "map"
    assert len(got.object_ids) == int(known.sum()) > 0.5 * len(scene.gaussians)
    np.testing.assert_array_equal(got.object_ids, expected.object_ids[known])
    np.testing.assert_array_equal(got.points, scene.gaussians.means[known])
    np.testing.assert_allclose(got.confidence, expected.confidence[known])
    np.testing.assert_array_equal(ma.semantic_cloud_to_arrays(clouds.messages[-1]).object_ids, got.object_ids)

    # (c) accuracy against ground truth (disc protocol on the received points)
    live, ref = miou(scene, got.points, got.object_ids), miou(scene, scene.gaussians.means, expected.object_ids)
    assert live >= ref - 0.01, (live, ref)
    # and per Gaussian: the label of the object each Gaussian was sampled from
    truth = gaussian_truth(scene)[known]
    on_object = truth != 0xFFFFFF
    accuracy = float(np.mean(got.object_ids[on_object] == truth[on_object]))
    offline_accuracy = float(np.mean(expected.object_ids[known][on_object] == truth[on_object]))
    print(f"live mIoU {live:.4f} (offline {ref:.4f}), per-Gaussian accuracy {accuracy:.4f} ({offline_accuracy:.4f})")
    assert accuracy >= offline_accuracy - 0.01

    # Objects and markers describe the same objects, named from labels_file.
    final = objects.messages[-1]
    ids = sorted(o.id for o in final.objects)
    assert ids == sorted(set(got.object_ids.tolist()) - {0xFFFFFF})
    assert all(o.label == names[o.id] for o in final.objects)
    # mapping_node alone has no guesses: labels_file's names, else none.
    assert all(o.label_source == ("given" if o.label else "") for o in final.objects)
    texts = {m.id: m.text for m in markers.messages[-1].markers if m.ns == "monovoc/labels"}
    assert all(texts[o.id] == (o.label or f"#{o.id:06x}") for o in final.objects)
    assert all(o.num_gaussians > 0 and 0 < o.num_observations <= N_KEYFRAMES for o in final.objects)
    boxes = [m for m in markers.messages[-1].markers if m.ns == "monovoc/boxes"]
    assert sorted(m.id for m in boxes) == ids
