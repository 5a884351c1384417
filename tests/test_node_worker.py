"""The semantic_mapper's worker without ROS: queue policy, ordering, hooks, persistence."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from monovoc_ros.core.follow.keyframe_log import KeyframePoses
from monovoc_ros.core.follow.map_ahead import MapAhead
from monovoc_ros.core.follow.map_follow import FollowConfig, map_motion
from monovoc_ros.core.follow.map_motion import MapMotion
from monovoc_ros.core.follow.map_updater import GivenMotion, plan_map_update
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.camera import Intrinsics
from monovoc_ros.core.map.gaussians import GaussianMap, same_geometry
from monovoc_ros.core.map_store import current_snapshot, load_deferred, load_snapshot
from monovoc_ros.core.mapping import MapperConfig, SemanticMapper, SemanticResult
from monovoc_ros.core.object_geometry import object_geometry
from monovoc_ros.core.session import MappingSession
from monovoc_ros.nodes.diagnostics import MapperStats, RejectionLog
from monovoc_ros.nodes.worker import (
    KEYFRAMES_PER_REINTEGRATION_STEP,
    MapWorker,
    Preparation,
    TaskQueue,
    WorkerSettings,
    WorkerStopped,
    _Ahead,
    _Task,
)
from monovoc_ros.offline import map_events
from monovoc_ros.ros_harness import wait_until
from tests.evidence import assert_same_evidence
from tests.geometry import assert_same_geometry
from tests.node_scene import RecordingLog

CAM = Intrinsics(30.0, 30.0, 15.5, 11.5, 32, 24)


def plane_map(n: int = 200, seed: int = 0, ids: bool = True) -> GaussianMap:
    rng = np.random.default_rng(seed)
    means = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-0.7, 0.7, n), np.full(n, 2.0)])
    return GaussianMap(
        means,
        np.full((n, 3), 0.05),
        np.tile([1.0, 0, 0, 0], (n, 1)),
        np.full(n, 0.8),
        ids=np.arange(n) + 1000 if ids else None,
    )


def keyframe(stamp: int, shift: int = 0) -> Keyframe:
    mask = np.zeros((24, 32, 3), np.uint8)
    mask[:, : 16 + shift] = (200, 30, 30)
    mask[:, 16 + shift :] = (30, 200, 30)
    return Keyframe(stamp, stamp, np.eye(4), CAM, mask)


class Sink:
    def __init__(self):
        self.published = []

    def publish(self, mapper, result):
        self.published.append((None if mapper is None else mapper.n_keyframes, result))
        return 0


def make_worker(tmp_path: Path | None = None, **settings) -> tuple[MapWorker, Sink, RecordingLog]:
    sink, log = Sink(), RecordingLog()
    opts = {"queue_size": 8, "publish_period_s": 0.0, "save_period_s": 0.0}
    opts.update(settings)
    worker = MapWorker(MapperConfig(), WorkerSettings(**opts), sink=sink, log=log)
    return worker, sink, log


def drain(worker: MapWorker, timeout: float = 10.0) -> None:
    """Waits until everything queued so far has run (a call is queued behind it)."""
    worker.call(lambda: None).result(timeout)


def test_queue_drops_the_oldest_keyframe_and_never_maps_or_calls():
    q = TaskQueue(max_keyframes=2)
    gmap = plane_map()
    q.put_map(gmap)
    future = q.put_call(lambda: 1)
    assert q.put_keyframe(keyframe(1)) is None
    assert q.put_keyframe(keyframe(2)) is None
    dropped = q.put_keyframe(keyframe(3))
    assert dropped is not None and dropped.stamp_ns == 1
    assert q.keyframes == 2 and len(q) == 4
    kinds = [q.take(0).kind for _ in range(4)]
    assert kinds == ["map", "call", "keyframe", "keyframe"]
    assert not future.done()


def test_consecutive_maps_coalesce_but_not_across_keyframes():
    q = TaskQueue(4)
    a, b, c = plane_map(seed=1), plane_map(seed=2), plane_map(seed=3)
    assert not q.put_map(a)
    assert q.put_map(b)  # replaces a
    q.put_keyframe(keyframe(1))
    assert not q.put_map(c)
    tasks = [q.take(0) for _ in range(3)]
    assert [t.kind for t in tasks] == ["map", "keyframe", "map"]
    assert tasks[0].payload is b and tasks[2].payload is c


def test_without_a_map_keyframes_wait_and_other_tasks_pass():
    worker, _, _ = make_worker()
    worker.submit_keyframe(keyframe(1))
    worker.start()
    try:
        assert worker.submit(lambda mapper: mapper).result(5) is None  # ran behind the waiting keyframe
        assert worker.keyframes_waiting == 1 and worker.stats.keyframes_processed == 0
        worker.submit_map(plane_map())
        drain(worker, timeout=30.0)  # the first integration may load the rasterizer's kernels
        assert worker.submit(lambda mapper: mapper.state.stamps_ns.tolist()).result(5) == [1]
        assert worker.keyframes_waiting == 0
    finally:
        worker.stop()


def test_worker_integrates_in_order_like_an_offline_mapper():
    worker, sink, _ = make_worker()
    seen = []
    worker.add_keyframe_listener(lambda kf, mapper: seen.append((kf.stamp_ns, mapper.n_keyframes)))
    worker.start()
    try:
        for stamp in (1, 2):  # before the map: they wait
            worker.submit_keyframe(keyframe(stamp, shift=stamp))
        worker.submit_map(plane_map())
        for stamp in (3, 4):
            worker.submit_keyframe(keyframe(stamp, shift=stamp))
        drain(worker)
        state = worker.submit(lambda mapper: mapper.state).result(5)
    finally:
        worker.stop()
    offline = SemanticMapper(plane_map())
    for stamp in (1, 2, 3, 4):
        offline.integrate(keyframe(stamp, shift=stamp))
    assert_same_evidence(state, offline.state)
    np.testing.assert_array_equal(state.stamps_ns, [1, 2, 3, 4])
    assert seen == [(1, 1), (2, 2), (3, 3), (4, 4)]
    assert worker.stats.keyframes_processed == 4
    assert sink.published  # published once the queue ran empty


def test_duplicate_stamps_are_counted_and_change_nothing():
    worker, _, log = make_worker()
    worker.submit_map(plane_map())
    worker.submit_keyframe(keyframe(5))
    worker.submit_keyframe(keyframe(5, shift=3))
    worker.start()
    try:
        drain(worker)
        weights = worker.submit(lambda m: m.state.total_weight.copy()).result(5)
    finally:
        worker.stop()
    assert worker.stats.rejected["duplicate_stamp"] == 1 and worker.stats.keyframes_processed == 1
    offline = SemanticMapper(plane_map())
    offline.integrate(keyframe(5))
    np.testing.assert_array_equal(weights, offline.state.total_weight)
    assert any("already in the map" in msg for _, msg in log.lines)


def test_full_queue_drops_oldest_and_counts():
    worker, _, _ = make_worker(queue_size=2)
    for stamp in range(1, 6):  # worker not started and no map: all wait
        worker.submit_keyframe(keyframe(stamp))
    assert worker.stats.keyframes_dropped == 3
    worker.submit_map(plane_map())
    worker.start()
    try:
        drain(worker)
        stamps = worker.submit(lambda m: m.state.stamps_ns.tolist()).result(5)
    finally:
        worker.stop()
    assert stamps == [4, 5]


def test_map_update_by_ids_and_unchanged_maps_are_skipped():
    worker, _, log = make_worker()
    old = plane_map()
    worker.submit_map(old)
    worker.submit_keyframe(keyframe(1))
    worker.submit_map(plane_map())  # equal arrays: no update
    worker.start()
    try:
        drain(worker)
        moved = GaussianMap(old.means[::-1] + [0.5, 0, 0], old.scales, old.quats, old.opacities, ids=old.ids[::-1])
        before = worker.submit(lambda m: m.state.total_weight.copy()).result(5)
        worker.submit_map(moved)
        after = worker.submit(lambda m: m.state.total_weight.copy()).result(5)
    finally:
        worker.stop()
    assert worker.stats.maps_unchanged == 1 and worker.stats.map_updates == 1
    np.testing.assert_array_equal(after, before[::-1])  # evidence followed the ids
    assert any(f"{len(old)} new by id, 0 by position; motion by ids" in msg for _, msg in log.lines)


def _without_ids_moved(gmap: GaussianMap, shift: float, seed: int) -> GaussianMap:
    """`gmap` re-ordered, jittered 1 mm and shifted along x, without ids (as most SLAM front-ends send it)."""
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(gmap))
    means = gmap.means[order] + rng.normal(0, 0.001, (len(gmap), 3)) + [shift, 0, 0]
    return GaussianMap(means, gmap.scales[order], gmap.quats[order], gmap.opacities[order])


def test_map_updates_are_prepared_beside_the_worker_with_the_offline_result():
    first = plane_map(400, ids=False)
    second = _without_ids_moved(first, 0.01, seed=1)
    third = _without_ids_moved(second, 0.01, seed=2)
    shrunk = first.subset(np.arange(40))  # refused (map_shrink): the next plan's base is not the map in use
    steps = [first, keyframe(1), second, keyframe(2), shrunk, keyframe(3), third, keyframe(4)]
    worker, _, log = make_worker()
    for step in steps:  # all queued before the worker starts: each map's plan is of the map queued before it
        (worker.submit_map if isinstance(step, GaussianMap) else worker.submit_keyframe)(step)
    worker.start()
    try:
        drain(worker)
        live = worker.submit(lambda m: (m.state, m.gaussians)).result(5)
    finally:
        worker.stop()
    offline = MappingSession(MapperConfig())
    for step in steps:
        if isinstance(step, GaussianMap):
            offline.add_map(step)
        else:
            offline.add_keyframe(step)
            offline.integrate_next()
    assert live[1] is third and offline.mapper.gaussians is third
    assert_same_evidence(live[0], offline.mapper.state)
    assert worker.stats.map_updates == 2 and worker.stats.rejected["map_shrink"] == 1
    # second was prepared against first; third against shrunk, which was refused: computed by the worker
    assert worker.stats.map_updates_prepared == 1 and worker.stats.map_prepare_s > 0
    assert worker.stats.map_update_carried_share > 0.9


def test_a_plan_is_used_only_for_the_maps_it_was_made_of():
    first = plane_map(400, ids=False)
    second = _without_ids_moved(first, 0.01, seed=1)
    session = MappingSession(MapperConfig())
    assert session.plan_map(None, first) is None  # no map in use: nothing to prepare
    session.add_map(first)
    assert session.plan_map(None, first) is None  # the same map again
    plan = session.plan_map(None, second)
    assert plan is not None and plan.applies_to(first, second, MapperConfig().follow())
    assert not plan.applies_to(second, second, MapperConfig().follow())
    assert not plan.applies_to(first, second, FollowConfig(radius=0.05))
    session.add_map(second, plan=session.plan_map(second, first))  # of other maps: computed again
    assert session.stats.map_updates_prepared == 0
    session.add_map(first, plan=session.plan_map(None, first))
    assert session.stats.map_updates == 2 and session.stats.map_updates_prepared == 1


def test_a_plan_takes_a_motion_estimated_elsewhere_only_for_its_maps_and_equals_its_own():
    first = plane_map(400, ids=False)
    second = _without_ids_moved(first, 0.01, seed=1)
    config = MapperConfig().follow()
    own = plan_map_update(first, second, config)
    estimated: Future = Future()
    estimated.set_result(map_motion(first, second, config.motion))  # what the map reader process sends
    given = plan_map_update(first, second, config, given=GivenMotion(first, config.motion, estimated))
    assert given.motion_given and not own.motion_given
    np.testing.assert_array_equal(given.follow.sources, own.follow.sources)
    for name in ("rotation", "translation", "origin", "offsets"):
        np.testing.assert_array_equal(getattr(given.follow.motion, name), getattr(own.follow.motion, name))
    # Taken as given, not estimated again: a motion that is not the maps' own shows.
    elsewhere: Future = Future()
    elsewhere.set_result(MapMotion(translation=np.array([0.0, 0.0, 0.25]), by="registration"))
    moved = plan_map_update(first, second, config, given=GivenMotion(first, config.motion, elsewhere))
    assert moved.motion_given and moved.follow.motion.translation[2] == 0.25
    # Of the same map sent again (another object, the same arrays: a SLAM re-publishing it, a new map reader's
    # latched copy): taken.
    again = GaussianMap(first.means.copy(), first.scales.copy(), first.quats.copy(), first.opacities.copy())
    copied = plan_map_update(first, second, config, given=GivenMotion(again, config.motion, estimated))
    assert copied.motion_given
    np.testing.assert_array_equal(copied.follow.sources, own.follow.sources)
    # Of another old map (one centre moved a micrometre too), another configuration, none was estimated (its Future
    # holds None), or none came in time (a reader that hangs): estimated here.
    means = first.means.copy()
    means[7, 0] += 1e-6
    nudged = GaussianMap(means, first.scales, first.quats, first.opacities)
    nothing: Future = Future()
    nothing.set_result(None)
    other = replace(config.motion, sample=1000)
    for hint in (
        GivenMotion(second, config.motion, estimated),
        GivenMotion(nudged, config.motion, estimated),
        GivenMotion(first, other, estimated),
        GivenMotion(first, config.motion, nothing),
        GivenMotion(first, config.motion, Future(), wait_s=0.05),
    ):
        plan = plan_map_update(first, second, config, given=hint)
        assert not plan.motion_given
        np.testing.assert_array_equal(plan.follow.sources, own.follow.sources)


def test_the_worker_takes_a_given_motion_only_for_the_map_its_update_starts_from():
    """As the node with its map reader: each map comes with the motion from the map before it; a map refused by the
    worker (map_shrink) leaves the next map's given motion unused, and the result is the offline one either way."""
    first = plane_map(400, ids=False)
    second = _without_ids_moved(first, 0.01, seed=1)
    shrunk = first.subset(np.arange(40))  # refused: the map in use stays `second`
    third = _without_ids_moved(second, 0.01, seed=2)
    fourth = _without_ids_moved(third, 0.01, seed=3)
    maps = [first, second, shrunk, third, fourth]
    config = MapperConfig().follow().motion
    worker, _, _ = make_worker()
    worker.start()
    try:
        for i, (before, gmap) in enumerate(zip([None, *maps], maps, strict=False)):
            given = None
            if before is not None:
                motion: Future = Future()
                motion.set_result(map_motion(before, gmap, config))
                given = GivenMotion(before, config, motion)
            worker.submit_map(gmap, given=given)
            worker.submit_keyframe(keyframe(i + 1))
            drain(worker)
        live = worker.submit(lambda m: (m.state, m.gaussians)).result(5)
    finally:
        worker.stop()
    offline = MappingSession(MapperConfig())
    for i, gmap in enumerate(maps):
        offline.add_map(gmap)
        offline.add_keyframe(keyframe(i + 1))
        offline.integrate_next()
    assert live[1] is fourth and offline.mapper.gaussians is fourth
    assert_same_evidence(live[0], offline.mapper.state)
    assert worker.stats.map_updates == 3 and worker.stats.rejected["map_shrink"] == 1
    # second's and fourth's motions were taken; third's was of `shrunk`, not of the map in use (`second`)
    assert worker.stats.map_motions_given == 2


