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

import numpy as np

from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.object_geometry import ObjectGeometry, percentile_boxes

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
    last. The first horizontal direction is the world axis least aligned with up, made horizontal."""
    up = np.asarray(up, np.float64)
    up = up / np.linalg.norm(up)
    e = np.zeros(3)
    e[int(np.argmin(np.abs(up)))] = 1.0
    h1 = e - (e @ up) * up
    h1 /= np.linalg.norm(h1)
    h2 = np.cross(up, h1)
    return np.stack([h1, h2, up])


def upright_geometry(
    gaussians: GaussianMap, geometry: ObjectGeometry, up: np.ndarray, floor_percentile: float
) -> tuple[float, dict[int, tuple[np.ndarray, float]]]:
    """(floor height, {object id: (extent with height last, lowest point above the floor)}), from the
    percentile boxes of the Gaussians that shape each object (``geometry.shape_ids``) in the upright frame;
    the map-frame boxes themselves when the map frame already is upright (z up)."""
    rotation = upright_rotation(up)
    means = gaussians.means.astype(np.float64) @ rotation.T
    floor = float(np.percentile(means[:, 2], floor_percentile)) if len(means) else 0.0
    if np.allclose(rotation, np.eye(3)):
        summaries = list(geometry.objects)
    else:
        upright = GaussianMap(means.astype(np.float32), gaussians.scales, gaussians.quats, gaussians.opacities)
        summaries = percentile_boxes(upright, geometry.shape_ids)
    out = {s.id: (np.maximum(s.bbox_max - s.bbox_min, 0.0), float(s.bbox_min[2] - floor)) for s in summaries}
    return floor, out
