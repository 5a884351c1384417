"""The keyframe log (core.follow.keyframe_log) and re-integration (core.session): exact, interleavable, persistent."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from monovoc_ros import offline
from monovoc_ros.core.evidence.palette import UNOBSERVED_ID
from monovoc_ros.core.follow.keyframe_log import KeyframeLog, KeyframePoses, decode_mask, encode_mask
from monovoc_ros.core.follow.map_updater import MAX_REBUILD_RESTARTS
from monovoc_ros.core.map_store import load_snapshot, save_snapshot
from monovoc_ros.core.segments.segment_labels import SegmentLabel
from monovoc_ros.core.session import MappingSession
from monovoc_ros.synthetic import churn
from tests.node_scene import assemble, scene_messages, small_scene


def _keyframes(n: int = 8):
    return assemble(scene_messages()[:n])


def _shifted(kf, dx: float = 0.02):
    T = kf.cam_to_world.copy()
    T[0, 3] += dx
    return replace(kf, cam_to_world=T)


def _session(gaussians, keyframes) -> MappingSession:
    """A session with the map and these keyframes integrated (as the live worker runs them)."""
    session = MappingSession()
    session.add_map(gaussians)
    for kf in keyframes:
        session.add_keyframe(kf)
        session.integrate_next()
    return session


def _same_state(a, b) -> None:
    for name in a.state.ARRAYS:
        np.testing.assert_array_equal(getattr(a.state, name), getattr(b.state, name))
    np.testing.assert_array_equal(a.state.stamps_ns, b.state.stamps_ns)


def test_log_round_trip_keeps_masks_poses_segments(tmp_path):
    kfs = _keyframes(3)
    kfs[1] = replace(kfs[1], segments=(SegmentLabel(0x112233, "chair", 0.5),))
    log = KeyframeLog()
    for kf in kfs:
        log.add(kf)
    assert 0 < log.nbytes < 3 * 40_000  # masks compress to a few KB each
    log.save(tmp_path / "log.npz")
    back = KeyframeLog.load(tmp_path / "log.npz")
    assert len(back) == 3 and back.nbytes == log.nbytes and back.complete
    for kf, entry in zip(kfs, back.entries, strict=True):
        again = entry.keyframe()
        np.testing.assert_array_equal(again.mask, kf.mask)
        np.testing.assert_array_equal(again.cam_to_world, kf.cam_to_world)
        assert again.stamp_ns == kf.stamp_ns and again.intrinsics == kf.intrinsics and again.rgb is None
    assert back.entries[1].segments == (SegmentLabel(0x112233, "chair", 0.5),)
    (tmp_path / "bad.npz").write_bytes(b"not a log")
    with pytest.raises(ValueError, match="unreadable keyframe log"):
        KeyframeLog.load(tmp_path / "bad.npz")


def test_mask_codec_round_trips_reads_old_png_logs_and_refuses_bad_bytes():
    mask = _keyframes(1)[0].mask  # (H, W, 3) uint8
    h, w = mask.shape[:2]
    blob = encode_mask(mask)
    np.testing.assert_array_equal(decode_mask(blob, h, w), mask)
    assert len(blob) < mask.nbytes / 20
    ok, png = cv2.imencode(".png", np.ascontiguousarray(mask[:, :, ::-1]))  # how logs were saved before zstd
    assert ok
    np.testing.assert_array_equal(decode_mask(png.tobytes(), h, w), mask)
    assert decode_mask(blob, h + 1, w) is None  # not a mask of these intrinsics
    assert decode_mask(png.tobytes(), h, w + 1) is None
    assert decode_mask(blob[: len(blob) // 2], h, w) is None
    assert decode_mask(b"not a mask", h, w) is None


def test_log_is_bounded_oldest_first():
    kfs = _keyframes(4)
    log = KeyframeLog()
    for kf in kfs:
        log.add(kf)
    small = KeyframeLog(max_bytes=log.entries[2].nbytes + log.entries[3].nbytes)  # room for the last two
    for kf in kfs:
        small.add(kf)
    assert len(small) == 2 and small.dropped == 2 and not small.complete
    assert [e.stamp_ns for e in small.entries] == [kfs[2].stamp_ns, kfs[3].stamp_ns]


def test_snapshot_keeps_the_log(tmp_path):
    scene, kfs = small_scene(), _keyframes(3)
    mapper, _ = offline.map_events([scene.gaussians, *kfs])
    save_snapshot(mapper, tmp_path / "map", export_cloud=False)
    back = load_snapshot(tmp_path / "map")
    assert [e.stamp_ns for e in back.keyframe_log.entries] == [kf.stamp_ns for kf in kfs]
    np.testing.assert_array_equal(back.keyframe_log.entries[2].keyframe().mask, kfs[2].mask)


def test_corrected_poses_reintegrate_to_the_fresh_map_of_the_corrected_keyframes():
    scene, kfs = small_scene(), _keyframes(8)
    corrected = [_shifted(kf) for kf in kfs[:5]]
    poses = KeyframePoses(tuple((kf.stamp_ns, kf.cam_to_world) for kf in corrected))
    rebuilt, stats = offline.map_events([scene.gaussians, *kfs[:5], poses, *kfs[5:]])
    fresh, _ = offline.map_events([scene.gaussians, *corrected, *kfs[5:]])
    _same_state(rebuilt, fresh)
    assert stats.reintegrations == 1 and stats.keyframes_reintegrated == 5 and not stats.reintegrating
    np.testing.assert_array_equal(rebuilt.result().object_ids, fresh.result().object_ids)
    # The same poses again change nothing: no second re-integration.
    _, again = offline.map_events([scene.gaussians, *kfs[:5], poses, poses])
    assert again.reintegrations == 1


def test_interleaved_reintegration_serves_old_labels_and_ends_as_offline():
    """As the live worker runs it: keyframes keep arriving between re-integration steps."""
    scene, kfs = small_scene(), _keyframes(8)
    corrected = [_shifted(kf) for kf in kfs[:5]]
    session = _session(scene.gaussians, kfs[:5])
    old = session.mapper
    session.add_keyframe_poses(KeyframePoses(tuple((kf.stamp_ns, kf.cam_to_world) for kf in corrected)))
    assert session.reintegrating and session.mapper is old  # the old labels meanwhile
    for kf in kfs[5:]:
        session.reintegration_step()
        session.add_keyframe(kf)
        session.integrate_next()
        assert session.mapper is old
    while session.reintegration_step():
        pass
    assert session.mapper is not old and session.stats.keyframes_reintegrated == 8
    fresh, _ = offline.map_events([scene.gaussians, *corrected, *kfs[5:]])
    _same_state(session.mapper, fresh)


def test_bad_keyframe_poses_are_refused_and_change_nothing():
    scene, kfs = small_scene(), _keyframes(3)
    session = _session(scene.gaussians, kfs)
    nan = kfs[0].cam_to_world.copy()
    nan[0, 3] = np.nan
    far = _shifted(kfs[1], 25.0).cam_to_world
    skew = kfs[2].cam_to_world.copy()
    skew[:3, :3] *= 2.0
    for T, stamp in ((nan, kfs[0].stamp_ns), (far, kfs[1].stamp_ns), (skew, kfs[2].stamp_ns)):
        assert session.add_keyframe_poses(KeyframePoses(((stamp, T),))) == 0
    assert session.stats.rejected["bad_keyframe_poses"] == 3 and not session.reintegrating
    np.testing.assert_array_equal(session.mapper.keyframe_log.entries[0].cam_to_world, kfs[0].cam_to_world)
    # Poses of keyframes the log never saw are ignored.
    assert session.add_keyframe_poses(KeyframePoses(((123, kfs[0].cam_to_world),))) == 0


def test_poor_transfer_reintegrates_with_poses_moved_by_the_map():
    scene, kfs = small_scene(), _keyframes(6)
    closure = churn.then(churn.densify(scene.gaussians, prune=0.1), churn.loop_closure, degrees=1.0)
    config = replace(offline.MapperConfig(), reintegrate_below=0.99)  # 10% pruned: the transfer counts as poor
    mapper, stats = offline.map_events([scene.gaussians, *kfs, closure.gaussians], config)
    assert stats.reintegrations == 1 and stats.keyframes_reintegrated == 6
    moved = [replace(kf, cam_to_world=closure.move_pose(kf.cam_to_world)) for kf in kfs]
    for entry, kf in zip(mapper.keyframe_log.entries, moved, strict=True):
        np.testing.assert_allclose(entry.cam_to_world, kf.cam_to_world, atol=2e-3)
    fresh, _ = offline.map_events([closure.gaussians, *moved], config)
    agree = np.mean(mapper.result().object_ids == fresh.result().object_ids)
    assert agree > 0.99


def test_poses_of_keyframes_not_integrated_yet_apply_when_they_are():
    """Live, a keyframe can still be in the synchronizer when the SLAM's path arrives: it takes its corrected
    pose when integrated, and the map ends as the offline one that saw the path after it."""
    scene, kfs = small_scene(), _keyframes(6)
    corrected = [_shifted(kf) for kf in kfs]
    poses = KeyframePoses(tuple((kf.stamp_ns, kf.cam_to_world) for kf in corrected))
    live, live_stats = offline.map_events([scene.gaussians, *kfs[:4], poses, *kfs[4:]])
    after, _ = offline.map_events([scene.gaussians, *kfs, poses])
    _same_state(live, after)
    assert live_stats.reintegrations == 1
    np.testing.assert_array_equal(live.keyframe_log.entries[5].cam_to_world, corrected[5].cam_to_world)


def test_an_incomplete_log_never_replaces_the_evidence():
    """A bounded log that dropped keyframes (or a snapshot from before the log) cannot rebuild the state:
    the re-integration is skipped and counted, the evidence kept."""
    scene, kfs = small_scene(), _keyframes(4)
    config = replace(offline.MapperConfig(), keyframe_log_bytes=0)
    poses = KeyframePoses(tuple((kf.stamp_ns, _shifted(kf).cam_to_world) for kf in kfs))
    mapper, stats = offline.map_events([scene.gaussians, *kfs, poses], config)
    assert stats.reintegrations == 0 and stats.rejected["reintegration_incomplete_log"] == 0  # nothing logged moved
    assert mapper.n_keyframes == 4 and len(mapper.keyframe_log) == 0 and not mapper.keyframe_log.complete
    closure = churn.loop_closure(scene.gaussians, degrees=1.0)
    bent = replace(offline.MapperConfig(), keyframe_log_bytes=0, reintegrate_below=1.0)
    mapper, stats = offline.map_events(
        [scene.gaussians, *kfs, churn.densify(closure.gaussians, prune=0.2).gaussians], bent
    )
    assert stats.rejected["reintegration_incomplete_log"] == 1 and stats.reintegrations == 0
    assert mapper.n_keyframes == 4 and mapper.state.observed.sum() > 0.5 * len(mapper.gaussians)


def test_a_snapshot_without_a_log_is_marked_incomplete(tmp_path):
    scene, kfs = small_scene(), _keyframes(2)
    mapper, _ = offline.map_events([scene.gaussians, *kfs])
    info = save_snapshot(mapper, tmp_path / "map", export_cloud=False)
    (info.path / "keyframe_log.npz").unlink()  # as written before the log existed
    back = load_snapshot(tmp_path / "map")
    assert len(back.keyframe_log) == 0 and back.keyframe_log.dropped == 2 and not back.keyframe_log.complete


def test_a_job_skips_entries_the_log_dropped_before_it_reached_them():
    from monovoc_ros.core.follow.map_updater import Reintegration

    scene, kfs = small_scene(), _keyframes(6)
    mapper, _ = offline.map_events([scene.gaussians, *kfs[:5]])
    job = Reintegration(mapper, "test")
    mapper.keyframe_log.max_bytes = 3 * mapper.keyframe_log.entries[0].nbytes  # room for about 3
    mapper.integrate(kfs[5])  # logged: the oldest entries go
    kept = [e.stamp_ns for e in mapper.keyframe_log.entries]
    assert mapper.keyframe_log.dropped >= 2
    while not job.caught_up:
        job.step()
    assert job.refused == 0 and list(job.mapper.state.stamps_ns) == kept


def test_a_corrupt_logged_mask_is_refused_not_fatal():
    scene, kfs = small_scene(), _keyframes(3)
    session = _session(scene.gaussians, kfs)
    log = session.mapper.keyframe_log
    log.entries[1] = replace(log.entries[1], mask_blob=b"not a mask")
    session.add_keyframe_poses(KeyframePoses(tuple((kf.stamp_ns, _shifted(kf).cam_to_world) for kf in kfs)))
    while session.reintegration_step():
        pass
    assert session.mapper.n_keyframes == 2 and session.stats.reintegrations == 1


def test_an_empty_path_clears_pending_poses_and_an_unrelated_map_replaces_an_unobserved_one():
    scene, kfs = small_scene(), _keyframes(2)
    session = MappingSession()
    session.add_map(scene.gaussians)
    session.add_keyframe_poses(KeyframePoses(((kfs[0].stamp_ns, _shifted(kfs[0]).cam_to_world),)))
    session.add_keyframe_poses(KeyframePoses(()))
    session.add_keyframe(kfs[0])
    session.integrate_next()
    np.testing.assert_array_equal(session.mapper.keyframe_log.entries[0].cam_to_world, kfs[0].cam_to_world)
    # Before any evidence, a map that does not register (another place) is simply taken.
    fresh = MappingSession()
    fresh.add_map(scene.gaussians)
    far = churn.loop_closure(scene.gaussians, degrees=0.0, translation=(40.0, 0.0, 0.0)).gaussians
    assert fresh.add_map(far) and fresh.stats.rejected["map_motion"] == 0


def test_a_rebuild_that_lost_keyframes_to_the_bound_or_to_a_new_map_is_never_swapped_in():
    scene, kfs = small_scene(), _keyframes(6)
    corrected = KeyframePoses(tuple((kf.stamp_ns, _shifted(kf).cam_to_world) for kf in kfs[:5]))
    session = _session(scene.gaussians, kfs[:5])
    live = session.mapper
    session.add_keyframe_poses(corrected)
    assert session.reintegrating
    live.keyframe_log.max_bytes = 3 * live.keyframe_log.entries[0].nbytes  # the log starts dropping
    session.add_keyframe(kfs[5])
    session.integrate_next()
    while session.reintegration_step():
        pass
    assert session.mapper is live and live.n_keyframes == 6  # the evidence of every keyframe is kept
    assert session.stats.rejected["reintegration_incomplete_log"] == 1 and session.stats.reintegrations == 0
    # A map update during a rebuild when the log can no longer rebuild: the old rebuild (of the old map)
    # is dropped too, so the new map stays.
    session = _session(scene.gaussians, kfs[:5])
    session.add_keyframe_poses(corrected)
    session.mapper.keyframe_log.dropped = 1
    closure = churn.loop_closure(scene.gaussians, degrees=1.0).gaussians
    assert session.add_map(closure) and not session.reintegrating
    assert session.mapper.gaussians is closure


def test_map_updates_faster_than_a_rebuild_cannot_keep_it_from_finishing():
    """A SLAM sending maps while a rebuild runs (every two keyframes of it here): the first updates restart it
    (MAX_REBUILD_RESTARTS), the next ones carry the rebuild's evidence over with the live one's, and the rebuild
    goes on where it was and is swapped in; an update that needed a rebuild of its own starts the next one then."""
    scene, kfs = small_scene(), _keyframes(8)
    corrected = [_shifted(kf) for kf in kfs]
    session = _session(scene.gaussians, kfs)
    old = session.mapper
    session.add_keyframe_poses(KeyframePoses(tuple((kf.stamp_ns, kf.cam_to_world) for kf in corrected)))
    current, moves, updates, steps = scene.gaussians, [], 0, 0
    while session.reintegration_step():
        steps += 1
        if session.mapper is old and steps % 2 == 0:  # mid-rebuild: a new map
            churned = churn.then(churn.densify(current, split=0.02, prune=0.0, seed=updates), churn.loop_closure,
                                 degrees=0.2, translation=(0.005, 0.0, 0.0), seed=updates)  # fmt: skip
            current = churned.gaussians
            moves.append(churned.move_pose)
            assert session.add_map(current) and session.reintegrating
            updates += 1
    # Restarted twice (steps 2 and 4), then 8 steps of which 3 carried an update over.
    assert updates == MAX_REBUILD_RESTARTS + 3 and session.mapper is not old and session.mapper.gaussians is current
    assert session.stats.reintegrations == 1 and session.stats.keyframes_reintegrated == 8
    # The rebuilt log's poses moved with the maps as the live log's did (the corrected poses were in the frame
    # of the first new map already: only the later ones moved them).
    for entry, live, kf in zip(session.mapper.keyframe_log.entries, old.keyframe_log.entries, corrected, strict=True):
        np.testing.assert_array_equal(entry.cam_to_world, live.cam_to_world)
        T = kf.cam_to_world
        for move in moves[1:]:
            T = move(T)
        np.testing.assert_allclose(entry.cam_to_world, T, atol=2e-3)
    # Its labels are those of a fresh mapping of the corrected keyframes on the final map, but for the few
    # Gaussians whose evidence came over the updates.
    entries = session.mapper.keyframe_log.entries
    moved = [replace(kf, cam_to_world=e.cam_to_world) for kf, e in zip(corrected, entries, strict=True)]
    fresh, _ = offline.map_events([current, *moved])
    observed = fresh.result().object_ids != UNOBSERVED_ID
    agree = np.mean(session.mapper.result().object_ids[observed] == fresh.result().object_ids[observed])
    carried = np.mean(old.result().object_ids[observed] == fresh.result().object_ids[observed])  # no rebuild
    assert agree > 0.95 and agree > carried, (agree, carried)

    # An update that needed a rebuild of its own (10% of the map pruned), carried over mid-rebuild: the next
    # rebuild starts once this one is swapped in, and both finish.
    session = MappingSession(replace(offline.MapperConfig(), reintegrate_below=0.95))
    session.add_map(scene.gaussians)
    for kf in kfs:
        session.add_keyframe(kf)
        session.integrate_next()
    session.add_keyframe_poses(KeyframePoses(tuple((kf.stamp_ns, kf.cam_to_world) for kf in corrected)))
    current = scene.gaussians
    for seed in range(MAX_REBUILD_RESTARTS + 1):  # the last one is carried over
        session.reintegration_step()
        current = churn.densify(current, prune=0.1 if seed == MAX_REBUILD_RESTARTS else 0.0, split=0.0, seed=seed)
        assert session.add_map(current.gaussians)
        current = current.gaussians
    while session.reintegration_step():
        pass
    assert session.stats.reintegrations == 2 and not session.reintegrating


def _per_frame_closure(rates, seed: int, refine_m: float):
    """A per-frame-id session (the small scene's masks renumbered per frame, with segmenter-like noise when
    `rates` has some) of 8 keyframes, then a loop closure: the map moved 2 deg (re-ordered, ids kept so that
    Gaussians can be followed), and the SLAM's corrected path, the poses moved with the map and refined by
    `refine_m` along x; re-integrated. Returns (per Gaussian of the new map: its object id before the
    closure, after the swap, in a fresh mapping of the same corrected keyframes), the old and new mappers'
    object geometry and the closure."""
    from monovoc_ros.core.evaluation.datasets import CorruptedMasks

    scene = small_scene()
    seq = CorruptedMasks(scene, shuffled=True, rates=rates, seed=seed)
    kfs = [seq.keyframe(i) for i in range(8)]
    config = replace(offline.MapperConfig(), mask_ids="per_frame")
    session = MappingSession(config)
    session.add_map(scene.gaussians)
    for kf in kfs:
        session.add_keyframe(kf)
        session.integrate_next()
    old = session.mapper  # the map update takes its new map in place; the rebuild replaces it
    before, old_geometry = old.result().object_ids, old.result().objects(old.gaussians)
    old_gaussian_ids = old.gaussians.ids
    closure = churn.loop_closure(scene.gaussians, degrees=2.0, seed=5, keep_ids=True)
    refine = np.eye(4)
    refine[0, 3] = refine_m
    corrected = [replace(kf, cam_to_world=refine @ closure.move_pose(kf.cam_to_world)) for kf in kfs]
    session.add_map(closure.gaussians)
    session.add_keyframe_poses(KeyframePoses(tuple((kf.stamp_ns, kf.cam_to_world) for kf in corrected)))
    while session.reintegration_step():
        pass
    assert session.stats.reintegrations == 1 and session.mapper is not old
    new = session.mapper
    order = np.argsort(old_gaussian_ids)
    rows = order[np.searchsorted(old_gaussian_ids[order], new.gaussians.ids)]  # (N,) old row of each new Gaussian
    fresh, _ = offline.map_events([closure.gaussians, *corrected], config)  # what the rebuild named them
    ids = (before[rows], new.result().object_ids, fresh.result().object_ids)
    return ids, old_geometry, new.result().objects(new.gaussians), closure, (old, new)


def test_per_frame_object_ids_survive_a_reintegration():
    """Per-frame ids, a segmenter's noise (merged, split, dropped segments) and corrected poses refined by
    2 mm: the rebuild associates the logged segments afresh and names the objects its own way (a tenth of
    the Gaussians under other ids), yet after the swap the objects keep the ids they had."""
    from monovoc_ros.core.segments.segment_noise import NoiseRates

    rates = NoiseRates(split=0.2, merge=0.1, drop=0.1)
    (before, after, fresh), _, _, _, (old, new) = _per_frame_closure(rates, seed=4, refine_m=0.002)
    both = (before != UNOBSERVED_ID) & (after != UNOBSERVED_ID)
    kept = np.mean(after[both] == before[both])
    assert kept >= 0.95, kept
    assert np.mean(fresh[both] == before[both]) < kept - 0.05  # the ids a rebuild gives by itself
    # Every object of the map before (but slivers) is there after, under its id.
    ids, counts = np.unique(before[before != UNOBSERVED_ID], return_counts=True)
    present = set(after[after != UNOBSERVED_ID].tolist())
    assert set(ids[counts >= 0.01 * counts.sum()].tolist()) <= present
    # The ids the old map issued are never given to another object later.
    assert set(old.associator.issued) <= set(new.associator.issued)
    assert len(set(new.associator.issued)) == len(new.associator.issued)


def test_per_frame_reintegration_keeps_ids_and_geometry_of_unchanged_objects(tmp_path):
    """Per-frame ids without noise, the poses corrected with the map (and by 1.5 mm): every Gaussian keeps its object
    id, and each object's geometry (the boxes and centroids the queries answer with) moved with the map; the
    adopted ids go through a snapshot."""
    (before, after, _), old_geometry, new_geometry, closure, (_, new) = _per_frame_closure(None, 3, 0.0015)
    both = (before != UNOBSERVED_ID) & (after != UNOBSERVED_ID)
    assert np.mean(after[both] == before[both]) >= 0.99
    assert set(before[before != UNOBSERVED_ID].tolist()) == set(after[after != UNOBSERVED_ID].tolist())
    moved = closure.move_pose(np.eye(4))
    old_objects = {o.id: o for o in old_geometry.objects}
    assert [o.id for o in new_geometry.objects] == sorted(old_objects)
    # Things, not the room's shell: a floor's or wall's centroid wanders with the confidence of its far edges.
    things = [o for o in new_geometry.objects if np.max(o.bbox_max - o.bbox_min) < 1.5]
    assert len(things) >= 10
    for o in things:
        expected = moved[:3, :3] @ old_objects[o.id].centroid + moved[:3, 3]
        assert np.linalg.norm(o.centroid - expected) < 0.02, (hex(o.id), o)
    save_snapshot(new, tmp_path / "map", export_cloud=False)
    back = load_snapshot(tmp_path / "map")
    np.testing.assert_array_equal(back.result().object_ids, new.result().object_ids)
    assert back.associator.to_json() == new.associator.to_json()
