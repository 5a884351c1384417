"""EWA projection of 3D Gaussians to image-space ellipses (METHOD.md section 2), plain NumPy float64.

This is the definition the fast kernels are held against. Per Gaussian it gives the camera depth, the
projected mean, the conic (inverse 2D covariance) and the footprint: the rectangle of 16x16 tiles that
the radius box touches. As in the CUDA rasterizers, a Gaussian reaches every pixel of those tiles and no
pixel outside them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monovoc_ros.core.raster.constants import (
    COV2D_DILATION,
    EIGEN_FLOOR,
    FOV_MARGIN,
    NEAR_PLANE,
    RADIUS_SIGMAS,
    TILE,
)
from monovoc_ros.core.raster.inputs import View


@dataclass
class Projection:
    depth: np.ndarray  # (N,) camera-space z of the mean
    mean2d: np.ndarray  # (N, 2) pixel coordinates (u, v) of the projected mean
    conic: np.ndarray  # (N, 3) inverse 2D covariance as (a, b, c): q(d) = a dx^2 + 2 b dx dy + c dy^2
    radius: np.ndarray  # (N,) int64 pixels
    rect: np.ndarray  # (N, 4) int64 tile range x0, x1, y0, y1 (x1, y1 exclusive), clipped to the grid
    visible: np.ndarray  # (N,) bool: in front of the near plane and touching at least one tile


def tile_grid(width: int, height: int) -> tuple[int, int]:
    return (width + TILE - 1) // TILE, (height + TILE - 1) // TILE


def jacobian_limits(view: View) -> tuple[float, float, float, float]:
    """Bounds on x/z and y/z where the projection Jacobian is evaluated (gsplat's form of inria's 1.3 tan)."""
    k = view.intrinsics
    tan_x, tan_y = 0.5 * k.width / k.fx, 0.5 * k.height / k.fy
    return (
        k.cx / k.fx + FOV_MARGIN * tan_x,
        (k.width - k.cx) / k.fx + FOV_MARGIN * tan_x,
        k.cy / k.fy + FOV_MARGIN * tan_y,
        (k.height - k.cy) / k.fy + FOV_MARGIN * tan_y,
    )


def project(means: np.ndarray, covariances: np.ndarray, view: View) -> Projection:
    """Projects Gaussians with world means (N, 3) and world covariances (N, 3, 3) into `view`."""
    means = np.asarray(means, dtype=np.float64).reshape(-1, 3)
    cov = np.asarray(covariances, dtype=np.float64).reshape(-1, 3, 3)
    k = view.intrinsics
    R, t = view.world_to_cam[:3, :3], view.world_to_cam[:3, 3]
    cam = means @ R.T + t
    x, y, z = cam[:, 0], cam[:, 1], cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        front = np.isfinite(cam).all(axis=1) & (z >= NEAR_PLANE) & (z <= view.far)
        zs = np.where(front, z, 1.0)
        lim_xn, lim_xp, lim_yn, lim_yp = jacobian_limits(view)
        xz = np.clip(x / zs, -lim_xn, lim_xp)
        yz = np.clip(y / zs, -lim_yn, lim_yp)
        J = np.zeros((len(means), 2, 3))
        J[:, 0, 0] = k.fx / zs
        J[:, 0, 2] = -k.fx * xz / zs
        J[:, 1, 1] = k.fy / zs
        J[:, 1, 2] = -k.fy * yz / zs
        M = J @ R
        cov2 = M @ cov @ np.swapaxes(M, 1, 2)
        a = cov2[:, 0, 0] + COV2D_DILATION
        b = cov2[:, 0, 1]
        c = cov2[:, 1, 1] + COV2D_DILATION
        det = a * c - b * b
        front &= np.isfinite(det) & (det > 0)
        det = np.where(front, det, 1.0)
        conic = np.stack([c / det, -b / det, a / det], axis=1)
        mid = 0.5 * (a + c)
        lam = mid + np.sqrt(np.maximum(EIGEN_FLOOR, mid * mid - det))
        radius = np.where(front, np.ceil(RADIUS_SIGMAS * np.sqrt(np.where(front, lam, 0.0))), 0.0)
        u = np.where(front, k.fx * x / zs + k.cx, 0.0)
        v = np.where(front, k.fy * y / zs + k.cy, 0.0)
    gx, gy = tile_grid(k.width, k.height)
    with np.errstate(invalid="ignore"):
        rect = np.stack(
            [
                np.clip(np.floor((u - radius) / TILE), 0, gx),
                np.clip(np.floor((u + radius + TILE - 1) / TILE), 0, gx),
                np.clip(np.floor((v - radius) / TILE), 0, gy),
                np.clip(np.floor((v + radius + TILE - 1) / TILE), 0, gy),
            ],
            axis=1,
        )
    rect = np.where(front[:, None], rect, 0).astype(np.int64)
    visible = front & (rect[:, 1] > rect[:, 0]) & (rect[:, 3] > rect[:, 2])
    radius = np.minimum(radius, 2**62).astype(np.int64)
    return Projection(z, np.stack([u, v], axis=1), conic, radius, rect, visible)
