"""Which surface points a camera trajectory observed: a SLAM system only creates Gaussians there.

A point is seen from a keyframe when it lies in front of the camera (beyond the rasterizer's near
plane), projects inside the image, faces the camera, and nothing nearer lies on the ray from the camera
centre to it. Occlusion is decided by casting that exact ray through the analytic scene: the first hit
must be the point itself, within ``DEPTH_TOLERANCE`` along the ray. That is the keyframe's ray-cast depth
test taken at the point's exact sub-pixel position, so no pixel quantisation at silhouettes marks a
point behind an edge as seen.

Two implementations: ``observed_views`` (numba: per point, keyframes in turn, an any-hit test that stops
at the first occluder, and no further keyframes once ``need`` saw it) and ``observed_views_reference``
(NumPy: per keyframe, the nearest hit of every ray from ``raycast.cast_rays``).
"""

from __future__ import annotations

import numba
import numpy as np

from monovoc_ros.core.map.camera import Intrinsics
from monovoc_ros.synthetic.raycast import (
    _box,
    _cylinder,
    _outside_sphere,
    _plane,
    _sphere,
    bounding_spheres,
    cast_rays,
)

NEAR_PLANE = 0.2  # metres: the rasterizer's near plane (METHOD section 2)
DEPTH_TOLERANCE = 0.005  # metres along the ray: how much nearer than the point the first hit may be


def _spread_order(m: int) -> np.ndarray:
    """0..m-1 ordered so each prefix spreads along the loop (bit-reversed keys): early views see most points."""
    bits = max(1, int(np.ceil(np.log2(max(m, 2)))))
    keys = [int(f"{k:0{bits}b}"[::-1], 2) for k in range(m)]
    return np.argsort(keys, kind="stable")


@numba.njit(cache=True, nogil=True)
def _occluded(ox, oy, oz, dx, dy, dz, limit, kinds, params, spheres):
    """Whether any primitive is hit at ray parameter T_MIN < t < limit (any hit will do: no sorting)."""
    a = dx * dx + dy * dy + dz * dz
    for k in range(kinds.shape[0]):
        if _outside_sphere(ox, oy, oz, dx, dy, dz, a, spheres[k], limit):
            continue
        kind = kinds[k]
        if kind == 0:
            t = _box(ox, oy, oz, dx, dy, dz, params[k])[0]
        elif kind == 1:
            t = _cylinder(ox, oy, oz, dx, dy, dz, params[k])[0]
        elif kind == 2:
            t = _sphere(ox, oy, oz, dx, dy, dz, params[k])[0]
        else:
            t = _plane(ox, oy, oz, dx, dy, dz, params[k])[0]
        if t < limit:
            return True
    return False


@numba.njit(cache=True, nogil=True)
def _views_kernel(points, normals, rot, origin, order, k, near, tolerance, need, kinds, params, spheres,
                  out_views, out_cos):  # fmt: skip
    fx, fy, cx, cy, width, height = k[0], k[1], k[2], k[3], k[4], k[5]
    for i in range(points.shape[0]):
        views, best = 0, 0.0
        for f in order:
            rx, ry, rz = points[i, 0] - origin[f, 0], points[i, 1] - origin[f, 1], points[i, 2] - origin[f, 2]
            dist = np.sqrt(rx * rx + ry * ry + rz * rz)
            cos = -(normals[i, 0] * rx + normals[i, 1] * ry + normals[i, 2] * rz) / max(dist, 1e-12)
            z = rx * rot[f, 0, 2] + ry * rot[f, 1, 2] + rz * rot[f, 2, 2]
            if cos <= 0.0 or z <= near:
                continue
            u = fx * (rx * rot[f, 0, 0] + ry * rot[f, 1, 0] + rz * rot[f, 2, 0]) / z + cx
            v = fy * (rx * rot[f, 0, 1] + ry * rot[f, 1, 1] + rz * rot[f, 2, 1]) / z + cy
            if u < -0.5 or u >= width - 0.5 or v < -0.5 or v >= height - 0.5:
                continue
            # Rays of length 1 to the point: a hit before 1 - tolerance / dist is an occluder.
            if _occluded(origin[f, 0], origin[f, 1], origin[f, 2], rx, ry, rz, 1.0 - tolerance / dist,
                         kinds, params, spheres):  # fmt: skip
                continue
            views += 1
            best = max(best, cos)
            if need > 0 and views >= need:
                break
        out_views[i] = views
        out_cos[i] = best


