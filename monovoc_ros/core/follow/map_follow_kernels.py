"""Numba kernels that keep a map update fast at robot scale (1-2M Gaussians), each with a plain twin that
tests hold it against:

* `move_points`: the motion of core.follow.map_motion (rigid, then the trilinear field); twin `MapMotion.apply`.
* `grid_nearest` (`PointGrid`, to search one grid many times): per query the nearest point within its own
  radius, on a sorted uniform grid; twin `map_follow.nearest_within_reference` (scipy's cKDTree).
* `surface_normals_kernel`: the normal of each flat Gaussian (the registration's targets); twin
  `map_motion.surface_normals_reference`.
* `field_sums`: the smooth field's per-node least-squares sums in one pass; twin `map_motion.field_sums_reference`
  (numpy's bincount, whose sums it equals bit for bit: the same products added in the same order).

At 1M Gaussians on 2 cores the twins take 0.65 s (the field) and ~0.8 s (tree build and query); the kernels
a few tens of milliseconds each (benchmarks/bench_map_churn.py). The covariance kernel (Sigma = R S S^T R^T)
and the parallel row gather (used here and by the evidence stores) are core.map.gaussians'.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from monovoc_ros.core.map.gaussians import finite_box, gather_rows
from monovoc_ros.core.map.sorting import argsort_keys, radix_argsort

# Grid keys pack three 21-bit cell coordinates (2M cells per axis: 40 km at 2 cm).
_BITS = 21
_OFFSET = 1 << (_BITS - 1)


@numba.njit(cache=True, nogil=True, inline="always")
def _corner(frac, base, d, size):  # pragma: no cover - numba
    """Weight and index of one trilinear corner along one axis (d: 0 lower, 1 upper)."""
    return (frac if d else 1.0 - frac), min(base + d, size - 1)


@numba.njit(cache=True, nogil=True, inline="always")
def _cell_of(q, origin, spacing, size):  # pragma: no cover - numba
    g = min(max((q - origin) / spacing, 0.0), size - 1.0)
    b = min(int(np.floor(g)), max(size - 2, 0))
    return b, g - b


@numba.njit(cache=True, nogil=True, parallel=True)
def move_points(points, rotation, translation, offsets, origin, spacing):  # pragma: no cover - numba
    """(N, 3) float64: points (N, 3) moved by R p + t + trilinear(offsets) at R p + t (grid clamped). Scalars only:
    four scratch arrays per point took 3/4 of its time."""
    n = points.shape[0]
    out = np.empty((n, 3))
    gx, gy, gz = offsets.shape[0], offsets.shape[1], offsets.shape[2]
    for i in numba.prange(n):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        q0 = rotation[0, 0] * px + rotation[0, 1] * py + rotation[0, 2] * pz + translation[0]
        q1 = rotation[1, 0] * px + rotation[1, 1] * py + rotation[1, 2] * pz + translation[1]
        q2 = rotation[2, 0] * px + rotation[2, 1] * py + rotation[2, 2] * pz + translation[2]
        b0, f0 = _cell_of(q0, origin[0], spacing, gx)
        b1, f1 = _cell_of(q1, origin[1], spacing, gy)
        b2, f2 = _cell_of(q2, origin[2], spacing, gz)
        a0 = a1 = a2 = 0.0
        for c in range(8):
            w0, ii = _corner(f0, b0, (c >> 2) & 1, gx)
            w1, jj = _corner(f1, b1, (c >> 1) & 1, gy)
            w2, kk = _corner(f2, b2, c & 1, gz)
            w = w0 * w1 * w2
            a0 += w * offsets[ii, jj, kk, 0]
            a1 += w * offsets[ii, jj, kk, 1]
            a2 += w * offsets[ii, jj, kk, 2]
        out[i, 0] = q0 + a0
        out[i, 1] = q1 + a1
        out[i, 2] = q2 + a2
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def _key(ix, iy, iz):
    return ((ix + _OFFSET) << (2 * _BITS)) | ((iy + _OFFSET) << _BITS) | (iz + _OFFSET)


@numba.njit(cache=True, nogil=True, inline="always")
def _slot(key, bits):
    # Fibonacci hashing: the top `bits` bits of the product depend on every bit of the packed key.
    return np.int64((np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(64 - bits))


@numba.njit(cache=True, nogil=True)
def _cell_table(cell_keys):
    """Open-addressing hash table cell key -> cell index (keys -1 where empty)."""
    bits = 4
    while (1 << bits) < 2 * cell_keys.shape[0]:
        bits += 1
    size = 1 << bits
    mask = size - 1
    keys = np.full(size, -1, np.int64)
    values = np.empty(size, np.int64)
    for c in range(cell_keys.shape[0]):
        h = _slot(cell_keys[c], bits)
        while keys[h] != -1:
            h = (h + 1) & mask
        keys[h] = cell_keys[c]
        values[h] = c
    return keys, values


@numba.njit(cache=True, nogil=True, inline="always")
def _find(keys, values, bits, key):
    mask = keys.shape[0] - 1
    h = _slot(key, bits)
    while True:
        k = keys[h]
        if k == key:
            return values[h]
        if k == -1:
            return -1
        h = (h + 1) & mask


@numba.njit(cache=True, nogil=True, parallel=True)
def _cell_keys(points, cell):  # pragma: no cover - numba
    n = points.shape[0]
    keys = np.empty(n, np.int64)
    for i in numba.prange(n):
        ix = int(np.floor(points[i, 0] / cell))
        iy = int(np.floor(points[i, 1] / cell))
        iz = int(np.floor(points[i, 2] / cell))
        keys[i] = _key(ix, iy, iz)
    return keys


@numba.njit(cache=True, nogil=True, parallel=True)
def _box_cell_keys(points, cell, low, span):  # pragma: no cover - numba
    """(N,) int64 cell keys numbered on the cells' own box (low, span (3,) int64): x-major, as `_key` orders cells."""
    n = points.shape[0]
    keys = np.empty(n, np.int64)
    for i in numba.prange(n):
        ix = int(np.floor(points[i, 0] / cell)) - low[0]
        iy = int(np.floor(points[i, 1] / cell)) - low[1]
        iz = int(np.floor(points[i, 2] / cell)) - low[2]
        keys[i] = (ix * span[1] + iy) * span[2] + iz
    return keys


