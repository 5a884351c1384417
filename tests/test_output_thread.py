"""The output thread (nodes/output_thread.py): publications beside the worker, newest first, in order with calls."""

from __future__ import annotations

import threading
from concurrent.futures import CancelledError
from types import SimpleNamespace

import pytest
from test_node_worker import keyframe, plane_map

from monovoc_ros.core.mapping import MapperConfig
from monovoc_ros.nodes.diagnostics import MapperStats
from monovoc_ros.nodes.output_thread import OutputThread
from monovoc_ros.nodes.worker import MapWorker, WorkerSettings
from monovoc_ros.ros_harness import wait_until
from tests.node_scene import RecordingLog


def named(name: str) -> SimpleNamespace:
    """A stand-in Publication (without a result: nothing for the output thread to count)."""
    return SimpleNamespace(name=name, result=None)


class HeldSink:
    """Publishes (records the names of) publications only once released; fails on the one named "bad"."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.started = threading.Event()
        self.published: list = []

    def publish(self, publication) -> int:
        self.started.set()
        assert self.release.wait(10.0)
        if publication is not None and getattr(publication, "name", "") == "bad":
            raise RuntimeError("a publisher failed")
        self.published.append(getattr(publication, "name", publication))
        return len(self.published)


def test_a_waiting_publication_is_replaced_by_a_newer_one_and_calls_keep_their_order():
    sink, stats, log = HeldSink(), MapperStats(), RecordingLog()
    outputs = OutputThread(sink, stats, log)
    try:
        first = outputs.publish(None)
        assert sink.started.wait(5.0)  # the first is being published: the next ones wait
        second = outputs.publish(named("second"))
        order: list = []
        call = outputs.call(lambda: order.append(list(sink.published)))
        third = outputs.publish(named("third"))
        assert third is second  # one task publishes the newest of them
        sink.release.set()
        assert first.result(5.0) == 1 and third.result(5.0) == 2
        call.result(5.0)
    finally:
        outputs.stop(5.0)
    assert sink.published == [None, "third"] and stats.publications_replaced == 1 and stats.publishes == 2
    assert order == [[None, "third"]]  # after the publication queued before it (which took the newer one)


def test_a_failing_publication_is_counted_and_the_next_one_goes_out():
    sink, stats, log = HeldSink(), MapperStats(), RecordingLog()
    sink.release.set()
    outputs = OutputThread(sink, stats, log)
    try:
        with pytest.raises(RuntimeError, match="a publisher failed"):
            outputs.publish(named("bad")).result(5.0)
        assert outputs.publish(named("good")).result(5.0) == 1
    finally:
        outputs.stop(5.0)
    assert stats.worker_errors == 1 and any("a publisher failed" in msg for kind, msg in log.lines if kind == "error")


def test_stop_publishes_what_is_queued_and_nothing_after():
    sink, stats, log = HeldSink(), MapperStats(), RecordingLog()
    outputs = OutputThread(sink, stats, log)
    outputs.publish(named("first"))
    assert sink.started.wait(5.0)
    last = outputs.publish(named("last"))
    threading.Timer(0.1, sink.release.set).start()
    outputs.stop(5.0)
    assert last.done() and sink.published == ["first", "last"]
    late = outputs.publish(named("late"))
    with pytest.raises(CancelledError):
        late.result(0)
    assert sink.published == ["first", "last"]


def test_the_worker_integrates_keyframes_while_a_publication_is_built():
    """A publication at 1M Gaussians takes 0.1-0.25 s: the keyframes behind it must not wait for it."""
    sink = HeldSink()
    worker = MapWorker(
        MapperConfig(), WorkerSettings(queue_size=8, publish_period_s=0.0), sink=sink, log=RecordingLog()
    )
    asked: list[int] = []  # a result listener hears every publication the worker hands over
    worker.add_result_listener(lambda mapper, result: asked.append(mapper.n_keyframes))
    worker.submit_map(plane_map())
    worker.start()
    try:
        assert sink.started.wait(10.0)  # the first publication is held
        for stamp in range(1, 4):  # one at a time: each ends with an empty queue and asks for a publication
            worker.submit_keyframe(keyframe(stamp))
            wait_until(lambda s=stamp: asked[-1:] == [s], 10.0, "a keyframe integrated behind a publication")
        assert not sink.published
        sink.release.set()
        wait_until(lambda: len(sink.published) == 2, 10.0, "the newest state published")
    finally:
        sink.release.set()
        worker.stop()
    # The first, then the newest: the publications of keyframes 1 and 2 were replaced while they waited.
    assert [p.keyframes for p in sink.published] == [0, 3] and worker.stats.publications_replaced == 2
