"""semantic_mapper services: save_map, load_map (snapshot or PLY), reset, publish; answered while busy."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

import msg_adapters as ma
from monovoc_ros.core.evidence.palette import UNOBSERVED_ID
from monovoc_ros.core.map.ply import save_ply
from monovoc_ros.core.map_store import load_snapshot
from monovoc_ros.nodes.keyframe_publisher import KeyframePublisher, keyframe_messages
from monovoc_ros.nodes.qos import latched_qos
from monovoc_ros.nodes.service_call import RESEND_S
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

BACKLOG_ROUNDS = 5  # the 16 keyframes again with new stamps, to keep the worker busy


def test_services(tmp_path):
    from sensor_msgs.msg import PointCloud2
    from std_srvs.srv import Trigger

    from monovoc_interfaces.srv import LoadMap, Reset, SaveMap

    scene, messages = small_scene(), scene_messages()
    keyframes = assemble(messages)
    expected = offline_mapper(scene.gaussians, keyframes).result().object_ids
    map_dir = (tmp_path / "map").resolve()
    ply = tmp_path / "map.ply"
    save_ply(ply, scene.gaussians)
    env = ros_environment(tmp_path)
    params = {"map_directory": str(map_dir), "save_period_s": 0.0, "queue_size": 200, "diagnostics_period_s": 0.2}
    with mapper_with_client(env, params) as (node, client):
        clouds = MessageCollector()
        client.node.create_subscription(PointCloud2, "/monovoc/semantic_cloud", clouds, latched_qos())
        diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
        publisher = KeyframePublisher(client.node)
        clients = {
            name: client.node.create_client(srv, f"/monovoc/{name}")
            for name, srv in (("save_map", SaveMap), ("load_map", LoadMap), ("reset", Reset), ("publish", Trigger))
        }
        for cli in clients.values():
            wait_for_service(cli, timeout=20.0, process=node)

        def call(name, request, timeout=30.0, **resend):
            return call_service(clients[name], request, timeout, process=node, **resend)

        def last_cloud():
            return ma.semantic_cloud_to_arrays(clouds.messages[-1])

        # Before any map: clear failures, not hangs. The first calls of a fresh client are sent again when unanswered
        # (Fast DDS drops a response whose client it has not matched yet: monovoc_ros.nodes.service_call); these two
        # change nothing, so running twice is harmless.
        response = call("save_map", SaveMap.Request(), resend_s=RESEND_S)
        assert not response.success and "no map" in response.message
        response = call("load_map", LoadMap.Request(), resend_s=RESEND_S)
        assert not response.success and "does not exist" in response.message
        assert call("reset", Reset.Request(keep_gaussians=True)).success

        for pub in publisher.all_publishers():
            wait_for_subscribers(pub, timeout=20.0, process=node)
        publisher.publish_map(scene.gaussians)
        for msgs in messages:
            publisher.publish_messages(msgs)
        diagnostics.wait_for(lambda v: v["keyframes_processed"] == str(N_KEYFRAMES), 20.0, process=node)

        # save_map with an empty directory writes map_directory.
        response = call("save_map", SaveMap.Request())
        assert response.success and response.directory == str(map_dir), response.message
        assert load_snapshot(map_dir).n_keyframes == N_KEYFRAMES

        # Busy: a backlog of keyframes. Diagnostics keep coming and services still answer.
        backlog = [
            keyframe_messages(
                scene.keyframe(i), stamp_ns=int(keyframes[-1].stamp_ns) + (r * N_KEYFRAMES + i + 1) * 10**8
            )
            for r in range(BACKLOG_ROUNDS)
            for i in range(N_KEYFRAMES)
        ]
        busy = []
        watching = threading.Event()

        def watch():
            while not watching.is_set():
                busy.append(diagnostics.values().get("queue_length", "0"))
                time.sleep(0.05)

        watcher = threading.Thread(target=watch)
        watcher.start()
        for msgs in backlog:
            publisher.publish_messages(msgs)
        diagnostics.wait_for(lambda v: int(v["queue_length"]) > 0, 20.0, process=node)
        start = time.monotonic()
        response = call("publish", Trigger.Request(), timeout=60.0)
        answered = time.monotonic() - start
        assert response.success, response.message
        total = N_KEYFRAMES * (1 + BACKLOG_ROUNDS)
        done = diagnostics.wait_for(lambda v: v["keyframes_processed"] == str(total), 60.0, process=node)
        watching.set()
        watcher.join()
        assert done["keyframes_dropped"] == "0"
        assert sum(1 for q in busy if int(q) > 0) >= 2, busy  # diagnostics kept flowing while the worker was busy
        print(f"publish answered after {answered:.2f} s behind the backlog")

        # reset (keep Gaussians): an empty semantic map is published.
        assert call("reset", Reset.Request(keep_gaussians=True)).success
        # The cloud of the backlog's last keyframes may still be on its way (it was once the first one after the
        # reset's answer): wait for the empty one.
        wait_until(lambda: len(last_cloud().object_ids) == 0, 20.0, "the empty cloud after the reset", process=node)
        diagnostics.wait_for(lambda v: v["has_map"] == "true" and v["last_stamp_ns"] == "0", 10.0, process=node)

        # load_map of the saved directory restores the 16-keyframe state.
        response = call("load_map", LoadMap.Request())
        assert response.success and response.directory == str(map_dir), response.message
        assert response.num_gaussians == len(scene.gaussians) and response.num_objects > 0
        wait_until(lambda: ma.header_stamp_ns(clouds.messages[-1]) == keyframes[-1].stamp_ns, 10.0, "the loaded map")
        np.testing.assert_array_equal(last_cloud().object_ids, expected[expected != UNOBSERVED_ID])

        # reset (everything), then load_map of a PLY path: a fresh map.
        assert call("reset", Reset.Request(keep_gaussians=False)).success
        diagnostics.wait_for(lambda v: v["has_map"] == "false", 10.0, process=node)
        response = call("load_map", LoadMap.Request(directory=str(ply)))
        assert response.success and response.num_gaussians == len(scene.gaussians) and response.num_objects == 0
        diagnostics.wait_for(lambda v: v["has_map"] == "true" and v["observed_gaussians"] == "0", 10.0, process=node)
        response = call("load_map", LoadMap.Request(directory=str(tmp_path / "missing")))
        assert not response.success and "missing does not exist" in response.message
        loop = tmp_path / "loop"
        loop.symlink_to(loop)  # a caller's bad path: refused with its reason, not counted as the node's failure
        for service, request in (("load_map", LoadMap.Request), ("save_map", SaveMap.Request)):
            response = call(service, request(directory=str(loop / "map")))
            assert not response.success and str(loop) in response.message, response.message
        # Counted (or not) before they answered: the diagnostics of a publication after them tell.
        published = int(diagnostics.values()["publishes"])
        assert call("publish", Trigger.Request()).success
        values = diagnostics.wait_for(lambda v: int(v["publishes"]) > published, 10.0, process=node)
        assert values["service_errors"] == "0"

        assert node.stop() == 0
    # A clean shutdown saved the fresh PLY map (new since the last save) as the final snapshot.
    final = load_snapshot(map_dir)
    assert final.n_keyframes == 0 and len(final.gaussians) == len(scene.gaussians)
