"""semantic_mapper persistence: kill -9 after a periodic snapshot, restart with resume, send the rest.

The final snapshot must equal an offline run over exactly the keyframe stamps it holds, and those are all
sent stamps except the ones integrated between the last periodic snapshot and the kill. Deterministic
whatever the timing (issue 9, case 11): the loss is measured against the snapshot CURRENT named at the kill
(a second periodic snapshot may land before it), and the resumed node saves only at shutdown, so its final
snapshot is always written and logged.
"""

from __future__ import annotations

import signal

import numpy as np
import pytest

from monovoc_ros.core.evidence.votes import VoteState
from monovoc_ros.core.map_store import current_snapshot, load_snapshot
from monovoc_ros.nodes.keyframe_publisher import KeyframePublisher
from monovoc_ros.ros_harness import (
    ClientNode,
    DiagnosticsMonitor,
    NodeProcess,
    ros_args,
    wait_for_subscribers,
    wait_until,
)
from tests.evidence import assert_same_evidence
from tests.node_scene import N_KEYFRAMES, NODE, assemble, offline_mapper, scene_messages, small_scene
from tests.rosutil import ros_environment

pytestmark = pytest.mark.ros

SAVE_PERIOD_S = 3.0


def snapshot_stamps(map_dir) -> list[int]:
    """Stamps in the snapshot CURRENT names ([] if none; retried while the node replaces snapshots)."""
    for _ in range(5):
        try:
            snap = current_snapshot(map_dir)
            return [] if snap is None else VoteState.load(snap / "state.npz").stamps_ns.tolist()
        except (OSError, ValueError):
            continue
    return []


def test_kill_9_loses_only_the_keyframes_since_the_last_snapshot(tmp_path):
    scene, messages = small_scene(), scene_messages()
    keyframes = assemble(messages)
    stamps = [kf.stamp_ns for kf in keyframes]
    map_dir = tmp_path / "map"
    env = ros_environment(tmp_path)
    params = {"map_directory": str(map_dir), "save_period_s": SAVE_PERIOD_S, "resume": True,
              "publish_rate_hz": 0.0, "diagnostics_period_s": 0.2}  # fmt: skip
    args = [*NODE, *ros_args(params)]

    with ClientNode(env, "client_1") as client:
        publisher = KeyframePublisher(client.node)
        diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
        publisher.publish_map(scene.gaussians)
        with NodeProcess.python(args, env, name="mapper_1") as node:
            for pub in publisher.all_publishers():
                wait_for_subscribers(pub, timeout=20.0, process=node)
            for msgs in messages[:6]:
                publisher.publish_messages(msgs)
            # A periodic snapshot with the first six keyframes...
            wait_until(lambda: snapshot_stamps(map_dir) == stamps[:6], 4 * SAVE_PERIOD_S, "a periodic snapshot",
                       process=node)  # fmt: skip
            # ... then three more, integrated but not yet saved when the node is killed.
            for msgs in messages[6:9]:
                publisher.publish_messages(msgs)
            diagnostics.wait_for(lambda v: v["keyframes_processed"] == "9", 10.0, process=node)
            node.proc.send_signal(signal.SIGKILL)
            node.proc.wait(10)
        assert node.returncode == -signal.SIGKILL
    saved_at_kill = snapshot_stamps(map_dir)
    kept = len(saved_at_kill)
    assert 6 <= kept <= 9 and saved_at_kill == stamps[:kept], saved_at_kill  # the last snapshot, nothing else
    assert load_snapshot(map_dir).n_keyframes == kept  # intact after SIGKILL

    # A fresh client: the killed node's participant would linger in the old one's graph.
    with ClientNode(env, "client_2") as client:
        publisher = KeyframePublisher(client.node)
        diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
        publisher.publish_map(scene.gaussians)  # the same map again (latched): must not disturb the state
        # No periodic snapshot this time: the one written at shutdown is the one checked below.
        resumed = [*NODE, *ros_args({**params, "save_period_s": 0.0})]
        with NodeProcess.python(resumed, env, name="mapper_2") as node:
            node.wait_for_output("resumed", 30.0)
            for pub in publisher.all_publishers():
                wait_for_subscribers(pub, timeout=20.0, process=node)
            for msgs in messages[9:]:
                publisher.publish_messages(msgs)
            rest = N_KEYFRAMES - 9
            # The map and the keyframes come on topics of their own: either may reach the worker first.
            done = diagnostics.wait_for(lambda v: v["keyframes_processed"] == str(rest) and v["maps_unchanged"] == "1",
                                        20.0, process=node)  # fmt: skip
            assert done["rejected_total"] == "0" and done["map_updates"] == "0"
            assert node.stop() == 0  # SIGINT: final snapshot
        assert "final snapshot" in node.output()

    final = load_snapshot(map_dir)
    expected_stamps = saved_at_kill + stamps[9:]
    assert final.state.stamps_ns.tolist() == expected_stamps
    offline = offline_mapper(scene.gaussians, [kf for kf in keyframes if kf.stamp_ns in set(expected_stamps)])
    assert_same_evidence(final.state, offline.state, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(final.state.ids, offline.state.ids)
    for key, value in offline.palette_builder.to_arrays().items():
        np.testing.assert_array_equal(final.palette_builder.to_arrays()[key], value)
    np.testing.assert_array_equal(final.result().object_ids, offline.result().object_ids)