def _two_keyframes_then_a_moved_map() -> tuple[MappingSession, GaussianMap, SemanticResult]:
    """A session of two keyframes on a map without ids whose newest result has its geometry; the map moved 1 cm."""
    first = plane_map(400, ids=False)
    session = MappingSession(MapperConfig())
    session.add_map(first)
    for stamp in (1, 2):
        session.add_keyframe(keyframe(stamp, shift=stamp))
        session.integrate_next()
    before = session.mapper.result()
    assert len(before.objects(first).objects) == 2
    return session, _without_ids_moved(first, 0.01, seed=1), before


def test_a_map_update_carries_the_labels_and_their_geometry_equals_one_from_scratch():
    session, second, before = _two_keyframes_then_a_moved_map()
    plan = session.plan_map(None, second)
    session.add_map(second, plan=plan)
    mapper = session.mapper
    after = mapper.result()
    # The transfer's prediction is the labelling the mapper computes from the carried evidence: the update's
    # seed (SemanticResult.carried) leaves no object to compute again.
    carried = before.carried(plan.follow.sources, second)
    np.testing.assert_array_equal(after.object_ids, carried.object_ids)
    session.add_keyframe(keyframe(3, shift=-4))
    session.integrate_next()
    for result in (after, mapper.result()):
        scratch = object_geometry(second, result.object_ids, result.confidence)
        assert_same_geometry(result.objects(second), scratch)


