"""The mapping worker: one thread that owns the SemanticMapper and applies every state change in order.

Subscription and service callbacks never touch the mapper; they put tasks into one queue:

* keyframes: bounded (`queue_size`); when full, the OLDEST waiting keyframe is dropped and counted.
  Keyframes that arrive before any Gaussian map wait in the queue (tasks behind them still run).
* Gaussian maps from the SLAM front-end: never dropped; a map that directly follows another pending map
  replaces it (only the newest of consecutive updates matters: no keyframe lies between them). A map
  without Gaussians, or one removing more than `map_update_max_shrink` of them, is refused and counted
  (monovoc_ros.ingest.map_update_refusal): one empty cloud must not wipe the map.
* calls (services, plugins): never dropped; run in arrival order with the rest, results via a Future.
  `load` reads and checks everything (the snapshot, then each load check such as objects.db) before it
  swaps anything in, so a failed load changes nothing.

Between tasks the worker publishes the semantic result (at most every `publish_period_s` while something
changed; period 0 = as soon as nothing runnable is queued) and saves periodic snapshots of new evidence.
The rasterizer's numba kernels release the GIL, so ROS callbacks keep running while a keyframe is
integrated. Nothing here imports ROS: the node wires it to topics (monovoc_ros.nodes.mapping_node).

Hooks for other components (object database, text queries), all run on the worker thread:
`add_keyframe_listener(fn(keyframe, mapper))` after each integrated keyframe, `add_result_listener(fn(mapper,
result))` after the semantic result was recomputed (before it is published), and `submit(fn(mapper))` to
read or change the mapper in order with everything else.
"""

from __future__ import annotations

import threading
import time
import traceback
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from monovoc_ros.core.gaussians import GaussianMap
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map_store import SnapshotInfo, load_snapshot, save_snapshot
from monovoc_ros.core.mapping import MapperConfig, SemanticMapper, SemanticResult
from monovoc_ros.core.ply import load_ply
from monovoc_ros.ingest import map_update_refusal
from monovoc_ros.nodes.diagnostics import MapperStats

KeyframeListener = Callable[[Keyframe, SemanticMapper], None]
ResultListener = Callable[[SemanticMapper, SemanticResult], None]
LoadCheck = Callable[[str, SemanticMapper], "Callable[[], None] | None"]


class Logger(Protocol):
    def info(self, msg: str) -> Any: ...
    def warning(self, msg: str) -> Any: ...
    def error(self, msg: str) -> Any: ...


class OutputSink(Protocol):
    """Where results go (the node's publishers); called on the worker thread."""

    def publish(self, mapper: SemanticMapper | None, result: SemanticResult | None) -> int:
        """Publishes the semantic map (None: no map, publish an empty one); returns the number of objects."""
        ...


class WorkerStopped(RuntimeError):
    """A call that was still queued when the worker stopped."""


@dataclass
class WorkerSettings:
    queue_size: int = 100  # keyframes
    publish_period_s: float = 1.0  # 0: publish as soon as nothing runnable is queued
    map_directory: str = ""  # periodic and final snapshots go here ("" = none)
    save_period_s: float = 30.0  # 0 = no periodic snapshots
    # A map update removing a larger share of the Gaussians (by id when both maps have ids, else by count) is
    # refused and counted (map_shrink): one empty or truncated cloud must not wipe the map. 1.0 = allow all.
    map_update_max_shrink: float = 0.5


@dataclass
class _Task:
    kind: str  # "keyframe" | "map" | "call"
    payload: Any
    future: Future | None = None
    name: str = ""


