"""Numba tile kernel of `label_render`: per pixel, the compositing weight of each object label, one pass.

It walks the same binned, depth-sorted tile lists as the rasterizer's `render_tiles` (the same
alpha, transmittance and stopping rule, so the weights are the rasterizer's w_ip) but, instead of
blending colors, adds each Gaussian's weight to its label's entry in a small per-pixel table. The
Gaussian's label index travels in the red channel of its packed row (a float32 holds integers below
2^24 exactly; -1 = unlabeled, which occludes but names nothing). Each tile gives the labels it meets
slots (TILE_LABELS of them), so the pixel loop adds into one slot's row, as SIMD-friendly as the
color blend of render_tiles. Plain twin:
`label_render.render_label_weights_reference`.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from monovoc_ros.core.evidence.palette_kernels import lower_bound
from monovoc_ros.core.raster.constants import TILE
from monovoc_ros.core.raster.numba_kernels import (
    _FASTMATH,
    ROW_RED,
    _alpha,
    _any_live,
    _blend,
    _fetch_add,
    _footprint,
    _pair_blocks,
    _reset_transmittance,
    _row_start,
    _tile_pixels,
)

_PIXELS = TILE * TILE
_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
# Distinct labels one tile keeps (in the order its Gaussians reach them, front to back); a further
# label's weight is lost (it counts as void). A 16x16 tile rarely shows more than a few objects.
TILE_LABELS = 8


@njit(cache=True, nogil=True, fastmath=_FASTMATH)
def _label_tile(t, rows, tile_start, tile_list, gx, width, height, out_label, out_weight):
    px = np.empty(_PIXELS, np.float32)
    py = np.empty(_PIXELS, np.float32)
    T = np.empty(_PIXELS, np.float32)
    # Per tile label slot, the summed weight of each pixel; row TILE_LABELS takes what names nothing.
    wt = np.zeros((TILE_LABELS + 1, _PIXELS), np.float32)
    slot_label = np.full(TILE_LABELS, -1, np.int32)
    used = 0
    _tile_pixels(t, gx, px, py)
    _reset_transmittance(t, gx, width, height, T)
    ox = (t % gx) * TILE
    oy = (t // gx) * TILE
    j0, j1 = tile_start[t], tile_start[t + 1]
    for j in range(j0, j1):
        r = tile_list[j]
        u, v, A, R, S, o = _footprint(rows, r)
        label = np.int32(rows[r, ROW_RED])
        s = TILE_LABELS
        if label >= 0:
            for q in range(used):
                if slot_label[q] == label:
                    s = q
                    break
            if s == TILE_LABELS and used < TILE_LABELS:
                slot_label[used] = label
                s = used
                used += 1
        acc = wt[s]
        br0, br1, lo, hi = _pair_blocks(rows, r, ox, oy)
        for br in range(br0, br1 + 1):
            first = _row_start(br)
            for k in range(first + lo, first + hi):
                w = _blend(T, k, _alpha(px[k], py[k], u, v, A, R, S, o))
                acc[k] += w
        if (j - j0) % 32 == 31 and not _any_live(T):
            break
    for k in range(_PIXELS):
        x = int(px[k])
        y = int(py[k])
        if x < width and y < height:
            # Void (unlabeled Gaussians plus the background's final transmittance) competes as one label.
            total = _F0
            for q in range(used):
                total += wt[q, k]
            best = np.int32(-1)
            best_w = _F1 - total
            for q in range(used):
                if wt[q, k] > best_w:
                    best = slot_label[q]
                    best_w = wt[q, k]
            out_label[y, x] = best
            out_weight[y, x] = best_w


@njit(cache=True, nogil=True, parallel=True)
def label_tiles(rows, tile_start, tile_list, tile_order, gx, width, height, out_label, out_weight, n_workers):
    n = tile_order.shape[0]
    counter = np.zeros(1, np.int64)
    for _ in prange(n_workers):
        m = _fetch_add(counter, 0)
        while m < n:
            _label_tile(tile_order[m], rows, tile_start, tile_list, gx, width, height, out_label, out_weight)
            m = _fetch_add(counter, 0)


@njit(parallel=True, cache=True, nogil=True)
def compact_index(ids: np.ndarray, table: np.ndarray, unobserved: np.uint32, out: np.ndarray) -> int:
    """Per Gaussian the position of its object id in the sorted ``table``: out (N,) int32, -1 where the id is
    ``unobserved``, -2 where it is not in the table; returns how many are not. ids (N,) uint32, table (R,)
    uint32 ascending. A binary search per Gaussian, in place of numpy's searchsorted + gather + compare
    (7 ms at 140k Gaussians; the association's budget is 40 ms). Plain twin:
    `association.compact_index_reference`."""
    r = table.shape[0]
    missing = 0
    for i in prange(ids.shape[0]):
        x = ids[i]
        if x == unobserved:
            out[i] = -1
            continue
        lo = lower_bound(table, x)
        if lo < r and table[lo] == x:
            out[i] = lo
        else:
            out[i] = -2
            missing += 1
    return missing
