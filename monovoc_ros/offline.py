"""Offline mapping: a dataset sequence or a recorded bag through a SemanticMapper, no ROS graph.

Bags go through the same KeyframeAssembler (via `monovoc_ros.bags.bag_events`) and the same map-update
rule as the live node, so `monovoc map --bag` and a live replay give the same semantic map.
"""

from __future__ import annotations

import statistics
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from tqdm import tqdm

from monovoc_ros.core.datasets import Sequence, open_sequence
from monovoc_ros.core.gaussians import GaussianMap
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.mapping import DuplicateKeyframeError, MapperConfig, SemanticMapper
from monovoc_ros.ingest import map_update_refusal

KeyframeListener = Callable[[Keyframe, SemanticMapper], None]


@dataclass
class RunStats:
    keyframes: int = 0
    seconds: list[float] = field(default_factory=list)  # SCD integration time per keyframe
    rejected: Counter = field(default_factory=Counter)  # reason -> count
    map_updates: int = 0
    wall_seconds: float = 0.0

    def summary(self) -> dict:
        ms = [1e3 * s for s in self.seconds]
        return {
            "keyframes": self.keyframes,
            "ms_per_keyframe_mean": round(statistics.fmean(ms), 2) if ms else None,
            "ms_per_keyframe_median": round(statistics.median(ms), 2) if ms else None,
            "rejected": dict(self.rejected),
            "map_updates": self.map_updates,
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
        raise ValueError(f"{sequence.name}: the sequence has no Gaussian map (give one with --gaussians)")
    mapper = SemanticMapper(gaussians, config)
    n = len(sequence) if max_keyframes is None else min(len(sequence), max_keyframes)
    stats = RunStats()
    start = time.perf_counter()
    with _progress(n, progress, "SCD") as bar:
        for i in range(n):
            _integrate(mapper, sequence.keyframe(i), stats, on_keyframe)
            bar.update()
    stats.wall_seconds = time.perf_counter() - start
    return mapper, stats


def map_events(
    events: Iterable[object],
    config: MapperConfig | None = None,
    *,
    max_keyframes: int | None = None,
    max_shrink: float = 0.5,
    progress: bool = False,
    on_keyframe: KeyframeListener | None = None,
) -> tuple[SemanticMapper, RunStats]:
    """Drives a mapper with bag events (GaussianMap, Keyframe or rejection objects) in order.

    The first map creates the mapper; later maps are SLAM updates. Keyframes that come before any map
    wait for it, as they do in the live node's queue. `max_keyframes` stops after that many integrated.
    Maps the live node refuses (empty, or removing more than `max_shrink` of the Gaussians) are refused and
    counted the same way.
    """
    mapper: SemanticMapper | None = None
    waiting: list[Keyframe] = []
    stats = RunStats()
    start = time.perf_counter()
    with _progress(None, progress, "SCD") as bar:
        for event in events:
            if max_keyframes is not None and stats.keyframes >= max_keyframes:
                break
            if isinstance(event, GaussianMap):
                refusal = map_update_refusal(mapper.gaussians if mapper else None, event, max_shrink)
                if refusal is not None:  # as the live node refuses it
                    stats.rejected[refusal[0]] += 1
                    continue
                if mapper is None:
                    mapper = SemanticMapper(event, config)
                else:
                    mapper.update_gaussians(event)
                    stats.map_updates += 1
                for keyframe in waiting[: None if max_keyframes is None else max(0, max_keyframes - stats.keyframes)]:
                    _integrate(mapper, keyframe, stats, on_keyframe)
                    bar.update()
                waiting.clear()
            elif isinstance(event, Keyframe):
                if mapper is None:
                    waiting.append(event)
                else:
                    _integrate(mapper, event, stats, on_keyframe)
                    bar.update()
            else:
                stats.rejected[getattr(event, "reason", "rejected")] += 1
    if mapper is None:
        raise ValueError("the bag holds no Gaussian map message")
    stats.wall_seconds = time.perf_counter() - start
    return mapper, stats


def map_bag(path: str, config: MapperConfig | None = None, ingest_config=None, **kwargs):
    from monovoc_ros.bags import bag_events

    return map_events(bag_events(path, ingest_config), config, **kwargs)


def _integrate(mapper: SemanticMapper, keyframe: Keyframe, stats: RunStats, on_keyframe) -> None:
    try:
        report = mapper.integrate(keyframe)
    except DuplicateKeyframeError:
        stats.rejected["duplicate_stamp"] += 1  # as the live node counts it
        return
    stats.keyframes += 1
    stats.seconds.append(report.seconds)
    if on_keyframe is not None:
        on_keyframe(report.keyframe or keyframe, mapper)  # per-frame mask ids: the mask in object colors
