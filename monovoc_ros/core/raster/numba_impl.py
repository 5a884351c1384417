"""The production CPU rasterizer: numba tile kernels (numba_kernels.py) driven per keyframe.

Per call: the chunks of the map the view may see (`live_chunks`: a building's map is mostly out of view),
float64 EWA projection of those, one global stable radix sort by depth, packing the visible
Gaussians into 64-byte rows in depth order, binning them into 16x16 tiles with the ellipse cull (a
stable counting sort, so every tile list is already front to back), compositing the tiles, and a
per-Gaussian reduction of the per-pair partial sums. All but the sort run on numba's threads.

Thread safety: one process-wide lock serializes calls. Numba's workqueue threading layer aborts when
two threads enter parallel code at once, two concurrent calls would only fight over the same cores,
and the lock lets the calls share one workspace of scratch arrays.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numba
import numpy as np

from monovoc_ros.core.map.gaussians import MAP_CHUNK, GaussianMap, gather_rows
from monovoc_ros.core.raster import numba_kernels as nk
from monovoc_ros.core.raster.constants import NEAR_PLANE, TILE
from monovoc_ros.core.raster.inputs import View
from monovoc_ros.core.raster.projection import jacobian_limits, tile_grid
from monovoc_ros.core.thread_pools import single_threaded_blas

_LOCK = threading.Lock()
single_threaded_blas()  # its threads would busy-wait on these kernels' cores (core.thread_pools)
_NO_VALID = np.ones((1, 1), dtype=np.bool_)
_NO_COLORS = np.zeros((1, 3), dtype=np.float32)
_ZERO_BG = np.zeros(3, dtype=np.float32)
_NO_MASK = np.zeros((1, 1, 3), dtype=np.uint8)
_NO_SLOTS = np.full((1, 1), -1, dtype=np.int8)
_NO_TILES = np.zeros(1, dtype=np.int32)


class Workspace:
    """Scratch arrays kept between calls: at 560k Gaussians, fresh ones would cost more in page faults
    than the whole projection. Buffers only grow (by at least 25%); use under _LOCK only."""

    def __init__(self) -> None:
        self._buffers: dict[str, np.ndarray] = {}

    def get(self, name: str, shape: tuple[int, ...], dtype) -> np.ndarray:
        size = int(np.prod(shape))
        buf = self._buffers.get(name)
        if buf is None or buf.size < size or buf.dtype != dtype:
            grown = 0 if buf is None or buf.dtype != dtype else int(1.25 * buf.size)
            buf = self._buffers[name] = np.empty(max(size, grown), dtype)
        return buf[:size].reshape(shape)

    def whole(self, name: str, dtype) -> np.ndarray:
        """The named buffer at its full size (empty if there is none yet), for a kernel that uses it
        when it is large enough and otherwise allocates one with headroom (then `adopt` it)."""
        buf = self._buffers.get(name)
        return buf if buf is not None and buf.dtype == dtype else np.empty(0, dtype)

    def adopt(self, name: str, array: np.ndarray) -> None:
        """Keeps an array that a kernel allocated because the named buffer was too small."""
        current = self._buffers.get(name)
        if current is None or array.size > current.size:  # a view of the buffer is never larger
            self._buffers[name] = array

    @property
    def nbytes(self) -> int:
        return sum(b.nbytes for b in self._buffers.values())


WORKSPACE = Workspace()


@dataclass
class Binned:
    """A view's visible Gaussians, packed and binned into tiles (mostly views of the workspace)."""

    order: np.ndarray  # (n_visible,) int32 map index of each depth rank
    rows: np.ndarray  # (n_visible, 16) float32 packed parameters in depth order
    tile_start: np.ndarray  # (n_tiles + 1,) int64 offsets into tile_list
    tile_list: np.ndarray  # (n_pairs,) int32 depth ranks, front to back per tile
    tile_slot: np.ndarray  # (n_pairs,) int64 Gaussian-major slot of each pair
    gauss_start: np.ndarray  # (n_visible + 1,) int64 first slot of each Gaussian
    tile_order: np.ndarray  # (n_tiles,) int64 tiles in scheduling order (most pairs first)
    grid: tuple[int, int]


# Pixels of slack in the chunk cull beyond the footprint's bound (its +3.9 px, float rounding).
_CULL_SLACK_PX = 8.0


