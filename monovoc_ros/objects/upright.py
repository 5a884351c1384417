"""Sizes and heights in a gravity-aligned frame, for the attribute descriptions ("0.9 m tall").

Maps do not all have z up. REP-103 frames and the synthetic room do ("+z"); a SLAM world that is the
first camera's OpenCV frame (Replica's traj.txt: x right, y down, z forward) has roughly "-y" up, but
only as level as that first camera was: office_0's first keyframe looks down, so measuring heights
along -y put the chairs "1.8 m above the floor". ``up_axis="auto"`` estimates up in two steps:

1. from the keyframe poses: the mean of the cameras' up directions (-y of each OpenCV camera). Roll is
   near zero for handheld and robot cameras and yaw varies, so horizontal parts partly cancel; but a
   camera that mostly looks down tilts the mean (office_0: 10 degrees off);
2. refined by horizontal surfaces: the normals of flat Gaussians (their shortest axis) within 30, then
   15, then 10 degrees of the current estimate, whose principal direction is the floor / table / ceiling
   normal. On office_0 this converges to 45 degrees from -y (the first camera looked down that much),
   with ~38k Gaussians agreeing within 10 degrees. Without flat Gaussians the camera estimate stays.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import numpy as np

from monovoc_ros.core.evidence.palette import VOID_ID
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.object_geometry import ObjectGeometry, percentile_boxes_at

AXES = {"+x": (0, 1.0), "-x": (0, -1.0), "+y": (1, 1.0), "-y": (1, -1.0), "+z": (2, 1.0), "-z": (2, -1.0)}


def axis_vector(name: str) -> np.ndarray:
    axis, sign = AXES[name]
    v = np.zeros(3)
    v[axis] = sign
    return v


def camera_up(cam_to_world: np.ndarray) -> np.ndarray:
    """World direction of an OpenCV camera's up (its -y axis)."""
    return -np.asarray(cam_to_world, np.float64)[:3, 1]


def estimate_up(gaussians: GaussianMap, hint: np.ndarray, max_samples: int = 50_000) -> np.ndarray:
    """Refines an up direction ``hint`` (e.g. the mean camera up) with the normals of flat Gaussians."""
    from monovoc_ros.core.map.camera import quat_wxyz_to_matrix

    up = np.asarray(hint, np.float64)
    up = up / np.linalg.norm(up)
    n = len(gaussians)
    if n == 0:
        return up
    pick = np.linspace(0, n - 1, min(n, max_samples)).astype(np.int64)
    scales = gaussians.scales[pick].astype(np.float64)
    order = np.argsort(scales, axis=1)
    ranked = np.take_along_axis(scales, order, axis=1)
    flat = ranked[:, 0] < 0.3 * ranked[:, 1]  # a disc, whose shortest axis is its surface normal
    if flat.sum() < 100:
        return up
    rotations = quat_wxyz_to_matrix(gaussians.quats[pick][flat]).astype(np.float64)
    normals = rotations[np.arange(rotations.shape[0]), :, order[flat, 0]]
    weights = gaussians.opacities[pick][flat].astype(np.float64)
    for degrees in (30.0, 15.0, 10.0):
        near = np.abs(normals @ up) > np.cos(np.radians(degrees))
        if near.sum() < 100:
            break
        moment = (normals[near] * weights[near, None]).T @ normals[near]
        candidate = np.linalg.eigh(moment)[1][:, -1]
        up = candidate * np.sign(candidate @ up)
    return up


def upright_rotation(up: np.ndarray) -> np.ndarray:
    """(3, 3) rotation whose rows are two horizontal directions and ``up``: ``points @ R.T`` has height
    last. The first horizontal direction is the first world axis other than the one most aligned with up, made
    horizontal: for a map whose up is near +z the frame is the map's own (x, y), so a yaw in it is the map's yaw.
    (The axis least aligned with up picked y for an estimated up of (1e-5, 2e-6, 1): a frame turned 90 degrees.)"""
    up = np.asarray(up, np.float64)
    up = up / np.linalg.norm(up)
    e = np.zeros(3)
    e[1 if int(np.argmax(np.abs(up))) == 0 else 0] = 1.0
    h1 = e - (e @ up) * up
    h1 /= np.linalg.norm(h1)
    h2 = np.cross(up, h1)
    return np.stack([h1, h2, up])


