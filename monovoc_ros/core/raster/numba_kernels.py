"""Numba kernels of the CPU tile rasterizer (see numba_impl.py for the pipeline and PERF_NOTES.md).

Layout and numeric choices, all for the compositing loop, which is nearly all of the time:
- A tile's 256 pixels are stored as sixteen 4x4 blocks (block-major, row-major inside a block). A
  Gaussian visits only the block rows and block columns its alpha >= 1/255 ellipse reaches, as one
  contiguous run of 16 to 64 pixels per block row, which LLVM turns into SIMD code.
- The pixel loop is float32 with unsigned indices (no negative-index wraparound code) and a
  polynomial exp built from an integer bit-cast (a libm call would stop vectorization); the
  per-pair sums are reductions that fast-math reassociation lets LLVM vectorize.
- A pixel's state is one float: its transmittance T, negated once the pixel has stopped (the
  termination rule fired), so stopped pixels keep their final T and blend nothing more.
- Per Gaussian-tile pair the tile kernel writes its partial sums to that pair's own slot (slots
  are numbered Gaussian-major), and a per-Gaussian reduction adds a Gaussian's consecutive slots in
  a fixed order: results do not depend on thread count or scheduling, and no per-thread buffers are
  needed.
- Parallel loops hand out work (tiles, chunks of Gaussians) through an atomic counter rather than
  numba's static split: on a shared machine a pre-empted thread then delays only its current item.
"""

from __future__ import annotations

import math

import numpy as np
from llvmlite import ir
from numba import njit, prange
from numba.core import cgutils, types
from numba.extending import intrinsic

from monovoc_ros.core.map.sorting import radix_argsort
from monovoc_ros.core.raster.constants import (
    ALPHA_MAX,
    ALPHA_MIN,
    COV2D_DILATION,
    DEPTH_MIN_COVERAGE,
    EIGEN_FLOOR,
    NEAR_PLANE,
    RADIUS_SIGMAS,
    T_MIN,
    TILE,
)

# Numba types a float literal as float64, which would promote the whole lane loop: use these.
_F0 = np.float32(0.0)
_F1 = np.float32(1.0)
_FHALF = np.float32(0.5)
_F_ALPHA_MAX = np.float32(ALPHA_MAX)
_F_ALPHA_MIN = np.float32(ALPHA_MIN)
_F_T_MIN = np.float32(T_MIN)
_F_NEG_HALF = np.float32(-0.5)
_F_EXP_LO = np.float32(-30.0)  # exp(-30) ~ 1e-13 is far below alpha's threshold; avoids denormals
_F_LOG2E = np.float32(1.4426950408889634)
_F_LN2_HI = np.float32(0.693359375)  # Cody-Waite split of ln 2 (Cephes expf)
_F_LN2_LO = np.float32(-2.12194440e-4)
_P0 = np.float32(1.9875691500e-4)
_P1 = np.float32(1.3981999507e-3)
_P2 = np.float32(8.3334519073e-3)
_P3 = np.float32(4.1665795894e-2)
_P4 = np.float32(1.6666665459e-1)
_P5 = np.float32(5.0000001201e-1)
_I127 = np.int32(127)
_I23 = np.int32(23)
_U16 = np.uint64(16)

# Reassociation lets LLVM vectorize the per-pair sums (exp_nonpositive stays accurate under it: tested).
_FASTMATH = {"reassoc", "contract", "nsz"}
_PIXELS = TILE * TILE
_CHUNK = 4096  # Gaussians per work item of the per-Gaussian parallel loops
_BLOCKS_PER_ROW = TILE // 4
# Distinct labels one Gaussian can collect in one keyframe before the rest count as "other".
_VOTE_BUFFER = 64
# The ellipse used for culling tiles and blocks is padded so that float32 rounding in the pixel loop
# can never reach a pixel the float64 cull dropped.
_CULL_THR_REL = 1e-3
_CULL_THR_ABS = 1e-3
_CULL_PAD_PX = 1e-2

# Packed per-Gaussian rows (64 bytes, depth order).
ROW_U, ROW_V, ROW_A, ROW_R, ROW_S, ROW_O, ROW_THR, ROW_EY, ROW_DYR, ROW_Z, ROW_RED, ROW_GREEN, ROW_BLUE = range(13)
ROW_WIDTH = 16


@intrinsic
def _int32_bits_as_float32(typingctx, bits):
    if bits != types.int32:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())

    return types.float32(types.int32), codegen


@intrinsic
def _fetch_add(typingctx, counters, index):
    """Atomically counters[index] += 1; returns the previous value."""
    if not (isinstance(counters, types.Array) and counters.dtype == types.int64 and counters.ndim == 1):
        return None

    def codegen(context, builder, signature, args):
        arr_type = signature.args[0]
        arr = context.make_array(arr_type)(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, arr_type, arr, [args[1]])
        return builder.atomic_rmw("add", ptr, ir.Constant(ir.IntType(64), 1), "monotonic")

    return types.int64(counters, types.intp), codegen


