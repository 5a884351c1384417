"""semantic_mapper: a changed Gaussian map while running (removed, added and moved Gaussians, with ids).

Evidence must follow the ids: kept Gaussians keep theirs (moved ones too), new ones start empty, removed
ones are gone; and the node's state must equal an offline mapper given the same map update.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import msg_adapters as ma
from monovoc_ros.core.follow.map_updater import update_map
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.map_store import load_snapshot
from monovoc_ros.nodes.keyframe_publisher import keyframe_messages
from monovoc_ros.ros_harness import (
    call_service,
)
from tests.evidence import assert_same_evidence
from tests.node_scene import N_KEYFRAMES, assemble, offline_mapper, running_mapper, scene_messages, small_scene

pytestmark = pytest.mark.ros


def changed_map(old: GaussianMap, seed: int = 0) -> GaussianMap:
    """10% removed, 10% of the rest moved by 0.3 m (far beyond any position tolerance), 2000 added, shuffled."""
    rng = np.random.default_rng(seed)
    n = len(old)
    keep = np.sort(rng.choice(n, size=int(0.9 * n), replace=False))
    means = old.means[keep].copy()
    moved = rng.random(keep.size) < 0.1
    means[moved] += np.float32([0.3, 0.0, 0.0])
    new = rng.choice(n, size=2000)
    ids = np.concatenate([old.ids[keep], old.ids.max() + 1 + np.arange(2000)])
    gmap = GaussianMap(
        np.concatenate([means, old.means[new] + np.float32([0.0, 0.0, 0.02])]),
        np.concatenate([old.scales[keep], old.scales[new]]),
        np.concatenate([old.quats[keep], old.quats[new]]),
        np.concatenate([old.opacities[keep], old.opacities[new]]),
        np.concatenate([old.colors[keep], old.colors[new]]),
        ids=ids,
    )
    return gmap.subset(rng.permutation(len(gmap)))


@pytest.mark.parametrize(("ahead", "reader_process"), [(0.0, True), (2.0, True), (0.0, False)])
def test_map_update_carries_evidence_by_id(tmp_path, ahead, reader_process):
    """With `map_update_ahead_s` 0 and 2 s: no keyframe comes after the map until its update is applied here (with
    the window, once the worker had no input for it), so the node ends as offline mapping does either way; and with
    the map topic read in the node's own process."""
    from monovoc_interfaces.srv import SaveMap

    scene, messages = small_scene(), scene_messages()
    keyframes = assemble(messages)
    update_msg = ma.gaussian_map_to_cloud(changed_map(scene.gaussians), stamp=keyframes[7].stamp_ns)
    updated = ma.cloud_to_gaussian_map(update_msg)  # what the node will see

    reference = offline_mapper(scene.gaussians, keyframes[:8])
    before = reference.state
    report = update_map(reference, updated)
    assert report.by_id == len(updated) - 2000 and report.dropped > 0
    mid_weights = reference.state.total_weight.copy()  # integrate() adds in place
    for keyframe in keyframes[8:]:
        reference.integrate(keyframe)

    # The transfer alone (10% moved 0.3 m bends the fitted motion: no re-integration of its own accord here).
    params = {
        "publish_rate_hz": 0.0,
        "diagnostics_period_s": 0.2,
        "reintegrate_below": 0.0,
        "map_update_ahead_s": ahead,
        "map_reader_process": reader_process,
    }
    with running_mapper(tmp_path, params) as mapper:
        node, diagnostics, publisher, save = mapper.node, mapper.diagnostics, mapper.publisher, mapper.save
        publisher.publish_map(scene.gaussians)
        for msgs in messages[:8]:
            publisher.publish_messages(msgs)
        diagnostics.wait_for(lambda v: v["keyframes_processed"] == "8", 20.0, process=node)
        publisher.gaussians.publish(update_msg)
        updated_values = diagnostics.wait_for(lambda v: v["map_updates"] == "1", 20.0, process=node)
        assert updated_values["map_updates_prepared"] == "1"  # its plan was made beside the worker
        # with its motion (here from the ids) estimated in the map reader process, when there is one
        assert updated_values["map_motions_given"] == ("1" if reader_process else "0")
        assert updated_values["map_updates_ahead"] == ("1" if ahead else "0")  # decided by the stamps alone
        assert call_service(save, SaveMap.Request(directory=str(tmp_path / "mid")), process=node).success
        for msgs in messages[8:]:
            publisher.publish_messages(msgs)
        done = diagnostics.wait_for(lambda v: v["keyframes_processed"] == str(N_KEYFRAMES), 20.0, process=node)
        assert done["gaussians"] == str(len(updated)) and done["map_version"] == "1"
        assert call_service(save, SaveMap.Request(directory=str(tmp_path / "final")), process=node).success
        assert report.describe() in node.output()

    mid = load_snapshot(tmp_path / "mid").state
    np.testing.assert_array_equal(mid.ids, updated.ids)
    # Evidence followed the ids: compare per id with the state before the update.
    old_index = {int(i): k for k, i in enumerate(before.ids)}
    kept = np.array([int(i) in old_index for i in updated.ids])
    src = np.array([old_index[int(i)] for i in updated.ids[kept]])
    assert_same_evidence(mid, before, rows=kept, expected_rows=src)
    # The 2000 new ids lie 2 cm from an old Gaussian: they take its evidence by position (where it had any).
    assert (~kept).sum() == 2000 and np.count_nonzero(mid.total_weight[~kept]) > 500
    moved = kept.copy()
    moved[kept] = np.any(updated.means[kept] != scene.gaussians.means[src], axis=1)
    assert moved.sum() > 1000 and np.all(mid.total_weight[moved] == before.total_weight[src[moved[kept]]])
    np.testing.assert_array_equal(mid.total_weight, mid_weights)

    final = load_snapshot(tmp_path / "final")
    assert_same_evidence(final.state, reference.state, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(final.result().object_ids, reference.result().object_ids)


def test_a_keyframe_stamped_after_a_map_update_that_reaches_the_node_first_keeps_its_logged_pose(tmp_path):
    """The SLAM moved its map 5 cm and posed keyframe 8 in the moved map, but the map (read by the map reader
    process) comes after it: the update moves the logged poses of keyframes 0-7 with the map and leaves keyframe
    8's, already in the new map's frame (core.follow.map_frames; it moved twice before the map's stamp was used)."""
    from monovoc_interfaces.srv import SaveMap

    scene, messages = small_scene(), scene_messages()
    keyframes = assemble(messages)
    shift = np.float32([0.0, 0.0, 0.05])
    g = scene.gaussians
    moved_map = GaussianMap(g.means + shift, g.scales, g.quats, g.opacities, g.colors, ids=g.ids,
                            stamp_ns=keyframes[8].stamp_ns - 1)  # fmt: skip
    sent = scene.keyframe(8).cam_to_world.copy()
    sent[:3, 3] += shift
    params = {"publish_rate_hz": 0.0, "diagnostics_period_s": 0.2, "reintegrate_below": 0.0}
    with running_mapper(tmp_path, params) as mapper:
        node, diagnostics, publisher, save = mapper.node, mapper.diagnostics, mapper.publisher, mapper.save
        publisher.publish_map(scene.gaussians, stamp_ns=keyframes[0].stamp_ns)
        for msgs in messages[:8]:
            publisher.publish_messages(msgs)
        publisher.publish_messages(keyframe_messages(replace(scene.keyframe(8), cam_to_world=sent)))
        diagnostics.wait_for(lambda v: v["keyframes_processed"] == "9", 20.0, process=node)
        publisher.publish_map(moved_map)
        done = diagnostics.wait_for(lambda v: v["map_updates"] == "1", 20.0, process=node)
        assert done["keyframes_before_their_map"] == "1" and done["keyframes_moved_into_map"] == "0"
        assert call_service(save, SaveMap.Request(directory=str(tmp_path / "m")), process=node).success
    logged = {e.stamp_ns: e.cam_to_world for e in load_snapshot(tmp_path / "m").keyframe_log.entries}
    for k in range(8):
        expected = scene.keyframe(k).cam_to_world.copy()
        expected[:3, 3] += shift
        np.testing.assert_allclose(logged[keyframes[k].stamp_ns], expected, atol=1e-4)
    np.testing.assert_allclose(logged[keyframes[8].stamp_ns], sent, atol=1e-4)
