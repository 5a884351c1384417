"""The mapper's life, one path for the live node and offline mapping (no ROS, no threads).

A `MappingSession` owns the SemanticMapper and applies, in the order they are given, everything that
changes it:

* keyframes: queued in the session; they wait while there is no Gaussian map (the newest `max_waiting`
  kept, older ones dropped and counted) and are integrated one at a time with `integrate_next` once
  there is one. A stamp already in the map is refused (duplicate_stamp), as is a keyframe the
  rasterizer refuses (integration_error); both leave the state untouched.
* Gaussian maps from the SLAM front-end: the first creates the mapper; a later one is a map update,
  skipped when it is the same map again (core.map.gaussians.same_geometry). What a map update and
  corrected keyframe poses do (refusals, the evidence carried over, the logged poses, re-integration) is
  the MapUpdater's (core.follow.map_updater); the session applies them in order and swaps a finished
  re-integration in.
* reset, save and load, with their listeners and load checks.

The live worker (monovoc_ros.nodes.worker) is a thread and a task queue around a session, offline
mapping (monovoc_ros.offline) a loop around one: the same events give the same evidence and the same
`SessionStats`, which both extend with counters of their own (transport, timing).
"""

from __future__ import annotations

import threading
from collections import Counter, deque
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from monovoc_ros.core.follow.keyframe_log import KeyframePoses
from monovoc_ros.core.follow.map_ahead import DEFAULT_AHEAD_S, MAX_AHEAD_S, MapAhead
from monovoc_ros.core.follow.map_frames import update_stamp
from monovoc_ros.core.follow.map_motion import MapMotion
from monovoc_ros.core.follow.map_updater import (
    GivenMotion,
    MapMotionError,
    MapUpdatePlan,
    MapUpdater,
    checked_poses,
    plan_map_update,
    pose_mover,
)
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.gaussians import GaussianMap, same_geometry
from monovoc_ros.core.map.ply import load_ply
from monovoc_ros.core.map_store import (
    SnapshotContent,
    SnapshotInfo,
    capture_snapshot,
    load_snapshot,
    save_snapshot,
)
from monovoc_ros.core.mapping import DuplicateKeyframeError, IntegrationReport, MapperConfig, SemanticMapper

# A map update removing a larger share of the Gaussians is refused; 1.0 allows every update.
DEFAULT_MAX_SHRINK = 0.5
# Rejections the session counts (SessionStats.rejected), beside those of message ingest:
#   duplicate_stamp     a keyframe whose stamp is already in the state (e.g. replayed after a resume)
#   integration_error   the rasterizer refused a keyframe (state untouched)
#   empty_gaussians     a Gaussian map without a single Gaussian (the map in use is kept)
#   map_shrink          a map update that would remove more than max_shrink of the Gaussians
#   map_motion          a map update whose estimated motion is not believable (core.follow.map_updater)
#   bad_keyframe_poses  corrected keyframe poses that are not rigid, not finite, or move a keyframe > 10 m
#   reintegration_incomplete_log  a re-integration skipped: the keyframe log lacks some integrated keyframes
SESSION_REASONS = (
    "duplicate_stamp", "integration_error", "empty_gaussians", "map_shrink", "map_motion", "bad_keyframe_poses",
    "reintegration_incomplete_log",
)  # fmt: skip

KeyframeListener = Callable[[Keyframe, SemanticMapper], None]
LoadCheck = Callable[[str, SemanticMapper], "Callable[[], None] | None"]
# May return a Future of work it goes on with beside the caller (objects.db's images and writes): see `saved`.
SaveListener = Callable[[str, SnapshotInfo, SemanticMapper], Future | None]
ListenerErrorHandler = Callable[[Callable[..., Any], Exception], None]


class Logger(Protocol):
    def info(self, msg: str) -> Any: ...
    def warning(self, msg: str) -> Any: ...
    def error(self, msg: str) -> Any: ...


