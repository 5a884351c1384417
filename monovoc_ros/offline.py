"""Offline mapping: a dataset sequence or a recorded bag through a MappingSession, no ROS graph.

The live node's worker is a thread around the same session (monovoc_ros.core.session), and bags go
through the same KeyframeAssembler (via `monovoc_ros.bags.bag_events`), so `monovoc map --bag` and a live
replay give the same semantic map: keyframes wait for the first map, unchanged maps are skipped, maps
removing more than `max_shrink` of the Gaussians refused, duplicate stamps refused, all counted alike, and the
keyframes stamped within `ahead_s` after a map update go ahead of it (core.follow.map_ahead).
"""

from __future__ import annotations

import statistics
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass, field

from tqdm import tqdm

from monovoc_ros.core.evaluation.datasets import Sequence, open_sequence
from monovoc_ros.core.follow.keyframe_log import KeyframePoses
from monovoc_ros.core.follow.map_ahead import DEFAULT_AHEAD_S, MapAhead
from monovoc_ros.core.follow.map_updater import MapUpdatePlan
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.mapping import MapperConfig, SemanticMapper
from monovoc_ros.core.session import DEFAULT_MAX_SHRINK, KeyframeListener, MappingSession, SessionStats


class NoMapError(ValueError):
    """The input gave no Gaussian map the mapper took: nothing to map onto."""


@dataclass
class RunStats(SessionStats):
    """The session's counters and the timing of an offline run."""

    seconds: list[float] = field(default_factory=list)  # integration time per keyframe
    wall_seconds: float = 0.0

    def summary(self) -> dict:
        ms = [1e3 * s for s in self.seconds]
        return {
            "keyframes": self.keyframes_processed,
            "ms_per_keyframe_mean": round(statistics.fmean(ms), 2) if ms else None,
            "ms_per_keyframe_median": round(statistics.median(ms), 2) if ms else None,
            "rejected": dict(self.rejected),
            "map_updates": self.map_updates,
            "maps_unchanged": self.maps_unchanged,
            "wall_seconds": round(self.wall_seconds, 2),
        }


def open_source(spec: str, layout: str = "auto", **options) -> Sequence:
    """A dataset folder (plain / nice-slam / hislam2 layout) or `synthetic[:VARIANT]`."""
    if spec == "synthetic" or spec.startswith("synthetic:"):
        from monovoc_ros.synthetic import SceneConfig, generate_scene

        variant = spec.partition(":")[2] or "clean"
        return generate_scene(SceneConfig(variant=variant))
    return open_sequence(spec, layout=layout, **options)


def _progress(total: int | None, show: bool, what: str) -> tqdm:
    return tqdm(total=total, desc=what, unit="kf", disable=not show, file=sys.stderr, dynamic_ncols=True)


def map_sequence(
    sequence: Sequence,
    config: MapperConfig | None = None,
    *,
    max_keyframes: int | None = None,
    progress: bool = False,
    on_keyframe: KeyframeListener | None = None,
) -> tuple[SemanticMapper, RunStats]:
    gaussians = sequence.load_gaussians()
    if gaussians is None:
        raise NoMapError(f"{sequence.name}: the sequence has no Gaussian map (give one with --gaussians)")
    n = len(sequence) if max_keyframes is None else min(len(sequence), max_keyframes)
    events = (gaussians, *(sequence.keyframe(i) for i in range(n)))
    return _run(events, config, DEFAULT_MAX_SHRINK, None, progress, n, on_keyframe)


def map_events(
    events: Iterable[object],
    config: MapperConfig | None = None,
    *,
    max_keyframes: int | None = None,
    max_shrink: float = DEFAULT_MAX_SHRINK,
    ahead_s: float = DEFAULT_AHEAD_S,
    progress: bool = False,
    on_keyframe: KeyframeListener | None = None,
) -> tuple[SemanticMapper, RunStats]:
    """Drives a MappingSession with bag events (GaussianMap, Keyframe or rejection objects) in order, as the
    live node's worker does: the first map creates the mapper, later maps are SLAM updates (unchanged ones
    skipped, those removing more than `max_shrink` of the Gaussians refused), keyframes before any map wait
    for it, those stamped within `ahead_s` after a map update go ahead of it (the node's map_update_ahead_s).
    `max_keyframes` stops after that many integrated.
    """
    return _run(events, config, max_shrink, max_keyframes, progress, None, on_keyframe, ahead_s)


def map_bag(path: str, config: MapperConfig | None = None, ingest_config=None, **kwargs):
    from monovoc_ros.bags import bag_events

    return map_events(bag_events(path, ingest_config), config, **kwargs)


def _run(
    events: Iterable[object],
    config: MapperConfig | None,
    max_shrink: float,
    max_keyframes: int | None,
    progress: bool,
    total: int | None,
    on_keyframe: KeyframeListener | None,
    ahead_s: float = DEFAULT_AHEAD_S,
) -> tuple[SemanticMapper, RunStats]:
    stats = RunStats()
    session = MappingSession(config, max_shrink=max_shrink, ahead_s=ahead_s, stats=stats)
    if on_keyframe is not None:
        session.add_keyframe_listener(on_keyframe)

    def room() -> bool:
        return max_keyframes is None or stats.keyframes_processed < max_keyframes

    # A map update the keyframes after it go ahead of (core.follow.map_ahead, the live worker's rule), its plan.
    ahead: tuple[MapAhead, MapUpdatePlan] | None = None

    def apply_ahead() -> None:
        nonlocal ahead
        if ahead is not None:
            (pending, plan), ahead = ahead, None
            session.add_map(pending.gaussians, plan=plan, taken_back=frozenset(pending.taken_back))

    start = time.perf_counter()
    with _progress(total, progress, "SCD") as bar:
        for event in events:
            # Rejections are no input: live they never reach the worker.
            if ahead is not None and isinstance(event, (GaussianMap, KeyframePoses, Keyframe)):
                if ahead[0].applies_before(event if isinstance(event, Keyframe) else None):
                    apply_ahead()
            if isinstance(event, GaussianMap):
                until = session.ahead_until(event)
                plan = session.plan_map(None, event) if until is not None else None
                if until is not None and plan is not None and not plan.refusal:
                    ahead = session.start_ahead(event, plan.follow.motion, until), plan
                else:
                    session.add_map(event, plan=plan)
            elif isinstance(event, Keyframe):
                session.add_keyframe(event if ahead is None else ahead[0].posed(event))
            elif isinstance(event, KeyframePoses):
                session.add_keyframe_poses(event)
            else:
                stats.reject(getattr(event, "reason", "rejected"))
            while session.reintegration_step():  # synchronous here; interleaved with keyframes live
                pass
            while session.keyframes_ready and room():
                report = session.integrate_next()
                if report is not None:
                    stats.seconds.append(report.seconds)
                    bar.update()
            if not room():  # stop reading: a map update after the last keyframe must not apply either
                break
    apply_ahead()  # the keyframes that went ahead of it expect it
    if session.mapper is None:
        raise NoMapError(f"no Gaussian map was given, or every one was refused (rejected: {dict(stats.rejected)})")
    stats.wall_seconds = time.perf_counter() - start
    return session.mapper, stats
