"""Publications beside the mapping worker (issue 25): the worker computes a publication's labels and hands them
over; the object geometry, the messages and the result listeners run here, on a thread of their own, while the
worker integrates the next keyframe.

At 2M Gaussians the geometry and the messages took 18% of the worker in the robot-scale bench's fast run (13% at
1M), time it did not integrate keyframes in. A publication reads only what the worker captured for it
(`PublishedMap`: immutable arrays and copies) and the `SemanticResult` (immutable, its geometry cached under its
own lock), so the worker may go on changing the mapper meanwhile.

Publications run in the order they were made. One that has not started when a newer one comes is replaced by it
(both requests get the newer one's outcome): a slow publication never builds up a backlog, and what is published is
always the newest map. Other work on the outputs (republishing the objects with new labels) runs on this thread
too, in order with the publications, so the outputs' state has one thread.
"""

from __future__ import annotations

import threading
import traceback
from collections import deque
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

from monovoc_ros.core.map.gaussians import GaussianMap


@dataclass(frozen=True)
class PublishedMap:
    """The mapper as one publication reports it, captured on the worker thread (`of`)."""

    gaussians: GaussianMap  # the map the result labels (immutable: a map update replaces it)
    n_keyframes: int
    stamp_ns: int | None  # the newest integrated keyframe's stamp (None: none yet)
    object_labels: Mapping[int, str]  # object id -> leading class name (SemanticMapper.object_labels)
    object_label_confidence: Mapping[int, float]  # SemanticMapper.object_label_confidence

    @classmethod
    def of(cls, mapper: Any) -> PublishedMap:
        """What a publication of `mapper` (core.mapping.SemanticMapper) needs; call on the worker thread."""
        n = mapper.n_keyframes
        return cls(
            mapper.gaussians,
            n,
            int(mapper.state.stamps_ns.max()) if n else None,
            dict(mapper.object_labels()),
            dict(mapper.object_label_confidence()),
        )


class PublicationStopped(RuntimeError):
    """Work handed to the publication thread after it stopped."""


@dataclass(eq=False)
class _Work:
    fn: Callable[[], Any]
    publication: bool  # a newer publication replaces it until it starts
    future: Future = field(default_factory=Future)


class PublicationThread:
    """One thread that runs publications and other work on the outputs in order; see the module docstring.
    `on_error(exc)`: a failure of any of them (logged by the owner); its Future holds it too."""

    def __init__(self, on_error: Callable[[BaseException, str], None], name: str = "monovoc-publication") -> None:
        self._on_error = on_error
        self._name = name
        self._cond = threading.Condition()
        self._queue: deque[_Work] = deque()
        self._closed = False
        self._thread: threading.Thread | None = None
        self.replaced = 0  # publications replaced by a newer one before they started

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name=self._name, daemon=True)
        self._thread.start()

    def publish(self, fn: Callable[[], Any]) -> Future:
        """Queues the publication `fn()`, replacing the last one queued if it has not started (its Future is the
        one returned: it gets this one's outcome). After `stop` the Future holds PublicationStopped."""
        with self._cond:
            last = self._queue[-1] if self._queue else None
            if last is not None and last.publication and not self._closed:
                last.fn = fn
                self.replaced += 1
                return last.future
            return self._put(_Work(fn, True))

    def call(self, fn: Callable[[], Any]) -> Future:
        """Queues `fn()` after everything queued. After `stop` the Future holds PublicationStopped."""
        with self._cond:
            return self._put(_Work(fn, False))

    def stop(self, timeout: float) -> bool:
        """Runs what is queued, then ends; waits at most `timeout` s. False when the thread is still busy then."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        if self._thread is None:
            return True
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def _put(self, work: _Work) -> Future:
        if self._closed:
            work.future.set_exception(PublicationStopped("the node is shutting down"))
        else:
            self._queue.append(work)
            self._cond.notify_all()
        return work.future

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._queue and not self._closed:
                    self._cond.wait()
                if not self._queue:
                    return
                work = self._queue.popleft()
            if not work.future.set_running_or_notify_cancel():
                continue
            try:
                work.future.set_result(work.fn())
            except Exception as exc:  # the thread must outlive any one failure
                self._on_error(exc, traceback.format_exc())
                work.future.set_exception(exc)
