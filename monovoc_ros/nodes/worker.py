"""The mapping worker: one thread and one task queue around the MappingSession (monovoc_ros.core.session),
which owns the SemanticMapper and the rules of its life; the worker applies every state change in order.

Subscription and service callbacks never touch the mapper; they put tasks into one queue:

* keyframes: bounded (`queue_size`); when full, the OLDEST waiting keyframe is dropped and counted.
  The session keeps keyframes that come before any Gaussian map (the newest `queue_size` of them) until
  one arrives; tasks behind them still run.
* Gaussian maps from the SLAM front-end: never dropped; a map that directly follows another pending map
  replaces it (only the newest of consecutive updates matters: no keyframe lies between them). Its update's
  registration and evidence sources (~90% of an update without ids) are prepared at once on a planning
  thread against the map queued before it (`MappingSession.plan_map`; the registration already done by the map
  reader process when it was of that map: `GivenMotion`), while the worker integrates the keyframes ahead of it;
  when its turn comes the worker applies the plan if that map is the one in use
  (else the session computes the update itself: the same function, the same result). The keyframes stamped within
  `map_update_ahead_s` after a map do not wait for its plan: once the registration has the map's motion (about half
  of the plan) they go into the map in use, their poses taken back by that motion, and the update is applied
  before the first keyframe stamped later, before any other task, or once the worker has had no task for that
  long and the plan is ready (core.follow.map_ahead: the same rule as offline mapping's). The session
  skips unchanged maps and refuses (and counts) a map without Gaussians or one removing more than
  `map_update_max_shrink` of them: one empty cloud must not wipe the map.
* calls (services, plugins): never dropped; run in arrival order with the rest, results via a Future.
  `load` reads and checks everything (the snapshot, then each load check such as objects.db) before it
  swaps anything in, so a failed load changes nothing.

Between tasks the worker publishes the semantic result (at most every `publish_period_s` while something
changed; period 0 = as soon as nothing runnable is queued, and every BUSY_PUBLISH_PERIOD_S while something
is, or less often when publishing would take more than BUSY_PUBLISH_SHARE of the worker) and saves periodic
snapshots of new evidence.
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
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, CancelledError, Future, ThreadPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from monovoc_ros.core.follow.keyframe_log import KeyframePoses
from monovoc_ros.core.follow.map_ahead import DEFAULT_AHEAD_S, MapAhead
from monovoc_ros.core.follow.map_updater import GivenMotion, MapUpdatePlan
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.gaussians import GaussianMap, same_geometry
from monovoc_ros.core.map_store import SnapshotInfo, write_snapshot
from monovoc_ros.core.mapping import MapperConfig, SemanticMapper, SemanticResult
from monovoc_ros.core.session import (
    DEFAULT_MAX_SHRINK,
    KeyframeListener,
    LoadCheck,
    Logger,
    MappingSession,
    SaveListener,
)
from monovoc_ros.nodes.diagnostics import MapperStats

ResultListener = Callable[[SemanticMapper, SemanticResult], None]


@dataclass(frozen=True)
class Preparation:
    """A map update being prepared beside the worker (MappingSession.plan_map)."""

    plan: Future  # its MapUpdatePlan (None: nothing to prepare)
    motion: Future  # the map's MapMotion as soon as the registration has it (None: refused or none)


# (base, gaussians) -> the update being prepared, or None (TaskQueue.put_map).
MapPreparer = Callable[[GaussianMap | None, GaussianMap], Preparation | None]
# With publish_period_s 0 (publish as soon as nothing runnable is queued), a worker that never runs out of work
# still publishes this often (s): a robot outrunning the mapper sees its map grow, late, rather than never
# (the robot-scale bench's 2M run published no cloud at all). Less often when a publication takes more than
# BUSY_PUBLISH_SHARE of that time (at 1M Gaussians one took ~0.35 s: the work it is behind with comes first).
BUSY_PUBLISH_PERIOD_S = 1.0
BUSY_PUBLISH_SHARE = 0.2
# While keyframes wait, a re-integration in progress advances one step (one logged keyframe, about a live
# keyframe's cost) per this many live keyframes integrated: the robot's newest evidence comes first. At 2M
# Gaussians every map update of the robot-scale bench bent the map past REINTEGRATE_BEND_M, and a step after
# every keyframe took 36-40% of the worker, the same rebuild restarted or followed map after map. When nothing
# waits it steps at full speed.
KEYFRAMES_PER_REINTEGRATION_STEP = 3
# How often an idle worker looks whether the map update keyframes went ahead of is due (s): its plan ready and no
# task for `map_update_ahead_s` since the last one ended.
_AHEAD_POLL_S = 0.05
# How often an idle worker looks whether the snapshot being written is done (s).
_SNAPSHOT_POLL_S = 0.1
# How long `stop` waits for the task in progress beyond its drain bound (a keyframe takes ~0.1 s).
STOP_GRACE_S = 1.0
# What `stop` expects the final snapshot (its files and its save listeners: objects.db) to take at least: a base,
# a share per million Gaussians and one per MB of keyframes deferred with it (mask and RGB). Measured on a 2-core
# machine with two busy processes beside the node: 0.62 s for the bundled bag's 140k Gaussians with 5 keyframes
# of 0.71 MB deferred, 0.97 s with 30 (objects.db 0.36 s of each); the files alone 0.3-0.5 s at 1-2M (issue 25).
SAVE_S_BASE = 0.5
SAVE_S_PER_MILLION = 0.4
SAVE_S_PER_DEFERRED_MB = 0.02
# The estimate is multiplied by this: a snapshot written under load takes longer than the one timed before.
SAVE_S_MARGIN = 1.5


# The MapperStats field that a task's worker time is added to.
_ACTIVITY = {"keyframe": "worker_s_keyframes", "map": "worker_s_map_updates", "call": "worker_s_calls"}


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
    map_update_max_shrink: float = DEFAULT_MAX_SHRINK
    # Seconds of stamps after a map update whose keyframes go into the map in use while its plan is made, their poses
    # taken back by its motion (core.follow.map_ahead); 0 = they wait for its plan.
    map_update_ahead_s: float = DEFAULT_AHEAD_S


@dataclass
class _Task:
    kind: str  # "keyframe" | "map" | "call"
    payload: Any
    future: Future | None = None  # a call's result
    name: str = ""
    base: GaussianMap | None = None  # a map's: the map queued before it (None: none since the start)
    plan: Future | None = None  # a map's: its update prepared beside the worker (MappingSession.plan_map)
    motion: Future | None = None  # a map's: the motion of that update, known before the plan (Preparation)


@dataclass
class _Ahead:
    """A map update whose later keyframes go into the map in use (core.follow.map_ahead) until it is applied."""

    task: _Task
    ahead: MapAhead

    def due(self, task: _Task | None, idle_s: float, window_s: float) -> bool:
        """Whether to apply it before `task`: before any task but a keyframe, before a keyframe stamped at or after
        the window's end; with no task (`idle_s` since the last one), once that lasted the window and its plan is
        ready."""
        if task is None:
            return idle_s >= window_s and self.task.plan.done()
        return self.ahead.applies_before(task.payload if task.kind == "keyframe" else None)


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
        self._newest_map: GaussianMap | None = None  # the map in use once every queued map is applied

    @property
    def keyframes(self) -> int:
        return self._keyframes

    def __len__(self) -> int:
        return len(self._tasks)

    def put_keyframe(self, keyframe: Keyframe, bounded: bool = True) -> Keyframe | None:
        """Queues a keyframe; returns the keyframe dropped to make room, if any (none when not `bounded`:
        keyframes a previous run deferred, which must not push each other out)."""
        dropped = None
        with self._cond:
            if bounded and self._keyframes >= self.max_keyframes:
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

    def put_map(self, gaussians: GaussianMap, name: str = "", prepare: MapPreparer | None = None) -> bool:
        """Queues a map; returns True when it replaced a pending map queued right before it. `prepare(base,
        gaussians)` starts preparing the update from `base`, the map that will be in use when this one's turn
        comes if every map queued before it is taken (None: no map was queued since the start)."""
        with self._cond:
            coalesced = bool(self._tasks) and self._tasks[-1].kind == "map"
            base = self._newest_map
            if coalesced:
                replaced = self._tasks.pop()
                base = replaced.base
                if replaced.plan is not None:
                    replaced.plan.cancel()
            prepared = prepare(base, gaussians) if prepare is not None else None
            plan, motion = (prepared.plan, prepared.motion) if prepared is not None else (None, None)
            self._tasks.append(_Task("map", gaussians, name=name, base=base, plan=plan, motion=motion))
            self._newest_map = gaussians
            self._cond.notify()
        # The same map again is skipped by the session: the one before it stays in use. Compared outside the
        # lock (milliseconds at 1M Gaussians) so the worker's `take` never waits for it.
        if base is not None and same_geometry(base, gaussians):
            with self._cond:
                if self._newest_map is gaussians:
                    self._newest_map = base
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

    def take(self, timeout: float | None) -> _Task | None:
        """The oldest task, waiting up to `timeout` s (None: until one comes or the queue closes)."""
        deadline = None if timeout is None else time.monotonic() + max(timeout, 0.0)
        with self._cond:
            while not self._closed:
                if self._tasks:
                    task = self._tasks.popleft()
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

    def drain(self) -> list[_Task]:
        with self._cond:
            tasks = list(self._tasks)
            self._tasks.clear()
            self._keyframes = 0
            return tasks


class MapWorker:
    """A thread and a task queue around a MappingSession; see the module docstring. Start with `start()`,
    end with `stop()`."""

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
        self.settings = settings
        self.stats = stats or MapperStats()
        self.sink = sink
        self.log: Logger = log or _PrintLogger()
        self.queue = TaskQueue(settings.queue_size)
        self.session = MappingSession(
            config,
            max_shrink=settings.map_update_max_shrink,
            ahead_s=settings.map_update_ahead_s,
            max_waiting=settings.queue_size,
            stats=self.stats,
            log=self.log,
            mapper=mapper,
            on_listener_error=self._listener_failed,
        )
        self._result_listeners: list[ResultListener] = []
        self._thread: threading.Thread | None = None
        # Map updates are prepared here, beside the worker (numba kernels and numpy release the interpreter).
        self._planner = ThreadPoolExecutor(max_workers=1, thread_name_prefix="monovoc-map-plan")
        # Periodic snapshots are written here, one at a time (`_maybe_save`).
        self._writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="monovoc-snapshot")
        self._writing: Future | None = None
        self._output_dirty = True  # publish once at start (the map, or an empty one)
        self._unsaved = False  # evidence that no snapshot in map_directory holds yet
        self._last_publish = -float("inf")
        self._publish_s = 0.0  # the last publication's time
        self._published_s = 0.0  # every publication's time, summed (a task's time leaves out those within it)
        self._keyframes_since_step = 0  # live keyframes integrated since the last re-integration step
        self._ahead: _Ahead | None = None  # a map update later keyframes go ahead of (map_update_ahead_s)
        self._last_task = time.monotonic()  # when the worker last finished a task
        # Whether the worker is on a task (from taking it to the publications and saves after it): background
        # components defer their heavy work meanwhile (`busy`).
        self.working = False
        self._last_save = time.monotonic()
        # The last snapshot's time, save listeners included, and its map's size (stop's estimate).
        self._save_timed: tuple[float, int] | None = None
        self._capture_s = 0.0  # the periodic snapshot being written: its capture's time
        self._listener_work: list[Future] = []  # the last periodic snapshot's save listeners' work beside the worker

    # ------------------------------------------------------------------ public API (any thread)

    @property
    def mapper(self) -> SemanticMapper | None:
        """The current mapper. Read or change it only on the worker thread (listeners, `submit`)."""
        return self.session.mapper

    def busy(self) -> bool:
        """Keyframes wait, or the worker is on a task (any thread): when background work should wait."""
        return self.working or self.keyframes_waiting > 0

    @property
    def keyframes_waiting(self) -> int:
        """Keyframes not integrated yet: queued, or held by the session until there is a map (any thread:
        both are lengths of containers only the worker thread and the queue lock change)."""
        return self.queue.keyframes + self.session.waiting

    def add_keyframe_listener(self, fn: KeyframeListener) -> None:
        self.session.add_keyframe_listener(fn)

    def add_result_listener(self, fn: ResultListener) -> None:
        self._result_listeners.append(fn)

    def add_reset_listener(self, fn: Callable[[], None]) -> None:
        """fn() runs on the worker thread after a reset (the node clears its keyframe assembler)."""
        self.session.add_reset_listener(fn)

    def add_save_listener(self, fn: SaveListener) -> None:
        """fn(directory, info, mapper) runs on the worker thread after every snapshot (service, periodic, final):
        a periodic one is written beside the worker, and `mapper` may hold keyframes integrated meanwhile, but
        never another map (map updates, re-integration swaps, resets and loads wait for the write). fn may return
        a Future of work it goes on with beside the worker (objects.db's images and writes): save_map's snapshot
        and the final one wait for it, a periodic one does not (fn orders its own work)."""
        self.session.add_save_listener(fn)

    def add_load_check(self, fn: LoadCheck) -> None:
        """See MappingSession.add_load_check; runs on the worker thread."""
        self.session.add_load_check(fn)

    def submit_keyframe(self, keyframe: Keyframe, bounded: bool = True) -> Keyframe | None:
        """Queues a keyframe; returns the one dropped to make room (already counted), if any (see
        TaskQueue.put_keyframe for `bounded`)."""
        dropped = self.queue.put_keyframe(keyframe, bounded)
        if dropped is not None:
            self.stats.add(keyframes_dropped=1)
        self.stats.update(queue_length=self.keyframes_waiting)
        return dropped

    def submit_map(self, gaussians: GaussianMap, name: str = "", given: GivenMotion | None = None) -> None:
        """Queues a map; its update (registration, the evidence's sources) is prepared at once on the planning
        thread, so that the worker only applies it when its turn comes. `given`: its motion estimated elsewhere
        (the map reader process), taken by the plan when it is of the map it prepares the update from."""
        if self.queue.put_map(gaussians, name, lambda base, new: self._prepare_map(base, new, given)):
            self.stats.add(maps_coalesced=1)

    def _prepare_map(
        self, base: GaussianMap | None, gaussians: GaussianMap, given: GivenMotion | None
    ) -> Preparation | None:
        motion: Future = Future()

        def plan() -> MapUpdatePlan | None:
            start = time.perf_counter()
            try:
                return self.session.plan_map(base, gaussians, motion.set_result, given)
            finally:
                if not motion.done():  # nothing to prepare, or it failed
                    motion.set_result(None)
                self.stats.add(map_prepare_s=time.perf_counter() - start)

        try:
            return Preparation(self._planner.submit(plan), motion)
        except RuntimeError:  # stopping (a map decoded as the node shut down): the session computes it, if ever
            return None

    def _plan_of(self, task: _Task) -> MapUpdatePlan | None:
        """The plan prepared for a map task (waiting for it: the planning thread is ahead of the worker), or
        None (not prepared, cancelled, or failed: the session computes the update itself)."""
        if task.plan is None:
            return None
        mapper = self.session.mapper
        if task.base is not None and (mapper is None or task.base is not mapper.gaussians):
            task.plan.cancel()  # of a map not in use (refused, reset, loaded): no use waiting for it
            return None
        self._publish_before_waiting(task.plan)
        start = time.perf_counter()
        try:
            return task.plan.result()
        except CancelledError:
            return None
        except Exception as exc:  # the session's own computation raises it again where it is handled
            self.log.warning(f"map {task.name}: preparing its update failed ({type(exc).__name__}: {exc})")
            return None
        finally:
            self.stats.add(map_update_wait_s=time.perf_counter() - start)

    def submit_keyframe_poses(self, poses: KeyframePoses, name: str = "") -> Future:
        """Corrected keyframe poses, applied in order with keyframes and maps (core.session)."""
        return self.queue.put_call(lambda: self.session.add_keyframe_poses(poses, name), name)

    def submit(self, fn: Callable[[SemanticMapper | None], Any], name: str = "") -> Future:
        """Runs fn(mapper) on the worker thread, in order with keyframes and maps; its result in a Future."""
        return self.queue.put_call(lambda: fn(self.session.mapper), name)

    def call(self, fn: Callable[[], Any], name: str = "") -> Future:
        """Like `submit` for the worker's own operations (save, load, reset, publish_now)."""
        return self.queue.put_call(fn, name)

    def start(self) -> None:
        self._last_save = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="monovoc-mapper-worker", daemon=True)
        self._thread.start()

    def stop(self, *, final_snapshot: bool = True, within_s: float = 0.0) -> SnapshotInfo | None:
        """Stops the worker so that the final snapshot is written about `within_s` seconds from now (later only
        when the task in progress outlasts that, or the snapshot its estimate): queued keyframes are integrated
        while the snapshot's expected time (`save_estimate_s`) still fits, the rest deferred. Bounded: never
        waits for the task in progress on the worker thread longer than `within_s` plus STOP_GRACE_S (a map
        update at 2M takes ~1-2 s; without it there would be no final snapshot).

        Keyframes, maps and pose corrections queued are applied in order until the bound; keyframes left over
        are deferred: saved with the final snapshot (with a map directory) and integrated first on resume.
        Queued calls fail with WorkerStopped. Runs on the caller's thread once the worker has left its loop; a
        periodic snapshot still being written is finished first (0.5-0.9 s at 1-2M Gaussians), and counted.
        """
        start = time.monotonic()
        saving = bool(final_snapshot and self.settings.map_directory)

        def deadline(deferred_mb: float) -> float:  # recomputed as keyframes left to defer and timings change
            if not saving:
                return start + within_s
            writing = [self._writing, *self._listener_work]  # the worker thread may replace them meanwhile
            before = 2 if any(w is not None and not w.done() for w in writing) else 1  # finished before the final one
            return start + within_s - before * self.save_estimate_s(deferred_mb)

        self.queue.close()
        if self._thread is not None:
            self._thread.join(max(within_s, 0.0) + STOP_GRACE_S)  # a task in progress cannot be cut short
            if self._thread.is_alive():
                self.log.error(
                    f"shutdown: the worker is still busy after {time.monotonic() - start:.1f} s; no final snapshot "
                    f"({self.keyframes_waiting} keyframes not integrated since the last one)"
                )
                return None
        drained, deferred = self._drain(deadline)
        self._planner.shutdown(wait=False, cancel_futures=True)
        self._collect_snapshot(wait=True)
        self._writer.shutdown(wait=False)
        if drained or deferred:
            self.log.info(f"shutdown: integrated {drained} queued keyframes, deferred {len(deferred)}")
        if not (saving and self.session.mapper is not None):
            if deferred:
                why = "no map directory" if not self.settings.map_directory else "no map to save them with"
                self.log.warning(f"shutting down with {len(deferred)} keyframes not integrated ({why})")
            return None
        if not (self._unsaved or deferred):
            return None
        try:
            info = self.save(self.settings.map_directory, deferred)
            held = f", {len(deferred)} deferred to resume" if deferred else ""
            self.log.info(f"final snapshot: {info.path} ({info.keyframes} keyframes{held})")
            return info
        except Exception as exc:  # a full disk must not turn a clean shutdown into a crash
            self.log.error(f"final snapshot failed: {exc}")
        return None

    def save_estimate_s(self, deferred_mb: float = 0.0) -> float:
        """What `stop` expects the final snapshot with `deferred_mb` MB of keyframes to take (s), times
        SAVE_S_MARGIN: the last snapshot timed (scaled to a map grown since), never less than the guess from
        the sizes."""
        mapper = self.session.mapper
        n = 0 if mapper is None else len(mapper.gaussians)
        guess = SAVE_S_BASE + SAVE_S_PER_MILLION * n / 1e6 + SAVE_S_PER_DEFERRED_MB * deferred_mb
        if self._save_timed is not None:
            seconds, timed_n = self._save_timed
            guess = max(guess, seconds * max(1.0, n / max(timed_n, 1)))
        return SAVE_S_MARGIN * guess

    def _drain(self, deadline: Callable[[float], float]) -> tuple[int, list[Keyframe]]:
        """Applies the queued tasks in order until `deadline(MB of keyframes that stopping now would defer)`
        (on the caller's thread: the worker has left); returns (keyframes integrated, keyframes left over,
        oldest first, with any pose correction the session holds for them). After the deadline keyframes are
        kept, calls fail (WorkerStopped) and map updates are dropped (the SLAM sends its map again); a first
        map is still applied, or nothing could be saved."""
        integrated, late = 0, []

        def guarded(step: Callable[[], Any]) -> Any:
            try:
                return step()
            except Exception as exc:  # a stop must end in the final snapshot whatever one task does
                self.stats.add(worker_errors=1)
                self.log.error(f"shutdown: {type(exc).__name__}: {exc}\n{traceback.format_exc()}")
                return None

        longest = 0.0  # the longest keyframe so far: one is only started when one as long still fits
        queued = 0  # keyframe tasks taken from the queue and not handled yet
        mb = 0.0  # a keyframe's mask and RGB (MB)

        def left() -> float:
            return (self.session.waiting + queued + len(late)) * mb

        def integrate_ready() -> None:
            nonlocal integrated, longest
            while self.session.keyframes_ready and time.monotonic() + longest < deadline(left()):
                start = time.monotonic()
                if guarded(self.session.integrate_next) is not None:
                    integrated += 1
                    self._changed()
                longest = max(longest, time.monotonic() - start)

        def settle_ahead(drop: bool) -> None:
            """The map update keyframes went ahead of is applied while the deadline allows (the keyframes the session
            holds, posed in the map in use, first); else queued keyframes keep being taken back into the map in use
            until it is dropped as a queued map would be (the SLAM sends its map again)."""
            if self._ahead is None:
                return
            integrate_ready()
            if not self.session.keyframes_ready and time.monotonic() < deadline(left()):
                self._apply_ahead()
            if drop:
                self._ahead = None

        settle_ahead(drop=False)
        # Twice: an input callback still running when the queue closed may have put one more task.
        for _ in range(2):
            tasks = self.queue.drain()
            keyframes = [task.payload for task in tasks if task.kind == "keyframe"]
            queued, mb = len(keyframes), max([mb, *(_megabytes(k) for k in keyframes[:1])])
            for task in tasks:
                integrate_ready()  # the session's keyframes are older than any queued task, as in _run
                if task.kind != "keyframe":
                    settle_ahead(drop=True)  # only keyframes go ahead of it, as in _run
                if time.monotonic() < deadline(left()) or (task.kind == "map" and self.session.mapper is None):
                    guarded(lambda task=task: self._execute(task))
                elif task.kind == "keyframe":
                    late.append(task.payload)
                elif task.future is not None and task.future.set_running_or_notify_cancel():
                    task.future.set_exception(WorkerStopped(f"{task.name or 'call'}: the node is shutting down"))
                queued -= task.kind == "keyframe"
            integrate_ready()
        settle_ahead(drop=True)
        return integrated, self.session.take_waiting(late)

    # ------------------------------------------------------------------ operations (worker thread)

    def save(self, directory: str, deferred: Sequence[Keyframe] = ()) -> SnapshotInfo:
        self._collect_snapshot(wait=True)  # one writer at a time: snapshot numbers and CURRENT stay in order
        start = time.perf_counter()
        info = self.session.save(directory, deferred)
        self._timed_save(time.perf_counter() - start)
        if Path(directory).resolve() == _resolved(self.settings.map_directory):
            self._unsaved = False
            self._last_save = time.monotonic()
        return info

    def load(self, path: str) -> SemanticMapper:
        """MappingSession.load; a failed load changes nothing."""
        self._collect_snapshot(wait=True)  # the directory may be the one being written
        mapper = self.session.load(path)
        self._changed(unsaved=Path(path).resolve() != _resolved(self.settings.map_directory))
        return mapper

    def reset(self, keep_gaussians: bool) -> None:
        self._collect_snapshot(wait=True)
        self.session.reset(keep_gaussians)
        self._changed(unsaved=self.session.mapper is not None)

    def publish_now(self) -> tuple[SemanticResult | None, int]:
        """Recomputes and publishes the result now; returns it and the number of objects."""
        return self._publish()

    def objects_now(self) -> int:
        mapper = self.session.mapper
        if mapper is None:
            return 0
        return len(mapper.result().objects(mapper.gaussians).objects)

    # ------------------------------------------------------------------ the loop

    def _run(self) -> None:
        while not self.queue.closed:
            # Keyframes the session holds are older than anything queued: they go first.
            ready = self.session.keyframes_ready
            # A re-integration in progress advances between tasks: the queue is only polled meanwhile; a map update
            # keyframes went ahead of is looked at every _AHEAD_POLL_S (whether it is due while idle).
            if self.session.reintegrating:
                timeout = 0.0
            else:
                timeout = self._wait_time()
                if self._ahead is not None:
                    timeout = _AHEAD_POLL_S if timeout is None else min(timeout, _AHEAD_POLL_S)
            self.working = False
            task = None if ready else self.queue.take(timeout)
            if task is None and self.queue.closed:
                return
            self.working = True
            idle_s = time.monotonic() - self._last_task
            try:
                # Applied when due (`_Ahead.due`: only keyframes go ahead of it), but never while the session holds
                # keyframes: they are posed in the map in use. When idle, what the keyframes integrated ahead
                # changed is published first if a publication is due.
                ahead = self._ahead
                if ahead is not None and not ready and ahead.due(task, idle_s, self.settings.map_update_ahead_s):
                    if task is None:
                        self._maybe_publish()
                    self._apply_ahead()
                start = time.perf_counter()
                if ready:
                    if self.session.integrate_next() is not None:
                        self._changed()
                        self._keyframes_since_step += 1
                    self.stats.add(worker_s_keyframes=time.perf_counter() - start)
                elif task is not None:
                    published = self._published_s
                    self._execute(task)
                    self.stats.add(**{_ACTIVITY[task.kind]: self._task_seconds(start, published)})
                if ready or task is not None:
                    self._last_task = time.monotonic()
                if self.session.reintegrating and (
                    self.keyframes_waiting == 0 or self._keyframes_since_step >= KEYFRAMES_PER_REINTEGRATION_STEP
                ):
                    if self.session.reintegration_swaps_next:
                        self._collect_snapshot(wait=True)
                    start = time.perf_counter()
                    self._keyframes_since_step = 0
                    if not self.session.reintegration_step():
                        self._changed()  # the re-integrated state was swapped in
                    self.stats.add(worker_s_reintegration=time.perf_counter() - start, reintegration_steps=1)
                self.stats.update(queue_length=self.keyframes_waiting)
                self._maybe_publish()
                self._maybe_save()
            except Exception as exc:  # the worker must outlive any single bad task or listener
                self.stats.add(worker_errors=1)
                self.log.error(f"worker: {type(exc).__name__}: {exc}\n{traceback.format_exc()}")

    def _execute(self, task: _Task) -> None:
        if task.kind == "keyframe":
            keyframe = task.payload if self._ahead is None else self._ahead.ahead.posed(task.payload)
            self.session.add_keyframe(keyframe)
        elif task.kind == "map":
            if not self._start_ahead(task):
                self._apply_map(task)
        else:
            assert task.future is not None
            if not task.future.set_running_or_notify_cancel():
                return
            try:
                task.future.set_result(task.payload())
            except Exception as exc:
                task.future.set_exception(exc)

    def _apply_map(self, task: _Task, taken_back: frozenset[int] = frozenset()) -> None:
        self._collect_snapshot(wait=True)  # its save listeners see the map it was captured from
        if self.session.add_map(task.payload, task.name, self._plan_of(task), taken_back):
            self._changed()

    def _start_ahead(self, task: _Task) -> bool:
        """When the keyframes after this map update may go ahead of it (`MappingSession.ahead_until`): waits for its
        motion only and lets them into the map in use (core.follow.map_ahead); the update is applied, moving their
        logged poses with the map, when `_Ahead.due` says. Not for a map not prepared beside the worker, nor while
        stopping (`_drain` applies maps in line, within its deadline)."""
        mapper = self.session.mapper
        until = self.session.ahead_until(task.payload)
        if (
            until is None
            or task.plan is None
            or task.motion is None
            or mapper is None
            or task.base is not mapper.gaussians
            or self.queue.closed
        ):
            return False
        self._publish_before_waiting(task.motion)
        start = time.perf_counter()
        wait([task.motion, task.plan], return_when=FIRST_COMPLETED)
        self.stats.add(map_update_wait_s=time.perf_counter() - start)
        motion = task.motion.result() if task.motion.done() else None
        if motion is None:  # cancelled, refused, or nothing to prepare: `_apply_map` says why
            return False
        self._ahead = _Ahead(task, self.session.start_ahead(task.payload, motion, until))
        return True

    def _apply_ahead(self) -> None:
        """Applies the map update keyframes went ahead of, if any; a failure is logged and counted, never lets it stand
        in the way of the task behind it."""
        ahead, self._ahead = self._ahead, None
        if ahead is None:
            return
        start, published = time.perf_counter(), self._published_s
        try:
            self._apply_map(ahead.task, frozenset(ahead.ahead.taken_back))
        except Exception as exc:
            self.stats.add(worker_errors=1)
            self.log.error(f"map {ahead.task.name}: {type(exc).__name__}: {exc}\n{traceback.format_exc()}")
        self.stats.add(worker_s_map_updates=self._task_seconds(start, published))

    def _task_seconds(self, start: float, published: float) -> float:
        """A task's worker time since `start` (perf_counter), less the publications made within it (`_published_s`
        was `published` at `start`): they count as publication."""
        return time.perf_counter() - start - (self._published_s - published)

    def _publish_before_waiting(self, pending: Future) -> None:
        """The worker is about to wait for `pending` (a map update's plan or motion, computed beside it): what
        changed is published meanwhile when a publication is due (the keyframes integrated right before a map get
        their cloud ~0.3-0.8 s sooner at 1M Gaussians); with publish_period_s 0 even while tasks wait, unlike
        between tasks: the worker would only wait. Not while stopping."""
        if pending.done() or not self._output_dirty or self.queue.closed:
            return
        if time.monotonic() >= self._last_publish + self.settings.publish_period_s:
            self._publish()

    def _changed(self, unsaved: bool = True) -> None:
        self._output_dirty = True
        self._unsaved = self._unsaved or unsaved

    # ------------------------------------------------------------------ publishing and saving

    def _wait_time(self) -> float | None:
        now = time.monotonic()
        waits = []
        if self._output_dirty:
            period = self.settings.publish_period_s
            waits.append(0.0 if period == 0 else self._last_publish + period - now)
        if self._save_enabled() and self._unsaved:
            waits.append(self._last_save + self.settings.save_period_s - now)
        if self._writing is not None:
            waits.append(_SNAPSHOT_POLL_S)  # to finish it soon after it is written
        return max(min(waits), 0.0) if waits else None

    def _maybe_publish(self) -> None:
        if not self._output_dirty:
            return
        period = self.settings.publish_period_s
        if period == 0:
            busy = self.session.keyframes_ready or len(self.queue)
            wait = max(BUSY_PUBLISH_PERIOD_S, self._publish_s / BUSY_PUBLISH_SHARE)
            if busy and time.monotonic() < self._last_publish + wait:
                return
        elif time.monotonic() < self._last_publish + period:
            return
        self._publish()

    def _publish(self) -> tuple[SemanticResult | None, int]:
        start = time.perf_counter()
        self._output_dirty = False
        self._last_publish = time.monotonic()
        mapper = self.session.mapper
        result = mapper.result() if mapper is not None else None
        labelled = time.perf_counter()
        computed = result is None or result.objects_seconds is not None
        # Outputs first: the worker computes (and caches on the result) the object geometry before a
        # listener's thread, possibly of lower priority, asks the result for it and holds its lock.
        objects = self.sink.publish(mapper, result) if self.sink is not None else 0
        geometry_s = 0.0 if computed else (result.objects_seconds or 0.0)
        if mapper is not None and result is not None:
            for fn in self._result_listeners:
                try:
                    fn(mapper, result)
                except Exception as exc:
                    self._listener_failed(fn, exc)
        observed = int(result.observed.sum()) if result is not None else 0
        end = time.perf_counter()
        self._publish_s = end - start
        self._published_s += end - start
        self.stats.update(objects=objects, observed_gaussians=observed, publish_ms_last=1e3 * (end - start))
        self.stats.add(
            publishes=1,
            worker_s_labels=labelled - start,
            worker_s_objects=geometry_s,
            worker_s_publish=end - labelled - geometry_s,
        )
        return result, objects

    def _save_enabled(self) -> bool:
        return bool(self.settings.map_directory) and self.settings.save_period_s > 0

    def _maybe_save(self) -> None:
        """A periodic snapshot: captured here, written on the snapshot thread (its files, fsyncs and semantic.ply
        take most of it: ~0.5 s at 1M Gaussians), finished here when written (`_collect_snapshot`)."""
        self._collect_snapshot()
        if self._writing is not None or self._ahead is not None:  # a snapshot holds applied map updates only
            return
        if not (self._save_enabled() and self._unsaved and self.session.mapper is not None):
            return
        if time.monotonic() < self._last_save + self.settings.save_period_s:
            return
        directory = self.settings.map_directory
        start = time.perf_counter()
        try:
            content = self.session.capture()
        except Exception as exc:
            self._snapshot_failed(directory, exc)
            return
        self._writing = self._writer.submit(write_snapshot, content, directory)
        self._unsaved, self._last_save = False, time.monotonic()
        self._capture_s = time.perf_counter() - start
        self.stats.add(worker_s_snapshots=self._capture_s)

    def _collect_snapshot(self, wait: bool = False) -> None:
        """Finishes the periodic snapshot being written once it is (wait: waits for it): counted and the save
        listeners told, on this thread; a failed one is logged and its evidence saved again a period later."""
        future = self._writing
        if future is None or not (wait or future.done()):
            return
        self._writing = None
        directory = self.settings.map_directory
        start = time.perf_counter()
        try:
            info = future.result()
        except Exception as exc:
            self._unsaved = True  # what it captured is in no snapshot
            self._snapshot_failed(directory, exc)
            return
        self.stats.add(worker_s_snapshots=time.perf_counter() - start)
        start = time.perf_counter()  # the write is info.seconds, waited for or not
        going_on = self.session.saved(directory, info)
        told = time.perf_counter() - start
        # What the same snapshot would take in one go (the final one waits for its listeners' work).
        in_one_go = self._capture_s + info.seconds + told
        n = self._timed_save(in_one_go)
        self._listener_work = going_on

        def done(_: Future, before: float = in_one_go - told) -> None:  # on the listener's thread
            if self._listener_work is going_on:  # not a snapshot's before it (n: the size this one captured)
                self._save_timed = (before + time.perf_counter() - start, n)

        for future in going_on:  # done in order of their ends: the last one counts
            future.add_done_callback(done)
        self.stats.add(worker_s_snapshots=told)
        self.log.info(f"snapshot {info.path.name}: {info.keyframes} keyframes, written in {info.seconds:.2f} s")

    def _timed_save(self, seconds: float) -> int:
        """Records a snapshot's time with its map's size (returned)."""
        mapper = self.session.mapper
        self._save_timed = (seconds, 0 if mapper is None else len(mapper.gaussians))
        return self._save_timed[1]

    def _snapshot_failed(self, directory: str, exc: Exception) -> None:
        self._last_save = time.monotonic()  # retry one period later, not on every task
        self.stats.add(snapshot_errors=1)
        self.log.error(f"periodic snapshot to {directory} failed: {exc}")

    def _listener_failed(self, fn: Callable[..., Any], exc: Exception) -> None:
        self.stats.add(worker_errors=1)
        self.log.error(f"listener {getattr(fn, '__qualname__', fn)} failed: {type(exc).__name__}: {exc}")


class CoalescedCall:
    """`fn()` queued on a worker's thread by any thread, at most once at a time: a request made while one is
    queued joins it (it has not run yet, so it will see what changed). `on_done(future)`: each run's outcome."""

    def __init__(self, worker: MapWorker, fn: Callable[[], Any], name: str, on_done: Callable[[Future], None]):
        self._worker = worker
        self._fn = fn
        self._name = name
        self._on_done = on_done
        self._lock = threading.Lock()
        self._queued = False

    def __call__(self) -> None:
        with self._lock:
            if self._queued:
                return
            self._queued = True
        self._worker.call(self._run, self._name).add_done_callback(self._on_done)

    def _run(self) -> Any:
        with self._lock:
            self._queued = False  # requests from here on need another run
        return self._fn()


def _megabytes(keyframe: Keyframe) -> float:
    return (keyframe.mask.nbytes + (0 if keyframe.rgb is None else keyframe.rgb.nbytes)) / 1e6


def _resolved(directory: str) -> Path | None:
    return Path(directory).resolve() if directory else None


class _PrintLogger:
    def info(self, msg: str) -> None:
        print(msg)

    def warning(self, msg: str) -> None:
        print("WARNING:", msg)

    def error(self, msg: str) -> None:
        print("ERROR:", msg)
