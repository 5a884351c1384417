"""Publications beside the mapping worker: the worker captures what to publish (`Publication`, immutable) and
goes on with the next keyframe while `OutputThread` builds and sends the messages.

At 1M Gaussians one publication (the objects' geometry, the semantic cloud of ~800k points, objects and
markers) took 100-250 ms of the worker, a quarter of it at `publish_rate_hz` 1 (robot-scale bench, issue 25),
and a keyframe that arrived meanwhile waited for it. One thread publishes, in order, so the cloud, objects and
markers of one publication always agree; a publication still waiting when a newer one comes is replaced by it
(newest wins, counted in `publications_replaced`): only the newest state matters, and a publisher slower than
the keyframes must not build a backlog. Nothing here imports ROS: the node's `SemanticOutputs` is the sink.
"""

from __future__ import annotations

import threading
import time
import traceback
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import wait as wait_futures
from dataclasses import dataclass
from typing import Any, Protocol

from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.mapping import SemanticMapper, SemanticResult
from monovoc_ros.core.session import Logger
from monovoc_ros.nodes.diagnostics import MapperStats


@dataclass(frozen=True, eq=False)
class Publication:
    """What one publication reports, captured on the worker thread (`of`): the map, its labels and what else the
    outputs need of the mapper, none of which the worker changes afterwards (maps and results are immutable)."""

    gaussians: GaussianMap
    result: SemanticResult
    stamp_ns: int | None  # the newest integrated keyframe's stamp (None: none integrated yet)
    keyframes: int  # integrated keyframes
    segment_labels: dict[int, str]  # object id -> its segments' leading class name (SemanticMapper.object_labels)

    @classmethod
    def of(cls, mapper: SemanticMapper, result: SemanticResult) -> Publication:
        stamp = int(mapper.state.stamps_ns.max()) if mapper.n_keyframes else None
        return cls(mapper.gaussians, result, stamp, mapper.n_keyframes, mapper.object_labels())


class OutputSink(Protocol):
    """Where publications go (the node's publishers); called on the output thread only."""

    def publish(self, publication: Publication | None) -> int:
        """Publishes the semantic map (None: no map, publish an empty one); returns the number of objects."""
        ...


class OutputThread:
    """One thread that publishes `Publication`s, newest first (module docstring), and runs calls that read the
    sink's state (`call`) in order with them."""

    def __init__(self, sink: OutputSink | None, stats: MapperStats, log: Logger) -> None:
        self.sink = sink
        self.stats = stats
        self.log = log
        self.seconds = 0.0  # the last publication's time (the worker's publication rate follows it)
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="monovoc-outputs")
        self._lock = threading.Lock()
        self._pending: tuple[Publication | None] | None = None  # the waiting publication (a tuple: None is one)
        self._queued: Future | None = None  # the task that will publish it
        self._current: Future | None = None  # the task running or queued last (stop waits for it)

    def publish(self, publication: Publication | None) -> Future:
        """Queues `publication`, replacing one still waiting; the Future gives the number of objects published
        (of this publication or of a newer one that replaced it) or the sink's exception."""
        with self._lock:
            if self._queued is not None:
                self.stats.add(publications_replaced=1)
            self._pending = (publication,)
            if self._queued is None:
                self._queued = self._current = self._submit(self._publish_pending)
            return self._queued

    def call(self, fn: Callable[[], Any]) -> Future:
        """Runs fn() on the output thread after the publications queued so far."""
        with self._lock:
            self._current = self._submit(fn)
            return self._current

    def stop(self, timeout: float) -> None:
        """Publishes what is queued (the newest state), waiting for it up to `timeout` s; nothing is queued
        after this (the node destroys its publishers next)."""
        with self._lock:
            current = self._current
            self._executor.shutdown(wait=False)
        if current is not None:
            wait_futures([current], timeout=timeout)

    def _submit(self, fn: Callable[[], Any]) -> Future:
        try:
            return self._executor.submit(fn)
        except RuntimeError:  # stopped: nothing is published any more
            future: Future = Future()
            future.cancel()
            return future

    def _publish_pending(self) -> int:
        with self._lock:
            pending, self._pending, self._queued = self._pending, None, None
        assert pending is not None
        (publication,) = pending
        result = None if publication is None else publication.result
        computed = result is None or result.objects_seconds is not None  # its geometry came with an earlier one
        start = time.perf_counter()
        try:
            objects = self.sink.publish(publication) if self.sink is not None else 0
        except Exception as exc:
            self.stats.add(worker_errors=1)
            self.log.error(f"publication: {type(exc).__name__}: {exc}\n{traceback.format_exc()}")
            raise
        end = time.perf_counter()
        self.seconds = end - start
        geometry_s = 0.0 if computed else (result.objects_seconds or 0.0)
        observed = int(result.observed.sum()) if result is not None else 0
        self.stats.update(objects=objects, observed_gaussians=observed, publish_ms_last=1e3 * self.seconds)
        self.stats.add(publishes=1, output_s_objects=geometry_s, output_s_messages=self.seconds - geometry_s)
        return objects