def _updated_with_seed(seed: Future) -> tuple[SemanticMapper, GaussianMap, SemanticResult]:
    """A mapper of two keyframes whose map was updated with `seed` as the carried labels' Future; and the new map and
    the labels the seed should hold."""
    session, second, before = _two_keyframes_then_a_moved_map()
    sources = session.plan_map(None, second).follow.sources
    session.mapper.take_map(second, sources, seed)
    return session.mapper, second, before.carried(sources, second)


def _labels_while_the_seed_is_computed(
    mapper: SemanticMapper, seed: Future, settle: Callable[[], None]
) -> SemanticResult:
    """`mapper.result()` while `seed` is pending (a result() that waited for it would fail here, not hang: the
    seed is settled by `settle` 0.2 s after the check either way)."""
    with ThreadPoolExecutor(1) as pool:
        try:
            after = pool.submit(mapper.result).result(timeout=30)
            assert not seed.done()
        finally:
            threading.Timer(0.2, settle).start()
    return after


def test_the_labels_after_a_map_update_do_not_wait_for_the_geometry_it_carries(monkeypatch):
    import monovoc_ros.core.mapping as mapping

    starts: list = []  # the geometry each object_geometry call started from

    def spied(*args, previous=None, **kwargs):
        starts.append(previous)
        return object_geometry(*args, previous=previous, **kwargs)

    monkeypatch.setattr(mapping, "object_geometry", spied)
    seed = Future()
    mapper, second, carried = _updated_with_seed(seed)
    # The cloud is made of these labels: they are there while the seed is still being computed.
    after = _labels_while_the_seed_is_computed(mapper, seed, lambda: seed.set_result(carried))
    np.testing.assert_array_equal(after.object_ids, carried.object_ids)
    assert_same_geometry(after.objects(second), object_geometry(second, after.object_ids, after.confidence))
    assert starts[-1] is carried.objects(second)  # the geometry waited for the seed and started from it


def test_a_seed_that_failed_is_raised_by_the_geometry_once_then_it_is_computed_from_scratch():
    seed = Future()
    mapper, second, _ = _updated_with_seed(seed)
    failure = RuntimeError("the carried geometry failed")
    after = _labels_while_the_seed_is_computed(mapper, seed, lambda: seed.set_exception(failure))
    wait_until(seed.done, 10.0, "the seed to fail")
    with pytest.raises(RuntimeError, match="carried geometry failed"):
        after.objects(second)
    assert_same_geometry(after.objects(second), object_geometry(second, after.object_ids, after.confidence))


def test_same_geometry():
    a = plane_map()
    assert same_geometry(a, plane_map())
    assert not same_geometry(a, plane_map(seed=1))
    assert not same_geometry(a, plane_map(ids=False))
    assert not same_geometry(a, a.subset(np.arange(10)))


def test_listener_errors_are_logged_not_fatal():
    worker, _, log = make_worker()
    worker.add_keyframe_listener(lambda kf, m: 1 / 0)
    results = []
    worker.add_result_listener(lambda mapper, result: results.append(result.object_ids.copy()))
    worker.submit_map(plane_map())
    worker.submit_keyframe(keyframe(1))
    worker.submit_keyframe(keyframe(2))
    worker.start()
    try:
        drain(worker)
        worker.call(worker.publish_now).result(5)
    finally:
        worker.stop()
    assert worker.stats.keyframes_processed == 2 and worker.stats.worker_errors == 2
    assert results and len(results[-1]) == 200
    assert any("ZeroDivisionError" in msg for kind, msg in log.lines if kind == "error")


