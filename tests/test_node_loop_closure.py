"""semantic_mapper follows a loop closure: a shuffled, moved map without ids mid-run, then the SLAM's
corrected keyframe path on `keyframe_poses`; the node's final state equals offline mapping of the same
events (core.session: transfer by the map's motion, then re-integration of the keyframe log)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import msg_adapters as ma
from monovoc_ros import offline
from monovoc_ros.bags import BagWriter
from monovoc_ros.bags.qos import OfferedQos
from monovoc_ros.cli import main
from monovoc_ros.contract import KEYFRAME_POSES_TYPE, message_class, topic_names
from monovoc_ros.core.follow.keyframe_log import KeyframePoses
from monovoc_ros.core.map_store import load_snapshot
from monovoc_ros.nodes.keyframe_publisher import ROLE_ORDER, KeyframePublisher, keyframe_messages
from monovoc_ros.nodes.qos import input_qos
from monovoc_ros.ros_harness import (
    ClientNode,
    DiagnosticsMonitor,
    NodeProcess,
    call_service,
    ros_args,
    wait_for_service,
    wait_for_subscribers,
    wait_until,
)
from monovoc_ros.synthetic import churn
from tests.evidence import assert_same_evidence
from tests.node_scene import N_KEYFRAMES, assemble, mapper_with_client, scene_messages, small_scene
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
    with mapper_with_client(env, params) as (node, client):
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
        # The registration came from the map reader process (the node did not estimate it): the same result.
        assert done["map_motions_given"] == "1" and float(done["map_reader_motion_s"]) > 0
        assert call_service(save, SaveMap.Request(directory=str(tmp_path / "final")), process=node).success

    final = load_snapshot(tmp_path / "final")
    assert_same_evidence(final.state, reference.state, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(final.result().object_ids, reference.result().object_ids)
    assert len(final.keyframe_log) == N_KEYFRAMES


def test_queries_answer_the_same_objects_after_a_moved_map_without_ids(tmp_path):
    """The full node (object queries included) resumes a room, then the SLAM closes a loop: a shuffled map
    without ids, moved 2 deg / 8 cm. The same queries name the same objects, their boxes moved with the map."""
    from monovoc_interfaces.srv import TextQuery
    from monovoc_ros.embed import default_model_dir
    from tests.object_room import copy_directory, room_directory, room_id

    directory = copy_directory(room_directory(), tmp_path / "map")
    gaussians = load_snapshot(directory).gaussians
    closure = churn.loop_closure(replace(gaussians, ids=None), degrees=2.0, translation=(0.06, 0.05, 0.01), seed=9)
    env = ros_environment(tmp_path, extra={"MONOVOC_MODEL_DIR": str(default_model_dir())})
    params = {
        "map_directory": str(directory),
        "resume": True,
        "labels_file": str(directory / "labels.json"),
        "save_period_s": 0.0,
        "diagnostics_period_s": 0.2,
    }
    texts = ("a sofa", "a chair", "a table")
    with (
        NodeProcess.python(["-m", "monovoc_ros.nodes.semantic_mapper", *ros_args(params)], env, name="mapper") as node,
        ClientNode(env) as client,
    ):
        service = client.node.create_client(TextQuery, "/monovoc/query")
        wait_for_service(service, 30.0, process=node)

        def ask(text):
            answer = call_service(service, TextQuery.Request(text=text, top_k=3, min_score=-1.0), 20.0, process=node)
            assert answer.success, answer.message
            return [(o.id, np.array([o.centroid.x, o.centroid.y, o.centroid.z])) for o in answer.objects]

        before = {text: ask(text) for text in texts}
        assert before["a sofa"][0][0] == room_id("sofa")
        publisher = KeyframePublisher(client.node)
        wait_for_subscribers(publisher.gaussians, timeout=20.0, process=node)
        publisher.publish_map(closure.gaussians)
        diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
        done = diagnostics.wait_for(lambda v: v["map_updates"] == "1", 30.0, process=node)
        assert float(done["map_update_carried_share"]) > 0.99 and done["rejected.map_motion"] == "0"
        sofa_id, sofa_before = before["a sofa"][0]
        expected = closure.move_pose(np.eye(4))
        moved_sofa = expected[:3, :3] @ sofa_before + expected[:3, 3]
        # The object index takes the new geometry in the background: wait for the sofa to have moved.
        wait_until(lambda: np.linalg.norm(ask("a sofa")[0][1] - moved_sofa) < 0.02, 20.0, "the sofa moved with the map",
                   process=node)  # fmt: skip
        for text in texts:
            after = ask(text)
            assert [i for i, _ in after] == [i for i, _ in before[text]], text
            for (_, c_before), (_, c_after) in zip(before[text], after, strict=True):
                moved = expected[:3, :3] @ c_before + expected[:3, 3]
                assert np.linalg.norm(c_after - moved) < 0.02, (text, c_after, moved)
        assert sofa_id == room_id("sofa")


def write_loop_closure_bag(bag_path) -> None:
    """The small scene as a SLAM would record it: 8 keyframes, then (0.5 s later) a loop closure (the map
    moved 2 deg without ids, and the corrected keyframe path), then 8 keyframes in the corrected frame 1 s on."""
    scene = small_scene()
    topics = topic_names()
    first = assemble(scene_messages()[:HALF])
    closure = churn.loop_closure(replace(scene.gaussians, ids=None), degrees=2.0, seed=5)
    refine = np.eye(4)
    refine[1, 3] = -0.02  # the path also refines each keyframe by 2 cm
    corrected = KeyframePoses(tuple((kf.stamp_ns, refine @ closure.move_pose(kf.cam_to_world)) for kf in first))
    t_update = first[-1].stamp_ns + 500_000_000
    latched = OfferedQos(transient_local=True, depth=1)
    with BagWriter(bag_path) as w:
        w.write(topics["gaussians"], ma.gaussian_map_to_cloud(scene.gaussians, stamp=0), 0, qos=latched)
        for msgs in scene_messages()[:HALF]:
            for role in (r for r in ROLE_ORDER if r in msgs):
                w.write(topics[role], msgs[role], ma.header_stamp_ns(msgs[role]))
        w.write(topics["gaussians"], ma.gaussian_map_to_cloud(closure.gaussians, stamp=t_update), t_update, qos=latched)
        w.write(topics["keyframe_poses"], ma.keyframe_poses_to_path(corrected, stamp=t_update), t_update + 1_000_000)
        for i in range(HALF, N_KEYFRAMES):
            kf = scene.keyframe(i)
            moved = replace(kf, cam_to_world=closure.move_pose(kf.cam_to_world), stamp_ns=kf.stamp_ns + 1_000_000_000)
            msgs = keyframe_messages(moved)
            for role in (r for r in ROLE_ORDER if r in msgs):
                w.write(topics[role], msgs[role], moved.stamp_ns)


@pytest.mark.parametrize("fast", [False, True], ids=["recorded rate", "fast"])
def test_a_bag_with_a_loop_closure_maps_the_same_live_and_offline(tmp_path, fast):
    """`monovoc map --bag` and the node fed by `monovoc replay` of the same bag (map update and keyframe path
    included) end with the same semantic state; with --fast too: the replay waits for the node to take each map
    before the keyframes posed in it (monovoc_ros.bags.map_gate), which otherwise overtook it."""
    from monovoc_interfaces.srv import SaveMap

    bag = tmp_path / "loop.mcap"
    write_loop_closure_bag(bag)
    assert main(["map", "--bag", str(bag), "-o", str(tmp_path / "offline"), "--quiet"]) == 0
    reference = load_snapshot(tmp_path / "offline")
    assert len(reference.keyframe_log) == N_KEYFRAMES and reference.map_version == 1

    env = ros_environment(tmp_path)
    params = {"publish_rate_hz": 0.0, "diagnostics_period_s": 0.2}
    with mapper_with_client(env, params) as (node, client):
        diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
        save = client.node.create_client(SaveMap, "/monovoc/save_map")
        wait_for_service(save, process=node)
        command = [
            "-m",
            "monovoc_ros.cli",
            "replay",
            str(bag),
            "--wait-subscribers",
            "1",
            *(["--fast"] if fast else []),
        ]
        with NodeProcess.python(command, env, name="replay") as replay:
            wait_until(lambda: replay.returncode is not None, 60.0, "the replay to end", process=replay)
            assert replay.returncode == 0, replay.describe()
            gated = '"map_gate": true' if fast else '"map_gate": null'  # --fast waited for the node to take the map
            assert gated in replay.output() and '"maps_unconfirmed": 0' in replay.output(), replay.describe()
        done = diagnostics.wait_for(
            lambda v: v["keyframes_processed"] == str(N_KEYFRAMES) and v["reintegrations"] == "1"
            and v["reintegrating"] == "false" and v["map_updates"] == "1",
            30.0,
            process=node,
        )  # fmt: skip
        assert done["map_motions_given"] == "1"  # registered in the map reader process
        assert call_service(save, SaveMap.Request(directory=str(tmp_path / "live")), process=node).success
    live = load_snapshot(tmp_path / "live")
    assert_same_evidence(live.state, reference.state, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(live.result().object_ids, reference.result().object_ids)
