"""The kernels of core.object_geometry: every object's box and centroid in one parallel call (``percentile_boxes``)
and the main clusters of the objects' voxels (``main_voxel_clusters``).

Per object numpy's percentile and sums cost ~1.7 ms at a few thousand Gaussians, mostly call overhead: 130 ms
per publication after a keyframe at 1M Gaussians (25 objects changed), 300 ms from scratch (170 objects).
The plain twin is ``core.object_geometry.percentile_boxes_reference``; the tests hold the two equal bit for bit on
finite centres (up to the sign of a zero): the percentiles are numpy's "linear" method step by step on the order
statistics it reads (found by selection, not a sort: at 1M Gaussians a publication after two keyframes recomputes
objects of 100k+ Gaussians), and the sums run in row order as the reference's do. Where numpy would give NaN (an
axis with NaN, infinite values at the top) the kernel reads the sorted values; maps from the topic have neither.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(cache=True, nogil=True)
def _select(a, k):  # pragma: no cover - numba
    """Reorders ``a`` (n,) in place so that a[k] is its k-th smallest value, none after it smaller and none
    before it larger (Wirth's selection, median-of-three pivot), and returns it: O(n) expected where a sort is
    O(n log n). The value is the sort's whatever order it leaves (of +0.0 and -0.0, either)."""
    lo = 0
    hi = a.shape[0] - 1
    while lo < hi:
        mid = (lo + hi) // 2
        x, y, z = a[lo], a[mid], a[hi]
        pivot = max(min(x, y), min(max(x, y), z))
        i = lo
        j = hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while pivot < a[j]:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if j < k:
            lo = i
        if k < i:
            hi = j
    return a[k]


@njit(cache=True, nogil=True)
def _percentile(values, q, ordered):  # pragma: no cover - numba
    """numpy.percentile(method="linear") of ``values`` (n,) at quantile q in [0, 1], operation for operation, on
    the two order statistics it reads: selected (``values`` is reordered; NaN-free) or, if ``ordered``, read
    from ascending values."""
    n = values.shape[0]
    virtual = (n - 1) * q
    if virtual >= n - 1:
        return values[n - 1] if ordered else values.max()
    below = int(np.floor(virtual))
    if ordered:
        a = values[below]
        b = values[below + 1]
    else:
        a = _select(values, below)
        b = values[below + 1 :].min()  # the next order statistic: every value after `below` is >= a
    t = virtual - below
    diff = b - a
    if t >= 0.5:
        return b - diff * (1 - t)
    return a + diff * t


@njit(cache=True, nogil=True, parallel=True)
def percentile_boxes(means, opacities, rows, bounds, q_low, q_high, low, high, centroid):  # pragma: no cover
    """Object k's Gaussians are rows[bounds[k]:bounds[k + 1]] (non-empty, ascending) of ``means`` (N, 3) and
    ``opacities`` (N,): writes its box low[k], high[k] (the q_low and q_high quantiles per axis) and the
    opacity-weighted mean of the centres inside the box, centroid[k] (the plain mean when their opacities
    sum to zero)."""
    for k in prange(bounds.shape[0] - 1):
        start, end = bounds[k], bounds[k + 1]
        m = end - start
        pts = np.empty((m, 3), np.float64)
        for i in range(m):
            r = rows[start + i]
            for d in range(3):
                pts[i, d] = np.float64(means[r, d])
        column = np.empty(m, np.float64)
        for d in range(3):
            for i in range(m):
                column[i] = pts[i, d]
            ordered = np.isnan(column.sum())  # NaN breaks selection (its comparisons are all false): sort
            if ordered:
                column = np.sort(column)
            low[k, d] = _percentile(column, q_low, ordered)
            high[k, d] = _percentile(column, q_high, ordered)
        total = 0.0
        c0 = 0.0
        c1 = 0.0
        c2 = 0.0
        for i in range(m):
            x, y, z = pts[i, 0], pts[i, 1], pts[i, 2]
            if low[k, 0] <= x <= high[k, 0] and low[k, 1] <= y <= high[k, 1] and low[k, 2] <= z <= high[k, 2]:
                w = np.float64(opacities[rows[start + i]])
                total += w
                c0 += x * w
                c1 += y * w
                c2 += z * w
        if total > 0:
            centroid[k, 0] = c0 / total
            centroid[k, 1] = c1 / total
            centroid[k, 2] = c2 / total
        else:
            s0 = 0.0
            s1 = 0.0
            s2 = 0.0
            for i in range(m):
                s0 += pts[i, 0]
                s1 += pts[i, 1]
                s2 += pts[i, 2]
            centroid[k, 0] = s0 / m
            centroid[k, 1] = s1 / m
            centroid[k, 2] = s2 / m


@njit(cache=True, nogil=True)
def _root(parent, v):  # pragma: no cover - numba
    while parent[v] != v:
        parent[v] = parent[parent[v]]  # path halving
        v = parent[v]
    return v


@njit(cache=True, nogil=True)
def main_voxel_clusters(ordered, steps, object_shift, n_objects, min_share):  # pragma: no cover - numba
    """(M,) bool: which of the ascending voxel keys ``ordered`` (M,) int64 (one per Gaussian; the object in the
    bits from ``object_shift`` up, < n_objects) lie in a main cluster of their object: a connected component of
    its occupied voxels, neighbours being keys apart by one of ``steps`` (K,) (positive: half of the 26, the
    graph is symmetric), holding at least ``min_share`` of the Gaussians of the object's largest one (and at
    least one). Union-find over the distinct voxels; each step's neighbours are found by one merge-like walk
    of the sorted voxels. Twin: scipy's connected_components in core.object_geometry.main_cluster_ids_reference."""
    m = ordered.shape[0]
    voxel_of = np.empty(m, np.int64)
    voxels = np.empty(m, np.int64)
    sizes = np.zeros(m, np.int64)
    n = -1
    for i in range(m):
        if i == 0 or ordered[i] != ordered[i - 1]:
            n += 1
            voxels[n] = ordered[i]
        sizes[n] += 1
        voxel_of[i] = n
    n += 1
    parent = np.arange(n)
    for s in range(steps.shape[0]):
        step = steps[s]
        j = 0
        for v in range(n):
            target = voxels[v] + step
            while j < n and voxels[j] < target:
                j += 1
            if j == n:
                break
            if voxels[j] == target:
                a = _root(parent, v)
                b = _root(parent, j)
                if a != b:
                    parent[max(a, b)] = min(a, b)
    component_size = np.zeros(n, np.int64)
    for v in range(n):
        component_size[_root(parent, v)] += sizes[v]
    largest = np.zeros(n_objects, np.int64)
    for v in range(n):
        if parent[v] == v:
            o = voxels[v] >> object_shift
            largest[o] = max(largest[o], component_size[v])
    kept_voxel = np.empty(n, np.bool_)
    for v in range(n):
        need = max(1.0, min_share * largest[voxels[v] >> object_shift])
        kept_voxel[v] = component_size[_root(parent, v)] >= need
    out = np.empty(m, np.bool_)
    for i in range(m):
        out[i] = kept_voxel[voxel_of[i]]
    return out


@njit(cache=True, nogil=True)
def voxel_keys_by_object(order, cell_keys, slot_of, n_slots, object_shift):  # pragma: no cover - numba
    """The voxel keys of ``main_voxel_clusters`` from a map's Gaussians already in voxel order: ``order`` (F,) rows
    sorted by their packed voxel ``cell_keys`` (F,) (that order), ``slot_of`` (N,) each row's object (< n_slots) or
    -1 for rows not wanted. Returns the wanted rows' keys, object in the bits from ``object_shift`` up, ascending,
    and the rows in that order: a stable counting sort by object, two passes over the map where a sort of the
    wanted rows' keys took ~20 ms at 600k."""
    starts = np.zeros(n_slots + 1, np.int64)
    for i in range(order.shape[0]):
        s = slot_of[order[i]]
        if s >= 0:
            starts[s + 1] += 1
    for s in range(n_slots):
        starts[s + 1] += starts[s]
    keys = np.empty(starts[n_slots], np.int64)
    rows = np.empty(starts[n_slots], np.int64)
    for i in range(order.shape[0]):
        r = order[i]
        s = slot_of[r]
        if s >= 0:
            p = starts[s]
            starts[s] = p + 1
            keys[p] = (np.int64(s) << object_shift) | cell_keys[i]
            rows[p] = r
    return keys, rows
