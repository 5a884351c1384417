"""Publications beside the worker (nodes/publication.py): order, replacement, stop, and a worker that integrates
keyframes while a publication is slow."""

from __future__ import annotations

import threading

import pytest

from monovoc_ros.core.mapping import MapperConfig
from monovoc_ros.nodes.publication import PublicationStopped, PublicationThread, PublishedMap
from monovoc_ros.nodes.worker import MapWorker, WorkerSettings
from monovoc_ros.ros_harness import wait_until
from tests.node_scene import RecordingLog
from tests.test_node_worker import keyframe, plane_map


def started(errors: list | None = None) -> PublicationThread:
    thread = PublicationThread(lambda exc, trace: (errors if errors is not None else []).append(exc))
    thread.start()
    return thread


def test_a_publication_not_started_is_replaced_by_the_newer_one_in_its_place():
    thread = started()
    gate, ran = threading.Event(), []
    try:
        blocking = thread.call(lambda: gate.wait(10))
        first = thread.publish(lambda: ran.append("first") or "first")
        second = thread.publish(lambda: ran.append("second") or "second")
        after = thread.call(lambda: ran.append("call") or "call")
        third = thread.publish(lambda: ran.append("third") or "third")  # a call lies between: not replaced
        assert second is first and thread.replaced == 1
        gate.set()
        assert blocking.result(5) is True
        assert (first.result(5), after.result(5), third.result(5)) == ("second", "call", "third")
        assert ran == ["second", "call", "third"]
    finally:
        gate.set()
        assert thread.stop(5)


def test_a_failure_is_reported_and_the_thread_goes_on():
    errors: list[BaseException] = []
    thread = started(errors)
    try:
        failed = thread.call(lambda: 1 / 0)
        with pytest.raises(ZeroDivisionError):
            failed.result(5)
        assert thread.call(lambda: 7).result(5) == 7
        assert [type(e) for e in errors] == [ZeroDivisionError]
    finally:
        assert thread.stop(5)


def test_stop_runs_what_is_queued_and_refuses_what_comes_after():
    thread = started()
    gate = threading.Event()
    thread.call(lambda: gate.wait(10))
    queued = thread.publish(lambda: "queued")
    gate.set()
    assert thread.stop(5)
    assert queued.result(0) == "queued"
    for late in (thread.publish(lambda: "late"), thread.call(lambda: "late")):
        with pytest.raises(PublicationStopped):
            late.result(0)


class SlowSink:
    """Blocks each publication until released: a slow cloud or geometry at robot scale."""

    def __init__(self):
        self.release = threading.Event()
        self.started = threading.Event()
        self.published: list[int] = []  # keyframes in each publication's map
        self.threads: set[str] = set()

    def publish(self, published: PublishedMap | None, result) -> int:
        self.threads.add(threading.current_thread().name)
        self.started.set()
        assert self.release.wait(10)
        self.published.append(0 if published is None else published.n_keyframes)
        return 0


def test_the_worker_integrates_keyframes_while_a_publication_is_slow_and_the_newest_map_is_published():
    sink = SlowSink()
    settings = WorkerSettings(queue_size=16, publish_period_s=0.0, save_period_s=0.0)
    worker = MapWorker(MapperConfig(), settings, sink=sink, log=RecordingLog())
    worker.start()
    try:
        assert sink.started.wait(10)  # the start-up publication (no map yet) holds the publication thread
        # Each input changes the map once; with nothing queued after it the worker publishes: it labels the map and
        # hands the publication over (one per input, as it is published once per change).
        for submit in [lambda: worker.submit_map(plane_map())] + [
            lambda stamp=stamp: worker.submit_keyframe(keyframe(stamp)) for stamp in range(1, 6)
        ]:
            labelled = worker.stats.worker_s_labels
            submit()
            wait_until(lambda labelled=labelled: worker.stats.worker_s_labels > labelled, 10, "a publication")
        # Integrated while the publication thread was still busy with the first publication.
        assert worker.stats.keyframes_processed == 5 and sink.published == []
        sink.release.set()
        wait_until(lambda: worker.stats.publishes == 2, 10, "the publications")
        # One publication waited; each newer one replaced it: the newest map is what was published.
        assert sink.published == [0, 5] and worker.stats.publications_replaced == 5
        assert sink.threads == {"monovoc-publication"}
    finally:
        sink.release.set()
        worker.stop(final_snapshot=False)
