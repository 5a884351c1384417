"""The mapper's life (core.session.MappingSession) driven directly, and the two loops around it (the live
worker and offline mapping) giving the same evidence and counters for the same events."""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest

from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.mapping import MapperConfig
from monovoc_ros.core.session import MappingSession, SessionStats
from monovoc_ros.nodes.worker import MapWorker, WorkerSettings
from monovoc_ros.offline import map_events
from tests.evidence import assert_same_evidence
from tests.node_scene import RecordingLog, offline_mapper, small_scene


def integrate_ready(session: MappingSession) -> list[int]:
    stamps = []
    while session.keyframes_ready:
        report = session.integrate_next()
        if report is not None:
            stamps.append(report.stamp_ns)
    return stamps


def test_session_life_counts_every_outcome(tmp_path):
    scene = small_scene()
    gaussians, kfs = scene.gaussians, [scene.keyframe(i) for i in range(6)]
    n = len(gaussians)
    log, seen, resets, saves = RecordingLog(), [], [], []
    session = MappingSession(MapperConfig(), max_waiting=2, log=log)
    session.add_keyframe_listener(lambda kf, mapper: seen.append((kf.stamp_ns, mapper.n_keyframes)))
    session.add_reset_listener(lambda: resets.append(session.mapper))
    session.add_save_listener(lambda directory, info, mapper: saves.append((directory, info.keyframes)))

    # Keyframes before a map wait (the newest max_waiting of them); nothing integrates.
    for kf in kfs[:3]:
        session.add_keyframe(kf)
    assert session.waiting == 2 and not session.keyframes_ready and session.integrate_next() is None
    assert session.stats.keyframes_dropped == 1 and not session.stats.has_map
    assert sum("no Gaussian map yet" in msg for _, msg in log.lines) == 1

    # The first map releases them, in order.
    assert session.add_map(gaussians, "first")
    assert session.stats.has_map and session.stats.gaussians == n
    assert integrate_ready(session) == [kfs[1].stamp_ns, kfs[2].stamp_ns]
    assert seen == [(kfs[1].stamp_ns, 1), (kfs[2].stamp_ns, 2)]

    # The same map again (equal arrays, another object) changes nothing.
    assert not session.add_map(gaussians.subset(np.arange(n)), "again")
    assert session.stats.maps_unchanged == 1 and session.stats.map_version == 0

    # A map update (a tenth pruned) keeps the survivors' evidence by id.
    keep = np.arange(n) % 10 != 0
    before = session.mapper.state.total_weight.copy()
    assert session.add_map(gaussians.subset(keep), "pruned")
    np.testing.assert_array_equal(session.mapper.state.total_weight, before[keep])
    assert session.stats.map_updates == 1 and session.stats.map_version == 1 and session.stats.gaussians == keep.sum()
    assert any(f"{keep.sum()} new by id, 0 by position" in msg for _, msg in log.lines)

    # A duplicate stamp is refused and leaves the state as it was.
    session.add_keyframe(kfs[2])
    assert integrate_ready(session) == [] and session.mapper.n_keyframes == 2
    assert any("already in the map" in msg for _, msg in log.lines)

    # Bad maps: empty, or removing more than max_shrink of the Gaussians (the map in use is kept).
    pruned = session.mapper.gaussians
    assert not session.add_map(pruned.subset(np.zeros(0, np.int64)), "empty")
    assert not session.add_map(pruned.subset(np.arange(len(pruned) // 4)), "shrunk")
    assert session.mapper.gaussians is pruned
    assert any("> map_update_max_shrink 0.5" in msg for _, msg in log.lines)

    # Save, go on, load: back to the saved evidence; a failing load check changes nothing.
    info = session.save(str(tmp_path / "map"))
    assert info.keyframes == 2 and saves == [(str(tmp_path / "map"), 2)]
    saved = session.mapper.state.total_weight.copy()  # the state itself changes in place
    session.add_keyframe(kfs[3])
    assert integrate_ready(session) == [kfs[3].stamp_ns]
    committed = []

    def check(path, mapper):
        if committed == ["refuse"]:
            raise ValueError("objects.db does not match")
        return lambda: committed.append(mapper.n_keyframes)

    session.add_load_check(check)
    committed.append("refuse")
    with pytest.raises(ValueError, match="objects.db"):
        session.load(str(tmp_path / "map"))
    assert session.mapper.n_keyframes == 3
    committed.clear()
    loaded = session.load(str(tmp_path / "map"))
    assert session.mapper is loaded and loaded.n_keyframes == 2 and committed == [2]
    np.testing.assert_array_equal(loaded.state.total_weight, saved)
    assert session.stats.snapshots_saved == 1 and session.stats.last_stamp_ns == kfs[2].stamp_ns

    # Reset: the semantic state, then the whole map; keyframes wait again.
    session.reset(keep_gaussians=True)
    assert session.mapper.n_keyframes == 0 and len(session.mapper.gaussians) == keep.sum()
    session.reset(keep_gaussians=False)
    assert session.mapper is None and not session.stats.has_map and len(resets) == 2
    session.add_keyframe(kfs[4])
    assert not session.keyframes_ready and session.waiting == 1
    with pytest.raises(ValueError, match="no map"):
        session.save(str(tmp_path / "other"))

    counters = session.stats.snapshot()
    assert counters["rejected"] == {"duplicate_stamp": 1, "empty_gaussians": 1, "map_shrink": 1}
    assert counters["keyframes_processed"] == 3 and counters["keyframes_dropped"] == 1
    assert (counters["map_updates"], counters["maps_unchanged"], counters["has_map"]) == (1, 1, False)


def test_a_failing_listener_propagates_unless_handled():
    scene = small_scene()
    failures = []
    for handler in (None, lambda fn, exc: failures.append(type(exc))):
        session = MappingSession(on_listener_error=handler)
        session.add_keyframe_listener(lambda kf, mapper: 1 / 0)
        session.add_map(scene.gaussians)
        session.add_keyframe(scene.keyframe(0))
        if handler is None:
            with pytest.raises(ZeroDivisionError):
                session.integrate_next()
        else:
            assert session.integrate_next() is not None
    assert failures == [ZeroDivisionError]


def test_worker_and_offline_mapping_give_the_same_evidence_for_the_same_events():
    scene = small_scene()
    gaussians, kfs = scene.gaussians, [scene.keyframe(i) for i in range(8)]
    n = len(gaussians)
    pruned = gaussians.subset(np.arange(n) % 10 != 0)
    # No two maps in a row: the worker would coalesce them (a transport policy, not the session's).
    events = [
        kfs[0], kfs[1], gaussians, kfs[2], gaussians.subset(np.arange(n)), kfs[3], pruned, kfs[4], kfs[4],
        pruned.subset(np.zeros(0, np.int64)), kfs[5], pruned.subset(np.arange(n // 4)), kfs[6], kfs[7],
    ]  # fmt: skip
    offline_seen, live_seen = [], []
    offline, offline_stats = map_events(
        events, MapperConfig(), on_keyframe=lambda kf, mapper: offline_seen.append(kf.stamp_ns)
    )

    worker = MapWorker(
        MapperConfig(), WorkerSettings(queue_size=100, publish_period_s=0.0, save_period_s=0.0), log=RecordingLog()
    )
    worker.add_keyframe_listener(lambda kf, mapper: live_seen.append(kf.stamp_ns))
    worker.start()
    try:
        for event in events:
            if isinstance(event, Keyframe):
                worker.submit_keyframe(event)
            else:
                worker.submit_map(event)
        state = worker.submit(lambda mapper: mapper.state).result(120)
    finally:
        worker.stop()

    assert_same_evidence(state, offline.state)
    np.testing.assert_array_equal(state.stamps_ns, offline.state.stamps_ns)
    assert live_seen == offline_seen == [kf.stamp_ns for kf in kfs]
    live, off = worker.stats.snapshot(), offline_stats.snapshot()
    # Times differ, and so does where an update was computed (prepared beside the worker live, in line offline).
    how = {"lock", "map_updates_prepared"}
    for name in (f.name for f in fields(SessionStats) if f.name not in how and not f.name.startswith("ms_")):
        assert live[name] == off[name], name
    assert live["map_updates_prepared"] == live["map_updates"] and off["map_updates_prepared"] == 0
    assert off["rejected"] == {"duplicate_stamp": 1, "empty_gaussians": 1, "map_shrink": 1}
    assert (off["map_updates"], off["maps_unchanged"], off["keyframes_processed"]) == (1, 1, 8)
    # Without map updates both equal a bare SemanticMapper fed the same keyframes.
    plain, _ = map_events([kfs[0], gaussians, *kfs[1:]], MapperConfig())
    assert_same_evidence(plain.state, offline_mapper(gaussians, kfs).state)
