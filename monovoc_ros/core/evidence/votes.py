"""Per-object vote evidence of one Gaussian map (METHOD.md section 8): the default semantic state.

Per Gaussian i and object o the evidence is ``V[i, o] = sum_p w_ip^k [label_p == o]`` over every pixel
of every integrated keyframe: plain float64 sums, so integration order does not matter and two states
of the same map merge by adding them. The label of a Gaussian is its argmax object; its confidence
is the vote margin ``(V1 - V2) / sum_o V[i, o]``. Voting is the closed-form optimum of the rendering L1
objective per object (FlashSplat), and unlike SCD's color average it cannot produce a third object's
color at the boundary of two.

Memory is bounded: each Gaussian keeps its `m` heaviest objects (`slots`) plus one "other" sum for
the rest: 12 m + 8 bytes per Gaussian (56 at m = 4). Whenever a Gaussian has seen at most m objects
(nearly all of them: a surface Gaussian sees its object and its neighbours') the state is exact; beyond
that a rarely seen object can be evicted to "other" and later votes for it restart its count.

Object ids are the packed palette colors (core.evidence.palette), so states built from the same masks agree
and states of two robots or two bags merge by object id. Stamps, ids, files and map updates behave as
for the SCD state (core.evidence.state.GaussianEvidence).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from monovoc_ros.core.evidence.palette import UNOBSERVED_ID
from monovoc_ros.core.evidence.state import GaussianEvidence

EMPTY_SLOT = UNOBSERVED_ID  # object id of an unused slot
DEFAULT_SLOTS = 4


def merge_slots_reference(
    objects: np.ndarray, votes: np.ndarray, other: np.ndarray, rows: np.ndarray, add_objects, add_votes, add_other
) -> None:
    """Plain twin of vote_kernels.merge_slots (in place, same ordering rule)."""
    m = objects.shape[1]
    for v, r in enumerate(rows):
        total: dict[int, float] = {}
        for o, w in zip(objects[r], votes[r], strict=True):
            if w > 0:
                total[int(o)] = total.get(int(o), 0.0) + float(w)
        for o, w in zip(add_objects[v], add_votes[v], strict=True):
            if w > 0:
                total[int(o)] = total.get(int(o), 0.0) + float(w)
        ranked = sorted(total.items(), key=lambda item: (-item[1], item[0]))
        objects[r] = [o for o, _ in ranked[:m]] + [EMPTY_SLOT] * max(0, m - len(ranked))
        votes[r] = [w for _, w in ranked[:m]] + [0.0] * max(0, m - len(ranked))
        other[r] += float(add_other[v]) + sum(w for _, w in ranked[m:])


def _distinct(rows: np.ndarray, n: int) -> bool:
    # A mark per Gaussian: O(V) where np.unique would sort.
    seen = np.zeros(n, bool)
    seen[rows] = True
    return int(np.count_nonzero(seen)) == rows.size


@dataclass(eq=False)
class VoteState(GaussianEvidence):
    objects: np.ndarray  # (N, m) uint32 object id per slot, heaviest first; EMPTY_SLOT where unused
    votes: np.ndarray  # (N, m) float64 votes per slot, descending
    other: np.ndarray  # (N,) float64 votes for objects not kept in a slot
    ids: np.ndarray | None = None  # (N,) int64 stable Gaussian ids
    stamps_ns: np.ndarray | None = None  # (K,) int64 stamps of the integrated keyframes

    FORMAT: ClassVar[str] = "monovoc_vote_state"
    WHAT: ClassVar[str] = "vote state"
    ARRAYS: ClassVar[tuple[str, ...]] = ("objects", "votes", "other")

    def __post_init__(self) -> None:
        objects = np.array(self.objects)
        votes = np.array(self.votes, dtype=np.float64)
        other = np.array(self.other, dtype=np.float64)
        if objects.ndim != 2 or objects.shape[1] < 1 or objects.dtype.kind not in "iu":
            raise ValueError(f"VoteState.objects: expected (N, m) integer ids, got {objects.shape} {objects.dtype}")
        n, m = objects.shape
        if votes.shape != (n, m) or other.shape != (n,):
            raise ValueError(f"VoteState: votes must be ({n}, {m}) and other ({n},), got {votes.shape}, {other.shape}")
        if not (np.isfinite(votes).all() and np.isfinite(other).all()) or (votes < 0).any() or (other < 0).any():
            raise ValueError("VoteState: votes must be finite and >= 0")
        if objects.size and (objects.min() < 0 or objects.max() > EMPTY_SLOT):
            raise ValueError("VoteState.objects: ids must be 32-bit unsigned")
        self.objects = objects.astype(np.uint32)
        self.votes = votes
        self.other = other
        self._init_common(n)

    @classmethod
    def zeros(cls, n: int, slots: int = DEFAULT_SLOTS, ids: np.ndarray | None = None) -> VoteState:
        if int(n) < 0 or int(slots) < 1:
            raise ValueError(f"VoteState.zeros: need n >= 0 and slots >= 1, got {n}, {slots}")
        n, slots = int(n), int(slots)
        objects = np.full((n, slots), EMPTY_SLOT, np.uint32)
        return cls._zeros(n, ids, objects=objects, votes=np.zeros((n, slots)), other=np.zeros(n))

    @property
    def slots(self) -> int:
        return self.objects.shape[1]

    def empty_like(self, n: int, ids: np.ndarray | None) -> VoteState:
        return VoteState.zeros(n, self.slots, ids)

    def add(self, rows: np.ndarray, objects: np.ndarray, votes: np.ndarray, other: np.ndarray, stamp_ns: int) -> None:
        """Adds one keyframe's votes: for each v, Gaussian rows[v] gets votes[v, e] for objects[v, e]
        (0 = unused entry) and other[v] for objects not named. Everything is checked before anything
        changes, so a rejected keyframe leaves the state as it was."""
        rows = np.asarray(rows)
        objects = np.asarray(objects)
        votes = np.asarray(votes, np.float64)
        other = np.asarray(other, np.float64)
        v = rows.shape[0] if rows.ndim == 1 else -1
        if v < 0 or rows.dtype.kind not in "iu" or objects.ndim != 2 or objects.shape[0] != v:
            raise ValueError(f"votes: expected rows (V,) and objects (V, E), got {rows.shape}, {objects.shape}")
        if votes.shape != objects.shape or other.shape != (v,):
            raise ValueError(
                f"votes: expected votes {objects.shape} and other ({v},), got {votes.shape}, {other.shape}"
            )
        if not (np.isfinite(votes).all() and np.isfinite(other).all()) or (votes < 0).any() or (other < 0).any():
            raise ValueError("votes must be finite and >= 0")
        if v and (rows.min() < 0 or rows.max() >= len(self) or not _distinct(rows, len(self))):
            raise ValueError(f"votes: rows must be distinct Gaussian indices in [0, {len(self)})")
        # Whole-array bounds first: a tenth of the cost of selecting the named entries, which only a
        # stray id in an unused entry makes necessary.
        if objects.size and (objects.min() < 0 or objects.max() > 0xFFFFFF):
            named = objects[votes > 0]
            if named.size and (named.min() < 0 or named.max() > 0xFFFFFF):
                raise ValueError("votes: object ids must be 24-bit packed colors")
        self._check_new_stamp(stamp_ns)
        self._merge(rows.astype(np.int64, copy=False), objects.astype(np.uint32, copy=False), votes, other)
        self.stamps_ns = np.append(self.stamps_ns, np.int64(stamp_ns))

    def _merge(self, rows, objects, votes, other) -> None:
        from monovoc_ros.core.evidence.vote_kernels import merge_slots

        merge_slots(self.objects, self.votes, self.other, rows, objects, votes, other)

    def merged(self, other: VoteState) -> VoteState:
        """The state holding both states' votes (same map; aligned by id when both have ids, else by
        position). Shared stamps raise: that keyframe would count twice. Exact when every Gaussian's
        objects of both states fit its slots."""
        take = self._aligned_rows(other)
        ids = self.ids if self.ids is not None else other.ids
        out = VoteState(self.objects, self.votes, self.other, ids, np.concatenate([self.stamps_ns, other.stamps_ns]))
        out._merge(np.arange(len(self), dtype=np.int64), other.objects[take], other.votes[take], other.other[take])
        return out

    def merge_objects(self, keep: int, drop: int) -> np.ndarray:
        """Object `drop` becomes object `keep`, exactly: every Gaussian's votes for `drop` are added to its
        votes for `keep` (as if every pixel that voted for `drop` had voted for `keep`). Returns the
        (R,) int64 rows that changed. Exact for the votes held in slots (evicted ones are in "other")."""
        keep, drop = int(keep), int(drop)
        if not (0 <= keep <= 0xFFFFFF and 0 <= drop <= 0xFFFFFF) or keep == drop:
            raise ValueError(f"merge_objects: need two distinct 24-bit object ids, got {keep:#x}, {drop:#x}")
        rows = np.flatnonzero(((self.objects == drop) & (self.votes > 0)).any(axis=1))
        objects = self.objects[rows]
        objects[objects == drop] = keep
        votes = self.votes[rows]
        self.objects[rows] = EMPTY_SLOT
        self.votes[rows] = 0.0
        self._merge(rows.astype(np.int64), objects, votes, np.zeros(rows.size))
        return rows

    def rename_objects(self, mapping: Mapping[int, int]) -> None:
        """Object ids renamed (old id -> new id; ids not in `mapping` stay): the same votes under other names
        (a rebuilt state taking the ids its predecessor's users know, core.segments.object_match). The new ids
        must be distinct and must not be ids that stay, else one Gaussian would hold one object in two slots."""
        moved = {int(a): int(b) for a, b in mapping.items() if int(a) != int(b)}
        if not moved:
            return
        src = np.array(sorted(moved), np.uint32)  # (K,)
        dst = np.array([moved[int(a)] for a in src], np.uint32)  # (K,)
        if np.unique(dst).size != dst.size or dst.max() > 0xFFFFFF:
            raise ValueError("rename_objects: new ids must be distinct 24-bit ids")
        pos = np.searchsorted(src, self.objects).clip(0, src.size - 1)  # (N, m)
        hit = src[pos] == self.objects  # (N, m)
        staying = np.unique(self.objects[~hit & (self.votes > 0)])
        if np.isin(dst, staying).any():
            raise ValueError("rename_objects: a new id is an id that stays")
        self.objects = np.where(hit, dst[pos], self.objects).astype(np.uint32)

    @property
    def observed(self) -> np.ndarray:
        """(N,) bool: Gaussians with a vote for some object."""
        return self.votes[:, 0] > 0

    @property
    def total_weight(self) -> np.ndarray:
        return self.votes.sum(axis=1) + self.other

    def relabel(self, rows: np.ndarray, ids: np.ndarray, confidence: np.ndarray) -> None:
        """Writes `labels` of the Gaussians `rows` into `ids` (N,) uint32 and `confidence` (N,) float32
        (the numba twin of `labels`, for the few rows a keyframe touched)."""
        from monovoc_ros.core.evidence.vote_kernels import label_rows

        label_rows(self.objects, self.votes, self.other, np.asarray(rows, np.int64), ids, confidence)

    def runner_up(self) -> np.ndarray:
        """(N,) uint32 the object with the second most votes of each Gaussian (UNOBSERVED_ID where none): where
        an object is being born inside another one, it is second before it leads."""
        if self.slots < 2:
            return np.full(len(self.votes), UNOBSERVED_ID, np.uint32)
        return np.where(self.votes[:, 1] > 0, self.objects[:, 1], UNOBSERVED_ID).astype(np.uint32)

    def support(self) -> np.ndarray:
        """(N,) float64 share of each Gaussian's leading object in its votes and the pooled ones (void votes
        included when void pixels are counted), 0 where unobserved."""
        best = self.votes[:, 0]
        total = best + self.other
        return np.divide(best, total, out=np.zeros(len(best)), where=total > 0)

    def labels(self, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Object id (uint32, UNOBSERVED_ID where unobserved) and confidence (float32 vote margin
        (V1 - V2) / sum V, 0 where unobserved) of every Gaussian, or of `rows` alone."""
        votes = self.votes if rows is None else self.votes[rows]
        objects = self.objects if rows is None else self.objects[rows]
        other = self.other if rows is None else self.other[rows]
        seen = votes[:, 0] > 0
        ids = np.where(seen, objects[:, 0], UNOBSERVED_ID).astype(np.uint32)
        second = votes[:, 1] if self.slots > 1 else np.zeros(len(votes))
        total = votes.sum(axis=1) + other
        margin = np.divide(votes[:, 0] - second, total, out=np.zeros(len(votes)), where=seen)
        return ids, margin.astype(np.float32)


def weakly_supported(ids: np.ndarray, support: np.ndarray, min_support: float) -> np.ndarray:
    """(N,) bool: labelled Gaussians whose ``support`` is below ``min_support`` times the median support
    of the Gaussians labelled with the same object. ``ids`` (N,) uint32 (UNOBSERVED_ID = unlabelled),
    ``support`` (N,) float64 (VoteState.support)."""
    labelled = np.flatnonzero(ids != UNOBSERVED_ID)
    weak = np.zeros(len(ids), bool)
    if labelled.size == 0:
        return weak
    # By object, then by support, in one float64 key (id * 2 + support, support in [0, 1]): a third of lexsort's
    # time (35 -> 10 ms at 200k Gaussians, on every semantic-cloud update).
    order = labelled[np.argsort(ids[labelled].astype(np.float64) * 2.0 + support[labelled])]
    _, first, counts = np.unique(ids[order], return_index=True, return_counts=True)
    sorted_support = support[order]
    median = 0.5 * (sorted_support[first + (counts - 1) // 2] + sorted_support[first + counts // 2])
    weak[order] = sorted_support < min_support * np.repeat(median, counts)
    return weak