@njit(cache=True, nogil=True)
def exp_nonpositive(x):
    """exp(x) for float32 x <= 0, to ~1 ulp, vectorizable (inputs below -30 return exp(-30))."""
    x = x if x > _F_EXP_LO else _F_EXP_LO
    x = x if x < _F0 else _F0
    # k = round(x / ln 2); truncation toward zero of a negative number is its ceiling.
    k = np.int32(x * _F_LOG2E - _FHALF)
    kf = np.float32(k)
    r = x - kf * _F_LN2_HI
    r = r - kf * _F_LN2_LO
    p = (((((_P0 * r + _P1) * r + _P2) * r + _P3) * r + _P4) * r + _P5) * (r * r) + r + _F1
    # 2^k from its IEEE-754 bits; computed in int64 by numba, narrowed back by LLVM.
    return p * _int32_bits_as_float32(np.int32((k + _I127) << _I23))


# --- projection ---------------------------------------------------------------------------------


@njit(cache=True, nogil=True, inline="always")
def _project_one(i, means, cov6, R, fx, fy, cx, cy, lims, far, gx, gy, u, v, conic, depth, rect):
    mx, my, mz = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
    x = R[0, 0] * mx + R[0, 1] * my + R[0, 2] * mz + R[0, 3]
    y = R[1, 0] * mx + R[1, 1] * my + R[1, 2] * mz + R[1, 3]
    z = R[2, 0] * mx + R[2, 1] * my + R[2, 2] * mz + R[2, 3]
    rect[i, 0] = 0
    rect[i, 1] = 0
    rect[i, 2] = 0
    rect[i, 3] = 0
    depth[i] = np.float32(z)
    if not (z >= NEAR_PLANE and z <= far) or not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        return
    xz = min(max(x / z, -lims[0]), lims[1])
    yz = min(max(y / z, -lims[2]), lims[3])
    j00, j02 = fx / z, -fx * xz / z
    j11, j12 = fy / z, -fy * yz / z
    # M = J W (2x3), then Sigma2D = M Sigma M^T + dilation.
    m00 = j00 * R[0, 0] + j02 * R[2, 0]
    m01 = j00 * R[0, 1] + j02 * R[2, 1]
    m02 = j00 * R[0, 2] + j02 * R[2, 2]
    m10 = j11 * R[1, 0] + j12 * R[2, 0]
    m11 = j11 * R[1, 1] + j12 * R[2, 1]
    m12 = j11 * R[1, 2] + j12 * R[2, 2]
    sxx, sxy, sxz = np.float64(cov6[i, 0]), np.float64(cov6[i, 1]), np.float64(cov6[i, 2])
    syy, syz, szz = np.float64(cov6[i, 3]), np.float64(cov6[i, 4]), np.float64(cov6[i, 5])
    t0x = sxx * m00 + sxy * m01 + sxz * m02
    t0y = sxy * m00 + syy * m01 + syz * m02
    t0z = sxz * m00 + syz * m01 + szz * m02
    t1x = sxx * m10 + sxy * m11 + sxz * m12
    t1y = sxy * m10 + syy * m11 + syz * m12
    t1z = sxz * m10 + syz * m11 + szz * m12
    a = m00 * t0x + m01 * t0y + m02 * t0z + COV2D_DILATION
    b = m10 * t0x + m11 * t0y + m12 * t0z
    c = m10 * t1x + m11 * t1y + m12 * t1z + COV2D_DILATION
    det = a * c - b * b
    if not (det > 0.0) or not math.isfinite(det):
        return
    mid = 0.5 * (a + c)
    radius = math.ceil(RADIUS_SIGMAS * math.sqrt(mid + math.sqrt(max(EIGEN_FLOOR, mid * mid - det))))
    pu = fx * x / z + cx
    pv = fy * y / z + cy
    x0 = min(max(math.floor((pu - radius) / TILE), 0.0), gx)
    x1 = min(max(math.floor((pu + radius + TILE - 1) / TILE), 0.0), gx)
    y0 = min(max(math.floor((pv - radius) / TILE), 0.0), gy)
    y1 = min(max(math.floor((pv + radius + TILE - 1) / TILE), 0.0), gy)
    if x1 <= x0 or y1 <= y0:
        return
    rect[i, 0] = np.int32(x0)
    rect[i, 1] = np.int32(x1)
    rect[i, 2] = np.int32(y0)
    rect[i, 3] = np.int32(y1)
    u[i] = np.float32(pu)
    v[i] = np.float32(pv)
    # The conic [[c, -b], [-b, a]] / det factored as q(d) = A (dx + R dy)^2 + S dy^2: a sum of two
    # non-negative terms. On needle-like footprints the expanded form cancels; in float32 its worst
    # error in q was 25x that of this one (1e-3 against 4e-5 on the tests' needle scenes).
    conic[i, 0] = np.float32(c / det)
    conic[i, 1] = np.float32(-b / c)
    conic[i, 2] = np.float32(1.0 / c)


