"""The plain float64 rasterizer, written straight from METHOD.md sections 2-3, for tests on tiny scenes.

It builds the dense (pixels x Gaussians) weight matrix, so it is only usable for a few hundred
Gaussians and images of a few thousand pixels. The fast implementations are held against it.
"""

from __future__ import annotations

import numpy as np

from monovoc_ros.core.map.camera import Intrinsics, quat_wxyz_to_matrix
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.raster.constants import ALPHA_MAX, ALPHA_MIN, DEPTH_MIN_COVERAGE, T_MIN, TILE
from monovoc_ros.core.raster.inputs import View, check_view
from monovoc_ros.core.raster.projection import Projection, project
from monovoc_ros.core.raster.vote_tables import OTHER_LABEL, pixel_vote_labels, tile_slots_reference, top_entries

# Refuses scenes whose dense weight matrix would not fit comfortably in memory.
_MAX_MATRIX_ENTRIES = 50_000_000


def covariances64(gmap: GaussianMap) -> np.ndarray:
    """World covariances (N, 3, 3) in float64 straight from scales and quaternions."""
    R = quat_wxyz_to_matrix(gmap.quats)
    M = R * gmap.scales.astype(np.float64)[:, None, :]
    return M @ np.swapaxes(M, 1, 2)


def project_map(gmap: GaussianMap, view: View) -> Projection:
    return project(gmap.means, covariances64(gmap), view)


def composite(proj: Projection, width: int, height: int, opacities: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Dense weights w_ip (H*W, N) and final transmittance (H*W,) by front-to-back compositing."""
    n = len(proj.depth)
    if height * width * max(n, 1) > _MAX_MATRIX_ENTRIES:
        raise ValueError(f"reference rasterizer: {width}x{height} pixels x {n} Gaussians is too large")
    vs, us = np.divmod(np.arange(height * width), width)
    pu, pv = us.astype(np.float64), vs.astype(np.float64)
    tile_x, tile_y = us // TILE, vs // TILE
    weights = np.zeros((height * width, n))
    T = np.ones(height * width)
    done = np.zeros(height * width, dtype=bool)
    visible = np.flatnonzero(proj.visible)
    # Front to back; equal depths keep map order (the CUDA rasterizers' stable radix sort does the same).
    for i in visible[np.argsort(proj.depth[visible], kind="stable")]:
        x0, x1, y0, y1 = proj.rect[i]
        in_footprint = (tile_x >= x0) & (tile_x < x1) & (tile_y >= y0) & (tile_y < y1)
        dx, dy = pu - proj.mean2d[i, 0], pv - proj.mean2d[i, 1]
        a, b, c = proj.conic[i]
        power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
        alpha = np.minimum(ALPHA_MAX, opacities[i] * np.exp(power))
        blends = in_footprint & ~done & (power <= 0.0) & (alpha >= ALPHA_MIN)
        next_T = T * (1.0 - alpha)
        stops = blends & (next_T < T_MIN)
        done |= stops
        blends &= ~stops
        weights[blends, i] = alpha[blends] * T[blends]
        T[blends] = next_T[blends]
    return weights, T


def pixel_weights(gmap: GaussianMap, intrinsics: Intrinsics, cam_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The dense (H*W, N) float64 matrix of w_ip (row = v * W + u) and the (H*W,) final transmittance."""
    view = check_view(gmap, intrinsics, cam_to_world)
    proj = project_map(gmap, view)
    return composite(proj, view.width, view.height, gmap.opacities.astype(np.float64))


def accumulate(
    gmap: GaussianMap,
    mask: np.ndarray,
    view: View,
    valid: np.ndarray | None,
    background: np.ndarray | None,
    weight_power: int = 1,
) -> tuple[np.ndarray, np.ndarray, int]:
    proj = project_map(gmap, view)
    weights, T = composite(proj, view.width, view.height, gmap.opacities.astype(np.float64))
    weights = weights**weight_power
    y = mask.reshape(-1, 3).astype(np.float64)
    if mask.dtype == np.uint8:
        y = y / 255.0
    if background is not None:
        y = y - T[:, None] * background.astype(np.float64)
    if valid is not None:
        keep = valid.reshape(-1)
        weights, y = weights[keep], y[keep]
    return weights.T @ y, weights.sum(axis=0), int(proj.visible.sum())


def render(
    gmap: GaussianMap, colors: np.ndarray, view: View, background: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    proj = project_map(gmap, view)
    weights, T = composite(proj, view.width, view.height, gmap.opacities.astype(np.float64))
    image = weights @ colors.astype(np.float64)
    if background is not None:
        image += T[:, None] * background.astype(np.float64)
    coverage = 1.0 - T
    depth_sum = weights @ np.where(proj.visible, proj.depth, 0.0)
    depth = np.where(coverage > DEPTH_MIN_COVERAGE, depth_sum / np.where(coverage > 0, coverage, 1.0), 0.0)
    h, w = view.height, view.width
    return image.reshape(h, w, 3), T.reshape(h, w), depth.reshape(h, w)


def dense_votes(
    weights: np.ndarray, labels: np.ndarray, width: int, height: int, n_labels: int
) -> tuple[np.ndarray, np.ndarray]:
    """Per Gaussian votes (N, n_labels) and pooled "other" votes (N,) from dense weights (H*W, N)."""
    slot_map, table = tile_slots_reference(labels, width, height)
    vote = pixel_vote_labels(slot_map, table, width).reshape(-1)
    dense = np.zeros((weights.shape[1], n_labels))
    for lab in np.unique(vote[vote >= 0]):
        dense[:, lab] = weights[vote == lab].sum(axis=0)
    return dense, weights[vote == OTHER_LABEL].sum(axis=0)


def accumulate_votes(
    gmap: GaussianMap, labels: np.ndarray, view: View, weight_power: int, slots: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    proj = project_map(gmap, view)
    weights, _ = composite(proj, view.width, view.height, gmap.opacities.astype(np.float64))
    n_labels = int(labels.max()) + 1 if labels.size else 0
    dense, other = dense_votes(weights**weight_power, labels, view.width, view.height, max(n_labels, 1))
    rows = np.flatnonzero(proj.visible)
    top_labels, top_weights, rest = top_entries(dense[rows], other[rows], slots)
    return rows.astype(np.int64), top_labels, top_weights, rest, int(rows.size)