def test_publish_rate_limits_and_final_state_is_published():
    worker, sink, _ = make_worker(publish_period_s=0.3)
    worker.submit_map(plane_map())
    worker.start()
    try:
        for stamp in range(1, 9):
            worker.submit_keyframe(keyframe(stamp))
            time.sleep(0.02)
        drain(worker)
        deadline = time.monotonic() + 5
        while (not sink.published or sink.published[-1][0] != 8) and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        worker.stop()
    assert sink.published[-1][0] == 8  # the newest state always goes out, one period later at most
    assert len(sink.published) <= 4  # start + at most ~1 per 0.3 s over ~0.2 s of keyframes + the last


def test_publishing_when_idle_still_publishes_a_worker_that_never_is():
    worker, sink, _ = make_worker(publish_period_s=0.0, queue_size=16)
    worker.submit_map(plane_map())
    for stamp in range(1, 11):  # queued before the start: the queue is never empty until the last one
        worker.submit_keyframe(keyframe(stamp))
        worker.call(lambda: time.sleep(0.25))
    start = time.monotonic()
    worker.start()
    try:
        drain(worker)
    finally:
        worker.stop()
    assert time.monotonic() - start >= 10 * 0.25 and sink.published[-1][0] == 10
    during = [n for n, _ in sink.published if n is not None and 0 < n < 10]  # before the queue ran empty
    assert during, sink.published  # every BUSY_PUBLISH_PERIOD_S (1 s) of the 2.5 s
    assert len(during) <= 4


def test_periodic_and_final_snapshots(tmp_path):
    worker, _, _ = make_worker(map_directory=str(tmp_path), save_period_s=0.2)
    worker.submit_map(plane_map())
    worker.submit_keyframe(keyframe(1))
    worker.start()
    try:
        deadline = time.monotonic() + 5
        while current_snapshot(tmp_path) is None and time.monotonic() < deadline:
            time.sleep(0.02)
        assert load_snapshot(tmp_path).n_keyframes == 1
        worker.submit_keyframe(keyframe(2))
        drain(worker)
    finally:
        info = worker.stop()  # the final snapshot holds keyframe 2 (unless a periodic one got there first)
    assert load_snapshot(tmp_path).state.stamps_ns.tolist() == [1, 2]
    assert info is None or info.keyframes == 2
    assert worker.stats.snapshots_saved >= 2


def test_a_periodic_snapshot_does_not_wait_for_its_listeners_work_and_save_map_does(tmp_path):
    """objects.db's images are encoded and written beside the worker: its save listener returns that work's
    Future. A periodic snapshot goes on without it; save_map returns only once it is done."""
    pool, gate, calls = ThreadPoolExecutor(max_workers=1), threading.Event(), []
    worker, _, _ = make_worker(map_directory=str(tmp_path / "map"), save_period_s=0.01, queue_size=64)
    worker.add_save_listener(lambda *_: calls.append(1) or pool.submit(gate.wait, 30))
    worker.submit_map(plane_map())
    worker.submit_keyframe(keyframe(1))
    worker.start()
    try:
        wait_until(lambda: worker.stats.snapshots_saved >= 1 and calls, 10.0, "a periodic snapshot")
        worker.submit_keyframe(keyframe(2))
        drain(worker)  # its listener's work still waits for the gate
        assert worker.stats.keyframes_processed == 2 and not gate.is_set()
        n = len(calls)
        saved = worker.call(lambda: worker.save(str(tmp_path / "explicit")), "save_map")
        wait_until(lambda: len(calls) > n, 10.0, "save_map's listener")
        assert not saved.done()  # waiting for the listener's work
        gate.set()
        assert saved.result(10).keyframes == 2
    finally:
        gate.set()
        worker.stop(final_snapshot=False)
        pool.shutdown()


def test_periodic_snapshots_are_written_beside_the_worker_as_captured(tmp_path):
    gmap = plane_map(60_000)  # writes long enough for keyframes to go on meanwhile
    worker, _, log = make_worker(map_directory=str(tmp_path), save_period_s=0.01, queue_size=64)
    worker.submit_map(gmap)
    frames = [keyframe(stamp, shift=stamp % 7 - 3) for stamp in range(1, 41)]
    worker.start()
    try:
        for kf in frames:
            worker.submit_keyframe(kf)
            time.sleep(0.005)
        drain(worker)
    finally:
        worker.stop(final_snapshot=False)
    saved = load_snapshot(tmp_path)
    assert worker.stats.snapshots_saved >= 2 and worker.stats.snapshot_errors == 0
    assert any("written in" in msg for _, msg in log.lines)
    offline = SemanticMapper(gmap)  # the state of exactly the keyframes it holds
    for kf in frames[: saved.n_keyframes]:
        offline.integrate(kf)
    assert_same_evidence(saved.state, offline.state)


def test_save_listeners_of_a_periodic_snapshot_see_the_map_it_was_captured_from(tmp_path):
    first = plane_map(60_000, ids=False)
    seen = []

    def listener(directory, info, mapper):
        meta = json.loads((info.path / "meta.json").read_text())
        snapshot = (meta["map_version"], meta["gaussians"])
        seen.append(mapper is not None and snapshot == (mapper.map_version, len(mapper.gaussians)))

    worker, _, _ = make_worker(map_directory=str(tmp_path), save_period_s=0.01, queue_size=64)
    worker.add_save_listener(listener)
    worker.submit_map(first)
    worker.start()
    try:
        for stamp in range(1, 31):
            worker.submit_keyframe(keyframe(stamp, shift=stamp % 5 - 2))
            if stamp == 10:  # a map update and a reset while snapshots are written
                worker.submit_map(_without_ids_moved(first, 0.01, seed=3).subset(np.arange(50_000)))
            if stamp == 20:
                worker.call(lambda: worker.reset(True))
            time.sleep(0.005)
        drain(worker)
    finally:
        worker.stop(final_snapshot=False)
    assert worker.stats.map_updates == 1 and len(seen) >= 2 and all(seen), seen


def test_a_failing_periodic_snapshot_is_counted_and_its_evidence_saved_a_period_later(tmp_path):
    target = tmp_path / "maps"
    target.write_text("")  # a file where the directory should be: the first writes fail
    worker, _, log = make_worker(map_directory=str(target), save_period_s=0.05)
    worker.submit_map(plane_map())
    for stamp in range(1, 4):
        worker.submit_keyframe(keyframe(stamp))
    worker.start()
    try:
        drain(worker)
        wait_until(lambda: worker.stats.snapshot_errors >= 1, 5.0, "a failed snapshot")
        target.unlink()  # no keyframe comes after: only the failed snapshot's evidence is unsaved
        wait_until(lambda: worker.stats.snapshots_saved >= 1, 5.0, "a snapshot after the failure")
    finally:
        worker.stop(final_snapshot=False)
    assert load_snapshot(target).n_keyframes == 3 and worker.stats.worker_errors == 0
    assert any(kind == "error" and "periodic snapshot" in msg for kind, msg in log.lines)