class TaskQueue:
    """FIFO of worker tasks; bounded for keyframes only (drop oldest), consecutive maps coalesced."""

    def __init__(self, max_keyframes: int) -> None:
        if max_keyframes < 1:
            raise ValueError(f"max_keyframes must be >= 1, got {max_keyframes}")
        self.max_keyframes = max_keyframes
        self._tasks: deque[_Task] = deque()
        self._keyframes = 0
        self._cond = threading.Condition()
        self._closed = False

    @property
    def keyframes(self) -> int:
        return self._keyframes

    def __len__(self) -> int:
        return len(self._tasks)

    def put_keyframe(self, keyframe: Keyframe) -> Keyframe | None:
        """Queues a keyframe; returns the keyframe dropped to make room, if any."""
        dropped = None
        with self._cond:
            if self._keyframes >= self.max_keyframes:
                for i, task in enumerate(self._tasks):
                    if task.kind == "keyframe":
                        del self._tasks[i]
                        self._keyframes -= 1
                        dropped = task.payload
                        break
            self._tasks.append(_Task("keyframe", keyframe))
            self._keyframes += 1
            self._cond.notify()
        return dropped

    def put_map(self, gaussians: GaussianMap, name: str = "") -> bool:
        """Queues a map; returns True when it replaced a pending map queued right before it."""
        with self._cond:
            coalesced = bool(self._tasks) and self._tasks[-1].kind == "map"
            if coalesced:
                self._tasks[-1] = _Task("map", gaussians, name=name)
            else:
                self._tasks.append(_Task("map", gaussians, name=name))
            self._cond.notify()
        return coalesced

    def put_call(self, fn: Callable[[], Any], name: str = "") -> Future:
        future: Future = Future()
        with self._cond:
            if self._closed:
                future.set_exception(WorkerStopped(f"{name or 'call'}: the worker has stopped"))
                return future
            self._tasks.append(_Task("call", fn, future, name))
            self._cond.notify()
        return future

    def runnable(self, has_map: bool) -> bool:
        with self._cond:
            return self._index(has_map) is not None

    def _index(self, has_map: bool) -> int | None:
        if has_map:
            return 0 if self._tasks else None
        # Without a map keyframes wait; maps and calls behind them go first.
        return next((i for i, t in enumerate(self._tasks) if t.kind != "keyframe"), None)

    def take(self, has_map: bool, timeout: float | None) -> _Task | None:
        """The next runnable task, waiting up to `timeout` s (None: until one comes or the queue closes)."""
        deadline = None if timeout is None else time.monotonic() + max(timeout, 0.0)
        with self._cond:
            while not self._closed:
                i = self._index(has_map)
                if i is not None:
                    task = self._tasks[i]
                    del self._tasks[i]
                    if task.kind == "keyframe":
                        self._keyframes -= 1
                    return task
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None
                self._cond.wait(remaining)
            return None

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def wake(self) -> None:
        with self._cond:
            self._cond.notify_all()

    def drain(self) -> list[_Task]:
        with self._cond:
            tasks = list(self._tasks)
            self._tasks.clear()
            self._keyframes = 0
            return tasks


def same_geometry(a: GaussianMap, b: GaussianMap) -> bool:
    """True when two maps are the same Gaussians (SLAM re-publishing an unchanged map, or the map a
    resumed snapshot was built from): applying it as an update would change nothing."""
    if a is b:
        return True
    if len(a) != len(b) or (a.ids is None) != (b.ids is None):
        return False
    if a.ids is not None and not np.array_equal(a.ids, b.ids):
        return False
    if not (np.array_equal(a.means, b.means) and np.array_equal(a.scales, b.scales)):
        return False
    if not np.array_equal(a.opacities, b.opacities):
        return False
    # Quaternions are re-normalized and colors re-encoded (f_dc) on every trip: equal up to rounding.
    if not np.allclose(a.quats, b.quats, rtol=0, atol=1e-6):
        return False
    if (a.colors is None) != (b.colors is None):
        return False
    return a.colors is None or np.allclose(a.colors, b.colors, rtol=0, atol=1e-5)


