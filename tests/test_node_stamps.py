"""Far-future stamps against the live node. Issue 9, case 4: a single valid pose stamped sec = 2^31 - 1
made every later pose `stamp_out_of_order` until a reset; it is rejected (stamp_future) and every later
keyframe is integrated. Issue 24: streams that resume after a pause longer than `max_stamp_lead_s` (a
robot that stood still, a restarted SLAM, a later bag) were all rejected as stamp_future, for good; every
keyframe after a pause of 100 s and of 1 h is integrated."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest

import msg_adapters as ma
from tests.node_scene import running_mapper, scene_messages, small_scene

pytestmark = pytest.mark.ros


def test_a_far_future_pose_does_not_block_mapping(tmp_path):
    scene, messages = small_scene(), scene_messages()
    outlier = copy.deepcopy(messages[3]["pose"])
    outlier.header.stamp = ma.ns_to_time((2**31 - 1) * 1_000_000_000)
    # With the interpreter's holds traced (what a user sets to find what stalls the node): the watch's file.
    params = {"publish_rate_hz": 0.0, "diagnostics_period_s": 0.2, "interpreter_hold_trace_ms": 250.0}
    with running_mapper(tmp_path, params, save_map=False) as run:
        run.publisher.publish_map(scene.gaussians)
        for msgs in messages[:3]:
            run.publisher.publish_messages(msgs)
        run.diagnostics.wait_for(lambda v: v["keyframes_processed"] == "3", 20.0, process=run.node)
        run.publisher.publishers["pose"].publish(outlier)
        for msgs in messages[3:8]:
            run.publisher.publish_messages(msgs)
        done = run.diagnostics.wait_for(
            lambda v: v["keyframes_processed"] == "8" and v["rejected.stamp_future"] == "1", 20.0, process=run.node
        )
        run.node.check_running()
    assert done["rejected.stamp_out_of_order"] == "0" and done["rejected_total"] == "1"
    assert done["stamp_epochs"] == "0" and done["stamps_held"] == "0"
    # Start-up's objects out of the garbage collector's full collections (rclpy, the kernels, the components).
    assert int(done["gc_frozen_objects"]) > 50_000
    trace = Path(done["interpreter_hold_trace_file"])
    assert trace.parent == Path(run.env["ROS_LOG_DIR"]) and trace.name.startswith("monovoc_interpreter_holds_")
    assert trace.is_file()


def restamped(msgs: dict, shift_ns: int) -> dict:
    out = {}
    for role, msg in msgs.items():
        copied = copy.deepcopy(msg)
        copied.header.stamp = ma.ns_to_time(ma.header_stamp_ns(msg) + shift_ns)
        out[role] = copied
    return out


def test_keyframes_after_a_pause_of_100_s_and_of_1_h_are_all_integrated(tmp_path):
    scene, messages = small_scene(), scene_messages()
    params = {"publish_rate_hz": 0.0, "diagnostics_period_s": 0.2}
    with running_mapper(tmp_path, params, save_map=False) as run:
        run.publisher.publish_map(scene.gaussians)
        # The same stretch of keyframes three times: as recorded, 100 s later, then an hour after that.
        for n, shift_s in enumerate((0, 100, 3700), start=1):
            for msgs in messages[:4]:
                run.publisher.publish_messages(restamped(msgs, shift_s * 1_000_000_000))
            done = run.diagnostics.wait_for(
                lambda v, n=n: v["keyframes_processed"] == str(4 * n), 30.0, process=run.node
            )
        run.node.check_running()
    assert done["rejected_total"] == "0" and done["stamp_epochs"] == "2" and done["stamps_held"] == "0"


def test_inputs_held_for_a_silent_topic_are_released_after_reorder_wait_s_each_time(tmp_path):
    """The flush of held inputs is armed only while something is held: a keyframe whose pose is late is handed
    on after `reorder_wait_s` with no other traffic to push it, then completed by its pose, twice (the flush is
    armed again after it went quiet)."""
    scene, messages = small_scene(), scene_messages()
    params = {"publish_rate_hz": 0.0, "diagnostics_period_s": 0.2, "reorder_wait_s": 0.5}
    with running_mapper(tmp_path, params) as run:
        run.publisher.publish_map(scene.gaussians)
        for msgs in messages[:3]:
            run.publisher.publish_messages(msgs)
        run.diagnostics.wait_for(lambda v: v["keyframes_processed"] == "3", 30.0, process=run.node)
        for k in (3, 4):
            run.publisher.publish_messages({role: msg for role, msg in messages[k].items() if role != "pose"})
            # Held while the pose topic is behind; nothing else arrives, so only the flush hands them on.
            released = run.diagnostics.wait_for(
                lambda v, k=k: v["messages_received.mask"] == str(k + 1) and v["inputs_waiting"] == "0",
                10.0,
                process=run.node,
            )  # fmt: skip
            assert released["keyframes_processed"] == str(k)
            run.publisher.publish_messages({"pose": messages[k]["pose"]})
            done = run.diagnostics.wait_for(
                lambda v, k=k: v["keyframes_processed"] == str(k + 1), 10.0, process=run.node
            )
        run.node.check_running()
    # The two keyframes' image, mask and camera_info, handed on by the wait limit.
    assert done["rejected_total"] == "0" and done["inputs_released_early"] == "6"
