"""How a SLAM map moved between two versions, estimated from the two maps themselves (METHOD section 10).

A 3DGS SLAM front-end rarely keeps per-Gaussian ids, yet on a loop closure it moves its whole map
rigidly or bends it smoothly (HI-SLAM2 moves each Gaussian with its anchor keyframe). `estimate_motion`
recovers that motion as a `MapMotion`:

1. a rigid part: trimmed point-to-point ICP of a sample of the old Gaussian centres against the new ones;
2. when the rigid part leaves the map unexplained (a bent map; with a sampled target map, also where a block's
   point-to-plane residuals stand off the new map's own: `_rigid_motion`), a smooth translation field on a coarse grid
   (`spacing` metres, trilinear between nodes), fitted to nearest-neighbour residuals measured along the
   surface normals of flat Gaussians (point-to-plane: sliding along a wall is no evidence), starting from a
   wide trim again (the bent part was the rigid fit's outliers), with every node pulled towards its
   neighbours (smooth, and defined where no point is).

When correspondences are known (Gaussian ids shared by the two maps) they replace the nearest-neighbour
search and both fits are direct.

The motion moves points (`apply`: old centres to where they are in the new map) and camera poses
(`move_pose`: the best rigid fit of the motion around the camera, so a keyframe integrated against the
old map can be re-integrated against the new one). Unbelievable motions are refused by core.follow.map_follow.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from monovoc_ros.core.follow.map_follow_kernels import (
    PointGrid,
    cell_order,
    field_sums,
    move_points,
    surface_normals_kernel,
)
from monovoc_ros.core.map.camera import quat_wxyz_to_matrix, validate_pose

# Grid cell of the registration's targets (m): ~40 of a 1M map's 250k-target sample per cell, and a query
# that finds no target within the first ICP trim (0.5 m) looks at 11^3 cells, not 21^3. Searching one grid
# took 3-5 ms per 12k queries where scipy's cKDTree took 23-30 ms (and 87 ms to build, the grid 25).
_TARGET_CELL_M = 0.1
_GRID_MAX_TRIM_M = 1.0  # beyond it (start_trim set wider than its 0.5 m), a k-d tree: no cube of cells to scan
# A new map with more targets than this in one grid cell is not registered (a motion that did not converge: refused
# once there is evidence). Each search scans a query's cells whole, and the k-d tree splits no pile of equal points:
# 30k Gaussians at one point took ~23 s to register. Replica office_0 holds at most 61 centres in a 10 cm cell.
_MAX_CELL_TARGETS = 4096
# Poses moved together by MapMotion.move_poses (a (chunk, support) distance matrix: 64 x 20k float64, 10 MB).
_POSE_CHUNK = 64
_FIRST_AXES = np.diag([1.0, 1.0, 0.0])
_LAST_AXIS = np.diag([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class MotionConfig:
    sample: int = 12000  # old centres the smooth field is fitted to (seeded random sample)
    rigid_sample: int = 4000  # of which the rigid ICP uses the first this many
    target_sample: int = 250_000  # new centres searched (sampled beyond this many)
    spacing: float = 1.5  # metres between the nodes of the smooth field
    rigid_iterations: int = 30
    field_iterations: int = 40
    rigid_tolerance: float = 1e-4  # ICP stops when an iteration changes R and t by less (rad + m)
    # Metres: the field is settled when 90% of its supported nodes move less than this in an iteration.
    field_tolerance: float = 5e-4
    start_trim: float = 0.5  # metres: pairs farther apart are outliers in the first ICP iteration
    field_start_trim: float = 0.3  # metres: the same for the field's first iteration, then times field_trim_decay
    field_trim_decay: float = 0.75
    min_trim: float = 0.02  # metres: the trim distance never shrinks below this
    # The rigid motion alone is kept when this share of the sample pairs up with a median residual under
    # rigid_residual metres (the noise of a re-sampled surface); otherwise a field follows the bend.
    rigid_inliers: float = 0.95
    rigid_residual: float = 0.005
    # With sampled targets (maps over target_sample) that residual is mostly the sample's spacing, which hides a
    # bend of a few mm: there the rigid motion must also leave every block of `rigid_block` metres (holding at
    # least `rigid_block_points` of the sample) a median point-to-plane residual within `rigid_plane_residual`
    # metres of the new map's own (flat targets: the plane does not depend on the sample's spacing).
    rigid_plane_residual: float = 0.0005
    rigid_block: float = 4.0
    rigid_block_points: int = 200
    max_rms: float = 0.03  # metres: a fit leaving a larger inlier residual did not converge
    smoothing: float = 3.0  # pseudo-points pulling each field node towards its neighbours' mean
    seed: int = 0


@dataclass(frozen=True)
class MapMotion:
    """p -> R p + t + field(R p + t): a rigid motion then a smooth translation field (trilinear between its
    nodes, clamped to the grid's border outside it)."""

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))  # (3, 3) float64
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) float64
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) float64 grid node (0, 0, 0)
    spacing: float = 1.0
    offsets: np.ndarray = field(default_factory=lambda: np.zeros((1, 1, 1, 3)))  # (GX, GY, GZ, 3) float64
    rms: float = 0.0  # metres: residual of the inlier pairs after the fit
    inliers: float = 1.0  # share of sampled old centres with a new centre within the final trim distance
    converged: bool = True
    by: str = "identity"  # "identity", "registration" or "ids"

    def field_at(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) float64 field offsets at points already moved by the rigid part (trilinear)."""
        return _trilinear(self.offsets, self.origin, self.spacing, points)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) float64: `points` (N, 3) of the old map where the motion puts them in the new one."""

        def c(a: np.ndarray) -> np.ndarray:  # one compiled signature: C-contiguous float64 everywhere
            return np.ascontiguousarray(a, np.float64)

        points = c(points).reshape(-1, 3)
        return move_points(
            points, c(self.rotation), c(self.translation), c(self.offsets), c(self.origin), float(self.spacing)
        )

    def apply_reference(self, points: np.ndarray) -> np.ndarray:
        """Plain twin of `apply` (numpy; tests hold them equal)."""
        q = np.asarray(points, np.float64) @ self.rotation.T + self.translation
        return q + self.field_at(q)

    @property
    def bend(self) -> float:
        """Metres: the largest offset of the smooth field, how far the map bends beyond one rigid motion."""
        return float(np.linalg.norm(self.offsets, axis=-1).max()) if self.offsets.size else 0.0

    @property
    def rotation_deg(self) -> float:
        return float(np.degrees(np.arccos(np.clip((np.trace(self.rotation) - 1) / 2, -1.0, 1.0))))

    def max_displacement(self, points: np.ndarray) -> float:
        """Metres: the largest distance the motion moves any of `points` (N, 3)."""
        points = np.asarray(points, np.float64)
        if not len(points):
            return 0.0
        return float(np.linalg.norm(self.apply(points) - points, axis=1).max())

    def move_pose(self, cam_to_world: np.ndarray, support: np.ndarray, moved: np.ndarray | None = None) -> np.ndarray:
        """(4, 4) float64: the camera pose moved with the map: the rigid fit of the motion over `support`
        (M, 3), old centres around the camera (`moved`: where the motion puts them, when known); with fewer
        than 3, the rigid rotation and the motion of the camera centre."""
        T = validate_pose(cam_to_world, what="cam_to_world")
        support = np.asarray(support, np.float64)
        if len(support) < 3:
            centre = T[None, :3, 3]
            R, t = self.rotation, self.apply(centre)[0] - self.rotation @ centre[0]
        else:
            R, t = kabsch(support, self.apply(support) if moved is None else moved)
        out = np.eye(4)
        out[:3, :3] = R @ T[:3, :3]
        out[:3, 3] = R @ T[:3, 3] + t
        return out

    def move_poses(self, cam_to_world: np.ndarray, support: np.ndarray, moved: np.ndarray, radius: float) -> np.ndarray:
        """(P, 4, 4) float64: each of the poses `cam_to_world` (P, 4, 4) moved as `move_pose` moves it with the
        old centres `support` (S, 3) within `radius` metres of its camera (`moved` (S, 3): where the motion puts
        them), all at once: each camera's fit from sums over its ball (one matrix product per chunk of poses),
        where a ball query and a fit per pose took ~1.6 ms at 1M Gaussians, and a keyframe log holds thousands."""
        poses = np.asarray(cam_to_world, np.float64).reshape(-1, 4, 4)
        support = np.asarray(support, np.float64).reshape(-1, 3)
        out = np.array(poses)
        if not len(poses):
            return out
        origin = support.mean(axis=0) if len(support) else np.zeros(3)
        src, dst = support - origin, np.asarray(moved, np.float64).reshape(-1, 3) - origin  # centred: exact sums
        # Per support point: 1, its old and moved coordinates, and their outer product (what a fit sums).
        outer = (src[:, :, None] * dst[:, None, :]).reshape(-1, 9)
        terms = np.concatenate([np.ones((len(src), 1)), src, dst, outer], axis=1)  # (S, 16)
        src_sq = np.einsum("ij,ij->i", src, src)
        for start in range(0, len(poses), _POSE_CHUNK):
            chunk = poses[start : start + _POSE_CHUNK]
            centres = chunk[:, :3, 3] - origin  # (C, 3)
            d2 = np.einsum("ij,ij->i", centres, centres)[:, None] + src_sq[None, :] - 2.0 * centres @ src.T
            sums = (d2 <= radius * radius).astype(np.float64) @ terms  # (C, 16)
            n = sums[:, 0]
            fit = n >= 3
            R = np.broadcast_to(self.rotation, (len(chunk), 3, 3)).copy()
            t = np.empty((len(chunk), 3))
            if fit.any():
                cs = sums[fit, 1:4] / n[fit, None]
                cd = sums[fit, 4:7] / n[fit, None]
                H = sums[fit, 7:].reshape(-1, 3, 3) - n[fit, None, None] * cs[:, :, None] * cd[:, None, :]
                U, _, Vt = np.linalg.svd(H)
                V, Ut = np.swapaxes(Vt, 1, 2), np.swapaxes(U, 1, 2)
                d = np.sign(np.linalg.det(V @ Ut))
                d[d == 0] = 1.0
                R[fit] = V @ (d[:, None, None] * _LAST_AXIS + _FIRST_AXES) @ Ut
                t[fit] = cd - np.einsum("nij,nj->ni", R[fit], cs) + origin - R[fit] @ origin
            if (~fit).any():  # too little support: the rigid rotation and the motion of the camera centre
                centre = chunk[~fit, :3, 3]
                t[~fit] = self.apply(centre) - centre @ self.rotation.T
            out[start : start + _POSE_CHUNK, :3, :3] = R @ chunk[:, :3, :3]
            out[start : start + _POSE_CHUNK, :3, 3] = np.einsum("nij,nj->ni", R, chunk[:, :3, 3]) + t
        return out


def kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R (3, 3), t (3,)) minimizing sum |R src + t - dst|^2 for paired points src, dst (N, 3)."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    H = (src - cs).T @ (dst - cd)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, cd - R @ cs


def _trilinear_weights(origin: np.ndarray, spacing: float, shape: tuple, points: np.ndarray):
    """Per point the 8 surrounding node indices (N, 8, 3) int64 and weights (N, 8) float64; points
    outside the grid are clamped to its border."""
    g = (points - origin) / spacing
    hi = np.array(shape, np.float64) - 1
    g = np.clip(g, 0.0, hi)
    base = np.minimum(np.floor(g), np.maximum(hi - 1, 0)).astype(np.int64)
    frac = g - base
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], np.int64)  # (8, 3)
    idx = np.minimum(base[:, None, :] + corners[None], np.array(shape, np.int64) - 1)
    w = np.prod(np.where(corners[None] == 1, frac[:, None, :], 1.0 - frac[:, None, :]), axis=2)
    return idx, w


def _trilinear(offsets: np.ndarray, origin: np.ndarray, spacing: float, points: np.ndarray) -> np.ndarray:
    if not np.any(offsets):
        return np.zeros((len(points), 3))
    idx, w = _trilinear_weights(origin, spacing, offsets.shape[:3], points)
    return np.einsum("nk,nkc->nc", w, offsets[idx[..., 0], idx[..., 1], idx[..., 2]])


