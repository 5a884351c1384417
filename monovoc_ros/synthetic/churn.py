"""Seeded generators of what a live 3DGS SLAM does to its map (METHOD section 10), for tests and benchmarks.

Each returns a new `GaussianMap` (re-ordered, without ids unless `keep_ids`) and a `PoseMover` that
moves a camera pose the way the SLAM would correct it (identity for densify/prune):

* `densify`: a share of the Gaussians split in two along their major axis (children 0.5 sigma from
  the parent's centre, scales / 1.6), a share pruned, every mean jittered by a few millimetres.
* `loop_closure`: the whole map moved rigidly (rotation about the vertical through its centre, then a
  translation).
* `drift_correction`: a smooth bend: the rotation and translation grow linearly along the map's longest
  horizontal axis, from zero at one end to the given values at the other (HI-SLAM2 moves Gaussians with
  their anchor keyframes, so the correction varies smoothly through the map). Applied to the true map
  it gives the drifted map a SLAM holds before the correction (benchmarks/bench_map_churn.py).
* `shuffled`: the same map re-ordered.

Children of a split get fresh ids (one keeps the parent's) when ids are kept, as SLAM systems with ids do.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from monovoc_ros.core.map.camera import quat_wxyz_to_matrix
from monovoc_ros.core.map.gaussians import GaussianMap

PoseMover = Callable[[np.ndarray], np.ndarray]  # (4, 4) cam_to_world -> (4, 4) corrected


@dataclass(frozen=True)
class Churned:
    gaussians: GaussianMap
    move_pose: PoseMover


def unmoved(T: np.ndarray) -> np.ndarray:
    """The pose mover of an update that moves nothing (densify, prune, re-order)."""
    return np.array(T, np.float64)


def _rot_z(deg: float) -> np.ndarray:
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _build(gmap: GaussianMap, rows, means, scales, quats, ids, keep_ids: bool, rng) -> GaussianMap:
    """The new map of Gaussians taken from `rows` of gmap with the given geometry, shuffled."""
    order = rng.permutation(len(rows))
    return GaussianMap(
        np.asarray(means, np.float32)[order],
        np.asarray(scales, np.float32)[order],
        np.asarray(quats, np.float32)[order],
        gmap.opacities[rows][order],
        None if gmap.colors is None else gmap.colors[rows][order],
        np.asarray(ids, np.int64)[order] if keep_ids else None,
    )


def _ids(gmap: GaussianMap) -> np.ndarray:
    return gmap.ids if gmap.ids is not None else np.arange(len(gmap), dtype=np.int64)


def shuffled(gmap: GaussianMap, *, seed: int = 0, keep_ids: bool = False) -> Churned:
    """The same Gaussians re-ordered (what every SLAM map update also does)."""
    rng = np.random.default_rng(seed)
    rows = np.arange(len(gmap))
    out = _build(gmap, rows, gmap.means, gmap.scales, gmap.quats, _ids(gmap), keep_ids, rng)
    return Churned(out, unmoved)


def densify(
    gmap: GaussianMap, *, split: float = 0.2, prune: float = 0.05, jitter: float = 0.002, seed: int = 0,
    keep_ids: bool = False,
) -> Churned:  # fmt: skip
    """`split` of the Gaussians split in two, `prune` removed, every mean jittered by N(0, jitter) metres."""
    rng = np.random.default_rng(seed)
    n = len(gmap)
    ids = _ids(gmap)
    fate = rng.random(n)
    keep = np.flatnonzero(fate >= prune + split)
    parents = np.flatnonzero((fate >= prune) & (fate < prune + split))
    R = quat_wxyz_to_matrix(gmap.quats[parents].astype(np.float64))
    major = np.argmax(gmap.scales[parents], axis=1)
    axis = R[np.arange(len(parents)), :, major]  # (P, 3) world direction of each parent's major axis
    half = 0.5 * gmap.scales[parents, major].astype(np.float64)[:, None] * axis
    rows = np.concatenate([keep, parents, parents])
    means = np.concatenate([gmap.means[keep], gmap.means[parents] + half, gmap.means[parents] - half])
    means = means.astype(np.float64) + rng.normal(0.0, jitter, (len(rows), 3))
    scales = gmap.scales[rows].astype(np.float64)
    scales[len(keep) :] /= 1.6
    next_id = int(ids.max()) + 1 if n else 0
    new_ids = np.concatenate([ids[keep], ids[parents], next_id + np.arange(len(parents), dtype=np.int64)])
    out = _build(gmap, rows, means, scales, gmap.quats[rows], new_ids, keep_ids, rng)
    return Churned(out, unmoved)


def _moved(gmap: GaussianMap, R: np.ndarray, t: np.ndarray, keep_ids: bool, seed: int) -> GaussianMap:
    """gmap with Gaussian i moved by (R[i], t[i]) ((N, 3, 3), (N, 3)), shuffled."""
    rng = np.random.default_rng(seed)
    rows = np.arange(len(gmap))
    means = np.einsum("nij,nj->ni", R, gmap.means.astype(np.float64)) + t
    xyzw = Rotation.from_matrix(R @ quat_wxyz_to_matrix(gmap.quats.astype(np.float64))).as_quat()
    quats = xyzw[:, [3, 0, 1, 2]]
    return _build(gmap, rows, means, gmap.scales, quats, _ids(gmap), keep_ids, rng)


def _pose_mover(motion: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]) -> PoseMover:
    def move(T: np.ndarray) -> np.ndarray:
        T = np.asarray(T, np.float64)
        R, t = motion(T[None, :3, 3])
        out = np.eye(4)
        out[:3, :3] = R[0] @ T[:3, :3]
        out[:3, 3] = R[0] @ T[:3, 3] + t[0]
        return out

    return move


def loop_closure(
    gmap: GaussianMap, *, degrees: float = 2.0, translation: tuple = (0.06, 0.05, 0.01), seed: int = 0,
    keep_ids: bool = False,
) -> Churned:  # fmt: skip
    """The whole map rotated by `degrees` about the vertical through its centre, then translated."""
    centre = gmap.means.astype(np.float64).mean(axis=0)
    R = _rot_z(degrees)
    t = np.asarray(translation, np.float64) + centre - R @ centre

    def motion(p: np.ndarray):
        return np.broadcast_to(R, (len(p), 3, 3)), np.broadcast_to(t, (len(p), 3))

    R_all, t_all = motion(gmap.means)
    return Churned(_moved(gmap, R_all, t_all, keep_ids, seed), _pose_mover(motion))


def drift_correction(
    gmap: GaussianMap, *, degrees: float = 3.0, translation: tuple = (0.09, 0.07, 0.03), seed: int = 0,
    keep_ids: bool = False,
) -> Churned:  # fmt: skip
    """A smooth bend: at fraction s in [0, 1] along the map's longest horizontal axis, a rotation of
    s * `degrees` about the vertical through the map's centre and a translation of s * `translation`."""
    means = gmap.means.astype(np.float64)
    centre = means.mean(axis=0)
    span = means.max(axis=0) - means.min(axis=0)
    axis = int(np.argmax(span[:2]))
    lo, length = means[:, axis].min(), max(float(span[axis]), 1e-9)
    trans = np.asarray(translation, np.float64)

    def motion(p: np.ndarray):
        s = np.clip((p[:, axis] - lo) / length, 0.0, 1.0)
        a = np.radians(degrees) * s
        c, sn = np.cos(a), np.sin(a)
        R = np.zeros((len(p), 3, 3))
        R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -sn, sn, c, 1.0
        t = centre - np.einsum("nij,j->ni", R, centre) + s[:, None] * trans
        return R, t

    R_all, t_all = motion(means)
    return Churned(_moved(gmap, R_all, t_all, keep_ids, seed), _pose_mover(motion))


def then(first: Churned, second: Callable[..., Churned], **options) -> Churned:
    """`second` (a generator) applied to `first`'s map; poses move by both, first's motion first."""
    out = second(first.gaussians, **options)
    return Churned(out.gaussians, lambda T: out.move_pose(first.move_pose(T)))