def live_chunks(gmap: GaussianMap, view: View) -> np.ndarray:
    """(C,) bool: the chunks of `gmap.chunk_bounds` that may hold a Gaussian the view's projection keeps.

    A chunk is dropped only when every Gaussian of it is culled whatever its covariance: its depth is below the
    near plane or beyond `far` for the whole box of means, or its footprint misses the tile grid on one side. A
    footprint's radius is ceil(3 sqrt(lambda_max)) with lambda_max <= trace + 0.32 <= |J W|_F^2 s^2 + 0.92 (s the
    largest scale, J the Jacobian at the clamped x/z), so radius * z <= 3 sqrt(K) s + 3.9 z with K bounding
    |J W|_F^2 z^2; `u + radius < 0` is then implied by fx x + (cx + slack) z + 3 sqrt(K) s < 0, linear in the
    mean: its largest value over the chunk's box decides (and likewise for the other three sides)."""
    lower, upper, reach = gmap.chunk_bounds
    k = view.intrinsics
    rot, trans = view.world_to_cam[:3, :3], view.world_to_cam[:3, 3]
    lim_xn, lim_xp, lim_yn, lim_yp = jacobian_limits(view)
    spectral = float(np.linalg.norm(rot, 2))
    lx, ly = max(lim_xn, lim_xp), max(lim_yn, lim_yp)
    bound = 3.0 * spectral * np.sqrt(k.fx**2 * (1 + lx**2) + k.fy**2 * (1 + ly**2))
    gx, gy = tile_grid(k.width, k.height)
    center, half = 0.5 * (lower + upper), 0.5 * (upper - lower)

    def extremes(x: float, y: float, z: float) -> tuple[np.ndarray, np.ndarray]:
        """Smallest and largest value over each box of x * x_cam + y * y_cam + z * z_cam."""
        w = x * rot[0] + y * rot[1] + z * rot[2]
        mid = center @ w + (x * trans[0] + y * trans[1] + z * trans[2])
        spread = half @ np.abs(w)
        return mid - spread, mid + spread

    with np.errstate(invalid="ignore"):  # NaN boxes (non-finite chunks) compare false: kept
        z_lo, z_hi = extremes(0.0, 0.0, 1.0)
        pad = bound * reach
        culled = (z_hi < NEAR_PLANE) | (z_lo > view.far)
        culled |= extremes(k.fx, 0.0, k.cx + _CULL_SLACK_PX)[1] + pad < 0.0
        culled |= extremes(k.fx, 0.0, k.cx - TILE * gx - _CULL_SLACK_PX)[0] - pad > 0.0
        culled |= extremes(0.0, k.fy, k.cy + _CULL_SLACK_PX)[1] + pad < 0.0
        culled |= extremes(0.0, k.fy, k.cy - TILE * gy - _CULL_SLACK_PX)[0] - pad > 0.0
    return ~culled


def bin_view(gmap: GaussianMap, view: View, colors: np.ndarray | None, workers: int) -> Binned:
    """Projection, depth order, packing and tile binning; call under _LOCK."""
    ws = WORKSPACE
    k = view.intrinsics
    n = len(gmap)
    gx, gy = tile_grid(k.width, k.height)
    u = ws.get("u", (n,), np.float32)
    v = ws.get("v", (n,), np.float32)
    conic = ws.get("conic", (n, 3), np.float32)
    depth = ws.get("depth", (n,), np.float32)
    rect = ws.get("rect", (n, 4), np.int32)
    lims = np.array(jacobian_limits(view), dtype=np.float64)
    live = live_chunks(gmap, view)
    placed = gmap.placed  # the Gaussians in chunk order: u, v, conic, depth and rect are by place too
    nk.project(
        placed.means, placed.covariances, view.world_to_cam, float(k.fx), float(k.fy), float(k.cx), float(k.cy),
        lims, float(view.far), k.width, k.height, u, v, conic, depth, rect, live, MAP_CHUNK, workers,
    )  # fmt: skip
    by_depth = nk.visible_by_depth(depth, rect, placed.members, live, MAP_CHUNK)
    order = placed.members[by_depth]
    rows = ws.get("rows", (len(by_depth), nk.ROW_WIDTH), np.float32)
    rects = ws.get("rects", (len(by_depth), 4), np.int32)
    # The colors of the visible Gaussians only, in depth order (not all N of them in chunk order).
    visible_colors = _NO_COLORS if colors is None else gather_rows(np.ascontiguousarray(colors), order)
    nk.pack_rows(
        by_depth, u, v, conic, depth, placed.opacities, visible_colors, colors is not None, rows, rects, rect, workers
    )
    tile_start, tile_list, tile_slot, gauss_start = nk.bin_tiles(
        rows, rects, gx * gy, gx, workers, ws.whole("tile_list", np.int32), ws.whole("tile_slot", np.int64)
    )
    ws.adopt("tile_list", tile_list)
    ws.adopt("tile_slot", tile_slot)
    tile_list, tile_slot = tile_list[: tile_start[-1]], tile_slot[: tile_start[-1]]
    # Costly tiles first, so that the last tiles handed out are cheap ones.
    tile_order = np.argsort(-np.diff(tile_start), kind="stable")
    return Binned(order, rows, tile_start, tile_list, tile_slot, gauss_start, tile_order, (gx, gy))