# Weight of the point-to-point part on flat targets: keeps a node defined where all its surfaces are parallel.
_SLIDE = 0.05


class _Targets:
    """Where each sampled old centre is in the new map: its nearest new centre (registration) or its
    known partner (ids)."""

    def __init__(
        self, new: np.ndarray, known: np.ndarray | None, config: MotionConfig, frames: tuple | None = None
    ) -> None:
        self.known = known
        self._others = np.zeros((0, 3))  # new centres that are not targets (when the targets are a sample)
        self._frames: tuple | None = None
        if known is None:
            rng = np.random.default_rng(config.seed + 1)
            rows = np.arange(len(new))
            if len(new) > config.target_sample:  # every k-th after a random start: a permutation costs more
                step = len(new) / config.target_sample
                rows = (rng.random() * step + step * np.arange(config.target_sample)).astype(np.int64)
            self.points = np.asarray(new[rows], np.float64)
            self.grid = PointGrid.build(self.points, _TARGET_CELL_M)
            self._frames = None if frames is None else (frames[0][rows], frames[1][rows])
            if len(rows) < len(new):
                sampled = np.zeros(len(new), bool)
                sampled[rows] = True
                others = rng.choice(len(new), config.rigid_sample)
                self._others = np.asarray(new[others[~sampled[others]]], np.float64)

    def _nearest_rows(self, queries: np.ndarray, trim: float) -> np.ndarray:
        """`_nearest`'s rows only: the distances took a third of a grid search's time."""
        if trim > _GRID_MAX_TRIM_M:
            return self._nearest(queries, trim)[0]
        return self.grid.nearest(queries, np.full(len(queries), trim))

    def _nearest(self, queries: np.ndarray, trim: float) -> tuple[np.ndarray, np.ndarray]:
        """Per query (Q, 3) its nearest target within `trim` metres: (row (Q,) int64, -1 for none; distance
        (Q,) float64, inf for none)."""
        if trim > _GRID_MAX_TRIM_M:  # the grid would scan (2 trim / cell)^3 cells for a query without a target
            d, i = self._tree.query(queries, k=1, distance_upper_bound=trim)
            return np.where(np.isfinite(d), i, -1), d
        i = self._nearest_rows(queries, trim)
        d = np.full(len(queries), np.inf)
        hit = i >= 0
        d[hit] = np.linalg.norm(self.points[i[hit]] - queries[hit], axis=1)
        return i, d

    @property
    def crowded(self) -> int:
        """The most targets in one grid cell (0 with known partners): a map whose centres pile up (`_sample`)."""
        if self.known is not None or not len(self.points):
            return 0
        return int(np.diff(self.grid.cell_starts).max())

    @cached_property
    def _tree(self) -> cKDTree:
        """For trims beyond _GRID_MAX_TRIM_M (a configured start_trim): unbalanced (sliding midpoint), built in
        2/3 of the time and queried as fast on office_0."""
        return cKDTree(self.points, balanced_tree=False)

    @cached_property
    def normals(self) -> np.ndarray | None:
        """(T, 3) surface normal per target (zero where not flat): for the field, and for the rigid motion's
        test when the targets are a sample (`_rigid_motion`)."""
        return None if self._frames is None else surface_normals(*self._frames)

    def floor(self, trim: float) -> tuple[float, float, float | None]:
        """(share within trim, median distance, median point-to-plane distance) of the new map's own centres
        to their nearest target: what a perfectly registered old centre can reach when the targets are a
        sample, farther apart than the map's centres ((1, 0, None) when every new centre is a target; the
        last is None too without flat targets)."""
        if not len(self._others):
            return 1.0, 0.0, None
        i, d = self._nearest(self._others, trim)
        near = i >= 0
        plane = None
        if self.normals is not None and near.any():
            normals = self.normals[i[near]]
            flat = np.any(normals != 0, axis=1)
            if flat.any():
                offsets = (self.points[i[near]] - self._others[near])[flat]
                plane = float(np.median(np.abs(np.einsum("ni,ni->n", offsets, normals[flat]))))
        return float(near.mean()), float(np.median(d[near])) if near.any() else trim, plane

    def subset(self, rows: slice) -> _Targets:
        """The targets of the sample's rows `rows` (known partners are per sample row; a grid is shared)."""
        out = copy.copy(self)
        if self.known is not None:
            out.known = self.known[rows]
        return out

    def pairs(
        self, moved: np.ndarray, trim: float, normals: bool = False
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(inlier mask (S,), target (S, 3), target normal (S, 3) or None) for the sample at its current
        positions `moved` (S, 3); normals only when asked (the rigid fit needs none)."""
        if self.known is not None:
            target = self.known
            inlier = np.linalg.norm(target - moved, axis=1) <= trim
            return inlier, target, None
        i = self._nearest_rows(moved, trim)
        inlier = i >= 0
        target = np.where(inlier[:, None], self.points[np.maximum(i, 0)], moved)
        return inlier, target, None if not normals or self.normals is None else self.normals[i]


def surface_normals(quats: np.ndarray, scales: np.ndarray, flat: float = 0.3) -> np.ndarray:
    """(N, 3) float64 unit normal (the axis of the smallest scale) of each flat Gaussian (smallest scale under
    `flat` times the middle one), zero for the others. quats (N, 4) wxyz, scales (N, 3). Only the rotation's
    column of the smallest axis is computed (map_follow_kernels.surface_normals_kernel); `surface_normals_reference`
    is its twin."""
    if len(quats) == 0:
        return np.zeros((0, 3))
    return surface_normals_kernel(np.ascontiguousarray(quats), np.ascontiguousarray(scales), float(flat))


def warm_up_kernels() -> None:
    """Loads (or compiles) the registration's kernels that core.warm_up's small map update does not reach, with the
    types a SLAM map gives them: the normals of sampled targets (maps beyond `MotionConfig.target_sample`) and the
    smooth field's sums (bent maps). Left to their first use, compiling them stalled a fresh install's first such
    map update."""
    surface_normals(np.array([[1, 0, 0, 0]], np.float32), np.array([[0.01, 0.1, 0.1]], np.float32))
    field_sums(np.zeros((1, 8), np.int64), np.zeros((1, 8)), np.zeros((1, 3, 3)), np.zeros((1, 3)), 1)


def surface_normals_reference(quats: np.ndarray, scales: np.ndarray, flat: float = 0.3) -> np.ndarray:
    """Plain twin of `surface_normals`: whole rotation matrices."""
    order = np.argsort(scales, axis=1, kind="stable")
    R = quat_wxyz_to_matrix(np.asarray(quats, np.float64))
    normals = R[np.arange(len(R)), :, order[:, 0]]
    s = np.take_along_axis(np.asarray(scales, np.float64), order, axis=1)
    return np.where((s[:, 0] < flat * s[:, 1])[:, None], normals, 0.0)


def estimate_motion(
    old: np.ndarray,
    new: np.ndarray,
    config: MotionConfig | None = None,
    *,
    old_rows: np.ndarray | None = None,
    new_rows: np.ndarray | None = None,
    new_frames: tuple[np.ndarray, np.ndarray] | None = None,
) -> MapMotion:
    """The motion taking the old map's centres `old` (N, 3) to the new map's `new` (M, 3).

    `old_rows`, `new_rows` (K,) int64: known correspondences (the same Gaussian id in both maps); when
    given (K >= 3) they are the only pairs used. Otherwise pairs are nearest neighbours (registration),
    and `new_frames` (the new Gaussians' quats (M, 4) and scales (M, 3)) lets the field weigh residuals
    along the surface normals of flat Gaussians (point-to-plane: sliding along a wall is not evidence).

    Four steps: the sample of old centres and their targets (`_sample`), the rigid fit (`_fit_rigid`),
    whether the rigid motion explains the map (`_rigid_motion`), else the smooth field (`_fit_field`) and
    how well the whole motion fits (`_field_motion`).
    """
    config = config or MotionConfig()
    sample = _sample(old, new, config, old_rows, new_rows, new_frames)
    if sample is None:
        return MapMotion(converged=False, inliers=0.0)
    rigid = _fit_rigid(sample, config)
    if isinstance(rigid, MapMotion):  # the fit ran out of pairs
        return rigid
    R, t, trim = rigid
    rigid_moved = sample.src @ R.T + t
    if not sample.known:
        explained = _rigid_motion(sample, R, t, rigid_moved, trim, config)
        if explained is not None:
            return explained
    grid = _fit_field(sample, rigid_moved, trim, config)
    return _field_motion(sample, R, t, rigid_moved, grid, config)


@dataclass
class _Sample:
    """Old centres sampled for the fit (S, 3) and where to look for each in the new map."""

    src: np.ndarray
    targets: _Targets
    known: bool  # the targets are the known partners (ids)
    by: str  # MapMotion.by


def _sample(
    old: np.ndarray,
    new: np.ndarray,
    config: MotionConfig,
    old_rows: np.ndarray | None,
    new_rows: np.ndarray | None,
    new_frames: tuple[np.ndarray, np.ndarray] | None,
) -> _Sample | None:
    """The sample of `estimate_motion` (None: fewer than 3 centres in a map, nothing to register; or a new map whose
    centres pile up in one place, `_MAX_CELL_TARGETS`)."""
    rng = np.random.default_rng(config.seed)
    known = old_rows is not None and new_rows is not None and len(old_rows) >= 3
    # Rows are sampled before they are gathered: gathering every partner at 1M Gaussians took 64 ms.
    if known:
        pick = rng.choice(len(old_rows), min(config.sample, len(old_rows)), replace=False)
        src = np.asarray(old[old_rows[pick]], np.float64)
        return _Sample(src, _Targets(new, np.asarray(new[new_rows[pick]], np.float64), config), True, "ids")
    if len(old) < 3 or len(new) < 3:
        return None
    src = np.asarray(old[rng.choice(len(old), min(config.sample, len(old)), replace=False)], np.float64)
    targets = _Targets(new, None, config, new_frames)
    if targets.crowded > _MAX_CELL_TARGETS:
        return None
    return _Sample(src, targets, False, "registration")


def _fit_rigid(sample: _Sample, config: MotionConfig) -> tuple[np.ndarray, np.ndarray, float] | MapMotion:
    """Trimmed ICP of the sample's first `rigid_sample` rows: (R, t, the final trim distance), or a motion
    that did not converge when fewer than 3 pairs are left."""
    R, t = np.eye(3), np.zeros(3)
    src, known = sample.src, sample.known
    trim = config.start_trim if not known else np.inf
    rigid = slice(0, config.rigid_sample)  # the sample is random: its first rows are a smaller random sample
    rigid_targets = sample.targets.subset(rigid)
    for _ in range(config.rigid_iterations):
        moved = src[rigid] @ R.T + t
        inlier, target, _ = rigid_targets.pairs(moved, trim)
        if inlier.sum() < 3:
            return MapMotion(converged=False, inliers=float(inlier.mean()), by=sample.by)
        R_new, t_new = kabsch(src[rigid][inlier], target[inlier])
        step = np.linalg.norm(R_new - R) + np.linalg.norm(t_new - t)
        R, t = R_new, t_new
        res = np.linalg.norm(src[rigid][inlier] @ R.T + t - target[inlier], axis=1)
        if not known:
            trim = max(config.min_trim, 3.0 * float(np.median(res)) + 0.01)
        if step < config.rigid_tolerance:
            break
    return R, t, trim


def _rigid_motion(
    sample: _Sample, R: np.ndarray, t: np.ndarray, rigid_moved: np.ndarray, trim: float, config: MotionConfig
) -> MapMotion | None:
    """The rigid motion alone when it explains the map (densified, pruned, moved as a whole), else None (a
    field follows the bend)."""
    inlier, target, normals = sample.targets.pairs(rigid_moved, trim, normals=True)
    res = np.linalg.norm(target - rigid_moved, axis=1)[inlier]
    share, spacing, plane_floor = sample.targets.floor(trim)
    explained = res.size and np.median(res) <= config.rigid_residual + spacing
    if explained and plane_floor is not None and normals is not None:
        worst = worst_block_plane_residual(
            rigid_moved[inlier], (target - rigid_moved)[inlier], normals[inlier], config.rigid_block,
            config.rigid_block_points,
        )  # fmt: skip
        explained = worst <= plane_floor + config.rigid_plane_residual
    if inlier.mean() >= config.rigid_inliers * share and explained:
        rms = float(np.sqrt(np.mean(res**2)))
        return MapMotion(R, t, rms=rms, inliers=float(inlier.mean()), converged=rms <= config.max_rms, by=sample.by)
    return None


def worst_block_plane_residual(
    points: np.ndarray, residuals: np.ndarray, normals: np.ndarray, block: float, min_points: int
) -> float:
    """Metres: the largest per-block median of |residual . normal| over the pairs with a flat target, in cubes
    of `block` metres holding at least `min_points` of them (0 when none does). points, residuals, normals:
    (S, 3); normals zero where the target is not flat. A bend leaves its far blocks off their planes while a
    rigid motion leaves every block at the noise of the surfaces."""
    flat = np.any(normals != 0, axis=1)
    off_plane = np.abs(np.einsum("ni,ni->n", residuals[flat], normals[flat]))
    # The pairs grouped by block as the grid searches group points by cell (np.unique of the blocks' rows, axis=0,
    # sorted a structured copy and held the interpreter ~8 ms for the 12k sample).
    order, keys = cell_order(np.ascontiguousarray(points[flat], np.float64), block)
    if not len(keys):
        return 0.0
    starts = np.flatnonzero(np.concatenate(([True], keys[1:] != keys[:-1], [True])))  # each block's run, then the end
    worst = 0.0
    for a, b in zip(starts[:-1].tolist(), starts[1:].tolist(), strict=True):
        if b - a >= min_points:
            worst = max(worst, float(np.median(off_plane[order[a:b]])))
    return worst


@dataclass
class _Field:
    """The smooth field over the rigidly moved sample: its grid, and per sample point its 8 nodes and weights."""

    origin: np.ndarray  # (3,) grid node (0, 0, 0)
    offsets: np.ndarray  # (GX, GY, GZ, 3)
    weights: np.ndarray  # (S, 8) trilinear weights
    nodes: np.ndarray  # (S, 8) flat node indices
    trim: float  # the pairs' trim distance after the fit

    def at_sample(self) -> np.ndarray:
        """(S, 3) the field's offsets at the sample points."""
        return np.einsum("nk,nkc->nc", self.weights, self.offsets.reshape(-1, 3)[self.nodes])


def _fit_field(sample: _Sample, rigid_moved: np.ndarray, trim: float, config: MotionConfig) -> _Field:
    """The smooth translation field fitted to the residuals the rigid motion left (module docstring, step 2)."""
    targets, known = sample.targets, sample.known
    lo, hi = rigid_moved.min(axis=0), rigid_moved.max(axis=0)
    shape = tuple(int(v) for v in np.maximum(np.ceil((hi - lo) / config.spacing).astype(int) + 1, 2))
    offsets = np.zeros((*shape, 3))
    idx, w = _trilinear_weights(lo, config.spacing, shape, rigid_moved)
    flat = np.ravel_multi_index((idx[..., 0], idx[..., 1], idx[..., 2]), shape)  # (S, 8)
    n_nodes = int(np.prod(shape))
    # The field starts from a wide trim again: where the map bends, the rigid fit left residuals that the
    # rigid phase's final trim (set by the well-fitting part) rejects as outliers.
    field_trim = np.inf if known else config.field_start_trim
    for _ in range(config.field_iterations):
        field_now = np.einsum("nk,nkc->nc", w, offsets.reshape(-1, 3)[flat])
        moved = rigid_moved + field_now
        inlier, target, normals = targets.pairs(moved, max(trim, field_trim), normals=True)
        r = np.where(inlier[:, None], target - moved, 0.0)
        wi = w * inlier[:, None]
        # Per point a 3x3 metric: n n^T (+ a little of I) on flat targets, I elsewhere (point-to-point).
        A = np.broadcast_to(np.eye(3), (len(r), 3, 3)).copy()
        if normals is not None:
            flat_target = np.any(normals != 0, axis=1)
            A[flat_target] = np.einsum("ni,nj->nij", normals[flat_target], normals[flat_target]) + _SLIDE * np.eye(3)
        Ar = np.einsum("nij,nj->ni", A, r)
        num, M, den = field_sums(flat, wi, A, Ar, n_nodes)
        cur = offsets.reshape(-1, 3)
        neighbour = _neighbour_mean(offsets).reshape(-1, 3)
        # Least squares per node with a pull towards the neighbours' mean: smooth, and defined where no point
        # is: (M + s I) o = M cur + num + s neighbour.
        lhs = M + config.smoothing * np.eye(3)
        rhs = np.einsum("nij,nj->ni", M, cur) + num + config.smoothing * neighbour
        updated = np.linalg.solve(lhs, rhs[..., None])[..., 0]
        supported = den > 0
        moved_by = np.linalg.norm(updated - cur, axis=1)[supported]
        change = float(np.percentile(moved_by, 90)) if moved_by.size else 0.0
        offsets = updated.reshape(offsets.shape)
        if change < config.field_tolerance and field_trim <= trim:
            break
        field_trim *= config.field_trim_decay
        if not known:
            res = np.linalg.norm(r[inlier], axis=1)
            trim = max(config.min_trim, 3.0 * float(np.median(res)) + 0.01) if res.size else trim
    return _Field(lo, offsets, w, flat, trim)


def field_sums_reference(
    flat: np.ndarray, weights: np.ndarray, A: np.ndarray, Ar: np.ndarray, n_nodes: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plain twin of map_follow_kernels.field_sums: numpy's bincount per channel. flat (S, 8) int64 nodes, weights
    (S, 8), A (S, 3, 3), Ar (S, 3) float64."""
    keys = flat.ravel()
    num = np.stack([np.bincount(keys, (weights * Ar[:, c, None]).ravel(), n_nodes) for c in range(3)], axis=1)
    M = np.stack(
        [np.bincount(keys, (weights * A[:, a, b, None]).ravel(), n_nodes) for a in range(3) for b in range(3)], axis=1
    ).reshape(n_nodes, 3, 3)
    return num, M, np.bincount(keys, weights.ravel(), n_nodes)


def _field_motion(
    sample: _Sample, R: np.ndarray, t: np.ndarray, rigid_moved: np.ndarray, grid: _Field, config: MotionConfig
) -> MapMotion:
    """The rigid motion and the field, with how well they fit together."""
    field_now = grid.at_sample()
    inlier, target, _ = sample.targets.pairs(rigid_moved + field_now, grid.trim if not sample.known else np.inf)
    res = np.linalg.norm(target - rigid_moved - field_now, axis=1)[inlier]
    rms = float(np.sqrt(np.mean(res**2))) if res.size else float("inf")
    # A bent map never settles on one rigid motion: what counts is how well the whole motion fits.
    converged = sample.known or rms <= config.max_rms
    return MapMotion(R, t, grid.origin, config.spacing, grid.offsets, rms, float(inlier.mean()), converged, sample.by)


def _neighbour_mean(offsets: np.ndarray) -> np.ndarray:
    """(GX, GY, GZ, 3): per node the mean of its 6-neighbours' offsets (border nodes: the ones they have)."""
    total = np.zeros_like(offsets)
    count = np.zeros(offsets.shape[:3] + (1,))
    for axis in range(3):
        n = offsets.shape[axis]
        if n < 2:
            continue
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[axis], hi[axis] = slice(0, n - 1), slice(1, n)
        total[tuple(lo)] += offsets[tuple(hi)]
        count[tuple(lo)] += 1
        total[tuple(hi)] += offsets[tuple(lo)]
        count[tuple(hi)] += 1
    return total / np.maximum(count, 1)