@dataclass
class SessionStats:
    """Counters of the mapper's life. Thread-safe: a live node reads them from its diagnostics timer."""

    keyframes_processed: int = 0  # integrated into the semantic state
    keyframes_dropped: int = 0  # dropped for room (oldest first): waiting without a map, or a full queue
    ms_per_keyframe_last: float = 0.0  # integration time
    ms_per_keyframe_total: float = 0.0
    gaussians: int = 0
    has_map: bool = False
    map_version: int = 0
    map_updates: int = 0  # map updates applied (core.follow.map_updater)
    map_updates_prepared: int = 0  # of them, applied with a plan prepared beforehand (`plan_map`)
    map_motions_given: int = 0  # of those, with a motion estimated elsewhere (live: the map reader process)
    map_updates_ahead: int = 0  # map updates later keyframes went ahead of into the map in use, counted as they start
    # Keyframes integrated before the map they were posed in (stamped at or before them) reached the mapper: that
    # map's update left their logged poses; and keyframes posed in a map older than the one in use, moved into it
    # before they were integrated (core.follow.map_frames).
    keyframes_before_their_map: int = 0
    keyframes_moved_into_map: int = 0
    maps_unchanged: int = 0  # maps identical to the current one (skipped)
    map_update_carried_share: float = 1.0  # last map update: share of labelled Gaussians whose evidence was carried
    ms_map_update_last: float = 0.0  # the last map update's time (registration, transfer; when prepared: the rest)
    reintegrations: int = 0  # re-integrations swapped in
    keyframes_reintegrated: int = 0
    ms_reintegration_total: float = 0.0  # summed over the re-integrations swapped in
    reintegrating: bool = False  # one is in progress (the old labels are served meanwhile)
    keyframe_log_bytes: int = 0
    keyframe_log_keyframes: int = 0
    snapshots_saved: int = 0
    last_stamp_ns: int = 0  # newest integrated keyframe
    rejected: Counter = field(default_factory=Counter)  # reason -> count
    lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def update(self, **values: Any) -> None:
        with self.lock:
            for key, value in values.items():
                setattr(self, key, value)

    def add(self, **increments: float) -> None:
        with self.lock:
            for key, value in increments.items():
                setattr(self, key, getattr(self, key) + value)

    def reject(self, reason: str, count: int = 1) -> None:
        with self.lock:
            self.rejected[reason] += count

    def snapshot(self) -> dict[str, Any]:
        """A consistent copy of every counter (plus the derived mean time per keyframe)."""
        with self.lock:
            out = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in ("lock", "rejected")}
            out["rejected"] = dict(self.rejected)
        processed = out["keyframes_processed"]
        out["ms_per_keyframe_mean"] = out.pop("ms_per_keyframe_total") / processed if processed else 0.0
        return out