@njit(cache=True, nogil=True, parallel=True)
def project(
    means, cov6, world_to_cam, fx, fy, cx, cy, lims, far, width, height, u, v, conic, depth, rect, live, chunk,
    n_workers,
):  # fmt: skip
    """EWA projection in float64 (see projection.py); rect = (0, 0, 0, 0) marks a culled Gaussian (before the
    near plane, beyond `far`, or touching no tile) and
    conic holds the factored form (A, R, S) of the inverse 2D covariance (see _project_one). Only the chunks of
    `chunk` consecutive Gaussians that `live` (n_chunks,) keeps are projected: the others' outputs are left as
    they were. The map's arrays come in the order of its chunks (GaussianMap.placed; `chunk` is MAP_CHUNK, an argument:
    numba's cache would keep another module's constant as it was compiled)."""
    n = means.shape[0]
    gx = (width + TILE - 1) // TILE
    gy = (height + TILE - 1) // TILE
    n_chunks = (n + chunk - 1) // chunk
    counter = np.zeros(1, np.int64)
    for _ in prange(n_workers):
        c = _fetch_add(counter, 0)
        while c < n_chunks:
            if live[c]:
                for i in range(c * chunk, min(n, (c + 1) * chunk)):
                    _project_one(
                        i, means, cov6, world_to_cam, fx, fy, cx, cy, lims, far, gx, gy, u, v, conic, depth, rect
                    )  # fmt: skip
            c = _fetch_add(counter, 0)


# --- depth order and packing ----------------------------------------------------------------------