def test_a_failing_save_listener_is_counted_and_the_worker_goes_on(tmp_path):
    worker, _, log = make_worker(map_directory=str(tmp_path), save_period_s=0.01)
    worker.add_save_listener(lambda directory, info, mapper: 1 / 0)
    worker.submit_map(plane_map())
    worker.start()
    try:
        for stamp in range(1, 4):
            worker.submit_keyframe(keyframe(stamp))
            drain(worker)
            time.sleep(0.03)
        assert worker.submit(lambda m: m.n_keyframes).result(5) == 3
    finally:
        worker.stop()  # no exception from the listener here either
    assert worker.stats.worker_errors >= 1 and worker.stats.snapshots_saved >= 1
    assert load_snapshot(tmp_path).n_keyframes == 3
    assert any("ZeroDivisionError" in msg for kind, msg in log.lines if kind == "error")


def test_a_map_after_stop_is_refused_quietly_and_a_republished_map_keeps_plans_in_use():
    first = plane_map(400, ids=False)
    again = GaussianMap(first.means.copy(), first.scales, first.quats, first.opacities)  # the same map re-sent
    second = _without_ids_moved(first, 0.01, seed=1)
    worker, _, _ = make_worker()
    for step in (first, keyframe(1), again, keyframe(2), second, keyframe(3)):
        (worker.submit_map if isinstance(step, GaussianMap) else worker.submit_keyframe)(step)
    worker.start()
    try:
        drain(worker)
    finally:
        worker.stop(final_snapshot=False)
    assert worker.stats.maps_unchanged == 1 and worker.stats.map_updates == 1
    assert worker.stats.map_updates_prepared == 1  # planned against the map in use, not the re-sent copy
    worker.submit_map(second)  # a callback still decoding at shutdown: no exception


def test_calls_run_in_order_and_fail_after_stop(tmp_path):
    worker, _, _ = make_worker()
    worker.submit_map(plane_map())
    worker.submit_keyframe(keyframe(1))
    saved = worker.call(lambda: worker.save(str(tmp_path / "a")))
    worker.submit_keyframe(keyframe(2))
    worker.start()
    try:
        assert saved.result(5).keyframes == 1  # saved before keyframe 2, as queued
        worker.call(lambda: worker.reset(keep_gaussians=True)).result(5)
        assert worker.submit(lambda m: (m.n_keyframes, len(m.gaussians))).result(5) == (0, 200)
        worker.call(lambda: worker.load(str(tmp_path / "a"))).result(5)
        assert worker.submit(lambda m: m.n_keyframes).result(5) == 1
        worker.call(lambda: worker.reset(keep_gaussians=False)).result(5)
        assert worker.submit(lambda m: m).result(5) is None
        with pytest.raises(ValueError, match="no map"):
            worker.call(lambda: worker.save(str(tmp_path / "b"))).result(5)
    finally:
        worker.stop()
    with pytest.raises(WorkerStopped):
        worker.call(lambda: None).result(1)


def test_the_worker_is_busy_while_on_a_task_so_background_work_waits():
    """`busy` (what the object index defers its embedding on): keyframes queued, or the worker on a task."""
    worker, _, _ = make_worker()
    worker.submit_map(plane_map())
    started, release = threading.Event(), threading.Event()
    worker.start()
    try:
        wait_until(lambda: not worker.busy(), 5.0, "the map taken, the worker idle")
        done = worker.call(lambda: (started.set(), release.wait(5)))
        assert started.wait(5) and worker.busy() and worker.keyframes_waiting == 0  # on a task, nothing queued
        release.set()
        done.result(5)
        wait_until(lambda: not worker.busy(), 5.0, "the worker idle again")
    finally:
        worker.stop()


def test_service_waits_do_not_block_other_threads():
    # A call waiting behind a slow task; another thread meanwhile can still queue and count keyframes.
    worker, _, _ = make_worker()
    release = threading.Event()
    worker.submit_map(plane_map())
    worker.call(lambda: release.wait(5))
    worker.start()
    try:
        behind = worker.call(lambda: "done")
        worker.submit_keyframe(keyframe(1))
        assert worker.stats.queue_length == 1 and not behind.done()
        release.set()
        assert behind.result(5) == "done"
    finally:
        worker.stop()


def test_rejection_log_throttles_per_reason():
    lines, now = [], [0.0]
    log = RejectionLog(lines.append, interval_s=5.0, clock=lambda: now[0])
    assert log("bad_pose", "a") and not log("bad_pose", "b") and log("bad_mask", "c")
    now[0] = 6.0
    assert log("bad_pose", "d")
    assert lines[-1] == "rejected (bad_pose): d (+1 more since the last report)"
    # A detail quoting a hostile input (a 1 MB image encoding) is a line, not a dump.
    assert log("bad_image", "Image: unsupported encoding " + "e" * 1_000_000)
    assert lines[-1].endswith("... (999028 characters more)") and len(lines[-1]) < 1100


def test_stats_snapshot_mean():
    stats = MapperStats()
    stats.add(keyframes_processed=2, ms_per_keyframe_total=30.0)
    stats.reject("bad_pose")
    snap = stats.snapshot()
    assert snap["ms_per_keyframe_mean"] == 15.0 and snap["rejected"] == {"bad_pose": 1}


def rgb_keyframe(stamp: int) -> Keyframe:
    from dataclasses import replace

    rgb = np.random.default_rng(stamp).integers(0, 256, (24, 32, 3), dtype=np.uint8)
    return replace(keyframe(stamp, shift=stamp % 5), rgb=rgb)


def test_stop_drains_the_queue_within_its_bound(tmp_path):
    worker, _, log = make_worker(map_directory=str(tmp_path), queue_size=100)
    worker.submit_map(plane_map())
    for stamp in range(1, 21):
        worker.submit_keyframe(rgb_keyframe(stamp))
    info = worker.stop(within_s=60.0)  # never started: stop integrates all of them on this thread
    assert info is not None and info.keyframes == 20 and load_snapshot(tmp_path).n_keyframes == 20
    assert load_deferred(tmp_path) == []
    assert any("integrated 20 queued keyframes, deferred 0" in m for _, m in log.lines)