def observed_views(
    points: np.ndarray,
    normals: np.ndarray,
    poses: np.ndarray,
    intrinsics: Intrinsics,
    kinds: np.ndarray,
    params: np.ndarray,
    spheres: np.ndarray | None = None,
    *,
    need: int | None = None,
    tolerance: float = DEPTH_TOLERANCE,
) -> tuple[np.ndarray, np.ndarray]:
    """Per point: (number of keyframes that see it, largest cosine between its normal and a viewing ray).

    With ``need``, a point stops being tested once ``need`` keyframes saw it (counts are then capped
    at ``need``, and the cosine is over the views tested): deciding "seen at all" costs about one ray
    per seen point instead of one per point and keyframe.
    """
    points = np.ascontiguousarray(points, np.float64)
    normals = np.ascontiguousarray(normals, np.float64)
    poses = np.asarray(poses, np.float64)
    kinds = np.ascontiguousarray(kinds, np.int32)
    params = np.ascontiguousarray(params, np.float64)
    spheres = bounding_spheres(kinds, params) if spheres is None else np.ascontiguousarray(spheres, np.float64)
    k = intrinsics
    camera = np.array([k.fx, k.fy, k.cx, k.cy, k.width, k.height], np.float64)
    views, best = np.zeros(len(points), np.int32), np.zeros(len(points))
    _views_kernel(points, normals, np.ascontiguousarray(poses[:, :3, :3]), np.ascontiguousarray(poses[:, :3, 3]),
                  _spread_order(len(poses)).astype(np.int64), camera, NEAR_PLANE, float(tolerance),
                  int(need or 0), kinds, params, spheres, views, best)  # fmt: skip
    return views, best


def observed_views_reference(
    points: np.ndarray,
    normals: np.ndarray,
    poses: np.ndarray,
    intrinsics: Intrinsics,
    kinds: np.ndarray,
    params: np.ndarray,
    spheres: np.ndarray | None = None,
    *,
    need: int | None = None,
    tolerance: float = DEPTH_TOLERANCE,
) -> tuple[np.ndarray, np.ndarray]:
    """Plain twin of ``observed_views``: keyframe by keyframe, the nearest hit of each ray to a point."""
    points = np.asarray(points, np.float64)
    normals = np.asarray(normals, np.float64)
    n = len(points)
    views = np.zeros(n, np.int32)
    best_cos = np.zeros(n)
    k = intrinsics
    for i in _spread_order(len(poses)):
        T = np.asarray(poses[i], np.float64)
        origin, R = T[:3, 3], T[:3, :3]
        todo = np.flatnonzero(views < need) if need is not None else np.arange(n)
        if len(todo) == 0:
            break
        rel = points[todo] - origin
        cam = rel @ R
        z = cam[:, 2]
        dist = np.linalg.norm(rel, axis=1)
        cos = -np.sum(normals[todo] * rel, axis=1) / np.maximum(dist, 1e-12)
        front = (z > NEAR_PLANE) & (cos > 0)
        zs = np.where(front, z, 1.0)
        u = k.fx * cam[:, 0] / zs + k.cx
        v = k.fy * cam[:, 1] / zs + k.cy
        # Pixel centres sit at integers: pixel j covers [j - 0.5, j + 0.5).
        cand = front & (u >= -0.5) & (u < k.width - 0.5) & (v >= -0.5) & (v < k.height - 0.5)
        if not cand.any():
            continue
        # Rays of length 1 to the points: the first hit's parameter is the fraction of the way there.
        t, _, _ = cast_rays(origin, rel[cand], kinds, params, spheres)
        seen = t >= 1.0 - tolerance / dist[cand]
        idx = todo[cand][seen]
        views[idx] += 1
        best_cos[idx] = np.maximum(best_cos[idx], cos[cand][seen])
    return views, best_cos


def typical_pixel_size(primitives: list, poses: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """(P,) metres one pixel spans at each primitive, at the median depth of the keyframes that frame it.

    Optimisation fits a map to its keyframes at their resolution, so what it gets right at an edge is
    measured in their pixels. A primitive no keyframe frames gets the median over all keyframes.
    """
    k = intrinsics
    out = np.zeros(len(primitives))
    R, origin = poses[:, :3, :3], poses[:, :3, 3]
    for j, prim in enumerate(primitives):
        lo, hi = prim.bounds()
        cam = np.einsum("kji,kj->ki", R, (lo + hi) / 2 - origin)  # centre in each camera frame
        z = cam[:, 2]
        zs = np.where(z > NEAR_PLANE, z, 1.0)
        u, v = k.fx * cam[:, 0] / zs + k.cx, k.fy * cam[:, 1] / zs + k.cy
        framed = (z > NEAR_PLANE) & (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
        depth = z[framed] if framed.any() else np.linalg.norm((lo + hi) / 2 - origin, axis=1)
        out[j] = float(np.median(depth)) / k.fx
    return out
