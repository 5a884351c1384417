"""Object-level geometry of a semantic map: one object per palette color (METHOD section 5).

``object_geometry`` is THE geometry of the objects: the objects topic, its RViz markers, the query
answers and objects.db all report it (``SemanticResult.objects`` computes it once per result).

Which Gaussians describe an object's shape: confident ones in its main spatial cluster. Quantization
gives every observed Gaussian the nearest palette color, including Gaussians with weak or mixed evidence
(behind thin surfaces, at silhouettes, seen in few keyframes). Those land anywhere in the room, and for a
small object they can outnumber its own Gaussians (on the synthetic room at 140k Gaussians / 60
keyframes, 194 of the ball's 249 Gaussians lie elsewhere), so percentile boxes alone still span the room
("a large ball, 6 m wide"). Two filters fix the geometry (``main_cluster_ids``):

1. drop Gaussians whose confidence is below ``min_confidence``;
2. keep the largest 26-connected component of the object's occupied voxels (``voxel`` metres): an
   object is one piece, mislabeled Gaussians are scattered elsewhere. (``min_share`` < 1 also keeps
   components with that share of the largest one's Gaussians; on the synthetic room 0.2 let clusters of
   mislabeled Gaussians back in: the vase grew to 5.8 m, the picture to 5.6 m, so the default is 1.)

Of what is kept, the box spans the 1st..99th percentile of the centres on each axis (``percentile_boxes``:
a few stragglers inside the cluster do not inflate it) and the centroid is the opacity-weighted mean of
the centres inside that box. ``num_gaussians`` still counts all of the object's Gaussians.

Measured on the synthetic room (28 objects), error of the largest extent against the analytic solid's:

    map                          percentile box only         both filters (voxel 0.25 m)
                                 median   p75    max         median   p75    max
    140k Gaussians, 60 kf        2.31 m   3.90   5.76        0.018 m  0.069  0.65
     40k Gaussians, 24 kf        2.60 m   3.98   5.75        0.014 m  0.10   2.1

(the ball came out 6.0 m wide for 0.24 m before). Smaller voxels break thin or sparsely sampled parts
off (at 0.1 m and 40k Gaussians: median 0.38 m, the lamp lost its pole); 0.3 m starts merging
neighbours (140k: p75 0.18 m).

Speed (``benchmarks/bench_object_geometry.py``: office_0 tiled, labels of 30 mapped keyframes, 2 cores):
from scratch 23 / 127 / 270 ms at 0.2 / 1 / 2M Gaussians (the former implementation, kept as
``object_geometry_reference``: 31 / 175 / 399 ms). Each object's main cluster depends on its own Gaussians
only (the voxel keys hold the object), so given the geometry of an earlier labelling of the same map
(``previous``) only the objects whose Gaussians or confident Gaussians changed are computed again, with the
same result: 12 / 18 / 24 ms after one keyframe (9 objects changed, 70k of their Gaussians). The boxes and
centroids of all objects come from one parallel numba call and the main clusters from one union-find over the
voxels (core.object_geometry_kernels; on a 2.3-3.4x slower machine, 2026-12-05: 1M from scratch 430 -> 251-279
ms with the box kernel, then 171 ms with selection for the percentiles and the union-find (the reference: 402 ms
in that run); after one keyframe 57 -> 50-53 -> 27 ms). A live node's publication comes after several keyframes,
by which most objects changed (``bench_object_geometry.py --live 80``: office_0 tiled, keyframes in every tile, a
publication every 7 keyframes, a map update every 20): 101 -> 57 / 170 -> 81 ms at 1M / 2M since each map's
Gaussians are kept in voxel order (``_VoxelOrder``: the main clusters' keys without a sort), the objects' Gaussians
are grouped in row order in one pass and large objects' percentiles are selected beyond sampled pivots
(core.object_geometry_kernels).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from monovoc_ros.core.evidence.palette import UNOBSERVED_ID, VOID_ID, unpack_rgb
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.map.sorting import argsort_keys
from monovoc_ros.core.object_geometry_kernels import group_by_object, main_voxel_clusters, voxel_keys_by_object
from monovoc_ros.core.object_geometry_kernels import percentile_boxes as percentile_boxes_kernel

MIN_CONFIDENCE = 0.3
CLUSTER_VOXEL = 0.25  # metres; 0 keeps every Gaussian of the object (no cluster filter)
_LOW, _HIGH = 1.0, 99.0
_COORD_BITS = 13  # voxel coordinates per axis: 8192 voxels, 819 m at 0.1 m
_OFFSETS = np.array([(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)][14:], np.int64)
# A neighbour's key is the voxel's key plus this (cells stay in 1 .. 2**_COORD_BITS - 2: no field overflows).
_NEIGHBOUR_STEPS = (_OFFSETS << np.array([2 * _COORD_BITS, _COORD_BITS, 0])).sum(axis=1)
_ID_RANGE = 1 << 24  # object ids are packed 24-bit colors (VOID_ID the largest)


@dataclass
class ObjectSummary:
    id: int  # packed palette color r << 16 | g << 8 | b
    rgb: tuple[int, int, int]
    num_gaussians: int
    centroid: np.ndarray  # (3,) metres, map frame
    bbox_min: np.ndarray  # (3,)
    bbox_max: np.ndarray  # (3,)

    @property
    def extent(self) -> np.ndarray:
        return self.bbox_max - self.bbox_min


@dataclass(frozen=True, eq=False)
class _Labelling:
    """What an ObjectGeometry was computed from: what the next labelling of the same map is compared with."""

    gaussians: weakref.ref  # to the GaussianMap (not kept alive by its geometry)
    object_ids: np.ndarray  # (N,) uint32
    shaping: np.ndarray  # (N,) bool: the object Gaussians that may shape their object (confident ones)
    settings: tuple[float, float, bool]  # min_confidence, voxel, whether a confidence was given
    fits: bool  # the whole map's extent fits the voxel keys, so no labelling of it can overflow them
    voxels: _VoxelOrder | None  # the map's Gaussians in voxel order, kept for the next labelling of the map


class _VoxelOrder:
    """A map's Gaussians sorted by their voxel (the main clusters' keys without the object), made once per map when a
    labelling first recomputes much of it, kept by its labellings: the main clusters of many Gaussians then take a
    counting sort of their rows by object (two passes over the map) instead of a sort of their keys. At 1M
    Gaussians a publication after a few keyframes recomputes most objects (600k+ Gaussians): their keys' sort and
    making them took ~45 of the geometry's ~100 ms."""

    def __init__(self, voxel: float) -> None:
        self.voxel = voxel
        self._made = False
        self._sorted: tuple[np.ndarray, np.ndarray] | None = None

    def sorted(self, means: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """The rows (N,) int32 sorted by voxel and their packed voxel coordinates (N,) int64 in that order, of the
        map at ``means`` (N, 3); None where each labelling's keys are made from its own Gaussians instead: a centre
        that is not finite, or a map whose extent does not fit the keys (``_check_extent`` decides per labelling)."""
        if not self._made:  # two threads may both make it: the same arrays
            self._sorted, self._made = self._make(means), True
        return self._sorted

    def _make(self, means: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        if len(means) == 0 or not np.isfinite(means).all():
            return None
        cells = _cells(means, self.voxel)
        low, high = _bounds(cells)
        if (high - low).max() + 1 >= (1 << _COORD_BITS) - 1:
            return None
        # Offset for the whole map, not per labelling: the same voxels, the same neighbours, the same clusters.
        keys = _pack(np.zeros(len(cells), np.int64), cells - (low - 1))
        order = argsort_keys(keys)
        out = (order.astype(np.int32), keys[order])  # 12 bytes a Gaussian, kept as long as a geometry of the map
        for a in out:
            a.setflags(write=False)
        return out


@dataclass(frozen=True)
class ObjectGeometry:
    """The objects of one labelling of one Gaussian map."""

    objects: tuple[ObjectSummary, ...]  # sorted by id; void and unobserved are no objects
    shape_ids: np.ndarray  # (N,) uint32: the object ids of the Gaussians the boxes are made of, else UNOBSERVED_ID
    _labelling: _Labelling | None = field(default=None, repr=False, compare=False)

    @property
    def ids(self) -> np.ndarray:
        """(M,) uint32 object ids, in the order of ``objects``."""
        return np.array([s.id for s in self.objects], np.uint32)


def object_geometry(
    gaussians: GaussianMap,
    object_ids: np.ndarray,
    confidence: np.ndarray | None = None,
    *,
    min_confidence: float = MIN_CONFIDENCE,
    voxel: float = CLUSTER_VOXEL,
    previous: ObjectGeometry | None = None,
) -> ObjectGeometry:
    """Every object's box, centroid and Gaussian count (see the module docstring).

    ``object_ids``: (N,) uint32 per Gaussian; ``confidence``: (N,) float in [0, 1] or None (no filter).
    ``previous``: the geometry of an earlier labelling; when it is of the same map object with the same
    settings, only the objects whose Gaussians or confident Gaussians changed are computed again (the
    others are taken over), with the same result as a computation from scratch."""
    object_ids = np.array(object_ids, np.uint32)  # a copy: the next labelling is compared with it
    if object_ids.shape != (len(gaussians),):
        raise ValueError(f"object_ids: expected shape ({len(gaussians)},), got {object_ids.shape}")
    object_ids.setflags(write=False)
    real = (object_ids != UNOBSERVED_ID) & (object_ids != VOID_ID)
    shaping = real
    if voxel > 0 and confidence is not None and min_confidence > 0:
        shaping = real & (np.asarray(confidence) >= min_confidence)
    settings = (float(min_confidence), float(voxel), confidence is not None)
    before = previous._labelling if previous is not None else None
    if before is not None and before.gaussians() is gaussians and before.settings == settings:
        return _updated(gaussians, object_ids, shaping, previous, before)
    fits = voxel <= 0 or _extent_fits(gaussians.means, voxel)
    voxels = _VoxelOrder(voxel) if voxel > 0 and fits else None
    summaries, shape_rows = _objects_of(gaussians, object_ids, shaping, np.flatnonzero(real), voxel, voxels)
    shape_ids = object_ids
    if voxel > 0:
        shape_ids = np.full_like(object_ids, UNOBSERVED_ID)
        shape_ids[shape_rows] = object_ids[shape_rows]
        shape_ids.setflags(write=False)
    labelling = _Labelling(weakref.ref(gaussians), object_ids, shaping, settings, fits, voxels)
    return ObjectGeometry(tuple(summaries), shape_ids, labelling)


def _updated(
    gaussians: GaussianMap,
    object_ids: np.ndarray,
    shaping: np.ndarray,
    previous: ObjectGeometry,
    before: _Labelling,
) -> ObjectGeometry:
    """``object_geometry`` after ``previous`` of the same map: the changed objects computed again."""
    rows = np.flatnonzero((object_ids != before.object_ids) | (shaping != before.shaping))
    changed = np.union1d(object_ids[rows], before.object_ids[rows])
    changed = changed[changed < VOID_ID]
    labelling = _Labelling(before.gaussians, object_ids, shaping, before.settings, before.fits, before.voxels)
    if changed.size == 0:
        return ObjectGeometry(previous.objects, previous.shape_ids, labelling)
    voxel = before.settings[1]
    if not before.fits:  # the keys' range is the confident Gaussians' extent in the whole map
        _check_extent(_cells(gaussians.means[shaping], voxel), voxel)
    wanted = _id_table(changed)
    members = np.flatnonzero(wanted[np.minimum(object_ids, VOID_ID)])  # VOID_ID: False, where unobserved look
    summaries, shape_rows = _objects_of(gaussians, object_ids, shaping, members, voxel, before.voxels, changed)
    shape_ids = object_ids
    if voxel > 0:
        shape_ids = previous.shape_ids.copy()
        shape_ids[wanted[np.minimum(shape_ids, VOID_ID)]] = UNOBSERVED_ID
        shape_ids[shape_rows] = object_ids[shape_rows]
        shape_ids.setflags(write=False)
    gone = set(changed.tolist())
    kept = [s for s in previous.objects if s.id not in gone]
    objects = sorted(kept + summaries, key=lambda s: s.id)
    return ObjectGeometry(tuple(objects), shape_ids, labelling)


def _objects_of(
    gaussians: GaussianMap,
    object_ids: np.ndarray,
    shaping: np.ndarray,
    rows: np.ndarray,
    voxel: float,
    voxels: _VoxelOrder | None,
    candidates: np.ndarray | None = None,
) -> tuple[list[ObjectSummary], np.ndarray]:
    """The summaries of the objects of ``rows`` ((M,) ascending: every Gaussian of each of those objects)
    and the rows that shape them ((S,) ascending). ``candidates``: (K,) ascending ids that include them."""
    distinct, slot = _slots(object_ids[rows], candidates)
    counts = np.bincount(slot, minlength=distinct.size)
    if voxel > 0:
        shaped = _main_clusters(gaussians.means, rows, slot, distinct.size, shaping[rows], voxel, voxels=voxels)
        rows, slot = rows[shaped], slot[shaped]
    summaries = _boxes(gaussians.means, gaussians.opacities, distinct, rows, slot)
    for s, n in zip(summaries, counts[counts > 0].tolist(), strict=True):
        s.num_gaussians = n
    return summaries, rows


def percentile_boxes(gaussians: GaussianMap, object_ids: np.ndarray) -> list[ObjectSummary]:
    """Percentile box and centroid of the Gaussians of each id in ``object_ids`` (N,), sorted by id (void and
    unobserved skipped); ``num_gaussians`` counts the Gaussians given. ``object_geometry`` chooses them."""
    object_ids = np.asarray(object_ids, np.uint32)
    if object_ids.shape != (len(gaussians),):
        raise ValueError(f"object_ids: expected shape ({len(gaussians)},), got {object_ids.shape}")
    return percentile_boxes_at(gaussians.means, gaussians.opacities, object_ids)


def percentile_boxes_at(
    means: np.ndarray, opacities: np.ndarray, object_ids: np.ndarray, only: np.ndarray | None = None
) -> list[ObjectSummary]:
    """``percentile_boxes`` of Gaussians at ``means`` (N, 3) (in any frame) with ``opacities`` (N,), for the objects
    of ``object_ids`` (N,) uint32 among ``only`` ((K,) uint32 ascending object ids, below VOID_ID; None: all)."""
    rows = np.flatnonzero((object_ids != UNOBSERVED_ID) & (object_ids != VOID_ID))
    if only is not None:
        rows = rows[_id_table(only)[object_ids[rows]]]
    if rows.size == 0:
        return []
    distinct, slot = _slots(object_ids[rows], only)
    return _boxes(means, opacities, distinct, rows, slot)


def main_cluster_ids(
    means: np.ndarray,
    object_ids: np.ndarray,
    confidence: np.ndarray | None = None,
    *,
    min_confidence: float = MIN_CONFIDENCE,
    voxel: float = CLUSTER_VOXEL,
    min_share: float = 1.0,
) -> np.ndarray:
    """A copy of ``object_ids`` (N,) where Gaussians outside their object's main cluster are UNOBSERVED_ID.

    ``means``: (N, 3) Gaussian centres; ``confidence``: (N,) or None. An object left with nothing keeps
    all its Gaussians rather than vanishing."""
    object_ids = np.asarray(object_ids, np.uint32)
    means = np.asarray(means)
    real = (object_ids != UNOBSERVED_ID) & (object_ids != VOID_ID)
    shaping = real
    if confidence is not None and min_confidence > 0:
        shaping = real & (np.asarray(confidence) >= min_confidence)
    out = np.full_like(object_ids, UNOBSERVED_ID)
    rows = np.flatnonzero(real)
    if rows.size:
        distinct, slot = _slots(object_ids[rows])
        rows = rows[_main_clusters(means, rows, slot, distinct.size, shaping[rows], voxel, min_share)]
        out[rows] = object_ids[rows]
    return out


def _id_table(ids: np.ndarray) -> np.ndarray:
    """(2**24,) bool, True at ``ids`` (K,) uint32 < 2**24 (VOID_ID not among them): membership of every Gaussian's
    id by one lookup (a map's few hundred ids touch few of its pages), where np.isin sorts (300 ids among 1M / 2M
    Gaussians: 58 / 137 ms against ~3 / ~6)."""
    table = np.zeros(_ID_RANGE, bool)
    table[ids] = True
    return table


def _slots(ids: np.ndarray, candidates: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Ascending ids (K,) that include those of ``ids`` (M,) uint32 < 2**24 (``candidates`` when given, else
    exactly the distinct ones), and each one's index among them: np.unique(return_inverse=True) through a
    lookup table instead of a sort (~6x faster at 1M)."""
    distinct = candidates
    if distinct is None:
        seen = np.zeros(_ID_RANGE, bool)
        seen[ids] = True
        distinct = np.flatnonzero(seen).astype(np.uint32)
    # 16-bit slots make the stable argsort in _boxes a radix sort.
    table = np.empty(_ID_RANGE, np.uint16 if distinct.size <= 1 << 16 else np.int64)
    table[distinct] = np.arange(distinct.size)
    return distinct, table[ids]


def _boxes(
    means: np.ndarray, opacities: np.ndarray, distinct: np.ndarray, rows: np.ndarray, slot: np.ndarray
) -> list[ObjectSummary]:
    """Percentile box and centroid of each object of ``distinct`` (K,) with rows among ``rows`` (M,) ascending,
    where ``slot`` (M,) is each row's index in ``distinct``, of the Gaussians at ``means`` (N, 3) with
    ``opacities`` (N,) (core.object_geometry_kernels: grouped by object in one pass, then one parallel call)."""
    counts = np.bincount(slot, minlength=distinct.size)
    present = np.flatnonzero(counts)
    bounds = np.concatenate([[0], np.cumsum(counts[present])])
    low, high, centroid = (np.empty((present.size, 3)) for _ in range(3))
    # Rows stay ascending within an object: the sums of the reference, in its order.
    pts, weights = group_by_object(means, opacities, rows, slot, distinct.size)
    percentile_boxes_kernel(pts, weights, bounds, _LOW / 100, _HIGH / 100, low, high, centroid)
    ids = distinct[present]
    rgb = unpack_rgb(ids).tolist()
    return [
        ObjectSummary(oid, tuple(rgb[j]), n, centroid[j], low[j], high[j])
        for j, (oid, n) in enumerate(zip(ids.tolist(), counts[present].tolist(), strict=True))
    ]


def _cells(means: np.ndarray, voxel: float) -> np.ndarray:
    return np.floor(np.asarray(means, np.float64) / voxel).astype(np.int64)


def _bounds(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per column minimum and maximum of ``a`` (M, 3), M > 0: column by column, 10x faster than axis=0."""
    columns = [a[:, axis] for axis in range(a.shape[1])]
    return np.array([c.min() for c in columns]), np.array([c.max() for c in columns])


def _check_extent(cells: np.ndarray, voxel: float) -> None:
    """Raises unless ``cells`` (M, 3), offset to start at 1, leave room for a neighbour on either side."""
    if cells.size == 0:
        return
    low, high = _bounds(cells)
    if (high - low).max() + 1 >= (1 << _COORD_BITS) - 1:
        raise ValueError(f"map too large for {voxel} m voxels (more than {(1 << _COORD_BITS) - 2} per axis)")


def _extent_fits(means: np.ndarray, voxel: float) -> bool:
    """Whether every set of Gaussians of this map fits the voxel keys (cheap: the map's bounds only)."""
    if not np.isfinite(means).all():  # such a centre takes no votes (the rasterizer culls it): the others' bounds
        means = means[np.isfinite(means).all(axis=1)]
    if len(means) == 0:
        return True
    cells = _cells(np.stack(_bounds(means)), voxel)
    return int((cells[1] - cells[0]).max()) + 1 < (1 << _COORD_BITS) - 1


def _pack(object_slot: np.ndarray, cells: np.ndarray) -> np.ndarray:
    key = object_slot.astype(np.int64)
    for axis in range(3):
        key = (key << _COORD_BITS) | cells[:, axis]
    return key


def _main_clusters(
    means: np.ndarray,
    rows: np.ndarray,
    slot: np.ndarray,
    n_slots: int,
    shaping: np.ndarray,
    voxel: float,
    min_share: float = 1.0,
    voxels: _VoxelOrder | None = None,
) -> np.ndarray:
    """(M,) bool: which of ``rows`` (M,) shape their object (``main_cluster_ids``). ``means``: (N, 3) the map's
    centres; ``slot``: (M,) each row's object, < n_slots; ``shaping``: (M,) bool, the rows that may; ``voxels``:
    the map's voxel order, if it has one (the same result)."""
    index = np.flatnonzero(shaping)
    shapes = np.zeros(len(means), bool)  # per map row: in its object's main cluster
    if index.size:
        # Two passes over the map cost what sorting an eighth of it does.
        in_order = voxels.sorted(means) if voxels is not None and 8 * index.size >= len(means) else None
        if in_order is not None:
            # Read at random in voxel order: the narrowest type keeps more of it in cache (2M: 8 MB as int32).
            slot_of = np.full(len(means), -1, np.int16 if n_slots < 1 << 15 else np.int32)
            slot_of[rows[index]] = slot[index]
            keys, ordered = voxel_keys_by_object(*in_order, slot_of, n_slots, 3 * _COORD_BITS)
        else:
            centres = means[rows[index]]
            if not np.isfinite(centres).all():  # its cell would be garbage, and the union-find index out of bounds
                raise ValueError("object geometry: a Gaussian with a non-finite centre is labelled")
            cells = _cells(centres, voxel)
            _check_extent(cells, voxel)
            cells -= _bounds(cells)[0] - 1  # >= 1 so that neighbours at -1 stay non-negative
            keys = _pack(slot[index], cells)
            order = argsort_keys(keys)  # radix: numpy's quicksort took half of a publication's geometry at 1M
            keys, ordered = keys[order], rows[index[order]]
        kept = main_voxel_clusters(keys, _NEIGHBOUR_STEPS, 3 * _COORD_BITS, n_slots, float(min_share))
        shapes[ordered[kept]] = True
    out = shapes[rows]
    # An object left with nothing keeps all its Gaussians rather than vanishing.
    out |= (np.bincount(slot[out], minlength=n_slots) == 0)[slot]
    return out


# ------------------------------------------------------------------------------------ NumPy reference


def object_geometry_reference(
    gaussians: GaussianMap,
    object_ids: np.ndarray,
    confidence: np.ndarray | None = None,
    *,
    min_confidence: float = MIN_CONFIDENCE,
    voxel: float = CLUSTER_VOXEL,
) -> ObjectGeometry:
    """Every object's box, centroid and Gaussian count (see the module docstring).

    ``object_ids``: (N,) uint32 per Gaussian; ``confidence``: (N,) float in [0, 1] or None (no filter).
    """
    object_ids = np.asarray(object_ids, np.uint32)
    if object_ids.shape != (len(gaussians),):
        raise ValueError(f"object_ids: expected shape ({len(gaussians)},), got {object_ids.shape}")
    shape_ids = object_ids
    if voxel > 0:
        shape_ids = main_cluster_ids_reference(
            gaussians.means, object_ids, confidence, min_confidence=min_confidence, voxel=voxel
        )
    ids, counts = np.unique(object_ids, return_counts=True)
    all_counts = dict(zip(ids.tolist(), counts.tolist(), strict=True))
    boxes = percentile_boxes_reference(gaussians, shape_ids)
    for s in boxes:
        s.num_gaussians = all_counts[s.id]
    return ObjectGeometry(tuple(boxes), shape_ids)


def percentile_boxes_reference(gaussians: GaussianMap, object_ids: np.ndarray) -> list[ObjectSummary]:
    """Percentile box and centroid of the Gaussians of each id in ``object_ids`` (N,), sorted by id (void and
    unobserved skipped); ``num_gaussians`` counts the Gaussians given. ``object_geometry`` chooses them."""
    object_ids = np.asarray(object_ids, np.uint32)
    if object_ids.shape != (len(gaussians),):
        raise ValueError(f"object_ids: expected shape ({len(gaussians)},), got {object_ids.shape}")
    keep = (object_ids != UNOBSERVED_ID) & (object_ids != VOID_ID)
    index = np.flatnonzero(keep)
    if index.size == 0:
        return []
    order = index[np.argsort(object_ids[index], kind="stable")]
    ids, starts = np.unique(object_ids[order], return_index=True)
    bounds = np.append(starts, order.size)
    out = []
    for k, oid in enumerate(ids):
        members = order[bounds[k] : bounds[k + 1]]
        pts = gaussians.means[members].astype(np.float64)
        lo, hi = np.percentile(pts, [_LOW, _HIGH], axis=0)
        inside = np.all((pts >= lo) & (pts <= hi), axis=1)
        w = gaussians.opacities[members][inside].astype(np.float64)
        total = _in_row_order(w) if w.size else 0.0
        centroid = _in_row_order(pts[inside] * w[:, None]) / total if total > 0 else _in_row_order(pts) / len(pts)
        rgb = tuple(int(c) for c in unpack_rgb(np.uint32(oid)))
        out.append(ObjectSummary(int(oid), rgb, int(members.size), centroid, lo, hi))
    return out


def _in_row_order(a: np.ndarray) -> np.ndarray:
    """The sum over the first axis of ``a`` (M, ...), M > 0, added in row order, as the numba twin adds (numpy's
    sum adds pairwise: the same value up to rounding, not bit for bit)."""
    return np.cumsum(a, axis=0)[-1]


def main_cluster_ids_reference(
    means: np.ndarray,
    object_ids: np.ndarray,
    confidence: np.ndarray | None = None,
    *,
    min_confidence: float = MIN_CONFIDENCE,
    voxel: float = CLUSTER_VOXEL,
    min_share: float = 1.0,
) -> np.ndarray:
    """A copy of ``object_ids`` (N,) where Gaussians outside their object's main cluster are UNOBSERVED_ID.

    ``means``: (N, 3) Gaussian centres; ``confidence``: (N,) or None. An object left with nothing keeps
    all its Gaussians rather than vanishing."""
    object_ids = np.asarray(object_ids, np.uint32)
    means = np.asarray(means, np.float64)
    real = (object_ids != UNOBSERVED_ID) & (object_ids != VOID_ID)
    keep = real.copy()
    if confidence is not None and min_confidence > 0:
        keep &= np.asarray(confidence) >= min_confidence
    index = np.flatnonzero(keep)
    out = np.full_like(object_ids, UNOBSERVED_ID)
    if index.size:
        ids, slot = np.unique(object_ids[index], return_inverse=True)
        cells = np.floor(means[index] / voxel).astype(np.int64)
        cells -= cells.min(axis=0) - 1  # >= 1 so that neighbours at -1 stay non-negative
        if cells.max() >= (1 << _COORD_BITS) - 1:
            raise ValueError(f"map too large for {voxel} m voxels (more than {(1 << _COORD_BITS) - 2} per axis)")
        keys = _pack(slot, cells)
        voxels, voxel_of = np.unique(keys, return_inverse=True)
        rows, cols = [], []
        for offset in _OFFSETS:  # half of the 26 neighbours: the graph is symmetric
            vslot = voxels >> (3 * _COORD_BITS)
            vcells = np.stack([(voxels >> (_COORD_BITS * (2 - a))) & ((1 << _COORD_BITS) - 1) for a in range(3)], 1)
            neighbour = _pack(vslot, vcells + offset)
            pos = np.searchsorted(voxels, neighbour).clip(0, voxels.size - 1)
            hit = voxels[pos] == neighbour
            rows.append(np.flatnonzero(hit))
            cols.append(pos[hit])
        r, c = np.concatenate(rows), np.concatenate(cols)
        graph = coo_matrix((np.ones(r.size, np.int8), (r, c)), shape=(voxels.size, voxels.size))
        _, component = connected_components(graph, directed=False)
        gaussian_component = component[voxel_of]
        # Per object: its largest component and every component with at least min_share of its size.
        pair = gaussian_component.astype(np.int64) * ids.size + slot
        pairs, pair_of, counts = np.unique(pair, return_inverse=True, return_counts=True)
        pair_slot = pairs % ids.size
        largest = np.zeros(ids.size, np.int64)
        np.maximum.at(largest, pair_slot, counts)
        kept_pair = counts >= np.maximum(1, min_share * largest[pair_slot])
        main = kept_pair[pair_of]
        out[index[main]] = object_ids[index[main]]
    present = np.unique(out[out != UNOBSERVED_ID])
    lost = real & ~np.isin(object_ids, present)
    out[lost] = object_ids[lost]
    return out
