"""Numba kernel for `PaletteBuilder.update`: interior and blend pixel counts per color in one pass.

Its plain twins are `palette.interior_mask` and `palette.blend_mask` (tests hold the counts equal).
"""

from __future__ import annotations

import numba
import numpy as np

# Same exact integer blend test as palette.blend_mask: (|c-a|^2 |b-a|^2 - dot^2) / |b-a|^2 <= 9/4.
_BLEND_NUM = 9
_BLEND_DEN = 4


@numba.njit(cache=True, nogil=True, inline="always")
def lower_bound(ids: np.ndarray, value: np.uint32) -> int:
    """First position in the ascending ``ids`` whose id is >= ``value`` (ids.shape[0] when none): the binary
    search of every packed-color lookup in a kernel."""
    lo, hi = 0, ids.shape[0]
    while lo < hi:
        mid = (lo + hi) >> 1
        if ids[mid] < value:
            lo = mid + 1
        else:
            hi = mid
    return lo


@numba.njit(cache=True, nogil=True, inline="always")
def _is_blend(mask: np.ndarray, y: int, x: int, dy: int, dx: int) -> bool:
    dot = 0
    ab2 = 0
    ca2 = 0
    for ch in range(3):
        a = np.int64(mask[y - dy, x - dx, ch])
        ab = np.int64(mask[y + dy, x + dx, ch]) - a
        ca = np.int64(mask[y, x, ch]) - a
        dot += ca * ab
        ab2 += ab * ab
        ca2 += ca * ca
    return dot > 0 and dot < ab2 and _BLEND_DEN * (ca2 * ab2 - dot * dot) <= _BLEND_NUM * ab2


@numba.njit(cache=True, nogil=True)
def region_counts(mask: np.ndarray, packed: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per color of sorted `ids`: inner pixels whose 3x3 neighbourhood is all that color, and inner
    pixels that are a blend of two opposite neighbours (horizontal, vertical, diagonal)."""
    h, w = packed.shape
    interior = np.zeros(ids.shape[0], np.int64)
    blend = np.zeros(ids.shape[0], np.int64)
    last_c = np.uint32(0xFFFFFFFF)  # no 24-bit color: forces the first lookup
    last_k = 0
    for y in range(1, h - 1):
        for x in range(1, w - 1):
            c = packed[y, x]
            if c != last_c:  # colors come in runs: look each run up once
                last_c = c
                last_k = lower_bound(ids, c)
            if (
                packed[y, x - 1] == c
                and packed[y, x + 1] == c
                and packed[y - 1, x] == c
                and packed[y + 1, x] == c
                and packed[y - 1, x - 1] == c
                and packed[y - 1, x + 1] == c
                and packed[y + 1, x - 1] == c
                and packed[y + 1, x + 1] == c
            ):
                interior[last_k] += 1
                continue
            for d in range(4):
                dy = 0 if d == 0 else 1
                dx = 1 if d == 0 or d == 2 else (0 if d == 1 else -1)
                pa = packed[y - dy, x - dx]
                pb = packed[y + dy, x + dx]
                if pa != c and pb != c and pa != pb and _is_blend(mask, y, x, dy, dx):
                    blend[last_k] += 1
                    break
    return interior, blend
