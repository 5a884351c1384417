"""semantic_mapper follows a loop closure: a shuffled, moved map without ids mid-run, then the SLAM's
corrected keyframe path on `keyframe_poses`; the node's final state equals offline mapping of the same
events (core.session: transfer by the map's motion, then re-integration of the keyframe log)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import msg_adapters as ma
from monovoc_ros import offline
from monovoc_ros.contract import KEYFRAME_POSES_TYPE, message_class
from monovoc_ros.core.keyframe_log import KeyframePoses
from monovoc_ros.core.map_store import load_snapshot
from monovoc_ros.nodes.keyframe_publisher import KeyframePublisher, keyframe_messages
from monovoc_ros.nodes.qos import input_qos
from monovoc_ros.ros_harness import (
    ClientNode,
    DiagnosticsMonitor,
    NodeProcess,
    call_service,
    ros_args,
    wait_for_service,
    wait_for_subscribers,
)
from monovoc_ros.synthetic import churn
from tests.evidence import assert_same_evidence
from tests.node_scene import N_KEYFRAMES, NODE, assemble, scene_messages, small_scene
from tests.rosutil import ros_environment

pytestmark = pytest.mark.ros
HALF = 8


def test_loop_closure_without_ids_then_corrected_poses_live_equals_offline(tmp_path):
    from monovoc_interfaces.srv import SaveMap

    scene = small_scene()
    first = assemble(scene_messages()[:HALF])
    closure = churn.loop_closure(replace(scene.gaussians, ids=None), degrees=2.0, seed=5)
    map_msg = ma.gaussian_map_to_cloud(closure.gaussians, stamp=first[-1].stamp_ns)
    moved_map = ma.cloud_to_gaussian_map(map_msg)
    # The path also refines each keyframe by 2 cm (bundle adjustment): the log must be re-integrated.
    refine = np.eye(4)
    refine[0, 3] = 0.02
    corrected = KeyframePoses(tuple((kf.stamp_ns, refine @ closure.move_pose(kf.cam_to_world)) for kf in first))
    path_msg = ma.keyframe_poses_to_path(corrected, stamp=first[-1].stamp_ns)
    # The second half as the SLAM sends it after the closure: poses in the corrected frame.
    later = []
    for i in range(HALF, N_KEYFRAMES):
        kf = scene.keyframe(i)
        later.append(keyframe_messages(replace(kf, cam_to_world=closure.move_pose(kf.cam_to_world))))
    events = [scene.gaussians, *first, moved_map, ma.path_to_keyframe_poses(path_msg), *assemble(later)]
    reference, ref_stats = offline.map_events(events)
    assert ref_stats.map_updates == 1 and ref_stats.reintegrations == 1

    env = ros_environment(tmp_path)
    params = {"publish_rate_hz": 0.0, "diagnostics_period_s": 0.2}
    with (
        NodeProcess.python([*NODE, *ros_args(params)], env, name="semantic_mapper") as node,
        ClientNode(env) as client,
    ):
        diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
        publisher = KeyframePublisher(client.node)
        path_pub = client.node.create_publisher(
            message_class(KEYFRAME_POSES_TYPE), "/monovoc/keyframe_poses", input_qos(5)
        )
        save = client.node.create_client(SaveMap, "/monovoc/save_map")
        for pub in [*publisher.all_publishers(), path_pub]:
            wait_for_subscribers(pub, timeout=20.0, process=node)
        wait_for_service(save, process=node)
        publisher.publish_map(scene.gaussians)
        for msgs in scene_messages()[:HALF]:
            publisher.publish_messages(msgs)
        diagnostics.wait_for(lambda v: v["keyframes_processed"] == str(HALF), 20.0, process=node)
        publisher.gaussians.publish(map_msg)
        diagnostics.wait_for(lambda v: v["map_updates"] == "1", 20.0, process=node)
        path_pub.publish(path_msg)
        for msgs in later:
            publisher.publish_messages(msgs)
        done = diagnostics.wait_for(
            lambda v: v["keyframes_processed"] == str(N_KEYFRAMES) and v["reintegrations"] == "1"
            and v["reintegrating"] == "false",
            30.0,
            process=node,
        )  # fmt: skip
        assert float(done["map_update_carried_share"]) > 0.99
        assert call_service(save, SaveMap.Request(directory=str(tmp_path / "final")), process=node).success

    final = load_snapshot(tmp_path / "final")
    assert_same_evidence(final.state, reference.state, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(final.result().object_ids, reference.result().object_ids)
    assert len(final.keyframe_log) == N_KEYFRAMES