def test_keyframes_stop_has_no_time_for_are_deferred_to_the_snapshot_and_resumed(tmp_path):
    worker, _, log = make_worker(map_directory=str(tmp_path), queue_size=100)
    worker.submit_map(plane_map())
    sent = [rgb_keyframe(stamp) for stamp in range(1, 13)]
    for kf in sent:
        worker.submit_keyframe(kf)
    info = worker.stop(within_s=0.0)  # no time: the map goes in, every keyframe is deferred
    assert info is not None and info.keyframes == 0
    deferred = load_deferred(tmp_path)
    assert [k.stamp_ns for k in deferred] == [k.stamp_ns for k in sent]
    for got, kf in zip(deferred, sent, strict=True):  # whole keyframes: RGB included, bit-exact
        assert np.array_equal(got.mask, kf.mask) and np.array_equal(got.rgb, kf.rgb)
        assert np.array_equal(got.cam_to_world, kf.cam_to_world) and got.intrinsics == kf.intrinsics
    assert any("final snapshot" in m and "12 deferred to resume" in m for _, m in log.lines)

    resumed, _, _ = make_worker(map_directory=str(tmp_path), queue_size=100)
    resumed.session.load(str(tmp_path))
    for kf in load_deferred(tmp_path):
        resumed.submit_keyframe(kf)
    resumed.start()
    drain(resumed)
    resumed.stop()
    reference = SemanticMapper(plane_map())
    for kf in sent:
        reference.integrate(kf)
    assert load_snapshot(tmp_path).n_keyframes == 12 and load_deferred(tmp_path) == []
    assert_same_evidence(load_snapshot(tmp_path).state, reference.state)


def test_stop_leaves_the_final_snapshot_the_time_the_last_one_took(tmp_path):
    """Issue 24's flake: a fixed drain did not count the snapshot after it. A save listener (objects.db) that
    takes 0.4 s is timed on the save_map queued first; stop then integrates only while a snapshot as long
    still fits in its bound."""
    SemanticMapper(plane_map()).integrate(rgb_keyframe(1))  # the rasterizer's kernels loaded before timing
    worker, _, _ = make_worker(map_directory=str(tmp_path), queue_size=100)
    worker.add_save_listener(lambda *_: time.sleep(0.4))
    worker.add_keyframe_listener(lambda *_: time.sleep(0.05))
    worker.submit_map(plane_map())
    worker.submit_keyframe(rgb_keyframe(1))
    saved = worker.call(lambda: worker.save(str(tmp_path)), "save_map")
    estimate = worker.call(worker.save_estimate_s)
    for stamp in range(2, 41):
        worker.submit_keyframe(rgb_keyframe(stamp))
    start = time.monotonic()
    info = worker.stop(within_s=1.5)  # never started: everything runs here, in order
    elapsed = time.monotonic() - start
    deferred = load_deferred(tmp_path)
    assert saved.result(0).keyframes == 1 and 0.6 <= estimate.result(0) < 1.5  # 1.5 x (0.4 s + the files)
    assert info is not None and info.keyframes + len(deferred) == 40
    assert info.keyframes > 1 and deferred, (info.keyframes, len(deferred))
    assert elapsed < 1.5 + 0.25, elapsed  # a fixed 1.5 s drain and then the 0.4 s snapshot took 1.9 s


def test_stop_is_bounded_when_the_worker_is_busy(tmp_path):
    worker, _, log = make_worker(map_directory=str(tmp_path))
    worker.submit_map(plane_map())
    running, release = threading.Event(), threading.Event()
    worker.submit(lambda m: running.set() or release.wait(30))  # a task far longer than the bound
    worker.start()
    assert running.wait(10)
    start = time.monotonic()
    assert worker.stop(within_s=0.5) is None
    assert time.monotonic() - start < 0.5 + 1.0 + 0.5  # the bound plus the grace for the task in progress
    assert any("still busy" in m for _, m in log.lines)
    release.set()


def test_stop_applies_queued_calls_in_order_before_its_bound_and_refuses_them_after(tmp_path):
    worker, _, _ = make_worker(map_directory=str(tmp_path / "map"), queue_size=100)
    worker.submit_map(plane_map())
    worker.submit_keyframe(rgb_keyframe(1))
    saved = worker.call(lambda: worker.save(str(tmp_path / "between")), "save_map")
    worker.submit_keyframe(rgb_keyframe(2))
    assert worker.stop(within_s=60.0).keyframes == 2
    assert saved.result(0).keyframes == 1  # run in its place: after keyframe 1, before keyframe 2

    late, _, _ = make_worker(map_directory=str(tmp_path / "late"), queue_size=100)
    late.submit_map(plane_map())
    refused = late.call(lambda: late.save(str(tmp_path / "never")), "save_map")
    late.submit_keyframe(rgb_keyframe(1))
    assert late.stop(within_s=0.0).keyframes == 0 and [k.stamp_ns for k in load_deferred(tmp_path / "late")] == [1]
    with pytest.raises(WorkerStopped):
        refused.result(0)


class GeometrySink(Sink):
    """Reports objects, as the node's outputs do (the geometry after the cloud)."""

    def publish(self, mapper, result):
        super().publish(mapper, result)
        return 0 if result is None else len(result.objects(mapper.gaussians).objects)


def test_a_reintegration_steps_once_per_three_waiting_keyframes_and_finishes_when_none_wait():
    """Live keyframes first: while they wait, a rebuild takes one step per KEYFRAMES_PER_REINTEGRATION_STEP of
    them (it took one after each, half of the worker at 2M Gaussians); with nothing waiting it catches up."""
    worker, _, _ = make_worker(queue_size=64)
    seen: list[tuple[int, int]] = []  # (live keyframe, rebuild steps so far) right after its integration
    worker.add_keyframe_listener(lambda kf, _: seen.append((kf.stamp_ns, worker.stats.reintegration_steps)))
    worker.start()
    try:
        worker.submit_map(plane_map())
        for stamp in range(1, 10):
            worker.submit_keyframe(keyframe(stamp))
        drain(worker)
        release = threading.Event()
        worker.call(lambda: release.wait(10.0))  # everything below queues behind it
        shifted = np.eye(4)
        shifted[0, 3] = 0.01
        worker.submit_keyframe_poses(KeyframePoses(tuple((stamp, shifted) for stamp in range(1, 10))))
        for stamp in range(10, 22):
            worker.submit_keyframe(keyframe(stamp))
        release.set()
        drain(worker)
        wait_until(lambda: worker.stats.reintegrations == 1, 10.0, "the re-integration to finish", process=None)
    finally:
        worker.stop(final_snapshot=False)
    assert KEYFRAMES_PER_REINTEGRATION_STEP == 3
    # The corrected poses start the rebuild and it steps at once; then once per three live keyframes.
    assert [steps for stamp, steps in seen if stamp >= 10] == [1, 1, 1, 2, 2, 2, 3, 3, 3, 4, 4, 4]
    assert worker.stats.reintegration_steps == 9 + 12  # every logged keyframe, the live ones too, once