def accumulate(
    gmap: GaussianMap,
    mask: np.ndarray,
    view: View,
    valid: np.ndarray | None,
    background: np.ndarray | None,
    weight_power: int = 1,
) -> tuple[np.ndarray, np.ndarray, int]:
    n = len(gmap)
    color_sum = np.zeros((n, 3))
    weight_sum = np.zeros(n)
    if n == 0:
        return color_sum, weight_sum, 0
    scale = np.float32(1.0 / 255.0) if mask.dtype == np.uint8 else np.float32(1.0)
    with _LOCK:
        workers = numba.get_num_threads()
        b = bin_view(gmap, view, None, workers)
        if len(b.order) == 0:
            return color_sum, weight_sum, 0
        pair_acc = WORKSPACE.get("pair_acc", (len(b.tile_list), 4), np.float32)
        nk.accumulate_tiles(
            b.rows, b.tile_start, b.tile_list, b.tile_slot, b.tile_order, b.grid[0], view.width, view.height, mask,
            scale, _NO_VALID if valid is None else valid, valid is not None,
            _ZERO_BG if background is None else background, background is not None, np.int64(weight_power),
            False, _NO_SLOTS, pair_acc, _NO_TILES, workers,
        )  # fmt: skip
        nk.reduce_pairs(pair_acc, b.gauss_start, b.order, color_sum, weight_sum, workers)
        return color_sum, weight_sum, len(b.order)


def tile_slots(labels: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Numba twin of votes.tile_slots_reference: (H, W) int8 slot map and (tiles, 4) int32 label table."""
    gx, gy = tile_grid(width, height)
    slot_map = np.empty((height, width), np.int8)
    tile_labels = np.empty((gx * gy, 4), np.int32)
    nk.tile_slots(np.ascontiguousarray(labels, np.int32), gx, gy, slot_map, tile_labels, numba.get_num_threads())
    return slot_map, tile_labels


def accumulate_votes(
    gmap: GaussianMap, labels: np.ndarray, view: View, weight_power: int, slots: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Per visible Gaussian with votes, in map order: map index, the `slots` heaviest labels and their votes, and the
    rest; and the number of Gaussians in view."""
    n = len(gmap)
    empty = (np.zeros(0, np.int64), np.zeros((0, slots), np.int32), np.zeros((0, slots)), np.zeros(0), 0)
    if n == 0:
        return empty
    with _LOCK:
        workers = numba.get_num_threads()
        slot_map, tile_labels = tile_slots(labels, view.width, view.height)
        b = bin_view(gmap, view, None, workers)
        nv = len(b.order)
        if nv == 0:
            return empty
        pair_acc = WORKSPACE.get("pair_acc", (len(b.tile_list), 4), np.float32)
        pair_tile = WORKSPACE.get("pair_tile", (len(b.tile_list),), np.int32)
        nk.accumulate_tiles(
            b.rows, b.tile_start, b.tile_list, b.tile_slot, b.tile_order, b.grid[0], view.width, view.height,
            _NO_MASK, np.float32(1.0), _NO_VALID, False, _ZERO_BG, False, np.int64(weight_power),
            True, slot_map, pair_acc, pair_tile, workers,
        )  # fmt: skip
        # Only the Gaussians with votes are reduced (raster.accumulate_votes keeps no others).
        voted = nk.voted_ranks(pair_acc, b.gauss_start, workers)
        m = len(voted)
        out_labels = np.empty((m, slots), np.int32)
        out_weights = np.empty((m, slots))
        out_other = np.empty(m)
        # Written in map order: merging them into the per-Gaussian state then walks it in memory order,
        # which took a third of the time of depth order's scattered rows (vote_kernels.merge_slots).
        ranks = voted[nk.ranks_by_index(b.order[voted], n)]
        nk.reduce_votes(pair_acc, pair_tile, tile_labels, b.gauss_start, ranks, out_labels, out_weights, out_other,
                        workers)  # fmt: skip
        return b.order[ranks].astype(np.int64), out_labels, out_weights, out_other, nv


def render(
    gmap: GaussianMap, colors: np.ndarray, view: View, background: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    h, w = view.height, view.width
    image = np.zeros((h, w, 3), np.float32)
    trans = np.ones((h, w), np.float32)
    depth = np.zeros((h, w), np.float32)
    bg = _ZERO_BG if background is None else background
    if len(gmap) == 0:
        image[:] = bg
        return image, trans, depth
    with _LOCK:
        workers = numba.get_num_threads()
        b = bin_view(gmap, view, colors, workers)
        nk.render_tiles(
            b.rows, b.tile_start, b.tile_list, b.tile_order, b.grid[0], w, h, bg, image, trans, depth, workers
        )
    return image, trans, depth