class MappingSession:
    """Owns the SemanticMapper; see the module docstring. Not thread-safe: one caller applies everything.

    `on_listener_error(fn, exc)`: a failing listener is reported there and the session goes on (the live
    worker must outlive a bad listener); None lets the exception propagate (offline mapping fails loudly).
    """

    def __init__(
        self,
        config: MapperConfig | None = None,
        *,
        max_shrink: float = DEFAULT_MAX_SHRINK,
        ahead_s: float = DEFAULT_AHEAD_S,
        max_waiting: int | None = None,
        stats: SessionStats | None = None,
        log: Logger | None = None,
        mapper: SemanticMapper | None = None,
        on_listener_error: ListenerErrorHandler | None = None,
    ) -> None:
        if max_waiting is not None and max_waiting < 1:
            raise ValueError(f"max_waiting must be >= 1, got {max_waiting}")
        if not 0 <= ahead_s <= MAX_AHEAD_S:
            raise ValueError(f"ahead_s must be in [0, {MAX_AHEAD_S:g}], got {ahead_s}")
        self.config = config or MapperConfig()
        self.ahead_s = ahead_s  # core.follow.map_ahead; 0: map updates are applied in line
        self.max_waiting = max_waiting
        self.stats = stats if stats is not None else SessionStats()
        self.log: Logger = log or _SilentLogger()
        self._updates = MapUpdater(
            self.stats, self.log, max_shrink=max_shrink, reintegrate_below=self.config.reintegrate_below
        )
        self._mapper = mapper
        self._waiting: deque[Keyframe] = deque()
        self._warned_dropping = False  # one warning per stretch without a map, not one per keyframe
        self._on_listener_error = on_listener_error
        self._keyframe_listeners: list[KeyframeListener] = []
        self._reset_listeners: list[Callable[[], None]] = []
        self._save_listeners: list[SaveListener] = []
        self._load_checks: list[LoadCheck] = []
        # Corrected poses of keyframes not integrated yet (live, a keyframe can still be in the synchronizer
        # when the SLAM's path arrives): applied when that keyframe is integrated. The newest path wins.
        self._pending_poses: dict[int, np.ndarray] = {}
        self._refresh_map_stats()

    # ------------------------------------------------------------------ state

    @property
    def mapper(self) -> SemanticMapper | None:
        return self._mapper

    @property
    def waiting(self) -> int:
        """Keyframes given and not yet integrated (they wait here while there is no map)."""
        return len(self._waiting)

    @property
    def keyframes_ready(self) -> bool:
        """True when `integrate_next` has a keyframe to integrate."""
        return self._mapper is not None and bool(self._waiting)

    def take_waiting(self, later: Sequence[Keyframe] = ()) -> list[Keyframe]:
        """The keyframes given and not integrated, oldest first, then `later` ones (still queued elsewhere),
        removed from the session with the pose corrections it holds for them applied (a stopping node defers
        them to its final snapshot)."""
        out = [*self._waiting, *later]
        self._waiting.clear()
        return [replace(k, cam_to_world=self._pending_poses.pop(k.stamp_ns, k.cam_to_world)) for k in out]

    # ------------------------------------------------------------------ listeners

    def add_keyframe_listener(self, fn: KeyframeListener) -> None:
        """fn(keyframe, mapper) after each integrated keyframe (per-frame mask ids: the mask in object colors)."""
        self._keyframe_listeners.append(fn)

    def add_reset_listener(self, fn: Callable[[], None]) -> None:
        """fn() after a reset."""
        self._reset_listeners.append(fn)

    def add_save_listener(self, fn: SaveListener) -> None:
        """fn(directory, info, mapper) after every snapshot; it may return a Future of work it goes on with
        (`save` waits for it, a periodic snapshot's `saved` hands it back)."""
        self._save_listeners.append(fn)

    def add_load_check(self, fn: LoadCheck) -> None:
        """fn(path, mapper) runs after a map was read and before it replaces the current one: it reads and
        checks what it needs (the object database) and raises to fail the load, with nothing changed; it
        returns a function that swaps its part in (run right after the mapper is swapped), or None."""
        self._load_checks.append(fn)

    # ------------------------------------------------------------------ keyframes

    def add_keyframe(self, keyframe: Keyframe) -> Keyframe | None:
        """Queues a keyframe for `integrate_next`; returns the oldest one dropped for room (counted), if any."""
        self._waiting.append(keyframe)
        if self.max_waiting is None or len(self._waiting) <= self.max_waiting:
            return None
        dropped = self._waiting.popleft()
        self.stats.add(keyframes_dropped=1)
        if not self._warned_dropping:
            self._warned_dropping = True
            self.log.warning(
                f"no Gaussian map yet: keeping the newest {self.max_waiting} keyframes, dropping older ones "
                "(counted in keyframes_dropped)"
            )
        return dropped

    def integrate_next(self) -> IntegrationReport | None:
        """Integrates the oldest queued keyframe when there is a map; None when there is nothing to integrate
        or the keyframe was refused (counted)."""
        if not self.keyframes_ready:
            return None
        mapper, keyframe = self._mapper, self._waiting.popleft()
        assert mapper is not None
        corrected = self._pending_poses.pop(keyframe.stamp_ns, None)
        moved = None if corrected is not None else self._updates.frames.into_map(mapper.gaussians, keyframe)
        if corrected is not None:  # in the newest map's frame
            keyframe = replace(keyframe, cam_to_world=corrected)
        elif moved is not None:  # posed in a map older than the one in use
            keyframe = moved
        try:
            report = mapper.integrate(keyframe)
        except DuplicateKeyframeError:
            self.stats.reject("duplicate_stamp")
            self.log.warning(f"keyframe {keyframe.stamp_ns} is already in the map (replayed after a resume?): skipped")
            return None
        except ValueError as exc:
            self.stats.reject("integration_error")
            self.log.warning(f"keyframe {keyframe.stamp_ns} not integrated: {exc}")
            return None
        ms = 1e3 * report.seconds
        with self.stats.lock:
            self.stats.keyframes_processed += 1
            self.stats.keyframes_moved_into_map += moved is not None
            self.stats.ms_per_keyframe_last = ms
            self.stats.ms_per_keyframe_total += ms
            self.stats.last_stamp_ns = max(self.stats.last_stamp_ns, keyframe.stamp_ns)
            self.stats.keyframe_log_bytes = mapper.keyframe_log.nbytes
            self.stats.keyframe_log_keyframes = len(mapper.keyframe_log)
        integrated = report.keyframe or keyframe
        for fn in self._keyframe_listeners:
            self._notify(fn, integrated, mapper)
        return report

    # ------------------------------------------------------------------ maps

    def plan_map(
        self,
        base: GaussianMap | None,
        gaussians: GaussianMap,
        on_motion: Callable[[MapMotion | None], None] | None = None,
        given: GivenMotion | None = None,
    ) -> MapUpdatePlan | None:
        """The update of `base` (None: the map in use) to `gaussians` prepared for `add_map` (the registration
        and the evidence's sources: core.follow.map_updater.MapUpdatePlan), None when there is nothing to
        prepare (no map yet, or the same map again). Reads no state but the map in use, so a live node runs
        it on a thread of its own while the mapper goes on with keyframes. `on_motion`, `given`: see
        plan_map_update."""
        mapper = self._mapper
        base = base if base is not None else (mapper.gaussians if mapper is not None else None)
        if base is None or len(gaussians) == 0 or same_geometry(base, gaussians):
            return None
        return plan_map_update(base, gaussians, self.config.follow(), on_motion, given)

    @property
    def poses_corrected(self) -> bool:
        """Whether the SLAM's corrected poses wait for queued keyframes or will keep the next map update from
        moving the logged poses (they are in that map's frame already)."""
        mapper = self._mapper
        return bool(self._pending_poses) or (mapper is not None and mapper.keyframe_log.poses_given)

    def map_refusal(self, gaussians: GaussianMap) -> tuple[str, str] | None:
        """(reason, detail) when `add_map` would refuse `gaussians` before any registration (no Gaussians, or too
        many removed); None when it may take them."""
        return self._updates.refusal(self._mapper, gaussians)

    def ahead_until(self, gaussians: GaussianMap) -> int | None:
        """The stamp (ns) before which the keyframes after the map update to `gaussians` go ahead into the map in use
        (core.follow.map_ahead), or None when it is applied in line: `ahead_s` 0, no map in use, a re-integration in
        progress or the SLAM's corrected poses in play (they are in the new map's frame already), a map `add_map`
        would refuse or skip, or stamps that do not order the map after the one in use."""
        mapper = self._mapper
        if self.ahead_s <= 0 or mapper is None or self.reintegrating or self.poses_corrected:
            return None
        if self.map_refusal(gaussians) is not None or same_geometry(mapper.gaussians, gaussians):
            return None
        stamp = update_stamp(mapper.gaussians, gaussians)
        return stamp + round(self.ahead_s * 1e9) if stamp > 0 else None

    def start_ahead(self, gaussians: GaussianMap, motion: MapMotion, until_ns: int) -> MapAhead:
        """The map update to `gaussians` (of `ahead_until`, with its `motion` from the registration) that later
        keyframes go ahead of (counted); `add_map` applies it with the stamps it took back."""
        assert self._mapper is not None
        self.stats.add(map_updates_ahead=1)
        return MapAhead(gaussians, pose_mover(self._mapper.gaussians.means, motion), until_ns)

    def add_map(
        self,
        gaussians: GaussianMap,
        name: str = "",
        plan: MapUpdatePlan | None = None,
        taken_back: frozenset[int] = frozenset(),
    ) -> bool:
        """The first map or a map update; returns whether the map changed (False: refused or unchanged).
        `plan`: the update prepared by `plan_map`, used when it is of the map in use and this one. `taken_back`:
        stamps of keyframes posed in this map whose poses were taken back into the map in use before they were
        integrated (`MapAhead.taken_back`): their logged poses move with the update."""
        refusal = self.map_refusal(gaussians)
        if refusal is not None:
            reason, detail = refusal
            self.stats.reject(reason)
            self.log.warning(f"Gaussian map {name} refused: {detail}")
            return False
        if self._mapper is None:
            self._mapper = SemanticMapper(gaussians, self.config)
            self._updates.frames.started(gaussians)
            self._warned_dropping = False
            self.log.info(
                f"Gaussian map {name}: {len(gaussians)} Gaussians" + (" with ids" if gaussians.ids is not None else "")
            )
        elif same_geometry(self._mapper.gaussians, gaussians):
            self.stats.add(maps_unchanged=1)
            return False
        else:
            try:
                self._updates.update(self._mapper, gaussians, name, plan, taken_back)
            except MapMotionError as exc:
                self.stats.reject("map_motion")
                self.log.warning(f"Gaussian map {name} refused: {exc} (the map in use is kept)")
                return False
        self._refresh_map_stats()
        return True

    # ------------------------------------------------------------------ corrected poses, re-integration

    def add_keyframe_poses(self, poses: KeyframePoses, name: str = "") -> int:
        """Corrected keyframe poses (the SLAM's keyframe path); returns how many logged keyframes moved. Any
        moved keyframe starts a re-integration of the log against the current map; keyframes not integrated
        yet take their corrected pose when they are. Refused (bad_keyframe_poses, nothing changed) when a
        pose is not a finite rigid transform or moves a keyframe absurdly far."""
        mapper = self._mapper
        if not poses.poses:
            self._pending_poses = {}  # the newest path wins, an empty one too
            return 0
        try:
            checked = checked_poses(mapper.keyframe_log if mapper is not None else None, poses)
        except ValueError as exc:
            self.stats.reject("bad_keyframe_poses")
            self.log.warning(f"keyframe poses {name} refused: {exc}")
            return 0
        integrated = mapper.state.has_stamp if mapper is not None else (lambda stamp: False)
        self._pending_poses = {stamp: T for stamp, T in checked if not integrated(stamp)}
        if mapper is None:
            return 0
        return self._updates.correct_poses(mapper, dict(checked))

    @property
    def reintegrating(self) -> bool:
        return self._updates.reintegrating

    @property
    def reintegration_swaps_next(self) -> bool:
        """Whether the next `reintegration_step` swaps the rebuilt mapper in."""
        return self._updates.swap_next

    def reintegration_step(self) -> bool:
        """Advances the re-integration in progress by one keyframe, swapping its mapper in once it has caught
        up with the log; returns whether one is still in progress."""
        rebuilt = self._updates.step(self._mapper)
        if rebuilt is not None:
            self._mapper = rebuilt
            self._refresh_map_stats()
        return self._updates.reintegrating

    # ------------------------------------------------------------------ reset, save, load

    def reset(self, keep_gaussians: bool) -> None:
        """Clears the semantic state (keep_gaussians) or the whole map; queued keyframes stay queued."""
        self._updates.cancel()
        self._pending_poses = {}
        if keep_gaussians and self._mapper is not None:
            self._mapper = SemanticMapper(self._mapper.gaussians, self.config)
        else:
            self._mapper = None
        for fn in self._reset_listeners:
            fn()
        self._refresh_map_stats()
        self.log.info("reset: " + ("semantic state cleared" if keep_gaussians else "waiting for a new Gaussian map"))

    def save(self, directory: str, deferred: Sequence[Keyframe] = ()) -> SnapshotInfo:
        """A snapshot of the map; `deferred`: keyframes received but not integrated, saved with it (map_store)."""
        info = save_snapshot(self._mapper_to_save(), directory, deferred=deferred)
        for future in self.saved(directory, info):  # a save is whole when it returns (save_map, the last one)
            self._notify(future.result)
        return info

    def capture(self, deferred: Sequence[Keyframe] = ()) -> SnapshotContent:
        """The map's state as a snapshot holds it, now (map_store.capture_snapshot), for a snapshot written
        elsewhere (a live node's writer thread: map_store.write_snapshot, then `saved`)."""
        return capture_snapshot(self._mapper_to_save(), deferred)

    def _mapper_to_save(self) -> SemanticMapper:
        if self._mapper is None:
            raise ValueError("no map to save yet")
        return self._mapper

    def saved(self, directory: str, info: SnapshotInfo) -> list[Future]:
        """A snapshot was written into `directory`: counted, and the save listeners told; returns the Futures
        of the work they go on with beside the caller."""
        self.stats.add(snapshots_saved=1)
        going_on = (self._notify(fn, directory, info, self._mapper) for fn in self._save_listeners)
        return [future for future in going_on if isinstance(future, Future)]

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
        self._updates.cancel()
        self._mapper = mapper
        self._updates.frames.started(mapper.gaussians)
        for commit in commits:
            if commit is not None:
                commit()
        self._refresh_map_stats()
        self.log.info(f"loaded {source}: {len(mapper.gaussians)} Gaussians")
        return mapper

    # ------------------------------------------------------------------ internals

    def _refresh_map_stats(self) -> None:
        m = self._mapper
        self.stats.update(
            has_map=m is not None,
            gaussians=len(m.gaussians) if m else 0,
            map_version=m.map_version if m else 0,
            last_stamp_ns=int(m.state.stamps_ns.max()) if m is not None and m.n_keyframes else 0,
            keyframe_log_bytes=m.keyframe_log.nbytes if m else 0,
            keyframe_log_keyframes=len(m.keyframe_log) if m else 0,
        )

    def _notify(self, fn: Callable[..., Any], *args: Any) -> Any:
        """fn(*args), its errors handed to the listener error handler (None then) when there is one."""
        if self._on_listener_error is None:
            return fn(*args)
        try:
            return fn(*args)
        except Exception as exc:
            self._on_listener_error(fn, exc)
            return None


class _SilentLogger:
    def info(self, msg: str) -> None:
        pass

    def warning(self, msg: str) -> None:
        pass

    def error(self, msg: str) -> None:
        pass
