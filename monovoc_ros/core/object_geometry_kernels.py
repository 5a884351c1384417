"""The kernels of core.object_geometry: every object's box and centroid in one parallel call (``percentile_boxes``,
on the objects' Gaussians grouped by ``group_by_object``) and the main clusters of the objects' voxels
(``main_voxel_clusters``).

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
    return _interpolate(a, b, virtual - below)


@njit(cache=True, nogil=True, inline="always")
def _interpolate(a, b, t):  # pragma: no cover - numba
    """numpy's "linear" step between two neighbouring order statistics a <= b, t in [0, 1)."""
    diff = b - a
    if t >= 0.5:
        return b - diff * (1 - t)
    return a + diff * t


_SAMPLE = 128  # values per axis of an object sampled for the pivots of _tail_quantiles
_SAMPLE_SLACK = 8  # sample ranks between a quantile and its pivot
_SAMPLED_MIN = 2048  # smaller objects: selection on the whole column


@njit(cache=True, nogil=True)
def _tail_quantiles(pts, start, end, d, q_low, q_high, lows, highs):  # pragma: no cover - numba
    """(found, low, high): ``_percentile`` of pts[start:end, d] at q_low and at q_high, from the values beyond two
    pivots taken from a sample. One pass copies the values at or below the low pivot into ``lows`` and those at or
    above the high one into ``highs`` (each at least the object's size): these are the smallest and the largest
    values, so the order statistics a tail quantile reads are among them (found False when the sample misled:
    the caller selects on the whole column; or a NaN). At the 1st / 99th percentiles selection then runs on a few
    percent of the values: selection on the whole column, mispredicted branches at every step, took ~50 ns a
    Gaussian for the three axes."""
    m = end - start
    step = m // _SAMPLE
    sample = np.empty(_SAMPLE, np.float64)
    for i in range(_SAMPLE):
        sample[i] = pts[start + i * step, d]
    sample.sort()
    lo_pivot = sample[min(_SAMPLE - 1, int(q_low * (_SAMPLE - 1)) + _SAMPLE_SLACK)]
    hi_pivot = sample[max(0, int(np.ceil(q_high * (_SAMPLE - 1))) - _SAMPLE_SLACK)]
    n_lo = 0
    n_hi = 0
    finite = True
    for i in range(start, end):
        v = pts[i, d]
        if v <= lo_pivot:
            lows[n_lo] = v
            n_lo += 1
        if v >= hi_pivot:
            highs[n_hi] = v
            n_hi += 1
        finite &= v == v
    if not finite or not (lo_pivot == lo_pivot and hi_pivot == hi_pivot):
        return False, 0.0, 0.0
    out = np.empty(2, np.float64)
    for j, q in enumerate((q_low, q_high)):
        virtual = (m - 1) * q
        if virtual >= m - 1:  # the maximum: among the values above the high pivot (one of the values)
            out[j] = highs[:n_hi].max()
            continue
        below = int(np.floor(virtual))
        if below + 1 < n_lo:  # both order statistics are among the n_lo smallest values
            a = _select(lows[:n_lo], below)
            b = lows[below + 1 : n_lo].min()
        elif below >= m - n_hi:  # among the n_hi largest: rank below is rank below - (m - n_hi) there
            k = below - (m - n_hi)
            a = _select(highs[:n_hi], k)
            b = highs[k + 1 : n_hi].min()
        else:
            return False, 0.0, 0.0
        out[j] = _interpolate(a, b, virtual - below)
    return True, out[0], out[1]


@njit(cache=True, nogil=True)
def group_by_object(means, opacities, rows, slot, n_slots):  # pragma: no cover - numba
    """The centres (M, 3) and opacities (M,) float64 of ``rows`` (M,) ascending, grouped by their object ``slot``
    (M,) < n_slots (ascending), in row order within each: a counting sort that reads the map in row order. Gathering
    each object's rows one object after the other read it at random once a map update had re-ordered the map: 13
    against 4 ms for the boxes of 360k Gaussians at 1M."""
    m = rows.shape[0]
    fill = np.zeros(n_slots + 1, np.int64)
    for j in range(m):
        fill[slot[j] + 1] += 1
    for k in range(n_slots):
        fill[k + 1] += fill[k]
    pts = np.empty((m, 3), np.float64)
    weights = np.empty(m, np.float64)
    for j in range(m):
        r = rows[j]
        p = fill[slot[j]]
        fill[slot[j]] = p + 1
        for d in range(3):
            pts[p, d] = np.float64(means[r, d])
        weights[p] = np.float64(opacities[r])
    return pts, weights


@njit(cache=True, nogil=True, parallel=True)
def percentile_boxes(pts, weights, bounds, q_low, q_high, low, high, centroid):  # pragma: no cover
    """Object k's Gaussians are pts[bounds[k]:bounds[k + 1]] (non-empty; centres (M, 3), opacities ``weights`` (M,),
    both float64, as ``group_by_object`` groups them): writes its box low[k], high[k] (the q_low and q_high quantiles
    per axis) and the opacity-weighted mean of the centres inside the box, centroid[k] (the plain mean when their
    opacities sum to zero), summed in the rows' order."""
    for k in prange(bounds.shape[0] - 1):
        start, end = bounds[k], bounds[k + 1]
        m = end - start
        column = np.empty(m, np.float64)
        lows = np.empty(m if m >= _SAMPLED_MIN else 0, np.float64)
        highs = np.empty(m if m >= _SAMPLED_MIN else 0, np.float64)
        for d in range(3):
            if m >= _SAMPLED_MIN:
                found, low[k, d], high[k, d] = _tail_quantiles(pts, start, end, d, q_low, q_high, lows, highs)
                if found:
                    continue
            for i in range(m):
                column[i] = pts[start + i, d]
            ordered = np.isnan(column.sum())  # NaN breaks selection (its comparisons are all false): sort
            if ordered:
                column = np.sort(column)
            low[k, d] = _percentile(column, q_low, ordered)
            high[k, d] = _percentile(column, q_high, ordered)
        total = 0.0
        c0 = 0.0
        c1 = 0.0
        c2 = 0.0
        for i in range(start, end):
            x, y, z = pts[i, 0], pts[i, 1], pts[i, 2]
            if low[k, 0] <= x <= high[k, 0] and low[k, 1] <= y <= high[k, 1] and low[k, 2] <= z <= high[k, 2]:
                w = weights[i]
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
            for i in range(start, end):
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