@dataclass(frozen=True, eq=False)
class _Frame:
    """One map's centres in one upright frame (None: the map frame is upright) and its floor height."""

    gaussians: weakref.ref  # to the GaussianMap (not kept alive by it)
    rotation: np.ndarray  # (3, 3) upright_rotation
    floor_percentile: float
    means: np.ndarray | None  # (N, 3) float32 centres with height last
    floor: float

    def of(self, gaussians: GaussianMap, rotation: np.ndarray, floor_percentile: float) -> bool:
        return (
            self.gaussians() is gaussians
            and np.array_equal(self.rotation, rotation)
            and self.floor_percentile == floor_percentile
        )


@dataclass(frozen=True, eq=False)
class UprightGeometry:
    """The objects' sizes in the upright frame: ``extents`` {object id: (extent with height last, lowest point
    above the floor)} and the ``floor`` height; and what they were computed from, so that the next labelling of the
    same map in the same frame computes only the objects whose shaping Gaussians changed."""

    floor: float
    extents: dict[int, tuple[np.ndarray, float]]
    _frame: _Frame
    _shape_ids: np.ndarray  # (N,) uint32 ObjectGeometry.shape_ids


def upright_geometry(
    gaussians: GaussianMap,
    geometry: ObjectGeometry,
    up: np.ndarray,
    floor_percentile: float,
    previous: UprightGeometry | None = None,
) -> UprightGeometry:
    """The objects' upright sizes: the percentile boxes of the Gaussians that shape each object
    (``geometry.shape_ids``) in the upright frame; the map-frame boxes themselves when the map frame already is
    upright (z up). ``previous``: an earlier result; of the same map, up and percentile, only the objects whose
    shaping Gaussians changed are computed again (the same result: a box depends on its object's Gaussians only)."""
    rotation = upright_rotation(up)
    frame = previous._frame if previous is not None else None
    if frame is None or not frame.of(gaussians, rotation, floor_percentile):
        frame = _frame(gaussians, rotation, floor_percentile)
    shape_ids = geometry.shape_ids
    if frame.means is None:
        summaries, extents = list(geometry.objects), {}
    elif previous is not None and previous._frame is frame:
        rows = np.flatnonzero(shape_ids != previous._shape_ids)
        changed = np.union1d(shape_ids[rows], previous._shape_ids[rows])
        changed = changed[changed < VOID_ID]  # UNOBSERVED_ID (the largest) and VOID_ID are no objects
        gone = set(changed.tolist())
        extents = {k: v for k, v in previous.extents.items() if k not in gone}
        summaries = percentile_boxes_at(frame.means, gaussians.opacities, shape_ids, changed) if changed.size else []
    else:
        summaries, extents = percentile_boxes_at(frame.means, gaussians.opacities, shape_ids), {}
    floor = frame.floor
    for s in summaries:
        extent = np.maximum(s.bbox_max - s.bbox_min, 0.0)
        extent.setflags(write=False)  # kept from one labelling to the next, and handed to the index's records
        extents[s.id] = (extent, float(s.bbox_min[2] - floor))
    return UprightGeometry(floor, extents, frame, shape_ids)


def _frame(gaussians: GaussianMap, rotation: np.ndarray, floor_percentile: float) -> _Frame:
    means = gaussians.means.astype(np.float64) @ rotation.T
    floor = float(np.percentile(means[:, 2], floor_percentile)) if len(means) else 0.0
    upright = None if np.allclose(rotation, np.eye(3)) else means.astype(np.float32)
    return _Frame(weakref.ref(gaussians), rotation, float(floor_percentile), upright, floor)
