"""The map's object labels rendered into a view in one rasterization pass: per pixel the leading label.

Per pixel p and label o the weight is ``W_po = sum_{i: label_i = o} w_ip`` (the rasterizer's
compositing weights, METHOD.md section 2); unlabeled Gaussians and the final transmittance together
form "void" with weight ``1 - sum_o W_po``. A pixel's leading label is the heaviest of these, void
included (the `render_splat_labels` rule of core.evaluation.evaluation, which needs a pass per three labels).
This is what per-frame mask association (core.segments.association) measures segment overlap against.

"numba" is the production kernel (label_render_kernels); "reference" is its plain float64 twin from
the dense weight matrix (tiny scenes only). The numba kernel keeps TILE_LABELS labels per 16x16 tile.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monovoc_ros.core.map.camera import Intrinsics
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.raster.inputs import check_view

LABEL_IMPLEMENTATIONS = ("numba", "reference")


@dataclass
class LabelRendering:
    labels: np.ndarray  # (H, W) int32 leading label index, -1 where void leads
    weights: np.ndarray  # (H, W) float32 weight of the leading label (of void where void leads)


def _check_labels(labels: np.ndarray, n: int) -> np.ndarray:
    labels = np.asarray(labels)
    if labels.shape != (n,) or labels.dtype.kind not in "iu":
        raise ValueError(f"labels: expected ({n},) integer label indices, got {labels.shape} {labels.dtype}")
    if labels.size and (labels.min() < -1 or labels.max() >= 1 << 24):
        raise ValueError("labels: indices must be in [-1, 2^24)")
    return labels.astype(np.int32)


def render_label_weights(
    gmap: GaussianMap,
    labels: np.ndarray,
    intrinsics: Intrinsics,
    cam_to_world: np.ndarray,
    *,
    impl: str = "numba",
) -> LabelRendering:
    """Leading label index (-1 = void) and its weight per pixel; `labels` (N,) int, -1 = unlabeled."""
    if impl not in LABEL_IMPLEMENTATIONS:
        raise ValueError(f"impl must be one of {LABEL_IMPLEMENTATIONS}, got {impl!r}")
    view = check_view(gmap, intrinsics, cam_to_world)
    labels = _check_labels(labels, len(gmap))
    if impl == "reference":
        return render_label_weights_reference(gmap, labels, intrinsics, cam_to_world)
    import numba

    from monovoc_ros.core.raster import numba_impl
    from monovoc_ros.core.segments import label_render_kernels as lk

    h, w = view.height, view.width
    out_label = np.full((h, w), -1, np.int32)
    out_weight = np.ones((h, w), np.float32)
    if len(gmap) == 0:
        return LabelRendering(out_label, out_weight)
    colors = np.zeros((len(gmap), 3), np.float32)
    colors[:, 0] = labels  # exact: |label| < 2^24
    with numba_impl._LOCK:
        workers = numba.get_num_threads()
        b = numba_impl.bin_view(gmap, view, colors, workers)
        lk.label_tiles(b.rows, b.tile_start, b.tile_list, b.tile_order, b.grid[0], w, h, out_label, out_weight, workers)
    return LabelRendering(out_label, out_weight)


def render_label_weights_reference(
    gmap: GaussianMap, labels: np.ndarray, intrinsics: Intrinsics, cam_to_world: np.ndarray
) -> LabelRendering:
    """Plain float64 twin of the numba kernel (dense weights; ties go to the lowest label, void last)."""
    from monovoc_ros.core.raster.reference import pixel_weights

    labels = _check_labels(labels, len(gmap))
    weights, _ = pixel_weights(gmap, intrinsics, cam_to_world)  # (H*W, N)
    n_labels = int(labels.max()) + 1 if labels.size and labels.max() >= 0 else 0
    per_label = np.zeros((weights.shape[0], n_labels + 1))
    for o in range(n_labels):
        per_label[:, o] = weights[:, labels == o].sum(axis=1)
    per_label[:, -1] = 1.0 - per_label[:, :-1].sum(axis=1)
    best = np.argmax(per_label, axis=1)
    lead = np.where(best == n_labels, -1, best).astype(np.int32)
    h, w = intrinsics.height, intrinsics.width
    return LabelRendering(lead.reshape(h, w), per_label[np.arange(len(best)), best].astype(np.float32).reshape(h, w))
