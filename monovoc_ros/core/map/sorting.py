"""Stable radix argsorts of integer keys (numba), used by every stage from the map on: the map's spatial chunks
(core.map.gaussians), the rasterizer's depth order, grid cells, object voxels, objects.db's ids."""

from __future__ import annotations

import numpy as np
from numba import njit


def argsort_keys(keys: np.ndarray) -> np.ndarray:
    """(N,) int64 stable argsort of non-negative int64 keys (grid cells, voxels of objects: 63 bits, the high
    ones mostly shared): `radix_argsort` on 16-bit digits; twin numpy's `argsort(kind="stable")`. 1M keys:
    ~15 ms; numpy's quicksort 160 ms."""
    return radix_argsort(np.array(keys, np.int64), np.arange(len(keys), dtype=np.int64), 16, 64)


@njit(cache=True, nogil=True)
def radix_argsort(keys, idx, digit_bits, key_bits):
    """`idx` ordered by the non-negative integer `keys` (the same length), stable: LSD radix sort on
    `digit_bits`-bit digits of the low `key_bits` bits, skipping a digit every key shares. Both arrays are
    used as scratch; returns the sorted `idx`."""
    n = keys.shape[0]
    if n < 2:
        return idx
    keys2 = np.empty_like(keys)
    idx2 = np.empty_like(idx)
    radix = 1 << digit_bits
    digit_mask = radix - 1
    hist = np.empty(radix, np.int64)
    for shift in range(0, key_bits, digit_bits):
        hist[:] = 0
        for m in range(n):
            hist[(keys[m] >> shift) & digit_mask] += 1
        if hist[(keys[0] >> shift) & digit_mask] == n:
            continue
        total = 0
        for b in range(radix):
            c = hist[b]
            hist[b] = total
            total += c
        for m in range(n):
            b = (keys[m] >> shift) & digit_mask
            p = hist[b]
            hist[b] = p + 1
            keys2[p] = keys[m]
            idx2[p] = idx[m]
        keys, keys2 = keys2, keys
        idx, idx2 = idx2, idx
    return idx
