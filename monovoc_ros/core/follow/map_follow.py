"""Which old Gaussian's evidence each Gaussian of a new SLAM map takes (METHOD section 10).

`follow_map(old, new)` decides it in two steps (`follow_ids`, then `follow_positions`):

1. Ids win: a new Gaussian whose id is in the old map takes that Gaussian's evidence; the map's motion is
   estimated (core.follow.map_motion).
2. Every other new Gaussian (all of them when a map has no ids) takes the evidence of the old Gaussian
   nearest to it *after moving the old map by its estimated motion* (core.follow.map_motion: from the id
   pairs when there are any, else by registering the two maps), provided that one lies within
   ``radius + scale_factor * (its largest scale)`` (capped at max_radius). Nearest, not mutual: both
   children of a split (0.8 of their own sigma from the parent's centre) and every clone inherit their
   parent; a pruned Gaussian is nobody's nearest; a Gaussian that lands in empty space starts at zero,
   and the small radius keeps evidence from leaking onto a neighbouring object.

A motion that is not believable (the registration did not converge, too few inliers, or some part of
the map moves farther than `max_displacement`) is refused between the two steps (core.follow.map_updater),
so one absurd map never wipes the semantics.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from monovoc_ros.core.follow.map_follow_kernels import grid_nearest
from monovoc_ros.core.follow.map_motion import MapMotion, MotionConfig, estimate_motion
from monovoc_ros.core.map.gaussians import GaussianMap, id_partners


@dataclass(frozen=True)
class FollowConfig:
    radius: float = 0.03  # metres: base transfer radius
    scale_factor: float = 1.0  # plus this many times the new Gaussian's largest scale
    max_radius: float = 0.15  # metres
    max_displacement: float = 10.0  # metres: a motion moving any part of the map farther is refused
    min_inliers: float = 0.3  # share of the old sample that must find a partner in the new map
    motion: MotionConfig = field(default_factory=MotionConfig)


@dataclass
class FollowResult:
    sources: np.ndarray  # (M,) int64 row of the old map whose evidence each new Gaussian takes; -1: none
    motion: MapMotion
    by_id: int = 0  # new Gaussians matched by id
    by_position: int = 0  # new Gaussians matched by the moved position
    # The old map's finite centres, and the rows of finite centres of both maps (None: every row; no copies
    # at 1M Gaussians): Gaussians culled by the rasterizer neither take nor give evidence.
    old_means: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)), repr=False)
    old_finite: np.ndarray | None = field(default=None, repr=False)
    new_finite: np.ndarray | None = field(default=None, repr=False)


# Grid cell of nearest_within (m): 0.045-0.09 took 150 ms for 1M queries on office_0 tiled, 0.03 (the base
# radius) 200 ms and 0.015 390 ms: larger cells share each cell's lookups among more queries.
GRID_CELL_M = 0.05


def nearest_within(
    points: np.ndarray, queries: np.ndarray, radius: np.ndarray, cell: float = GRID_CELL_M
) -> np.ndarray:
    """(Q,) int64: per query (Q, 3) the row of its nearest point (N, 3) within its own radius (Q,), or -1
    (numba grid search in cubes of `cell` metres)."""
    return grid_nearest(points, queries, radius, cell)


def nearest_within_reference(points: np.ndarray, queries: np.ndarray, radius: np.ndarray) -> np.ndarray:
    """Plain twin of `nearest_within` (scipy's cKDTree)."""
    out = np.full(len(queries), -1, np.int64)
    if not len(points) or not len(queries):
        return out
    bound = float(radius.max()) * (1 + 1e-9)
    d, i = cKDTree(points).query(queries, k=1, distance_upper_bound=bound, workers=2)
    hit = np.isfinite(d) & (d <= radius)
    out[hit] = i[hit]
    return out


def transfer_radius(new: GaussianMap, rows: np.ndarray | None, config: FollowConfig) -> np.ndarray:
    """(len(rows),) float64 transfer radius of the new Gaussians `rows` (None: all of them)."""
    s = new.scales if rows is None else new.scales[rows]
    if not len(s):
        return np.zeros(0)
    largest = np.maximum(np.maximum(s[:, 0], s[:, 1]), s[:, 2]).astype(np.float64)  # 5x numpy's max(axis=1)
    return np.minimum(config.radius + config.scale_factor * largest, config.max_radius)


def follow_map(old: GaussianMap, new: GaussianMap, config: FollowConfig | None = None) -> FollowResult:
    """Source rows of the new map's evidence, and the map's motion (see the module docstring). Gaussians
    with non-finite means (culled by the rasterizer) neither take nor give evidence."""
    config = config or FollowConfig()
    return follow_positions(follow_ids(old, new, config), new, config)


def follow_ids(
    old: GaussianMap, new: GaussianMap, config: FollowConfig, motion: MapMotion | None = None
) -> FollowResult:
    """Step 1: the sources by id (-1 for every other new Gaussian) and the map's motion (`motion`: estimated
    beforehand by this function of these maps with `config.motion`, elsewhere; live, in the map reader process)."""
    old_ok = _finite_rows(old.means)  # None: every row (no copies at 1M Gaussians)
    new_ok = _finite_rows(new.means)
    old_means = old.means if old_ok is None else old.means[old_ok]
    sources = np.full(len(new), -1, np.int64)
    old_rows = new_rows = None
    if old.ids is not None and new.ids is not None:
        sources = id_partners(old.ids, new.ids)
        new_rows = np.flatnonzero(sources >= 0)
        if new_ok is not None:
            new_rows = new_rows[np.isin(new_rows, new_ok)]
        if old_ok is not None:
            new_rows = new_rows[np.isin(sources[new_rows], old_ok)]
        old_rows = sources[new_rows]
    by_ids = old_rows is not None and len(old_rows) >= 3
    if motion is None and by_ids:
        motion = estimate_motion(old.means, new.means, config.motion, old_rows=old_rows, new_rows=new_rows)
    elif motion is None:
        pick = slice(None) if new_ok is None else new_ok
        frames = (new.quats[pick], new.scales[pick])
        motion = estimate_motion(old_means, new.means[pick], config.motion, new_frames=frames)
    by_id = int(np.count_nonzero(sources >= 0))
    return FollowResult(sources, motion, by_id, 0, old_means, old_ok, new_ok)


def map_motion(old: GaussianMap, new: GaussianMap, config: MotionConfig) -> MapMotion:
    """The motion `follow_ids` finds from `old` to `new` with `config`: what a process holding both maps
    estimates for a plan elsewhere (core.follow.map_updater.GivenMotion)."""
    return follow_ids(old, new, FollowConfig(motion=config)).motion


def follow_positions(follow: FollowResult, new: GaussianMap, config: FollowConfig) -> FollowResult:
    """Step 2 on the result of `follow_ids` (in place, returned): every new Gaussian without a source by id
    takes the nearest old Gaussian, moved by the map's motion, within its transfer radius."""
    sources, old_ok = follow.sources, follow.old_finite
    rest = np.flatnonzero(sources < 0)
    if follow.new_finite is not None:
        rest = rest[np.isin(rest, follow.new_finite)]
    if rest.size and len(follow.old_means):
        moved = follow.motion.apply(follow.old_means)
        if rest.size == len(new):  # no ids: every new Gaussian, without gathering 1M rows twice
            found = nearest_within(moved, new.means, transfer_radius(new, None, config))
        else:
            found = nearest_within(moved, new.means[rest], transfer_radius(new, rest, config))
        if old_ok is not None:
            found = np.where(found >= 0, old_ok[np.maximum(found, 0)], -1)
        sources[rest] = found
    follow.by_position = int(np.count_nonzero(sources >= 0)) - follow.by_id
    return follow


def _finite_rows(means: np.ndarray) -> np.ndarray | None:
    """Rows of finite means, or None when every row is finite (the common case)."""
    if np.isfinite(means).all():  # one flat pass: a per-row reduction over 1M rows takes 20x longer
        return None
    return np.flatnonzero(np.isfinite(means).all(axis=1))
