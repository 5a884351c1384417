"""Numba kernel that adds per-object votes into the bounded per-Gaussian slots of a VoteState.

Plain twin: `votes.merge_slots_reference`. Per row the stored slots and the new entries are combined
(equal objects add), ordered by votes (descending, then object id ascending), the first `m` kept and
the rest added to "other"; exact whenever a row holds at most m objects.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from monovoc_ros.core.raster.numba_kernels import select_heaviest

EMPTY = np.uint32(0xFFFFFFFF)


_CHUNK = 2048  # rows per work item of the parallel loops


@njit(cache=True, nogil=True, parallel=True)
def merge_slots(objects, votes, other, rows, add_objects, add_votes, add_other):
    """In place, for each v: row rows[v] of (objects, votes, other) += (add_objects[v], add_votes[v], add_other[v]).
    Rows are distinct, so chunks of them run on numba's threads without sharing anything."""
    m = objects.shape[1]
    e = add_objects.shape[1]
    n_chunks = (rows.shape[0] + _CHUNK - 1) // _CHUNK
    for c in prange(n_chunks):
        objs = np.empty(m + e, np.uint32)
        wts = np.empty(m + e, np.float64)
        for v in range(c * _CHUNK, min(rows.shape[0], (c + 1) * _CHUNK)):
            r = rows[v]
            n = 0
            for a in range(m):
                if votes[r, a] > 0.0:
                    objs[n] = objects[r, a]
                    wts[n] = votes[r, a]
                    n += 1
            for a in range(e):
                w = add_votes[v, a]
                if w <= 0.0:
                    continue
                o = add_objects[v, a]
                q = 0
                while q < n and objs[q] != o:
                    q += 1
                if q == n:
                    objs[n] = o
                    wts[n] = 0.0
                    n += 1
                wts[q] += w
            select_heaviest(objs, wts, n, m)
            rest = add_other[v]
            for a in range(m, n):
                rest += wts[a]
            for a in range(m):
                objects[r, a] = objs[a] if a < n else EMPTY
                votes[r, a] = wts[a] if a < n else 0.0
            other[r] += rest


@njit(cache=True, nogil=True, parallel=True)
def label_rows(objects, votes, other, rows, out_ids, out_confidence):
    """out_ids[r] / out_confidence[r] for each r in rows: the leading object (EMPTY when unobserved) and
    the vote margin (V1 - V2) / (sum V + other). Plain twin: VoteState.labels."""
    m = objects.shape[1]
    n_chunks = (rows.shape[0] + _CHUNK - 1) // _CHUNK
    for c in prange(n_chunks):
        for v in range(c * _CHUNK, min(rows.shape[0], (c + 1) * _CHUNK)):
            r = rows[v]
            v1 = votes[r, 0]
            if v1 <= 0.0:
                out_ids[r] = EMPTY
                out_confidence[r] = np.float32(0.0)
                continue
            total = other[r]
            for a in range(m):
                total += votes[r, a]
            v2 = votes[r, 1] if m > 1 else 0.0
            out_ids[r] = objects[r, 0]
            out_confidence[r] = np.float32((v1 - v2) / total)