def cell_order(points: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """The points (N, 3) float64 sorted by cell: (order (N,) int64, stable, in the order of `_key`'s packed keys;
    sorted keys (N,) int64, equal within a packed key, as the search's table holds them). Cells within the packing's
    reach (+-2**20 per axis) are numbered on their own box, so a building's keys take ~24 bits and sort in two radix
    passes, where the 63-bit packed keys took four (1M points: 33 -> 15 ms)."""
    if not len(points):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    # The cells' box from the points' (floor of p / cell is monotonic in p: the same cells as per point).
    lower, upper, finite = finite_box(points)
    # A non-finite point (its cell coordinate is then anything), or cells beyond `_key`'s packing (there distinct
    # cells share a packed key, as the search's table does): the packed keys themselves.
    low = np.floor(lower / cell).astype(np.int64) if finite else np.zeros(3, np.int64)
    high = np.floor(upper / cell).astype(np.int64) if finite else np.zeros(3, np.int64)
    span = high - low + 1
    if finite < len(points) or int(low.min()) < -_OFFSET or int(high.max()) >= _OFFSET:
        keys = _cell_keys(points, float(cell))
        order = argsort_keys(keys)
        return order, keys[order]
    keys = _box_cell_keys(points, float(cell), low, span)  # < 2**63: each span is at most 2**21
    bits = max(1, (int(span[0]) * int(span[1]) * int(span[2]) - 1).bit_length())
    passes = -(-bits // 16)
    order = radix_argsort(keys.copy(), np.arange(len(keys), dtype=np.int64), -(-bits // passes), bits)
    return order, keys[order]


@numba.njit(cache=True, nogil=True, inline="always")
def _scan(sorted_points, order, cell_starts, c, qx, qy, qz, best, best_i):
    """The nearest of cell c's points if nearer than (best, best_i) (ties: the lower row)."""
    for s in range(cell_starts[c], cell_starts[c + 1]):
        ex = sorted_points[s, 0] - qx
        ey = sorted_points[s, 1] - qy
        ez = sorted_points[s, 2] - qz
        d = ex * ex + ey * ey + ez * ez
        i = order[s]
        if d < best or (d == best and (best_i < 0 or i < best_i)):
            best = d
            best_i = i
    return best, best_i


_MARGIN = 1e-6  # metres


@numba.njit(cache=True, nogil=True, inline="always")
def _face_gap(d, lo, hi):
    """Distance along one axis from a query to the neighbour cell at offset d (-1, 0, 1), never negative."""
    if d == 0:
        return 0.0
    gap = lo if d < 0 else hi
    return gap if gap > 0.0 else 0.0


@numba.njit(cache=True, nogil=True, parallel=True)
def _search(
    sorted_points, order, table_keys, table_values, cell_starts, queries, q_starts, radius, cell
):  # pragma: no cover
    """Per query (sorted by cell; q_starts: first query of each query cell) its nearest point within radius."""
    nq = queries.shape[0]
    out = np.full(nq, -1, np.int64)
    bits = 0
    while (1 << bits) < table_keys.shape[0]:
        bits += 1
    for g in numba.prange(q_starts.shape[0] - 1):
        j0 = q_starts[g]
        cx = int(np.floor(queries[j0, 0] / cell))
        cy = int(np.floor(queries[j0, 1] / cell))
        cz = int(np.floor(queries[j0, 2] / cell))
        # The 27 cells around this query cell, each looked up once for all its queries, when one first needs it
        # (-2: not yet): most queries find their match in their own cell, and each lookup is a cache miss in the
        # table (1M queries at 1M Gaussians: 27 lookups per query cell took ~half of the search).
        near = np.full(27, -2, np.int64)
        near[13] = _find(table_keys, table_values, bits, _key(cx, cy, cz))
        for j in range(j0, q_starts[g + 1]):
            r = radius[j]
            qx, qy, qz = queries[j, 0], queries[j, 1], queries[j, 2]
            best = r * r
            best_i = -1
            if near[13] >= 0:  # its own cell first: in a dense map the match is there and prunes the others
                best, best_i = _scan(sorted_points, order, cell_starts, near[13], qx, qy, qz, best, best_i)
            # Distances to the faces of its own cell, less a margin for the rounding of floor(p / cell).
            lo_x, hi_x = qx - cx * cell - _MARGIN, (cx + 1) * cell - qx - _MARGIN
            lo_y, hi_y = qy - cy * cell - _MARGIN, (cy + 1) * cell - qy - _MARGIN
            lo_z, hi_z = qz - cz * cell - _MARGIN, (cz + 1) * cell - qz - _MARGIN
            # Nearer to the best so far (or its radius) than to any face of its own cell: no neighbour cell holds a
            # nearer point (each is at least that face away). Most queries of a map update end here.
            face = min(lo_x, hi_x, lo_y, hi_y, lo_z, hi_z)
            if face <= 0.0 or face * face <= best:
                k = -1
                for dx in range(-1, 2):
                    gx = _face_gap(dx, lo_x, hi_x)
                    for dy in range(-1, 2):
                        gy = _face_gap(dy, lo_y, hi_y)
                        for dz in range(-1, 2):
                            k += 1
                            if k == 13:
                                continue
                            gz = _face_gap(dz, lo_z, hi_z)
                            if gx * gx + gy * gy + gz * gz > best:  # every point of that cell is farther
                                continue
                            if near[k] == -2:
                                near[k] = _find(table_keys, table_values, bits, _key(cx + dx, cy + dy, cz + dz))
                            if near[k] >= 0:
                                best, best_i = _scan(
                                    sorted_points, order, cell_starts, near[k], qx, qy, qz, best, best_i
                                )  # fmt: skip
            # Farther rings only when the radius reaches past them and nothing nearer than a cell was found:
            # a point of ring m is at least (m - 1) cells away.
            reach = int(np.ceil(r / cell))
            for ring in range(2, reach + 1):
                if best_i >= 0 and ((ring - 1) * cell) ** 2 >= best:
                    break
                for dx in range(-ring, ring + 1):
                    for dy in range(-ring, ring + 1):
                        # On the ring's side columns every z is new; inside the ring only its two caps.
                        step = 1 if (abs(dx) == ring or abs(dy) == ring) else 2 * ring
                        for dz in range(-ring, ring + 1, step):
                            c = _find(table_keys, table_values, bits, _key(cx + dx, cy + dy, cz + dz))
                            if c >= 0:
                                best, best_i = _scan(sorted_points, order, cell_starts, c, qx, qy, qz, best, best_i)
            out[j] = best_i
    return out


def _run_starts(sorted_keys: np.ndarray) -> np.ndarray:
    """(runs + 1,) int64: where each run of equal keys of `sorted_keys` (N,) starts, then N."""
    first = np.flatnonzero(np.concatenate(([True], sorted_keys[1:] != sorted_keys[:-1])))
    return np.append(first, len(sorted_keys)).astype(np.int64)


@dataclass(frozen=True)
class PointGrid:
    """Points binned in cubes of `cell` metres, sorted by cell, for nearest-within-radius searches
    (`PointGrid.nearest`): built once, searched as often as needed (the registration's targets)."""

    cell: float
    sorted_points: np.ndarray  # (N, 3) float64 the points in cell order
    order: np.ndarray  # (N,) int64 the row of each sorted point
    table_keys: np.ndarray  # open-addressing hash table: cell key -> index into cell_starts (keys -1: empty)
    table_values: np.ndarray
    cell_starts: np.ndarray  # (cells + 1,) int64 first sorted point of each cell

    @classmethod
    def build(cls, points: np.ndarray, cell: float) -> PointGrid:
        points = np.ascontiguousarray(points, np.float64).reshape(-1, 3)
        if not len(points):
            empty = np.zeros(0, np.int64)
            return cls(float(cell), points, empty, *_cell_table(empty), np.zeros(1, np.int64))
        # Stable; the order within a cell is free anyway: ties go to the lower row.
        order, sorted_keys = cell_order(points, cell)
        cell_starts = _run_starts(sorted_keys)
        sorted_points = gather_rows(points, order)
        # The table holds `_key`'s keys, which the search computes for any cell (beyond the box too).
        table_keys, table_values = _cell_table(_cell_keys(sorted_points[cell_starts[:-1]], float(cell)))
        return cls(float(cell), sorted_points, order, table_keys, table_values, cell_starts)

    def nearest(self, queries: np.ndarray, radius: np.ndarray) -> np.ndarray:
        """(Q,) int64: per query (Q, 3) the row of the nearest point within its radius (Q,) (ties: the lower
        row), or -1."""
        radius = np.ascontiguousarray(np.broadcast_to(radius, (len(queries),)), np.float64)
        if not len(self.order) or not len(queries):
            return np.full(len(queries), -1, np.int64)
        queries = np.ascontiguousarray(queries, np.float64)
        # Queries grouped by cell: each group looks its 27 neighbour cells up once, and neighbouring groups read
        # neighbouring memory.
        q_order, q_keys = cell_order(queries, self.cell)
        found = _search(
            self.sorted_points, self.order, self.table_keys, self.table_values, self.cell_starts,
            gather_rows(queries, q_order), _run_starts(q_keys), radius[q_order], self.cell,
        )  # fmt: skip
        out = np.empty(len(queries), np.int64)
        out[q_order] = found
        return out


def grid_nearest(points: np.ndarray, queries: np.ndarray, radius: np.ndarray, cell: float) -> np.ndarray:
    """(Q,) int64: per query (Q, 3) the row of the nearest of `points` (N, 3) within its radius (Q,) (ties: the
    lower row), or -1; points are binned in cubes of `cell` metres (about the typical radius)."""
    if not len(points) or not len(queries):
        return np.full(len(queries), -1, np.int64)
    return PointGrid.build(points, cell).nearest(queries, radius)


@numba.njit(cache=True, nogil=True)
def surface_normals_kernel(quats, scales, flat):  # pragma: no cover - numba
    """(N, 3) float64 unit normal (the axis of the smallest scale; the first of equal ones, NaN scales last) of each
    flat Gaussian (smallest scale under `flat` times the middle one), zero for the others: column j of the rotation
    of the normalized quaternion (N, 4) wxyz, the same float64 operations as the numpy code it replaced. 250k targets:
    ~2 ms where that took ~30."""
    n = quats.shape[0]
    out = np.zeros((n, 3))
    ordered = np.empty(3)  # the scales ascending, NaN last (as a stable argsort orders them)
    axes = np.empty(3, np.int64)
    for i in range(n):
        count = 0
        for a in range(3):  # insertion of the non-NaN scales, stable: the first of equal ones stays first
            scale = np.float64(scales[i, a])
            if scale != scale:
                continue
            b = count
            while b > 0 and ordered[b - 1] > scale:
                ordered[b] = ordered[b - 1]
                axes[b] = axes[b - 1]
                b -= 1
            ordered[b] = scale
            axes[b] = a
            count += 1
        if count < 2 or not ordered[0] < flat * ordered[1]:  # NaN among the two smallest: not flat
            continue
        j = axes[0]
        w, x, y, z = (np.float64(quats[i, 0]), np.float64(quats[i, 1]), np.float64(quats[i, 2]),
                      np.float64(quats[i, 3]))  # fmt: skip
        norm = np.sqrt(((w * w + x * x) + y * y) + z * z)
        w, x, y, z = w / norm, x / norm, y / norm, z / norm
        v = (x, y, z)
        k, m = (j + 1) % 3, (j + 2) % 3
        qj, qk, qm = v[j], v[k], v[m]
        out[i, j] = 1 - 2 * (qk * qk + qm * qm)
        out[i, k] = 2 * (qj * qk + w * qm)
        out[i, m] = 2 * (qj * qm - w * qk)
    return out


@numba.njit(cache=True, nogil=True)
def field_sums(flat, weights, A, Ar, n_nodes):  # pragma: no cover - numba
    """The smooth field's per-node sums over its sample's points p and their 8 nodes k (node flat[p, k], trilinear
    weight weights[p, k]): num (n_nodes, 3) of w Ar[p], M (n_nodes, 3, 3) of w A[p] and den (n_nodes,) of w."""
    num = np.zeros((n_nodes, 3))
    M = np.zeros((n_nodes, 3, 3))
    den = np.zeros(n_nodes)
    for p in range(flat.shape[0]):
        for k in range(flat.shape[1]):
            node = flat[p, k]
            w = weights[p, k]
            for c in range(3):
                num[node, c] += w * Ar[p, c]
            for a in range(3):
                for b in range(3):
                    M[node, a, b] += w * A[p, a, b]
            den[node] += w
    return num, M, den