class HeldPlans(MapWorker):
    """A worker whose map update plans are held until `release` is set, as a slow plan at robot scale is."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.release = threading.Event()

    def _prepare_map(self, base, gaussians, given):
        prepared = super()._prepare_map(base, gaussians, given)
        if prepared is None or base is None:  # the first map has nothing to prepare
            return prepared
        held: Future = Future()

        def hold() -> None:
            self.release.wait(10.0)
            held.set_result(prepared.plan.result())

        threading.Thread(target=hold, daemon=True).start()
        return Preparation(held, prepared.motion)


def moved_map(first: GaussianMap) -> tuple[GaussianMap, np.ndarray]:
    """The SLAM moved its map 5 cm (a loop closure): the moved map, and the motion (4, 4) that poses the next
    keyframes in it."""
    shift = np.eye(4)
    shift[2, 3] = 0.05
    return GaussianMap(first.means + shift[:3, 3], first.scales, first.quats, first.opacities, ids=first.ids), shift


@pytest.mark.parametrize("ahead", [False, True])
def test_keyframes_after_a_map_update_go_ahead_into_the_map_in_use_within_the_window(ahead):
    """map_update_ahead_s: keyframes stamped within it after a map go into the map in use while its plan is made,
    their poses taken back by its motion, and the update then moves their logged poses to where they were sent;
    the first keyframe stamped after the window applies the update first (waiting for its plan). With 0 they all
    wait for the update (as offline mapping with ahead_s 0 integrates them)."""
    settings = WorkerSettings(queue_size=16, publish_period_s=0.0, save_period_s=0.0,
                              map_update_ahead_s=2.0 if ahead else 0.0)  # fmt: skip
    worker = HeldPlans(MapperConfig(), settings, sink=Sink(), log=RecordingLog())
    first = replace(plane_map(), stamp_ns=1)
    second, shift = moved_map(first)
    second = replace(second, stamp_ns=4)
    late = 4 + 2 * 10**9  # the window's end
    seen: list[tuple[int, bool, np.ndarray]] = []  # (stamp, integrated into the first map, pose)
    worker.add_keyframe_listener(lambda kf, m: seen.append((kf.stamp_ns, m.gaussians is first, kf.cam_to_world)))
    worker.start()
    try:
        worker.submit_map(first)
        for stamp in range(1, 4):
            worker.submit_keyframe(keyframe(stamp))
        drain(worker)
        worker.submit_map(second)
        sent = {}
        for stamp in (4, 5, 6, late):
            kf = keyframe(stamp)
            sent[stamp] = shift @ kf.cam_to_world
            worker.submit_keyframe(replace(kf, cam_to_world=sent[stamp]))
        if ahead:
            wait_until(lambda: len(seen) == 6, 10.0, "the keyframes after the map", process=None)
            time.sleep(0.1)
            assert len(seen) == 6  # the one stamped after the window waits for the update, and it for its plan
            assert worker.session.mapper.gaussians is first
        worker.release.set()
        drain(worker)
        logged = {e.stamp_ns: e.cam_to_world for e in worker.session.mapper.keyframe_log.entries}
    finally:
        worker.stop(final_snapshot=False)
    assert worker.session.mapper.gaussians is second
    assert [stamp for stamp, _, _ in seen] == [1, 2, 3, 4, 5, 6, late]
    assert [into_first for stamp, into_first, _ in seen if stamp >= 4] == [ahead] * 3 + [False]
    for stamp, _, pose in seen[3:]:
        # Ahead: integrated 5 cm back, into the first map; the update moved the logged pose to where it was sent.
        back = 0.05 if ahead and stamp < late else 0.0
        np.testing.assert_allclose(pose[2, 3], sent[stamp][2, 3] - back, atol=1e-6)
        np.testing.assert_allclose(logged[stamp], sent[stamp], atol=1e-6)
    assert worker.stats.map_updates_ahead == int(ahead) and worker.stats.map_updates == 1


def test_keyframes_go_ahead_of_a_map_update_live_as_they_do_offline():
    """The rule is the input's (stamps and order), not the plan's speed: a worker whose plans are slow and offline
    mapping of the same events end with the same evidence and logged poses."""
    first = replace(plane_map(), stamp_ns=10**9)
    second, shift = moved_map(first)
    second = replace(second, stamp_ns=2 * 10**9)
    events: list = [first]
    for k in range(16):  # every 0.25 s from 1 s: the second map at 2 s, its window to 4 s
        stamp = 10**9 + k * 250_000_000
        if stamp == second.stamp_ns:
            events.append(second)
        kf = keyframe(stamp, shift=k % 5)
        events.append(replace(kf, cam_to_world=shift) if stamp >= second.stamp_ns else kf)
    offline, stats = map_events(events, ahead_s=2.0)
    assert stats.map_updates == 1 and stats.map_updates_ahead == 1
    settings = WorkerSettings(queue_size=32, publish_period_s=0.0, save_period_s=0.0, map_update_ahead_s=2.0)
    worker = HeldPlans(MapperConfig(), settings, sink=Sink(), log=RecordingLog())
    worker.start()
    try:
        for event in events:
            (worker.submit_map if isinstance(event, GaussianMap) else worker.submit_keyframe)(event)
        wait_until(lambda: worker.stats.keyframes_processed >= 12, 10.0, "the keyframes ahead", process=None)
        worker.release.set()
        drain(worker)
    finally:
        worker.stop(final_snapshot=False)
    live = worker.session.mapper
    assert live.gaussians is second and worker.stats.map_updates_ahead == 1
    assert_same_evidence(live.state, offline.state)
    a = {e.stamp_ns: e.cam_to_world for e in live.keyframe_log.entries}
    b = {e.stamp_ns: e.cam_to_world for e in offline.keyframe_log.entries}
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


def test_ahead_a_keyframe_stamped_before_the_map_update_is_not_taken_back():
    """With stamps: a keyframe stamped before the map update that it comes after is posed in the map in use (core.
    follow.map_frames): it goes ahead as sent, and the update moves its logged pose with the map; the keyframes
    stamped after the map are taken back and their logged poses end where they were sent."""
    settings = WorkerSettings(queue_size=16, publish_period_s=0.0, save_period_s=0.0, map_update_ahead_s=2.0)
    worker = HeldPlans(MapperConfig(), settings, sink=Sink(), log=RecordingLog())
    first = replace(plane_map(), stamp_ns=10)
    second, shift = moved_map(first)
    second = replace(second, stamp_ns=20)
    seen: dict[int, np.ndarray] = {}
    worker.add_keyframe_listener(lambda kf, m: seen.setdefault(kf.stamp_ns, kf.cam_to_world))
    worker.start()
    try:
        worker.submit_map(first)
        worker.submit_keyframe(keyframe(11))
        drain(worker)
        worker.submit_map(second)
        worker.submit_keyframe(keyframe(15))  # stamped before the second map: posed in the first
        for stamp in (21, 22):
            worker.submit_keyframe(replace(keyframe(stamp), cam_to_world=shift))
        wait_until(lambda: len(seen) == 4, 10.0, "the keyframes after the map", process=None)
        assert worker.session.mapper.gaussians is first
        worker.release.set()
        drain(worker)
        logged = {e.stamp_ns: e.cam_to_world for e in worker.session.mapper.keyframe_log.entries}
    finally:
        worker.stop(final_snapshot=False)
    assert worker.session.mapper.gaussians is second and worker.stats.map_updates_ahead == 1
    for stamp in (15, 21, 22):
        np.testing.assert_allclose(seen[stamp], np.eye(4), atol=1e-6)  # integrated into the first map
        np.testing.assert_allclose(logged[stamp], shift, atol=1e-6)  # in the second map's frame
    assert worker.stats.keyframes_before_their_map == 0 and worker.stats.keyframes_moved_into_map == 0


class MapSink:
    """Records, per publication, the map published and how many keyframes it holds."""

    def __init__(self):
        self.published: list[tuple[GaussianMap, int]] = []

    def publish(self, mapper, result):
        if mapper is not None:
            self.published.append((mapper.gaussians, mapper.n_keyframes))
        return 0


@pytest.mark.parametrize("ahead", [False, True])
def test_what_changed_is_published_while_the_worker_waits_for_a_map_updates_plan(ahead):
    """A keyframe integrated right before a map whose plan is not ready gets its cloud while the worker waits for
    that plan (or, ahead, for its motion), not after the update; ahead, the update is applied once the keyframes
    integrated ahead of it are published."""
    settings = WorkerSettings(queue_size=16, publish_period_s=0.0, save_period_s=0.0,
                              map_update_ahead_s=2.0 if ahead else 0.0)  # fmt: skip
    sink = MapSink()
    worker = HeldPlans(MapperConfig(), settings, sink=sink, log=RecordingLog())
    first = replace(plane_map(), stamp_ns=1)
    second, shift = moved_map(first)
    second = replace(second, stamp_ns=3)
    worker.start()
    try:
        worker.submit_map(first)
        worker.submit_keyframe(keyframe(1))
        drain(worker)
        gate = threading.Event()
        worker.call(lambda: gate.wait(10.0))  # the keyframe and the map queued behind it: no idle moment between
        worker.submit_keyframe(keyframe(2))
        worker.submit_map(second)
        gate.set()
        wait_until(lambda: (first, 2) in sink.published, 10.0, "keyframe 2 published before the update", process=None)
        assert worker.session.mapper.gaussians is first and worker.stats.map_updates == 0
        if ahead:
            worker.submit_keyframe(replace(keyframe(3), cam_to_world=shift))
            wait_until(lambda: (first, 3) in sink.published, 10.0, "the keyframe integrated ahead", process=None)
        worker.release.set()
        wait_until(lambda: worker.stats.map_updates == 1, 10.0, "the update", process=None)
        drain(worker)
    finally:
        worker.stop(final_snapshot=False)
    assert sink.published[-1] == (second, 3 if ahead else 2)


def test_a_map_update_keyframes_go_ahead_of_is_due_before_any_other_task_a_later_keyframe_or_a_long_idle():
    plan = Future()
    gaussians = replace(plane_map(), stamp_ns=10)
    pending = _Ahead(_Task("map", gaussians, plan=plan, motion=Future()), MapAhead(gaussians, None, 30))
    in_window, later = (_Task("keyframe", keyframe(s)) for s in (29, 30))
    call = _Task("call", lambda: None)
    assert not pending.due(in_window, 0.0, 2.0) and pending.due(later, 0.0, 2.0)  # by stamp
    assert pending.due(call, 0.0, 2.0)  # only keyframes go ahead of it
    # Stamped within the window's end but too far from the map's stamp to order against it (another clock).
    unordered = replace(pending.ahead, until_ns=30 * 10**9)
    assert replace(pending, ahead=unordered).due(_Task("keyframe", keyframe(20 * 10**9)), 0.0, 2.0)
    assert not pending.due(None, 5.0, 2.0)  # idle, but its plan is not ready
    plan.set_result(None)
    assert not pending.due(None, 1.0, 2.0) and pending.due(None, 2.0, 2.0)  # ready, and idle for the window


def test_a_stop_applies_the_map_update_keyframes_went_ahead_of_before_the_final_snapshot(tmp_path):
    settings = WorkerSettings(queue_size=16, publish_period_s=0.0, save_period_s=0.0, map_update_ahead_s=2.0,
                              map_directory=str(tmp_path / "m"))  # fmt: skip
    worker = HeldPlans(MapperConfig(), settings, sink=Sink(), log=RecordingLog())
    first = replace(plane_map(), stamp_ns=1)
    second, shift = moved_map(first)
    second = replace(second, stamp_ns=2)
    worker.start()
    worker.submit_map(first)
    worker.submit_keyframe(keyframe(1))
    drain(worker)
    worker.submit_map(second)
    for stamp in (2, 3):
        worker.submit_keyframe(replace(keyframe(stamp), cam_to_world=shift))
    wait_until(lambda: worker.stats.keyframes_processed == 3, 10.0, "the keyframes after the map", process=None)
    assert worker.stats.map_updates_ahead == 1 and worker.session.mapper.gaussians is first
    worker.release.set()  # its plan is ready as the node stops
    info = worker.stop(within_s=5.0)
    assert info is not None and worker.session.mapper.gaussians is second
    saved = load_snapshot(tmp_path / "m")
    np.testing.assert_array_equal(saved.gaussians.means, second.means)
    logged = {e.stamp_ns: e.cam_to_world for e in saved.keyframe_log.entries}
    for stamp in (2, 3):
        np.testing.assert_allclose(logged[stamp], shift, atol=1e-6)  # moved back to where they were sent


def test_worker_time_is_accounted_by_activity(tmp_path):
    settings = WorkerSettings(queue_size=8, publish_period_s=0.0, save_period_s=0.01, map_directory=str(tmp_path / "m"))
    worker = MapWorker(MapperConfig(), settings, sink=GeometrySink(), log=RecordingLog())
    worker.start()
    try:
        worker.submit_map(plane_map())
        for stamp in range(1, 6):
            worker.submit_keyframe(keyframe(stamp))
        drain(worker)
        worker.submit_map(plane_map(seed=1, ids=False))
        drain(worker)
        time.sleep(0.05)  # past the save period: the next task saves
        worker.submit_keyframe(keyframe(9))
        drain(worker)
    finally:
        worker.stop(final_snapshot=False)
    stats = worker.stats.snapshot()
    assert stats["keyframes_processed"] == 6
    for activity in ("keyframes", "map_updates", "labels", "objects", "publish", "snapshots", "calls"):
        assert stats[f"worker_s_{activity}"] > 0, activity
    # The activities are disjoint slices of the worker's time: together less than it ran.
    assert sum(v for k, v in stats.items() if k.startswith("worker_s_")) < 10.0
