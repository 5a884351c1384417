"""Map updates, one owner (METHOD section 10): what a new Gaussian map or corrected keyframe poses from the
SLAM front-end do to the mapper a MappingSession (core.session) holds.

* Refusals: a map without Gaussians (empty_gaussians) or one removing more than `max_shrink` of the
  Gaussians (map_shrink) is refused (`map_update_refusal`: one empty cloud must not wipe the map); so is a
  map whose estimated motion is not believable (`motion_refusal`: the registration did not converge, too
  few inliers, or part of the map moves farther than `max_displacement`), unless the map holds no evidence
  yet (nothing to protect: any new map is taken). Corrected poses that are not finite rigid transforms or
  move a logged keyframe farther than MAX_POSE_CORRECTION_M are refused (`checked_poses`).
* The update (`update_map`): which old Gaussian's evidence each new one takes (core.follow.map_follow),
  handed to the mapper (`take_map`), and the logged keyframe poses moved with the map, but for those of
  keyframes stamped after it that reached the mapper first: they are in its frame already
  (core.follow.map_frames, which also moves keyframes that come after a newer map).
* The log's pose state (`KeyframeLog.poses_given`, written here only): corrected poses the SLAM gave since
  the last map update are in the frame of its next map already, so that update does not move them again.
* Re-integration: whether a map update or corrected poses re-integrate the keyframe log
  (`MapUpdater.reintegration_reason`), and the re-integration in progress (`Reintegration`), stepped by the
  session and swapped in by it once it has caught up with the log; with per-frame mask ids its objects
  take the ids of the objects they replace first (`keep_object_ids`). A map update during a rebuild restarts
  it on the new map (so the live node ends as offline mapping does, which rebuilds at once), unless map updates
  have restarted it MAX_REBUILD_RESTARTS times in a row: then the update carries the rebuild's evidence to the
  new map as it carries the live evidence (the same sources: both mappers hold the same map) and the rebuild
  goes on, so that a SLAM sending maps faster than a rebuild takes cannot keep it from ever finishing; an
  update that needed a rebuild of its own then starts the next one when this one is swapped in. Corrected
  poses restart it (its keyframes were integrated with the old poses).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from concurrent.futures import CancelledError, Future, ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from monovoc_ros.core.evidence.palette import UNOBSERVED_ID
from monovoc_ros.core.follow.keyframe_log import KeyframeLog, KeyframePoses, LoggedKeyframe
from monovoc_ros.core.follow.map_follow import FollowConfig, FollowResult, follow_ids, follow_positions
from monovoc_ros.core.follow.map_frames import MapFrames, PoseMover, in_new_frame, update_stamp
from monovoc_ros.core.follow.map_motion import MapMotion, MotionConfig
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.camera import validate_pose
from monovoc_ros.core.map.gaussians import GaussianMap, removed_gaussians
from monovoc_ros.core.segments.object_match import match_objects

# Metres: a map update bending the map this much re-integrates (its evidence was rendered on the unbent map).
REINTEGRATE_BEND_M = 0.02
# Map updates that restart a rebuild in a row before the next ones carry it over instead (module docstring).
MAX_REBUILD_RESTARTS = 2
# Metres around a logged camera whose Gaussians define how the map moved there (its pose follows them).
_POSE_SUPPORT_M = 4.0
# Logged poses follow a map whose motion moves some part of it at least this far (metres); below it the
# estimated motion is the noise of a densified map, and moving poses by it would make them random-walk.
_POSE_MOVE_MIN_M = 0.01
# Corrected keyframe poses moving any keyframe farther than this (metres) are refused.
MAX_POSE_CORRECTION_M = 10.0
# Seconds a plan waits for a motion computed elsewhere (GivenMotion) before it estimates the motion itself: bounds
# the wait on a process that hangs or a registration that takes unusually long (1M Gaussians: the map reader's takes
# 0.15-0.4 s, 2M ~2x), which the plan then repeats.
GIVEN_MOTION_WAIT_S = 3.0
# Work beside a map update: the new map's arrays during its plan (`plan_map_update`), its labels' geometry once it
# is applied (`update_map`). Threads kept for the process: threads started per plan raised the 1M robot run's
# peak RSS from 1.5-1.7 to 1.8-2.2 GB (glibc gives a new thread's allocations an arena of its own). Nothing on
# them waits for anything on them.
_BESIDE = ThreadPoolExecutor(2, thread_name_prefix="monovoc-map-beside")


class Mapper(Protocol):
    """What map updates need of a mapper (core.mapping.SemanticMapper)."""

    config: Any  # MapperConfig: its follow() says how evidence is carried over
    gaussians: GaussianMap
    state: Any  # the evidence store: `observed`
    keyframe_log: KeyframeLog
    associator: Any  # core.segments.association.Associator with per-frame mask ids, else None

    @property
    def n_keyframes(self) -> int: ...

    def integrate(self, keyframe: Keyframe, logged: LoggedKeyframe | None = None) -> Any: ...

    def rebuilt(self) -> Mapper: ...

    def labelling(self) -> tuple[GaussianMap, Any] | None: ...  # (map, SemanticResult): its newest labels

    def take_map(self, gaussians: GaussianMap, sources: np.ndarray, seed: Future | None = None) -> tuple[int, int]: ...

    def result(self) -> Any: ...  # SemanticResult: `object_ids`

    def rename_objects(self, mapping: dict[int, int]) -> None: ...


class MapMotionError(ValueError):
    """A map update whose motion is not believable: refused, the map in use is kept."""


@dataclass
class MapUpdateReport:
    carried: int  # observed old Gaussians whose evidence went to at least one new Gaussian
    dropped: int  # observed old Gaussians whose evidence went nowhere (pruned, or nothing near their new place)
    gaussians: int  # size of the new map
    by_id: int  # new Gaussians that took their evidence by id
    by_position: int  # new Gaussians that took it by the moved position
    motion: MapMotion  # how the map moved (core.follow.map_motion)
    seconds: float = 0.0  # in update_map (live: the worker's part, when the update was prepared beside it)
    sources: np.ndarray | None = None  # (N_new,) int64 old row whose evidence each new Gaussian took, -1: none
    prepared: bool = False  # its MapUpdatePlan was prepared beforehand (live: beside the worker)
    motion_given: bool = False  # that plan's motion was estimated elsewhere (live: in the map reader process)
    mover: PoseMover | None = None  # how it moved camera poses (None: they stay)
    poses_kept: int = 0  # logged poses it would have moved that are stamped at or after it (in its frame already)

    @property
    def carried_share(self) -> float:
        """Share of the labelled (observed) old Gaussians whose evidence was carried over."""
        total = self.carried + self.dropped
        return self.carried / total if total else 1.0

    def describe(self) -> str:
        m = self.motion
        return (
            f"{self.gaussians} Gaussians; evidence of {self.carried} of {self.carried + self.dropped} labelled "
            f"Gaussians carried ({self.carried_share:.1%}), {self.by_id} new by id, {self.by_position} by position; "
            f"motion by {m.by}: {m.rotation_deg:.2f} deg, {np.linalg.norm(m.translation):.3f} m rigid, "
            f"bend {1e3 * m.bend:.0f} mm, residual {1e3 * m.rms:.1f} mm"
        )


# ---------------------------------------------------------------------- refusals


def map_update_refusal(old: GaussianMap | None, new: GaussianMap, max_shrink: float) -> tuple[str, str] | None:
    """(reason, detail) when a Gaussian map must not replace `old`: empty_gaussians for a map without
    Gaussians, map_shrink when it removes more than `max_shrink` of old's Gaussians (1.0 allows
    everything); None when it may."""
    if len(new) == 0:
        return "empty_gaussians", "it has no Gaussians (the map in use is kept)"
    if old is None or max_shrink >= 1.0:
        return None
    removed, total = removed_gaussians(old, new)
    if removed > max_shrink * total:
        return "map_shrink", (
            f"it removes {removed} of {total} Gaussians ({removed / total:.0%} > map_update_max_shrink "
            f"{max_shrink:g}); set map_update_max_shrink to 1 to allow it, or reset the map"
        )
    return None


def motion_refusal(follow: FollowResult, config: FollowConfig) -> str:
    """Why the map's estimated motion is not believable ("" when it is)."""
    motion = follow.motion
    if motion.by == "ids":
        pass  # correspondences are given: the fit converges by construction
    elif not motion.converged:
        return "the registration of the old map to the new one did not converge"
    if motion.inliers < config.min_inliers:
        return f"only {motion.inliers:.0%} of the old map found a partner in the new one (min {config.min_inliers:.0%})"
    step = max(1, len(follow.old_means) // 4096)
    moved = motion.max_displacement(follow.old_means[::step])
    if moved > config.max_displacement:
        return f"it moves part of the map by {moved:.1f} m (max {config.max_displacement:g} m)"
    return ""


def checked_poses(log: KeyframeLog | None, poses: KeyframePoses) -> list[tuple[int, np.ndarray]]:
    """The corrected poses as (stamp, validated (4, 4) cam_to_world); raises ValueError when a pose is not a
    finite rigid transform or moves a keyframe of `log` farther than MAX_POSE_CORRECTION_M."""
    logged = {} if log is None else {e.stamp_ns: e.cam_to_world for e in log.entries}
    checked = [(int(stamp), validate_pose(T, what=f"keyframe pose {stamp}")) for stamp, T in poses.poses]
    for stamp, T in checked:
        old = logged.get(stamp)
        if old is not None and np.linalg.norm(old[:3, 3] - T[:3, 3]) > MAX_POSE_CORRECTION_M:
            raise ValueError(f"keyframe {stamp} would move {np.linalg.norm(old[:3, 3] - T[:3, 3]):.1f} m")
    return checked


# ---------------------------------------------------------------------- the update and the logged poses


@dataclass(frozen=True, eq=False)
class GivenMotion:
    """The motion of a map update to a new map estimated elsewhere, by `follow_ids` of the same two maps with
    `config` (live: the map reader process registers each map it hands over against the one it handed over before,
    nodes/map_reader.py): `motion` is a Future of that MapMotion, or of None when it was not estimated (the reader
    failed, or ended first). A plan takes it only for that old map (the same object, or the same arrays the
    registration reads: a map sent again arrives as another object) and configuration (`motion_for`)."""

    base: GaussianMap  # the old map it was estimated against
    config: MotionConfig
    motion: Future
    wait_s: float = GIVEN_MOTION_WAIT_S  # the longest a plan waits for it

    def motion_for(self, old: GaussianMap, config: MotionConfig) -> MapMotion | None:
        """The given motion of `old` to the new map, when it is of `old` and `config`, waiting for it (at most
        `wait_s`); None when the plan must estimate it itself."""
        if self.config != config or not _registers_as(self.base, old):
            return None
        try:
            motion = self.motion.result(timeout=self.wait_s)
        except (FutureTimeout, CancelledError):
            return None
        return motion if isinstance(motion, MapMotion) else None


def _registers_as(a: GaussianMap, b: GaussianMap) -> bool:
    """Whether `follow_ids` reads the same arrays of `a` as of `b` (centres, frames and ids), exactly: not
    `same_geometry`, which allows rounding in the frames and would let a given motion differ from the plan's own."""
    if a is b:
        return True
    if len(a) != len(b) or (a.ids is None) != (b.ids is None):
        return False
    pairs = [(a.means, b.means), (a.quats, b.quats), (a.scales, b.scales), (a.ids, b.ids)]
    return all(x is None or np.array_equal(x, y) for x, y in pairs)


@dataclass(frozen=True, eq=False)
class MapUpdatePlan:
    """What a map update computes from the two maps alone (`plan_map_update`): the registration and the
    nearest old Gaussian of every new one, ~90% of an update without ids (1M Gaussians: ~1 s of 1.1 s). A
    live node prepares it beside the worker thread, which integrates keyframes meanwhile, against the map
    that will be in use when the update's turn comes; `update_map` takes it only when it is of exactly the
    maps and settings at hand, and computes its own otherwise (the same function: the same result)."""

    old: GaussianMap
    new: GaussianMap
    config: FollowConfig
    follow: FollowResult
    refusal: str  # motion_refusal ("" when the motion is believable; step 2 of the follow only then)
    motion_given: bool = False  # its motion was a GivenMotion's (estimated elsewhere), not estimated here

    def applies_to(self, old: GaussianMap, new: GaussianMap, config: FollowConfig) -> bool:
        return self.old is old and self.new is new and self.config == config


def plan_map_update(
    old: GaussianMap,
    new: GaussianMap,
    config: FollowConfig,
    on_motion: Callable[[MapMotion | None], None] | None = None,
    given: GivenMotion | None = None,
) -> MapUpdatePlan:
    """The map update of `old` to `new` up to the evidence transfer (see MapUpdatePlan); reads nothing else,
    so any thread may compute it. `on_motion` hears the map's motion (None: refused) as soon as it is known,
    before the transfer (a live worker may integrate keyframes meanwhile: nodes/worker.py). `given`: the motion
    estimated elsewhere, taken when it is of these maps (`GivenMotion.motion_for`): the same function of the same
    maps, so the same plan."""
    # The rasterizer's per-map values, cached with the map: here, beside a live worker, and not in its first
    # keyframe after the update (1M Gaussians: the chunks, and the covariances and other arrays in their order,
    # ~70 ms). They read the new map only, so the `_BESIDE` pool computes them during the registration, whose
    # serial Python leaves a core idle (1M in process: the plan 600-660 -> 520-570 ms; during the transfer too,
    # 490-510 ms, but its memory on top of theirs raised the 2M node's peak RSS by 0.45 GB).
    arrays = _BESIDE.submit(lambda: (new.chunk_bounds, new.placed))
    try:
        motion = given.motion_for(old, config.motion) if given is not None else None
        follow = follow_ids(old, new, config, motion)
        refusal = motion_refusal(follow, config)
        if on_motion is not None:
            on_motion(None if refusal else follow.motion)
    except BaseException:
        arrays.cancel()
        raise
    if refusal:  # taken only by a mapper without evidence, whose first keyframe computes them if need be
        arrays.cancel()
    else:
        arrays.result()
        follow_positions(follow, new, config)
    return MapUpdatePlan(old, new, config, follow, refusal, motion_given=motion is not None)


def update_map(
    mapper: Mapper, gaussians: GaussianMap, plan: MapUpdatePlan | None = None, taken_back: frozenset[int] = frozenset()
) -> MapUpdateReport:
    """Swaps a new map from the SLAM front-end into `mapper`, carrying its evidence over (core.follow.map_follow:
    by id where the maps share ids, else by the map's estimated motion) and moving the logged poses with it
    (`move_logged_poses`; `taken_back`: see there). `plan`: the update prepared beforehand (`plan_map_update`),
    used when it is of these maps. Raises MapMotionError, with nothing changed, when the motion is not
    believable and there is evidence."""
    start = time.perf_counter()
    old = mapper.gaussians
    config = mapper.config.follow()
    prepared = plan is not None and plan.applies_to(old, gaussians, config)
    if not prepared:
        plan = plan_map_update(old, gaussians, config)
    follow = plan.follow
    if plan.refusal and mapper.state.observed.any():  # nothing to protect: any new map is taken
        raise MapMotionError(plan.refusal)
    mover = pose_mover(old.means, follow.motion)
    kept = move_logged_poses(mapper.keyframe_log, mover, update_stamp(old, gaussians), taken_back)
    # The newest labels carried to the new map, their geometry computed beside the mapper's next steps (the
    # update's end, a keyframe): the first result after the update starts its geometry there.
    labelling = mapper.labelling()
    seed = None
    if labelling is not None and labelling[0] is old:
        seed = _BESIDE.submit(labelling[1].carried, follow.sources, gaussians)
    carried, labelled = mapper.take_map(gaussians, follow.sources, seed)
    return MapUpdateReport(
        carried=carried,
        dropped=labelled - carried,
        gaussians=len(gaussians),
        by_id=follow.by_id,
        by_position=follow.by_position,
        motion=follow.motion,
        seconds=time.perf_counter() - start,
        sources=follow.sources,
        prepared=prepared,
        motion_given=prepared and plan.motion_given,
        mover=mover,
        poses_kept=kept,
    )


def move_logged_poses(
    log: KeyframeLog, mover: PoseMover | None, stamp_ns: int, taken_back: frozenset[int] = frozenset()
) -> int:
    """A map update stamped `stamp_ns` (0: unknown): the logged poses moved by `mover` (`pose_mover`; None: they
    stay), unless the SLAM gave corrected poses since the last update, but for the keyframes stamped at or after
    the map (core.follow.map_frames.in_new_frame): they are in its frame already. `taken_back`: stamps of
    keyframes stamped after it whose poses were taken back into the map before it (core.follow.map_ahead): they
    move. Returns how many poses stayed for their stamps."""
    if log.poses_given:  # in the frame of this map already
        log.poses_given = False
        return 0

    if mover is None:
        return 0
    kept = {e.stamp_ns for e in log.entries if in_new_frame(stamp_ns, e.stamp_ns) and e.stamp_ns not in taken_back}
    log.move_poses(mover, kept.__contains__)
    return len(kept)


def pose_mover(means: np.ndarray, motion: MapMotion) -> PoseMover | None:
    """How a map update moves camera poses with the map whose old centres are `means` (N, 3): each by the motion's
    rigid fit around its camera; None when poses stay (the motion is the noise of a densified map)."""
    support = means[:: max(1, len(means) // 20000)].astype(np.float64)
    moved = motion.apply(support)
    if motion.by == "identity" or not len(support) or np.linalg.norm(moved - support, axis=1).max() < _POSE_MOVE_MIN_M:
        return None  # densify / prune noise: poses stay (no random walk)
    if not np.any(motion.offsets):  # one rigid motion: the same for every pose
        return lambda poses: np.stack([motion.move_pose(T, ()) for T in poses])
    return lambda poses: motion.move_poses(poses, support, moved, _POSE_SUPPORT_M)


def unmoved_pose(mover: PoseMover, cam_to_world: np.ndarray, iterations: int = 4) -> np.ndarray:
    """(4, 4) float64: the old map's pose that `mover` moves to `cam_to_world` (a pose in the new map), by
    fixed-point iteration on the local rigid motion `mover` applies around the camera (exact for one rigid
    motion; the field's fit changes slowly with the camera's position)."""
    target = np.asarray(cam_to_world, np.float64)
    guess = target
    for _ in range(iterations):
        local = mover(guess[None])[0] @ np.linalg.inv(guess)  # how the map moves around the guess
        guess = np.linalg.inv(local) @ target
    return guess


def correct_logged_poses(log: KeyframeLog, poses: dict[int, np.ndarray]) -> int:
    """Corrected poses (stamp -> validated (4, 4) cam_to_world) of logged keyframes; returns how many moved."""
    changed = log.set_poses(poses)
    if changed:  # in the frame of the SLAM's next map already: that update must not move them again
        log.poses_given = True
    return changed


# ---------------------------------------------------------------------- re-integration


class Reintegration:
    """A re-integration in progress: a fresh mapper of the current map into which the logged keyframes
    are integrated again, one per `step`, with their current poses. Keyframes integrated into the live
    mapper meanwhile are logged there and integrated here too, in the same order, so the result is the
    fresh mapper of every logged keyframe; it is swapped in when it has caught up."""

    def __init__(self, live: Mapper, reason: str) -> None:
        self.reason = reason
        self.mapper = live.rebuilt()
        self.log = live.keyframe_log
        self._done = 0  # entries of `log` integrated (counting ones the log dropped since for room)
        self._dropped_at_start = self.log.dropped
        self.refused = 0
        self.skipped = 0  # entries the log dropped before this job reached them
        self.seconds = 0.0
        self.map_updates = 0  # map updates carried over to this job's mapper
        self.restarts = 0  # map updates that restarted this rebuild in a row before this job
        self.again = ""  # why a map update carried over needs a rebuild of its own after this one ("": none)

    @property
    def caught_up(self) -> bool:
        return self._position >= len(self.log)

    @property
    def _position(self) -> int:
        return max(0, self._done - (self.log.dropped - self._dropped_at_start))

    def step(self) -> None:
        """Integrates the next logged keyframe (a refused one is counted and skipped)."""
        start = time.perf_counter()
        # Entries the bounded log dropped before this job reached them are gone: skipped, not re-counted.
        gone = self.log.dropped - self._dropped_at_start
        if gone > self._done:
            self.skipped += gone - self._done
            self._done = gone
        entry = self.log.entries[self._position]
        self._done += 1
        try:
            self.mapper.integrate(entry.keyframe(), logged=entry)
        except ValueError:
            self.refused += 1
        self.seconds += time.perf_counter() - start


def keep_object_ids(live: Mapper, rebuilt: Mapper) -> tuple[int, int]:
    """Per-frame mask ids: the rebuilt mapper's objects take the ids of the live mapper's objects they are
    (core.segments.object_match: by the Gaussians both label), so that everything that knows the live ids (the
    object database, query answers, the semantic cloud) sees the same id for the same object after the swap;
    the rest get ids the live associator never issued. Returns (rebuilt objects that kept an id, rebuilt
    objects). With global mask ids the ids are the masks' own colors, the same in both: nothing to do."""
    if rebuilt.associator is None or live.associator is None:
        return 0, 0
    if len(live.gaussians) != len(rebuilt.gaussians):  # a rebuild is always of the map in use
        raise ValueError("keep_object_ids: the rebuilt mapper labels another map")
    new_ids = rebuilt.result().object_ids  # (N,) uint32, what downstream will see
    matches = match_objects(live.result().object_ids, new_ids)
    rebuilt.rename_objects(rebuilt.associator.adopt_ids(live.associator, matches))
    return len(matches), int(np.unique(new_ids[new_ids != UNOBSERVED_ID]).size)


class MapUpdater:
    """Map updates and corrected poses as a MappingSession applies them, with the re-integration they start;
    counts in the session's `stats` (core.session.SessionStats) and reports to its `log`. See the module
    docstring."""

    def __init__(self, stats: Any, log: Any, *, max_shrink: float, reintegrate_below: float) -> None:
        self.stats = stats
        self.log = log
        self.max_shrink = max_shrink
        self.reintegrate_below = reintegrate_below
        self.job: Reintegration | None = None
        self.frames = MapFrames()  # the newest updates, for keyframes that come after a newer map

    def refusal(self, mapper: Mapper | None, gaussians: GaussianMap) -> tuple[str, str] | None:
        """(reason, detail) when `gaussians` must not become the map (`map_update_refusal`); None when it may."""
        return map_update_refusal(mapper.gaussians if mapper is not None else None, gaussians, self.max_shrink)

    def update(
        self,
        mapper: Mapper,
        gaussians: GaussianMap,
        name: str = "",
        plan: MapUpdatePlan | None = None,
        taken_back: frozenset[int] = frozenset(),
    ) -> MapUpdateReport:
        """A map update (`update_map` with `plan` and `taken_back`, raising MapMotionError), counted, then the
        re-integration it needs: a rebuild in progress starts over on the new map, or is carried over to it
        when map updates keep restarting it (module docstring)."""
        old = mapper.gaussians
        report = update_map(mapper, gaussians, plan, taken_back)
        self.frames.updated(old, gaussians, report.mover)
        self.stats.add(
            map_updates=1,
            map_updates_prepared=int(report.prepared),
            map_motions_given=int(report.motion_given),
            keyframes_before_their_map=report.poses_kept,
        )
        self.stats.update(map_update_carried_share=report.carried_share, ms_map_update_last=1e3 * report.seconds)
        early = f"; {report.poses_kept} keyframes stamped after it came first (poses kept)" if report.poses_kept else ""
        self.log.info(f"map update {name}: {report.describe()}{early}")
        reason = self.reintegration_reason(report) if mapper.n_keyframes else ""
        job = self.job
        if (
            job is not None
            and job.restarts >= MAX_REBUILD_RESTARTS
            and job.mapper.gaussians is old
            and job.log.complete
        ):
            # Maps come faster than rebuilds finish: this one follows the map as the live evidence did.
            job.mapper.take_map(gaussians, report.sources)
            job.mapper.keyframe_log.follow_poses(job.log)
            job.map_updates += 1
            job.again = job.again or reason
        elif job is not None:  # of the old map: starts over on the new one (`start` drops it if it cannot finish)
            self.start(mapper, job.reason)
            if self.job is not None:
                self.job.restarts = job.restarts + 1
        elif reason:
            self.start(mapper, reason)
        return report

    def reintegration_reason(self, report: MapUpdateReport) -> str:
        """Why a map update's transfer should be followed by a re-integration ("" when it should not)."""
        below = self.reintegrate_below
        if below <= 0:
            return ""
        if report.carried_share < below:
            share = report.carried_share
            return f"map update carried {share:.0%} of the labelled evidence (< reintegrate_below {below:g})"
        if report.motion.bend >= REINTEGRATE_BEND_M:
            return f"map update bends the map by {100 * report.motion.bend:.0f} cm"
        return ""

    def correct_poses(self, mapper: Mapper, poses: dict[int, np.ndarray]) -> int:
        """Corrected poses (`checked_poses`) of logged keyframes; any moved keyframe starts a re-integration of
        the log against the current map. Returns how many moved."""
        changed = correct_logged_poses(mapper.keyframe_log, poses)
        if changed:
            self.start(mapper, f"{changed} corrected keyframe poses")
        return changed

    # ------------------------------------------------------------------ the re-integration in progress

    @property
    def reintegrating(self) -> bool:
        return self.job is not None

    @property
    def swap_next(self) -> bool:
        """Whether the next `step` ends the re-integration in progress (its last logged keyframe is next)."""
        job = self.job
        return job is not None and job._position >= len(job.log) - 1

    def start(self, mapper: Mapper, reason: str) -> None:
        """Starts re-integrating `mapper`'s log (dropping a rebuild in progress: it is of an older map or
        older poses), unless the log lacks some of its keyframes."""
        self.job = None
        log = mapper.keyframe_log
        if not (log.complete and len(log) == mapper.n_keyframes):
            # A rebuild from a partial log would drop the evidence of the keyframes it lacks: keep the
            # carried-over evidence instead (the log was bounded by keyframe_log_bytes, or the map was
            # resumed from a snapshot without one).
            self.stats.reject("reintegration_incomplete_log")
            self.log.warning(
                f"not re-integrating ({reason}): the keyframe log holds {len(log)} of the map's "
                f"{mapper.n_keyframes} keyframes (keyframe_log_bytes); the carried-over evidence is kept"
            )
            return
        self.job = Reintegration(mapper, reason)
        self.stats.update(reintegrating=True)
        self.log.info(f"re-integrating {len(log)} logged keyframes: {reason}")

    def step(self, live: Mapper) -> Mapper | None:
        """Advances the re-integration in progress by one keyframe; returns its mapper once it has caught up
        with the log (the session swaps it in for `live`, the mapper in use, whose object ids it takes over:
        `keep_object_ids`), else None."""
        job = self.job
        if job is None:
            return None
        if not job.caught_up:
            job.step()
        if job.caught_up and job.skipped:
            # The bounded log dropped keyframes before the rebuild reached them: their evidence would be lost.
            self.cancel()
            self.stats.reject("reintegration_incomplete_log")
            self.log.warning(
                f"re-integration ({job.reason}) abandoned: the keyframe log dropped {job.skipped} "
                "keyframes before it reached them (keyframe_log_bytes); the carried-over evidence is kept"
            )
            return None
        if not job.caught_up:
            return None
        self.job = None
        job.mapper.keyframe_log.continues(job.log)
        kept, objects = keep_object_ids(live, job.mapper)
        with self.stats.lock:
            self.stats.reintegrations += 1
            self.stats.keyframes_reintegrated += job.mapper.n_keyframes
            self.stats.ms_reintegration_total += 1e3 * job.seconds
            self.stats.reintegrating = False
        self.log.info(
            f"re-integration ({job.reason}) done: {job.mapper.n_keyframes} keyframes in {job.seconds:.1f} s"
            + (f", {job.refused} refused" if job.refused else "")
            + (f", {job.map_updates} map updates followed" if job.map_updates else "")
            + (f"; {kept} of its {objects} objects kept their ids" if job.mapper.associator is not None else "")
        )
        if job.again:  # a map update carried over during this rebuild needs one of its own
            self.start(job.mapper, f"{job.again} (during the previous re-integration)")
        return job.mapper

    def cancel(self) -> None:
        if self.job is not None:
            self.log.info(f"re-integration ({self.job.reason}) cancelled")
        self.job = None
        self.stats.update(reintegrating=False)