class MapWorker:
    """Owns the SemanticMapper; see the module docstring. Start with `start()`, end with `stop()`."""

    def __init__(
        self,
        config: MapperConfig,
        settings: WorkerSettings,
        *,
        stats: MapperStats | None = None,
        sink: OutputSink | None = None,
        log: Logger | None = None,
        mapper: SemanticMapper | None = None,
    ) -> None:
        self.config = config
        self.settings = settings
        self.stats = stats or MapperStats()
        self.sink = sink
        self.log: Logger = log or _PrintLogger()
        self.queue = TaskQueue(settings.queue_size)
        self._mapper = mapper
        self._keyframe_listeners: list[KeyframeListener] = []
        self._result_listeners: list[ResultListener] = []
        self._thread: threading.Thread | None = None
        self._output_dirty = True  # publish once at start (the map, or an empty one)
        self._unsaved = False  # evidence that no snapshot in map_directory holds yet
        self._last_publish = -float("inf")
        self._last_save = time.monotonic()
        self._on_reset: list[Callable[[], None]] = []
        self._on_save: list[Callable[[str, SnapshotInfo, SemanticMapper], None]] = []
        self._load_checks: list[LoadCheck] = []
        self._refresh_map_stats()

    # ------------------------------------------------------------------ public API (any thread)

    @property
    def mapper(self) -> SemanticMapper | None:
        """The current mapper. Read or change it only on the worker thread (listeners, `submit`)."""
        return self._mapper

    def add_keyframe_listener(self, fn: KeyframeListener) -> None:
        self._keyframe_listeners.append(fn)

    def add_result_listener(self, fn: ResultListener) -> None:
        self._result_listeners.append(fn)

    def add_reset_listener(self, fn: Callable[[], None]) -> None:
        """fn() runs on the worker thread after a reset (the node clears its keyframe assembler)."""
        self._on_reset.append(fn)

    def add_save_listener(self, fn: Callable[[str, SnapshotInfo, SemanticMapper], None]) -> None:
        """fn(directory, info, mapper) runs on the worker thread after every snapshot (service, periodic, final)."""
        self._on_save.append(fn)

    def add_load_check(self, fn: LoadCheck) -> None:
        """fn(path, mapper) runs on the worker thread after a map was read and before it replaces the current
        one: it reads and checks what it needs (the object database) and raises to fail the load, with nothing
        changed; it returns a function that swaps its part in (run right after the mapper is swapped), or None."""
        self._load_checks.append(fn)

    def submit_keyframe(self, keyframe: Keyframe) -> Keyframe | None:
        """Queues a keyframe; returns the one dropped to make room (already counted), if any."""
        dropped = self.queue.put_keyframe(keyframe)
        if dropped is not None:
            self.stats.add(keyframes_dropped=1)
        self.stats.update(queue_length=self.queue.keyframes)
        return dropped

    def submit_map(self, gaussians: GaussianMap, name: str = "") -> None:
        if self.queue.put_map(gaussians, name):
            self.stats.add(maps_coalesced=1)

    def submit(self, fn: Callable[[SemanticMapper | None], Any], name: str = "") -> Future:
        """Runs fn(mapper) on the worker thread, in order with keyframes and maps; its result in a Future."""
        return self.queue.put_call(lambda: fn(self._mapper), name)

    def call(self, fn: Callable[[], Any], name: str = "") -> Future:
        """Like `submit` for the worker's own operations (save, load, reset, publish_now)."""
        return self.queue.put_call(fn, name)

    def start(self) -> None:
        self._last_save = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="monovoc-mapper-worker", daemon=True)
        self._thread.start()

    def stop(self, *, final_snapshot: bool = True, timeout: float | None = None) -> SnapshotInfo | None:
        """Stops after the task in progress; pending tasks are discarded (calls fail with WorkerStopped).

        With a map directory, unsaved evidence is written as a final snapshot (on this thread: the
        worker has exited by then).
        """
        self.queue.close()
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                self.log.error("worker did not stop in time; skipping the final snapshot")
                return None
        pending = self.queue.drain()
        keyframes = sum(t.kind == "keyframe" for t in pending)
        for task in pending:
            if task.future is not None:
                task.future.set_exception(WorkerStopped(f"{task.name or 'call'}: the node is shutting down"))
        if keyframes:
            self.log.warning(f"shutting down with {keyframes} queued keyframes not integrated")
        if final_snapshot and self.settings.map_directory and self._unsaved and self._mapper is not None:
            try:
                info = self.save(self.settings.map_directory)
                self.log.info(f"final snapshot: {info.path} ({info.keyframes} keyframes)")
                return info
            except Exception as exc:  # a full disk must not turn a clean shutdown into a crash
                self.log.error(f"final snapshot failed: {exc}")
        return None

    # ------------------------------------------------------------------ operations (worker thread)

    def save(self, directory: str) -> SnapshotInfo:
        if self._mapper is None:
            raise ValueError("no map to save yet")
        info = save_snapshot(self._mapper, directory)
        self.stats.add(snapshots_saved=1)
        if Path(directory).resolve() == _resolved(self.settings.map_directory):
            self._unsaved = False
            self._last_save = time.monotonic()
        for fn in self._on_save:
            fn(directory, info, self._mapper)
        return info

    def load(self, path: str) -> SemanticMapper:
        """Replaces the mapper: a snapshot directory (state included) or a PLY file (fresh state).

        Everything (the snapshot's files, then each load check: objects.db) is read and validated first;
        any failure raises and leaves the current map, its objects and the files untouched.
        """
        p = Path(path)
        if not p.exists():
            raise ValueError(f"{path} does not exist")
        if p.is_dir():
            mapper = load_snapshot(p, self.config)
            source = f"snapshot {p} ({mapper.n_keyframes} keyframes)"
        elif p.is_file() and p.suffix.lower() == ".ply":
            mapper = SemanticMapper(load_ply(p), self.config)
            source = f"PLY {p} (fresh semantic state)"
        else:
            raise ValueError(f"{path}: neither a map directory nor a .ply file")
        commits = [fn(path, mapper) for fn in self._load_checks]  # may raise: nothing swapped yet
        self._mapper = mapper
        for commit in commits:
            if commit is not None:
                commit()
        self._changed(unsaved=p.resolve() != _resolved(self.settings.map_directory))
        self.log.info(f"loaded {source}: {len(mapper.gaussians)} Gaussians")
        return mapper

    def reset(self, keep_gaussians: bool) -> None:
        if keep_gaussians and self._mapper is not None:
            self._mapper = SemanticMapper(self._mapper.gaussians, self.config)
        else:
            self._mapper = None
        for fn in self._on_reset:
            fn()
        self._changed(unsaved=self._mapper is not None)
        self.log.info("reset: " + ("semantic state cleared" if keep_gaussians else "waiting for a new Gaussian map"))

    def publish_now(self) -> tuple[SemanticResult | None, int]:
        """Recomputes and publishes the result now; returns it and the number of objects."""
        return self._publish()

    def objects_now(self) -> int:
        if self._mapper is None:
            return 0
        return len(self._mapper.result().objects(self._mapper.gaussians).objects)

    # ------------------------------------------------------------------ the loop

    def _run(self) -> None:
        while True:
            task = self.queue.take(self._mapper is not None, self._wait_time())
            if task is None and self.queue.closed:
                return
            try:
                if task is not None:
                    self._execute(task)
                self.stats.update(queue_length=self.queue.keyframes)
                self._maybe_publish()
                self._maybe_save()
            except Exception as exc:  # the worker must outlive any single bad task or listener
                self.stats.add(worker_errors=1)
                self.log.error(f"worker: {type(exc).__name__}: {exc}\n{traceback.format_exc()}")

    def _execute(self, task: _Task) -> None:
        if task.kind == "keyframe":
            self._integrate(task.payload)
        elif task.kind == "map":
            self._apply_map(task.payload, task.name)
        else:
            assert task.future is not None
            if not task.future.set_running_or_notify_cancel():
                return
            try:
                task.future.set_result(task.payload())
            except Exception as exc:
                task.future.set_exception(exc)

    def _integrate(self, keyframe: Keyframe) -> None:
        mapper = self._mapper
        assert mapper is not None
        if mapper.state.has_stamp(keyframe.stamp_ns):
            self.stats.reject("duplicate_stamp")
            self.log.warning(f"keyframe {keyframe.stamp_ns} is already in the map (replayed after a resume?): skipped")
            return
        try:
            report = mapper.integrate(keyframe)
        except ValueError as exc:
            self.stats.reject("integration_error")
            self.log.warning(f"keyframe {keyframe.stamp_ns} not integrated: {exc}")
            return
        ms = 1e3 * report.seconds
        with self.stats.lock:
            self.stats.keyframes_processed += 1
            self.stats.ms_per_keyframe_last = ms
            self.stats.ms_per_keyframe_total += ms
            self.stats.last_stamp_ns = max(self.stats.last_stamp_ns, keyframe.stamp_ns)
        self._changed()
        integrated = report.keyframe or keyframe  # per-frame mask ids: the mask in object colors
        for fn in self._keyframe_listeners:
            self._guarded(fn, integrated, mapper)

    def _apply_map(self, gaussians: GaussianMap, name: str) -> None:
        refusal = map_update_refusal(
            self._mapper.gaussians if self._mapper else None, gaussians, self.settings.map_update_max_shrink
        )
        if refusal is not None:
            reason, detail = refusal
            self.stats.reject(reason)
            self.log.warning(f"Gaussian map {name} refused: {detail}")
            return
        if self._mapper is None:
            self._mapper = SemanticMapper(gaussians, self.config)
            self.log.info(
                f"Gaussian map {name}: {len(gaussians)} Gaussians" + (" with ids" if gaussians.ids is not None else "")
            )
        elif same_geometry(self._mapper.gaussians, gaussians):
            self.stats.add(maps_unchanged=1)
            return
        else:
            report = self._mapper.update_gaussians(gaussians)
            self.stats.add(map_updates=1)
            self.log.info(
                f"map update {name}: {report.gaussians} Gaussians; evidence by {report.by}: "
                f"{report.carried} carried, {report.dropped} dropped"
            )
        self._changed()

    def _changed(self, unsaved: bool = True) -> None:
        self._output_dirty = True
        self._unsaved = self._unsaved or unsaved
        self._refresh_map_stats()

    def _refresh_map_stats(self) -> None:
        m = self._mapper
        self.stats.update(
            has_map=m is not None,
            gaussians=len(m.gaussians) if m else 0,
            map_version=m.map_version if m else 0,
            last_stamp_ns=int(m.state.stamps_ns.max()) if m is not None and m.n_keyframes else 0,
        )

    # ------------------------------------------------------------------ publishing and saving

    def _wait_time(self) -> float | None:
        now = time.monotonic()
        waits = []
        if self._output_dirty:
            period = self.settings.publish_period_s
            waits.append(0.0 if period == 0 else self._last_publish + period - now)
        if self._save_enabled() and self._unsaved:
            waits.append(self._last_save + self.settings.save_period_s - now)
        return max(min(waits), 0.0) if waits else None

    def _maybe_publish(self) -> None:
        if not self._output_dirty:
            return
        period = self.settings.publish_period_s
        if period == 0:
            if self.queue.runnable(self._mapper is not None):
                return
        elif time.monotonic() < self._last_publish + period:
            return
        self._publish()

    def _publish(self) -> tuple[SemanticResult | None, int]:
        start = time.perf_counter()
        self._output_dirty = False
        self._last_publish = time.monotonic()
        mapper = self._mapper
        result = mapper.result() if mapper is not None else None
        if mapper is not None and result is not None:
            for fn in self._result_listeners:
                self._guarded(fn, mapper, result)
        objects = self.sink.publish(mapper, result) if self.sink is not None else 0
        observed = int(result.observed.sum()) if result is not None else 0
        self.stats.update(
            objects=objects, observed_gaussians=observed, publish_ms_last=1e3 * (time.perf_counter() - start)
        )
        self.stats.add(publishes=1)
        return result, objects

    def _save_enabled(self) -> bool:
        return bool(self.settings.map_directory) and self.settings.save_period_s > 0

    def _maybe_save(self) -> None:
        if not (self._save_enabled() and self._unsaved and self._mapper is not None):
            return
        if time.monotonic() < self._last_save + self.settings.save_period_s:
            return
        try:
            info = self.save(self.settings.map_directory)
            self.log.info(f"snapshot {info.path.name}: {info.keyframes} keyframes in {info.seconds:.2f} s")
        except Exception as exc:
            self._last_save = time.monotonic()  # retry one period later, not on every task
            self.stats.add(snapshot_errors=1)
            self.log.error(f"periodic snapshot to {self.settings.map_directory} failed: {exc}")

    def _guarded(self, fn: Callable[..., Any], *args: Any) -> None:
        try:
            fn(*args)
        except Exception as exc:
            self.stats.add(worker_errors=1)
            self.log.error(f"listener {getattr(fn, '__qualname__', fn)} failed: {type(exc).__name__}: {exc}")


def _resolved(directory: str) -> Path | None:
    return Path(directory).resolve() if directory else None


class _PrintLogger:
    def info(self, msg: str) -> None:
        print(msg)

    def warning(self, msg: str) -> None:
        print("WARNING:", msg)

    def error(self, msg: str) -> None:
        print("ERROR:", msg)