@njit(cache=True, nogil=True)
def visible_by_depth(depth, rect, members, live, chunk):
    """Place indices (into the map's arrays in chunk order, see `project`) of the visible Gaussians of the `live`
    chunks, sorted by depth, ties in map order (`members`: each place's map index, GaussianMap.chunk_members):
    LSD radix sorts, first on the map index, then, stable, on the float32 depth's bit pattern (which orders like
    the value for positive floats)."""
    n = depth.shape[0]
    count = 0
    for c in range(live.shape[0]):
        if live[c]:
            for i in range(c * chunk, min(n, (c + 1) * chunk)):
                if rect[i, 1] > rect[i, 0]:
                    count += 1
    idx = np.empty(count, np.int32)
    keys = np.empty(count, np.int64)
    m = 0
    for c in range(live.shape[0]):
        if live[c]:
            for i in range(c * chunk, min(n, (c + 1) * chunk)):
                if rect[i, 1] > rect[i, 0]:
                    idx[m] = i
                    keys[m] = members[i]
                    m += 1
    index_bits = 1
    while (1 << index_bits) < n:
        index_bits += 1
    idx = radix_argsort(keys, idx, (index_bits + 1) // 2, index_bits)  # 2 passes
    bits = depth.view(np.uint32)
    depth_keys = np.empty(count, np.uint32)
    for m in range(count):
        depth_keys[m] = bits[idx[m]]
    return radix_argsort(depth_keys, idx, 11, 32)


@njit(cache=True, nogil=True, inline="always")
def _pack_one(r, i, u, v, conic, depth, opacities, colors, has_colors, rows, rects, rect):
    A = np.float64(conic[i, 0])
    R = np.float64(conic[i, 1])
    S = np.float64(conic[i, 2])
    B = A * R
    C = S + A * R * R
    o = np.float64(opacities[i])
    # q = d^T conic d <= thr  <=>  o exp(-q/2) >= 1/255; padded for the cull (module comment).
    thr = 2.0 * math.log(255.0 * o) if o > 0.0 else -1.0
    thr = thr + _CULL_THR_REL * abs(thr) + _CULL_THR_ABS
    ey = math.sqrt(thr / S) if thr > 0.0 else 0.0
    ex = math.sqrt(thr * C / (A * S)) if thr > 0.0 else 0.0
    rows[r, ROW_U] = u[i]
    rows[r, ROW_V] = v[i]
    rows[r, ROW_A] = conic[i, 0]
    rows[r, ROW_R] = conic[i, 1]
    rows[r, ROW_S] = conic[i, 2]
    rows[r, ROW_O] = opacities[i]
    rows[r, ROW_THR] = thr
    rows[r, ROW_EY] = ey
    rows[r, ROW_DYR] = -B * ex / C  # dy of the ellipse's rightmost point
    rows[r, ROW_Z] = depth[i]
    rows[r, ROW_RED] = colors[r, 0] if has_colors else 0.0
    rows[r, ROW_GREEN] = colors[r, 1] if has_colors else 0.0
    rows[r, ROW_BLUE] = colors[r, 2] if has_colors else 0.0
    rows[r, 13] = 0.0
    rows[r, 14] = 0.0
    rows[r, 15] = 0.0
    for k in range(4):
        rects[r, k] = rect[i, k]


@njit(cache=True, nogil=True, parallel=True)
def pack_rows(order, u, v, conic, depth, opacities, colors, has_colors, rows, rects, rect, n_workers):
    """Visible Gaussians' parameters in depth order, one 64-byte row each; `colors` (if any) are already in that
    order, one per row."""
    n = order.shape[0]
    n_chunks = (n + _CHUNK - 1) // _CHUNK
    counter = np.zeros(1, np.int64)
    for _ in prange(n_workers):
        c = _fetch_add(counter, 0)
        while c < n_chunks:
            for r in range(c * _CHUNK, min(n, (c + 1) * _CHUNK)):
                _pack_one(r, order[r], u, v, conic, depth, opacities, colors, has_colors, rows, rects, rect)
            c = _fetch_add(counter, 0)


# --- tile binning ---------------------------------------------------------------------------------


@njit(cache=True, nogil=True, inline="always")
def band_extent(rows, r, dy0, dy1):
    """x extent (relative to the mean) of the culling ellipse within dy0 <= dy <= dy1; lo > hi if empty."""
    thr = np.float64(rows[r, ROW_THR])
    ey = np.float64(rows[r, ROW_EY]) + _CULL_PAD_PX
    if thr <= 0.0 or dy1 < -ey or dy0 > ey:
        return 1.0, -1.0
    A = np.float64(rows[r, ROW_A])
    R = np.float64(rows[r, ROW_R])
    S = np.float64(rows[r, ROW_S])
    B = A * R
    det = A * S  # of the conic [[A, B], [B, C]] with C = S + A R^2
    lo_y = max(dy0, -ey)
    hi_y = min(dy1, ey)
    dyr = np.float64(rows[r, ROW_DYR])
    # The ellipse's right edge is concave in dy, its left edge convex: their extremes over the band
    # are at the extreme points of the ellipse clamped into the band.
    yr = min(max(dyr, lo_y), hi_y)
    yl = min(max(-dyr, lo_y), hi_y)
    hi = (-B * yr + math.sqrt(max(0.0, A * thr - det * yr * yr))) / A
    lo = (-B * yl - math.sqrt(max(0.0, A * thr - det * yl * yl))) / A
    return lo - _CULL_PAD_PX, hi + _CULL_PAD_PX


@njit(cache=True, nogil=True, inline="always")
def _tile_span(rows, r, ty, x0, x1):
    """Columns [a, b] of the tiles in tile row ty (within x0..x1-1) that the culling ellipse reaches."""
    u = np.float64(rows[r, ROW_U])
    v = np.float64(rows[r, ROW_V])
    lo, hi = band_extent(rows, r, ty * TILE - v, ty * TILE + TILE - 1 - v)
    if lo > hi:
        return 1, 0
    a = max(x0, int(math.ceil((u + lo - (TILE - 1)) / TILE)))
    b = min(x1 - 1, int(math.floor((u + hi) / TILE)))
    return a, b


@njit(cache=True, nogil=True, parallel=True)
def bin_tiles(rows, rects, n_tiles, gx, n_workers, list_buffer, slot_buffer):
    """Gaussian-tile pairs: a stable counting sort of the depth-ordered Gaussians into tile lists.

    Returns tile_start (n_tiles + 1) and, per pair in tile order, tile_list (its depth rank, front to
    back within a tile) and tile_slot (its Gaussian-major slot: Gaussian r owns slots
    gauss_start[r] .. gauss_start[r + 1] - 1), and gauss_start (n + 1). tile_list and tile_slot are
    the given buffers when these are large enough, else new ones with 25% headroom: only their first
    tile_start[n_tiles] entries are pairs (the caller slices them and keeps the buffers).
    """
    n = rows.shape[0]
    # Contiguous chunks of depth ranks keep each tile's list in depth order when filled chunk by chunk.
    n_chunks = max(1, min(64, (n + _CHUNK - 1) // _CHUNK))
    size = (n + n_chunks - 1) // n_chunks
    fill = np.zeros((n_chunks, n_tiles), np.int64)
    gauss_start = np.zeros(n + 1, np.int64)
    counter = np.zeros(2, np.int64)
    for _ in prange(n_workers):
        c = _fetch_add(counter, 0)
        while c < n_chunks:
            for r in range(c * size, min(n, (c + 1) * size)):
                pairs = 0
                for ty in range(rects[r, 2], rects[r, 3]):
                    a, b = _tile_span(rows, r, ty, rects[r, 0], rects[r, 1])
                    for tx in range(a, b + 1):
                        fill[c, ty * gx + tx] += 1
                    pairs += max(0, b - a + 1)
                gauss_start[r + 1] = pairs
            c = _fetch_add(counter, 0)
    for r in range(n):
        gauss_start[r + 1] += gauss_start[r]
    tile_start = np.zeros(n_tiles + 1, np.int64)
    total = 0
    for t in range(n_tiles):
        tile_start[t] = total
        for c in range(n_chunks):
            count = fill[c, t]
            fill[c, t] = total
            total += count
    tile_start[n_tiles] = total
    tile_list = list_buffer if list_buffer.shape[0] >= total else np.empty(total + total // 4, np.int32)
    tile_slot = slot_buffer if slot_buffer.shape[0] >= total else np.empty(total + total // 4, np.int64)
    for _ in prange(n_workers):
        c = _fetch_add(counter, 1)
        while c < n_chunks:
            for r in range(c * size, min(n, (c + 1) * size)):
                slot = gauss_start[r]
                for ty in range(rects[r, 2], rects[r, 3]):
                    a, b = _tile_span(rows, r, ty, rects[r, 0], rects[r, 1])
                    for tx in range(a, b + 1):
                        t = ty * gx + tx
                        p = fill[c, t]
                        fill[c, t] = p + 1
                        tile_list[p] = r
                        tile_slot[p] = slot
                        slot += 1
            c = _fetch_add(counter, 1)
    return tile_start, tile_list, tile_slot, gauss_start


# --- compositing ------------------------------------------------------------------------------------


@njit(cache=True, nogil=True, inline="always")
def _pixel_of(t, gx, k):
    """(x, y) of pixel k of tile t in block layout (block k // 16, row-major 4x4 inside a block)."""
    blk = k >> 4
    lane = k & 15
    return (t % gx) * TILE + (blk % _BLOCKS_PER_ROW) * 4 + (lane & 3), (t // gx) * TILE + (
        blk // _BLOCKS_PER_ROW
    ) * 4 + (lane >> 2)


@njit(cache=True, nogil=True)
def _tile_pixels(t, gx, px, py):
    """Pixel-centre coordinates of tile t in block layout."""
    for k in range(_PIXELS):
        x, y = _pixel_of(t, gx, k)
        px[k] = np.float32(x)
        py[k] = np.float32(y)


@njit(cache=True, nogil=True)
def _reset_transmittance(t, gx, width, height, T):
    """T = 1 on the image, -1 (stopped, so never blending) on a border tile's pixels off the image."""
    for k in range(_PIXELS):
        x, y = _pixel_of(t, gx, k)
        T[k] = _F1 if (x < width and y < height) else -_F1


@njit(cache=True, nogil=True)
def _load_observations(t, gx, width, height, mask, scale, valid, has_valid, y0, y1, y2, val):
    for k in range(_PIXELS):
        x, y = _pixel_of(t, gx, k)
        if x < width and y < height:
            y0[k] = np.float32(mask[y, x, 0]) * scale
            y1[k] = np.float32(mask[y, x, 1]) * scale
            y2[k] = np.float32(mask[y, x, 2]) * scale
            val[k] = _F1 if (not has_valid or valid[y, x]) else _F0
        else:
            y0[k] = _F0
            y1[k] = _F0
            y2[k] = _F0
            val[k] = _F0


@njit(cache=True, nogil=True, inline="always")
def _pair_blocks(rows, r, ox, oy):
    """The blocks of a tile (top-left pixel ox, oy) that the culling ellipse reaches, as block rows
    [br0, br1] (none when br1 < br0) times pixels [c0, c1) of each block row (from its first pixel).

    One column run for all the block rows, from the ellipse's x extent over their whole band: a run per
    block row visits ~20% fewer pixels but computes band_extent (two sqrt, two divisions) per block row,
    and accumulate_tiles took a third longer that way (bench: synthetic room, 140k). The extra pixels
    lie outside the ellipse, where alpha is below ALPHA_MIN: they blend alpha 0, leaving T and every
    sum exactly as they were."""
    u = np.float64(rows[r, ROW_U])
    v = np.float64(rows[r, ROW_V])
    ey = np.float64(rows[r, ROW_EY]) + _CULL_PAD_PX
    br0 = max(0, int(math.ceil((v - ey - oy - 3.0) * 0.25)))
    br1 = min(_BLOCKS_PER_ROW - 1, int(math.floor((v + ey - oy) * 0.25)))
    lo, hi = band_extent(rows, r, oy + br0 * 4 - v, oy + br1 * 4 + 3 - v)
    a = max(0, int(math.ceil((u + lo - ox - 3.0) * 0.25)))
    b = min(_BLOCKS_PER_ROW - 1, int(math.floor((u + hi - ox) * 0.25)))
    if lo > hi or b < a:
        return 0, -1, np.uint64(0), np.uint64(0)
    return br0, br1, np.uint64(a * 16), np.uint64(b * 16 + 16)


@njit(cache=True, nogil=True, inline="always")
def _row_start(br):
    """First pixel of block row br in the tile's block layout."""
    return np.uint64(br * _BLOCKS_PER_ROW * 16)


@njit(cache=True, nogil=True, inline="always")
def _footprint(rows, r):
    return rows[r, ROW_U], rows[r, ROW_V], rows[r, ROW_A], rows[r, ROW_R], rows[r, ROW_S], rows[r, ROW_O]


@njit(cache=True, nogil=True, fastmath=_FASTMATH)
def _alpha(px, py, u, v, A, R, S, o):
    dx = px - u
    dy = py - v
    t = dx + R * dy
    power = _F_NEG_HALF * (A * t * t + S * dy * dy)
    a = o * exp_nonpositive(power)
    a = a if a < _F_ALPHA_MAX else _F_ALPHA_MAX
    # A positive power can only be rounding error; the CUDA rasterizers skip it.
    return a if (a >= _F_ALPHA_MIN and power <= _F0) else _F0


@njit(cache=True, nogil=True, fastmath=_FASTMATH, inline="always")
def _blend(T, k, a):
    """Composites alpha `a` over pixel k: returns its weight a T and updates T, or, when T would fall
    below T_MIN, stops the pixel (T negated: it keeps its final value and blends nothing more)."""
    Tk = T[k]
    nT = Tk * (_F1 - a)
    go = nT >= _F_T_MIN
    T[k] = nT if go else -abs(Tk)
    return a * Tk if go else _F0


@njit(cache=True, nogil=True)
def _any_live(T):
    for k in range(T.shape[0]):
        if T[k] > _F0:
            return True
    return False


@njit(cache=True, nogil=True, fastmath=_FASTMATH)
def _transmittance_pass(rows, tile_list, j0, j1, t, gx, px, py, T):
    """Front-to-back compositing of one tile that only tracks transmittance."""
    ox = (t % gx) * TILE
    oy = (t // gx) * TILE
    for j in range(j0, j1):
        r = tile_list[j]
        u, v, A, R, S, o = _footprint(rows, r)
        br0, br1, lo, hi = _pair_blocks(rows, r, ox, oy)
        for br in range(br0, br1 + 1):
            first = _row_start(br)
            for k in range(first + lo, first + hi):
                _blend(T, k, _alpha(px[k], py[k], u, v, A, R, S, o))
        if (j - j0) % 32 == 31 and not _any_live(T):
            break


@njit(cache=True, nogil=True)
def _load_slots(t, gx, width, height, slot_map, o0, o1, o2, o3):
    """One-hot observations of a tile from its pixels' vote slots (slot_map: -1 = no evidence)."""
    for k in range(_PIXELS):
        x, y = _pixel_of(t, gx, k)
        s = slot_map[y, x] if (x < width and y < height) else np.int8(-1)
        o0[k] = _F1 if s == 0 else _F0
        o1[k] = _F1 if s == 1 else _F0
        o2[k] = _F1 if s == 2 else _F0
        o3[k] = _F1 if s == 3 else _F0


@njit(cache=True, nogil=True, fastmath=_FASTMATH)
def _accumulate_tile(t, rows, tile_start, tile_list, tile_slot, gx, width, height, mask, scale, valid, has_valid,
                     bg, has_bg, power, votes, slot_map, pair_acc, pair_tile):  # fmt: skip
    """Per pair of tile t, sum_p w^power o_c(p) for four observation channels o_0..o_3.

    SCD (votes False): o = (valid y_r, valid y_g, valid y_b, valid) with y = C - T_final b.
    Votes (votes True): o_c = [slot_map(p) == c], the pixel's object slot in this tile; the tile of
    every pair is recorded in pair_tile so that the reduction can name the slots' objects.
    """
    px = np.empty(_PIXELS, np.float32)
    py = np.empty(_PIXELS, np.float32)
    T = np.empty(_PIXELS, np.float32)
    o0 = np.empty(_PIXELS, np.float32)
    o1 = np.empty(_PIXELS, np.float32)
    o2 = np.empty(_PIXELS, np.float32)
    o3 = np.empty(_PIXELS, np.float32)
    _tile_pixels(t, gx, px, py)
    _reset_transmittance(t, gx, width, height, T)
    j0, j1 = tile_start[t], tile_start[t + 1]
    if votes:
        _load_slots(t, gx, width, height, slot_map, o0, o1, o2, o3)
    else:
        _load_observations(t, gx, width, height, mask, scale, valid, has_valid, o0, o1, o2, o3)
        if has_bg:
            # y_p = C_p - T_final(p) b needs T_final before any weight is summed: one extra pass.
            _transmittance_pass(rows, tile_list, j0, j1, t, gx, px, py, T)
            for k in range(_PIXELS):
                tf = abs(T[k])
                o0[k] -= tf * bg[0]
                o1[k] -= tf * bg[1]
                o2[k] -= tf * bg[2]
            _reset_transmittance(t, gx, width, height, T)
        # Validity folded into the observations: (w val)^k y = w^k (val y) for val in {0, 1}.
        for k in range(_PIXELS):
            o0[k] *= o3[k]
            o1[k] *= o3[k]
            o2[k] *= o3[k]
    ox = (t % gx) * TILE
    oy = (t // gx) * TILE
    for j in range(j0, j1):
        r = tile_list[j]
        u, v, A, R, S, o = _footprint(rows, r)
        acc_0 = _F0
        acc_1 = _F0
        acc_2 = _F0
        acc_3 = _F0
        br0, br1, lo, hi = _pair_blocks(rows, r, ox, oy)
        for br in range(br0, br1 + 1):
            first = _row_start(br)
            for k in range(first + lo, first + hi):
                w = _blend(T, k, _alpha(px[k], py[k], u, v, A, R, S, o))
                # w^power for power 1..4 by selects, which keep the loop vectorized (a pow call would not).
                w2 = w * w
                w = w if power == 1 else (w2 if power == 2 else (w2 * w if power == 3 else w2 * w2))
                acc_0 += w * o0[k]
                acc_1 += w * o1[k]
                acc_2 += w * o2[k]
                acc_3 += w * o3[k]
        s = tile_slot[j]
        pair_acc[s, 0] = acc_0
        pair_acc[s, 1] = acc_1
        pair_acc[s, 2] = acc_2
        pair_acc[s, 3] = acc_3
        if votes:
            pair_tile[s] = t
        if (j - j0) % 32 == 31 and not _any_live(T):
            for rest in range(j + 1, j1):
                pair_acc[tile_slot[rest], :] = _F0
                if votes:
                    pair_tile[tile_slot[rest]] = t
            break


@njit(cache=True, nogil=True, parallel=True)
def accumulate_tiles(rows, tile_start, tile_list, tile_slot, tile_order, gx, width, height, mask, scale, valid,
                     has_valid, bg, has_bg, power, votes, slot_map, pair_acc, pair_tile, n_workers):  # fmt: skip
    """Per-pair partial sums of every tile (see _accumulate_tile); tiles are taken in `tile_order`, one at a time."""
    n = tile_order.shape[0]
    counter = np.zeros(1, np.int64)
    for _ in prange(n_workers):
        m = _fetch_add(counter, 0)
        while m < n:
            _accumulate_tile(tile_order[m], rows, tile_start, tile_list, tile_slot, gx, width, height, mask, scale,
                             valid, has_valid, bg, has_bg, power, votes, slot_map, pair_acc, pair_tile)  # fmt: skip
            m = _fetch_add(counter, 0)


@njit(cache=True, nogil=True, parallel=True)
def reduce_pairs(pair_acc, gauss_start, order, color_sum, weight_sum, n_workers):
    """Per Gaussian, the float64 sum of its consecutive pair slots, written at its map index."""
    n = order.shape[0]
    n_chunks = (n + _CHUNK - 1) // _CHUNK
    counter = np.zeros(1, np.int64)
    for _ in prange(n_workers):
        c = _fetch_add(counter, 0)
        while c < n_chunks:
            for r in range(c * _CHUNK, min(n, (c + 1) * _CHUNK)):
                s0 = 0.0
                s1 = 0.0
                s2 = 0.0
                sw = 0.0
                for p in range(gauss_start[r], gauss_start[r + 1]):
                    s0 += pair_acc[p, 0]
                    s1 += pair_acc[p, 1]
                    s2 += pair_acc[p, 2]
                    sw += pair_acc[p, 3]
                i = order[r]
                weight_sum[i] = sw
                color_sum[i, 0] = s0
                color_sum[i, 1] = s1
                color_sum[i, 2] = s2
            c = _fetch_add(counter, 0)


# --- votes: tile slot tables and the per-Gaussian reduction --------------------------------------


@njit(cache=True, nogil=True)
def select_heaviest(keys, weights, n, k):
    """Moves the k heaviest of the first n entries to the front, in order: weight descending, then key
    ascending (a partial selection sort: n is a handful here)."""
    for a in range(min(n, k)):
        best = a
        for b in range(a + 1, n):
            if weights[b] > weights[best] or (weights[b] == weights[best] and keys[b] < keys[best]):
                best = b
        keys[a], keys[best] = keys[best], keys[a]
        weights[a], weights[best] = weights[best], weights[a]


@njit(cache=True, nogil=True, parallel=True)
def tile_slots(labels, gx, gy, slot_map, tile_labels, n_workers):
    """Each tile's object slots (see raster.votes): up to VOTE_TILE_SLOTS labels per tile, ordered by
    pixel count (descending, then label); a tile with more labels keeps the first three and pools the
    rest in slot 3 (label OTHER_LABEL). Writes every pixel's slot (-1 for label < 0) and the table."""
    h, w = labels.shape
    n_tiles = gx * gy
    counter = np.zeros(1, np.int64)
    for _ in prange(n_workers):
        found = np.empty(_PIXELS, np.int32)
        counts = np.empty(_PIXELS, np.int64)
        t = _fetch_add(counter, 0)
        while t < n_tiles:
            ox = (t % gx) * TILE
            oy = (t // gx) * TILE
            n = 0
            for y in range(oy, min(oy + TILE, h)):
                for x in range(ox, min(ox + TILE, w)):
                    lab = labels[y, x]
                    if lab < 0:
                        continue
                    q = 0
                    while q < n and found[q] != lab:
                        q += 1
                    if q == n:
                        found[n] = lab
                        counts[n] = 0
                        n += 1
                    counts[q] += 1
            select_heaviest(found, counts, n, n)
            for c in range(4):
                tile_labels[t, c] = found[c] if c < n else -1
            if n > 4:
                tile_labels[t, 3] = -2
            for y in range(oy, min(oy + TILE, h)):
                for x in range(ox, min(ox + TILE, w)):
                    lab = labels[y, x]
                    s = -1
                    if lab >= 0:
                        q = 0
                        while found[q] != lab:
                            q += 1
                        s = q if q < 3 or n <= 4 else 3
                    slot_map[y, x] = s
            t = _fetch_add(counter, 0)


@njit(cache=True, nogil=True)
def ranks_by_index(order, n):
    """(V,) int64 the depth ranks of `order` ((V,) map index per depth rank, distinct, < n) sorted by map index: a
    radix sort of the visible Gaussians' indices (two passes over V), where a mark per Gaussian of the map cost
    O(n) (1M: 1.2 ms and an 8 MB array per keyframe for ~94k visible)."""
    bits = 1
    while (1 << bits) < n:
        bits += 1
    return radix_argsort(order.astype(np.int64), np.arange(order.shape[0]), (bits + 1) // 2, bits)


@njit(cache=True, nogil=True, parallel=True)
def voted_ranks(pair_acc, gauss_start, n_workers):
    """(V',) int64 ascending: the depth ranks of the Gaussians with any positive vote in their pair slots, in one pass
    over the slots in memory order: every row that reduce_votes gives a weight or an `other` above 0, and a few it
    does not (a NaN beside a positive vote), which raster.accumulate_votes' filter drops as before. In a building
    most Gaussians in view are hidden (office_0 tiled to 1M: ~270k within 10 m, about half with any weight): the
    per-Gaussian reduction, whose reads follow map order and miss the cache, then skips them."""
    n = gauss_start.shape[0] - 1
    flags = np.zeros(n, np.bool_)
    n_chunks = (n + _CHUNK - 1) // _CHUNK
    counter = np.zeros(1, np.int64)
    for _ in prange(n_workers):
        c = _fetch_add(counter, 0)
        while c < n_chunks:
            for r in range(c * _CHUNK, min(n, (c + 1) * _CHUNK)):
                for p in range(gauss_start[r], gauss_start[r + 1]):
                    if pair_acc[p, 0] > 0 or pair_acc[p, 1] > 0 or pair_acc[p, 2] > 0 or pair_acc[p, 3] > 0:
                        flags[r] = True
                        break
            c = _fetch_add(counter, 0)
    return np.flatnonzero(flags)


@njit(cache=True, nogil=True, parallel=True)
def reduce_votes(pair_acc, pair_tile, tile_labels, gauss_start, ranks, out_labels, out_weights, out_other, n_workers):
    """Per Gaussian of depth rank r = ranks[at], the float64 votes of its pairs summed per label, written at
    at: the E heaviest labels (weight descending, then label) in out_labels / out_weights (-1 / 0 when
    fewer), the rest and the pooled slot 3 of crowded tiles in out_other."""
    n = ranks.shape[0]
    e = out_labels.shape[1]
    n_chunks = (n + _CHUNK - 1) // _CHUNK
    counter = np.zeros(1, np.int64)
    for _ in prange(n_workers):
        labs = np.empty(_VOTE_BUFFER, np.int32)
        wts = np.empty(_VOTE_BUFFER, np.float64)
        c = _fetch_add(counter, 0)
        while c < n_chunks:
            for at in range(c * _CHUNK, min(n, (c + 1) * _CHUNK)):
                r = ranks[at]
                m = 0
                other = 0.0
                for p in range(gauss_start[r], gauss_start[r + 1]):
                    t = pair_tile[p]
                    for ch in range(4):
                        wv = np.float64(pair_acc[p, ch])
                        if wv <= 0.0:
                            continue
                        lab = tile_labels[t, ch]
                        if lab < 0:
                            other += wv
                            continue
                        q = 0
                        while q < m and labs[q] != lab:
                            q += 1
                        if q == m:
                            if m == _VOTE_BUFFER:
                                other += wv
                                continue
                            labs[m] = lab
                            wts[m] = 0.0
                            m += 1
                        wts[q] += wv
                select_heaviest(labs, wts, m, e)
                for a in range(e):
                    out_labels[at, a] = labs[a] if a < m else -1
                    out_weights[at, a] = wts[a] if a < m else 0.0
                for a in range(e, m):
                    other += wts[a]
                out_other[at] = other
            c = _fetch_add(counter, 0)


@njit(cache=True, nogil=True, fastmath=_FASTMATH)
def _render_tile(t, rows, tile_start, tile_list, gx, width, height, bg, image, trans, depth):
    px = np.empty(_PIXELS, np.float32)
    py = np.empty(_PIXELS, np.float32)
    T = np.empty(_PIXELS, np.float32)
    c0 = np.zeros(_PIXELS, np.float32)
    c1 = np.zeros(_PIXELS, np.float32)
    c2 = np.zeros(_PIXELS, np.float32)
    cz = np.zeros(_PIXELS, np.float32)
    _tile_pixels(t, gx, px, py)
    _reset_transmittance(t, gx, width, height, T)
    ox = (t % gx) * TILE
    oy = (t // gx) * TILE
    j0, j1 = tile_start[t], tile_start[t + 1]
    for j in range(j0, j1):
        r = tile_list[j]
        u, v, A, R, S, o = _footprint(rows, r)
        cr, cg, cb, z = rows[r, ROW_RED], rows[r, ROW_GREEN], rows[r, ROW_BLUE], rows[r, ROW_Z]
        br0, br1, lo, hi = _pair_blocks(rows, r, ox, oy)
        for br in range(br0, br1 + 1):
            first = _row_start(br)
            for k in range(first + lo, first + hi):
                w = _blend(T, k, _alpha(px[k], py[k], u, v, A, R, S, o))
                c0[k] += w * cr
                c1[k] += w * cg
                c2[k] += w * cb
                cz[k] += w * z
        if (j - j0) % 32 == 31 and not _any_live(T):
            break
    for k in range(_PIXELS):
        x = int(px[k])
        y = int(py[k])
        if x < width and y < height:
            tf = abs(T[k])
            image[y, x, 0] = c0[k] + tf * bg[0]
            image[y, x, 1] = c1[k] + tf * bg[1]
            image[y, x, 2] = c2[k] + tf * bg[2]
            trans[y, x] = tf
            cover = _F1 - tf
            depth[y, x] = cz[k] / cover if cover > DEPTH_MIN_COVERAGE else _F0


@njit(cache=True, nogil=True, parallel=True)
def render_tiles(rows, tile_start, tile_list, tile_order, gx, width, height, bg, image, trans, depth, n_workers):
    n = tile_order.shape[0]
    counter = np.zeros(1, np.int64)
    for _ in prange(n_workers):
        m = _fetch_add(counter, 0)
        while m < n:
            _render_tile(tile_order[m], rows, tile_start, tile_list, gx, width, height, bg, image, trans, depth)
            m = _fetch_add(counter, 0)
