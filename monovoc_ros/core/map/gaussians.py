"""The Gaussian map: fixed geometry from the SLAM front-end, held as a struct of arrays.

All values are *activated*: scales in metres (exp of the PLY's log-scales), opacities in (0, 1)
(sigmoid of the PLY's logits), quaternions normalized in (w, x, y, z) order, colors RGB in [0, 1].
Arrays are read-only once the map is built, so derived values (3D covariances) can be cached.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from functools import cached_property

import numba
import numpy as np

from monovoc_ros.core.map.camera import quat_wxyz_to_matrix
from monovoc_ros.core.map.sorting import radix_argsort

# The per-Gaussian arrays a map is (besides `extra`): what a snapshot's map file holds and `digest` hashes.
ARRAY_FIELDS = ("means", "scales", "quats", "opacities", "colors", "ids", "semantics")
# Gaussians per chunk of `GaussianMap.chunk_members` (the rasterizer culls a view's chunks at once).
# office_0 tiled to 1M: a keyframe's live chunks held 279k Gaussians at 4096 (94k visible), 179k at 1024 (projection
# and depth order 7.4 -> 5.9 ms), 151k at 512 (no faster).
MAP_CHUNK = 1024
# Per axis of the Z-order grid (1024 cells over the map's box): a chunk spans several cells even in a dense room,
# and 30-bit keys sort in two radix passes (63-bit keys took four: 36 -> ~15 ms at 1M).
_MORTON_BITS = 10
_NON_FINITE_KEY = 1 << (3 * _MORTON_BITS)  # after every finite mean's key


def _frozen(a: np.ndarray | None, dtype, shape_tail: tuple, name: str, n: int | None) -> np.ndarray | None:
    if a is None:
        return None
    a = np.ascontiguousarray(a, dtype=dtype)
    if a.shape[1:] != shape_tail or (n is not None and a.shape[0] != n):
        want = ("N",) + shape_tail
        raise ValueError(f"GaussianMap.{name}: expected shape {want} with N={n}, got {a.shape}")
    a.setflags(write=False)
    return a


def all_distinct(values: np.ndarray) -> bool:
    """Whether the (N,) integers are pairwise distinct. A sort and a neighbour test: numpy 2.4's np.unique hashes
    integers, 13x slower on 1M distinct ids (700 against 53 ms) and holding the interpreter up to 0.16 s at a time
    (every other thread of the node waits), where the sort releases it."""
    ordered = np.sort(np.asarray(values).ravel())
    return not bool(np.any(ordered[1:] == ordered[:-1]))


@dataclass(frozen=True, eq=False)
class GaussianMap:
    means: np.ndarray  # (N, 3) float32, world frame, metres
    scales: np.ndarray  # (N, 3) float32, activated (metres)
    quats: np.ndarray  # (N, 4) float32, (w, x, y, z), normalized
    opacities: np.ndarray  # (N,) float32, activated, in (0, 1)
    colors: np.ndarray | None = None  # (N, 3) float32 RGB in [0, 1] (SH degree-0 color)
    ids: np.ndarray | None = None  # (N,) int64 stable per-Gaussian ids from the SLAM front-end
    semantics: np.ndarray | None = None  # (N, 3) float32, optional `semantics_*` PLY fields
    extra: dict = field(default_factory=dict)  # other named per-Gaussian arrays (e.g. f_rest)
    # The SLAM's stamp of this map (its message's header, ns); 0: unknown. Keyframes stamped at or after it are
    # posed in its frame (core.follow.map_frames).
    stamp_ns: int = 0

    def __post_init__(self) -> None:
        means = _frozen(self.means, np.float32, (3,), "means", None)
        n = means.shape[0]
        quats = np.ascontiguousarray(self.quats, dtype=np.float32)
        norms = quat_norms(_read_only(quats.view()))[:, None] if quats.ndim == 2 and quats.shape[1:] == (4,) else None
        if norms is not None and np.any(~np.isfinite(norms) | (norms <= 0)):
            raise ValueError("GaussianMap.quats: zero or non-finite quaternion")
        if norms is not None:
            # Only rows that are not unit already: renormalizing in float32 is not idempotent, and a map
            # must survive save/load bit for bit.
            off = np.abs(norms[:, 0] - 1.0) > 1e-6
            if off.any():
                quats = quats.copy()
                quats[off] /= norms[off]
        object.__setattr__(self, "means", means)
        object.__setattr__(self, "scales", _frozen(self.scales, np.float32, (3,), "scales", n))
        object.__setattr__(self, "quats", _frozen(quats, np.float32, (4,), "quats", n))
        object.__setattr__(self, "opacities", _frozen(self.opacities, np.float32, (), "opacities", n))
        object.__setattr__(self, "colors", _frozen(self.colors, np.float32, (3,), "colors", n))
        object.__setattr__(self, "ids", _frozen(self.ids, np.int64, (), "ids", n))
        object.__setattr__(self, "semantics", _frozen(self.semantics, np.float32, (3,), "semantics", n))
        if self.ids is not None and not all_distinct(self.ids):
            raise ValueError("GaussianMap.ids: ids must be unique")

    def __len__(self) -> int:
        return self.means.shape[0]

    def subset(self, index: np.ndarray) -> GaussianMap:
        """A map of the selected Gaussians (boolean mask or integer index), in that order."""

        def pick(a):
            return None if a is None else a[index]

        return GaussianMap(
            self.means[index],
            self.scales[index],
            self.quats[index],
            self.opacities[index],
            pick(self.colors),
            pick(self.ids),
            pick(self.semantics),
            {k: v[index] for k, v in self.extra.items()},
        )

    @cached_property
    def covariances(self) -> np.ndarray:
        """World-frame 3D covariances as (N, 6) float32: xx, xy, xz, yy, yz, zz.

        Computed once per map (not per keyframe): Sigma = R S S^T R^T with S = diag(scales), by a numba
        kernel (`covariances_kernel`; plain twin `covariances_reference`). At 1M Gaussians on 2 cores the twin
        (batched numpy 3x3 products) takes 0.64 s, the kernel a few tens of milliseconds.
        """
        out = covariances_kernel(self.quats, self.scales) if len(self) else np.zeros((0, 6), np.float32)
        out.setflags(write=False)
        return out

    @cached_property
    def chunk_members(self) -> np.ndarray:
        """(N,) int32: the Gaussians grouped by place into chunks of MAP_CHUNK, chunk c being
        ``chunk_members[c * MAP_CHUNK:(c + 1) * MAP_CHUNK]`` (ascending inside; Gaussians with a non-finite
        mean last). A view culls most chunks of a building's map at once (raster.numba_impl.live_chunks). Chunks
        of consecutive Gaussians relied on the SLAM's order, which a map update need not keep (the churn
        generator's re-orders it all, as a SLAM without stable storage may; densification appends the Gaussians
        it splits or clones from all over the map): office_0 tiled to 1M after five such updates had all of its
        257 chunks (of 4096) live in every view, 38-128 by place. The order is the Z-order curve of the means on a
        2**_MORTON_BITS grid over the map's box (radix sort; with `placed` ~70 ms at 1M, once per map, beside the
        worker for a live map update)."""
        return chunk_members_of(self.means)

    @property
    def placed(self) -> PlacedArrays:
        """What the rasterizer reads of each Gaussian, in the order of `chunk_members`: a view's live chunks are
        then contiguous memory. A SLAM map's own order may be anything (a map update may re-order it all): on
        office_0 tiled to 1M and shuffled, a view's projection and binning took 24 ms reading the Gaussians where
        they were, 9 ms in this order (11 ms in the order office_0's map was built). 44 bytes a Gaussian (the
        covariances are computed here, in this order), once per map with `chunk_bounds` (a live map update does
        it beside the worker)."""
        return self._placement[0]

    @property
    def chunk_bounds(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per chunk of `chunk_members`: the box of its means, lower (C, 3) and upper (C, 3) float64 corners,
        and its largest scale (C,) float64 (all NaN where a value of the chunk is not finite)."""
        return self._placement[1]

    @cached_property
    def _placement(self) -> tuple[PlacedArrays, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """`placed` and `chunk_bounds` in one pass over the Gaussians in chunk order (`place_kernel`; plain twins
        `gather_rows` with `covariances_kernel`, and `chunk_bounds_reference`): 1M Gaussians 75 -> ~40 ms, where
        the four gathers and the bounds each read the map in that scattered order."""
        members = self.chunk_members
        means, covariances, opacities, lower, upper, reach = place_kernel(
            members, self.means, self.quats, self.scales, self.opacities, MAP_CHUNK
        )
        placed = PlacedArrays(members, _read_only(means), _read_only(covariances), _read_only(opacities))
        return placed, (_read_only(lower), _read_only(upper), _read_only(reach))

    @cached_property
    def digest(self) -> str:
        """A hash of the arrays of ARRAY_FIELDS (blake2b, ~0.1 s at 1M Gaussians): maps of the same bytes have the
        same one. Computed once per map, like the covariances (a snapshot links an unchanged map file by it)."""
        h = hashlib.blake2b(digest_size=16)
        for name in ARRAY_FIELDS:
            a = getattr(self, name)
            if a is not None:
                h.update(f"{name}{a.dtype.str}{a.shape}".encode())
                h.update(np.ascontiguousarray(a).data)
        return h.hexdigest()

    @property
    def nbytes(self) -> int:
        arrays = [getattr(self, name) for name in ARRAY_FIELDS]
        return sum(a.nbytes for a in arrays if a is not None) + sum(v.nbytes for v in self.extra.values())


@dataclass(frozen=True)
class PlacedArrays:
    """A map's Gaussians in the order of its chunks (`GaussianMap.placed`): place p is Gaussian members[p]."""

    members: np.ndarray  # (N,) int32 each place's map index
    means: np.ndarray  # (N, 3) float32
    covariances: np.ndarray  # (N, 6) float32
    opacities: np.ndarray  # (N,) float32


def _read_only(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def chunk_members_of(means: np.ndarray) -> np.ndarray:
    """(N,) int32 `GaussianMap.chunk_members` of means (N, 3)."""
    n = len(means)
    if n == 0:
        return np.zeros(0, np.int32)
    low, high, finite = finite_box(means)
    if finite == 0:
        return np.arange(n, dtype=np.int32)
    scale = ((1 << _MORTON_BITS) - 1) / np.maximum(high - low, 1e-9)
    keys = morton_keys(means, low, scale)
    order = radix_argsort(keys, np.arange(n, dtype=np.int64), 16, 3 * _MORTON_BITS + 1)
    members = group_by_chunk(order, MAP_CHUNK)
    members.setflags(write=False)
    return members


@numba.njit(cache=True, nogil=True, parallel=True)
def quat_norms(quats):  # pragma: no cover - numba
    """(N,) float32 norms of quaternions (N, 4) float32, summed in numpy's order: np.linalg.norm(quats, axis=-1) bit
    for bit (its twin, `quat_norms_reference`), in one pass where numpy's temporaries took ~36 ms at 2M (every map
    message: in the map reader and again in the node)."""
    n = quats.shape[0]
    out = np.empty(n, np.float32)
    for i in numba.prange(n):
        s = quats[i, 0] * quats[i, 0]
        s += quats[i, 1] * quats[i, 1]
        s += quats[i, 2] * quats[i, 2]
        s += quats[i, 3] * quats[i, 3]
        out[i] = np.sqrt(s)
    return out


def quat_norms_reference(quats: np.ndarray) -> np.ndarray:
    """Plain twin of `quat_norms`."""
    return np.linalg.norm(np.asarray(quats, np.float32), axis=-1)


_BOX_BLOCKS = 64  # work items of `finite_box`


@numba.njit(cache=True, nogil=True, parallel=True)
def finite_box(means):  # pragma: no cover - numba
    """Per axis the smallest and largest coordinate, float64 (3,) each, of the points (N, 3) whose three coordinates
    are finite ((inf, -inf) where none is), and how many those are. One parallel pass where numpy's isfinite, mask
    and per-column min / max took ~32 ms at 1M."""
    n = means.shape[0]
    lows = np.full((_BOX_BLOCKS, 3), np.inf)
    highs = np.full((_BOX_BLOCKS, 3), -np.inf)
    counts = np.zeros(_BOX_BLOCKS, np.int64)
    for b in numba.prange(_BOX_BLOCKS):
        for i in range(b * n // _BOX_BLOCKS, (b + 1) * n // _BOX_BLOCKS):
            x, y, z = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
            if np.isfinite(x) and np.isfinite(y) and np.isfinite(z):
                lows[b, 0], highs[b, 0] = min(lows[b, 0], x), max(highs[b, 0], x)
                lows[b, 1], highs[b, 1] = min(lows[b, 1], y), max(highs[b, 1], y)
                lows[b, 2], highs[b, 2] = min(lows[b, 2], z), max(highs[b, 2], z)
                counts[b] += 1
    low = np.full(3, np.inf)
    high = np.full(3, -np.inf)
    for b in range(_BOX_BLOCKS):
        for a in range(3):
            low[a] = min(low[a], lows[b, a])
            high[a] = max(high[a], highs[b, a])
    return low, high, counts.sum()


def finite_box_reference(means: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Plain twin of `finite_box`."""
    box = np.asarray(means)[np.isfinite(means).all(axis=1)].astype(np.float64)
    if not len(box):
        return np.full(3, np.inf), np.full(3, -np.inf), 0
    return box.min(axis=0), box.max(axis=0), len(box)


@numba.njit(cache=True, nogil=True, parallel=True)
def morton_keys(means, low, scale):  # pragma: no cover - numba
    """(N,) int64 Z-order keys of means (N, 3) quantized as (p - low) * scale on _MORTON_BITS bits per axis (clamped
    into the grid); a non-finite mean gets _NON_FINITE_KEY, after every other."""
    n = means.shape[0]
    keys = np.empty(n, np.int64)
    top = (1 << _MORTON_BITS) - 1
    for i in numba.prange(n):
        key = 0
        finite = True
        for a in range(3):
            x = (np.float64(means[i, a]) - low[a]) * scale[a]
            if not np.isfinite(x):
                finite = False
                break
            key |= _spread_bits(min(max(int(x), 0), top)) << a
        keys[i] = key if finite else np.int64(_NON_FINITE_KEY)
    return keys


def morton_keys_reference(means: np.ndarray, low: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Plain twin of `morton_keys`: the bits interleaved one at a time."""
    with np.errstate(invalid="ignore"):
        x = (np.asarray(means, np.float64) - low) * scale
    finite = np.isfinite(x).all(axis=1)
    q = np.clip(np.where(np.isfinite(x), x, 0.0).astype(np.int64), 0, (1 << _MORTON_BITS) - 1)
    keys = np.zeros(len(x), np.int64)
    for b in range(_MORTON_BITS):
        for a in range(3):
            keys |= ((q[:, a] >> b) & 1) << (3 * b + a)
    return np.where(finite, keys, np.int64(_NON_FINITE_KEY))


@numba.njit(cache=True, nogil=True, inline="always")
def _spread_bits(q):  # pragma: no cover - numba
    """The 21 low bits of q three apart (bit b to bit 3 b): up to 21 bits per axis."""
    q &= 0x1FFFFF
    q = (q | (q << 32)) & 0x1F00000000FFFF
    q = (q | (q << 16)) & 0x1F0000FF0000FF
    q = (q | (q << 8)) & 0x100F00F00F00F00F
    q = (q | (q << 4)) & 0x10C30C30C30C30C3
    return (q | (q << 2)) & 0x1249249249249249


@numba.njit(cache=True, nogil=True)
def group_by_chunk(order, chunk):  # pragma: no cover - numba
    """(N,) int32: `order` (N,) cut into runs of `chunk`, each run's values ascending (a counting sort by run)."""
    n = order.shape[0]
    run = np.empty(n, np.int32)
    for j in range(n):
        run[order[j]] = j // chunk
    out = np.empty(n, np.int32)
    start = np.zeros((n + chunk - 1) // chunk, np.int64)
    for r in range(start.shape[0]):
        start[r] = r * chunk
    for i in range(n):
        out[start[run[i]]] = i
        start[run[i]] += 1
    return out


def chunk_bounds_reference(
    means: np.ndarray, scales: np.ndarray, members: np.ndarray, chunk: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plain twin of `GaussianMap.chunk_bounds` for means (N, 3) and scales (N, 3) in chunks of `chunk` of the
    Gaussians `members` (N,)."""
    lower, upper, reach = [], [], []
    for start in range(0, len(means), chunk):
        rows = members[start : start + chunk]
        m, s = means[rows].astype(np.float64), scales[rows].astype(np.float64)
        finite = np.isfinite(m).all() and np.isfinite(s).all()
        lower.append(m.min(axis=0) if finite else np.full(3, np.nan))
        upper.append(m.max(axis=0) if finite else np.full(3, np.nan))
        reach.append(s.max() if finite else np.nan)
    return np.reshape(lower, (-1, 3)), np.reshape(upper, (-1, 3)), np.array(reach, np.float64)


def covariances_reference(quats: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """Plain twin of `GaussianMap.covariances`: (N, 6) float32 from quats (N, 4) and scales (N, 3)."""
    R = quat_wxyz_to_matrix(quats)
    M = R * np.asarray(scales, np.float64)[:, None, :]
    cov = M @ np.swapaxes(M, 1, 2)
    return np.stack(
        [cov[:, 0, 0], cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 1], cov[:, 1, 2], cov[:, 2, 2]], axis=1
    ).astype(np.float32)


@numba.njit(cache=True, nogil=True, inline="always")
def _covariance(quats, scales, i, out, j):  # pragma: no cover - numba
    """out[j] = xx, xy, xz, yy, yz, zz of R diag(s^2) R^T for Gaussian i (quats (w, x, y, z)), in scalars: a (3, 3)
    scratch array per Gaussian cost the placement kernel 3x its time."""
    w, x, y, z = float(quats[i, 0]), float(quats[i, 1]), float(quats[i, 2]), float(quats[i, 3])
    norm = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / norm, x / norm, y / norm, z / norm
    r00, r01, r02 = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    r10, r11, r12 = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    r20, r21, r22 = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    s0, s1, s2 = float(scales[i, 0]) ** 2, float(scales[i, 1]) ** 2, float(scales[i, 2]) ** 2
    out[j, 0] = r00 * r00 * s0 + r01 * r01 * s1 + r02 * r02 * s2
    out[j, 1] = r00 * r10 * s0 + r01 * r11 * s1 + r02 * r12 * s2
    out[j, 2] = r00 * r20 * s0 + r01 * r21 * s1 + r02 * r22 * s2
    out[j, 3] = r10 * r10 * s0 + r11 * r11 * s1 + r12 * r12 * s2
    out[j, 4] = r10 * r20 * s0 + r11 * r21 * s1 + r12 * r22 * s2
    out[j, 5] = r20 * r20 * s0 + r21 * r21 * s1 + r22 * r22 * s2


@numba.njit(cache=True, nogil=True, parallel=True)
def covariances_kernel(quats, scales):  # pragma: no cover - numba
    """(N, 6) float32 xx, xy, xz, yy, yz, zz of R diag(s^2) R^T from (w, x, y, z) unit quaternions (N, 4)."""
    n = quats.shape[0]
    out = np.empty((n, 6), np.float32)
    for i in numba.prange(n):
        _covariance(quats, scales, i, out, i)
    return out


@numba.njit(cache=True, nogil=True, parallel=True)
def place_kernel(members, means, quats, scales, opacities, chunk):  # pragma: no cover - numba
    """`GaussianMap._placement`: the means (N, 3), covariances (N, 6) and opacities (N,) of the Gaussians `members`
    (N,) in that order (float32), and per chunk of `chunk` places the box of its means and its largest scale (twin
    `chunk_bounds_reference`): one pass, each chunk's Gaussians read once."""
    n = members.shape[0]
    chunks = (n + chunk - 1) // chunk
    placed_means = np.empty((n, 3), np.float32)
    covariances = np.empty((n, 6), np.float32)
    placed_opacities = np.empty(n, np.float32)
    lower = np.empty((chunks, 3))
    upper = np.empty((chunks, 3))
    reach = np.empty(chunks)
    for c in numba.prange(chunks):
        start, stop = c * chunk, min(n, (c + 1) * chunk)
        # The chunk's rows gathered first, in a loop of copies only: its cache misses overlap, where computing
        # on each row as it came took 4x as long (the misses one after the other).
        local_quats = np.empty((stop - start, 4), np.float32)
        local_scales = np.empty((stop - start, 3), np.float32)
        for j in range(start, stop):
            i = members[j]
            for a in range(3):
                placed_means[j, a] = means[i, a]
                local_scales[j - start, a] = scales[i, a]
            for a in range(4):
                local_quats[j - start, a] = quats[i, a]
            placed_opacities[j] = opacities[i]
        lo0 = lo1 = lo2 = np.inf
        hi0 = hi1 = hi2 = r = -np.inf
        nan = 0.0  # x - x is 0 for a finite x, NaN for inf and NaN: the chunk is finite when this stays 0
        for j in range(start, stop):
            x, y, z = np.float64(placed_means[j, 0]), np.float64(placed_means[j, 1]), np.float64(placed_means[j, 2])
            s0 = np.float64(local_scales[j - start, 0])
            s1 = np.float64(local_scales[j - start, 1])
            s2 = np.float64(local_scales[j - start, 2])
            nan += (x - x) + (y - y) + (z - z) + (s0 - s0) + (s1 - s1) + (s2 - s2)
            lo0, hi0 = min(lo0, x), max(hi0, x)
            lo1, hi1 = min(lo1, y), max(hi1, y)
            lo2, hi2 = min(lo2, z), max(hi2, z)
            r = max(r, max(s0, max(s1, s2)))
            _covariance(local_quats, local_scales, j - start, covariances, j)
        finite = nan == 0.0
        lower[c, 0], lower[c, 1], lower[c, 2] = (lo0, lo1, lo2) if finite else (np.nan, np.nan, np.nan)
        upper[c, 0], upper[c, 1], upper[c, 2] = (hi0, hi1, hi2) if finite else (np.nan, np.nan, np.nan)
        reach[c] = r if finite else np.nan
    return placed_means, covariances, placed_opacities, lower, upper, reach


# Ids up to this many times the maps' sizes are looked up in a table (SLAM ids are counters), others sorted.
_ID_TABLE_FACTOR = 8


def same_geometry(a: GaussianMap, b: GaussianMap) -> bool:
    """True when two maps are the same Gaussians (SLAM re-publishing an unchanged map, or the map a
    resumed snapshot was built from): applying it as an update would change nothing."""
    if a is b:
        return True
    if len(a) != len(b) or (a.ids is None) != (b.ids is None):
        return False
    if a.ids is not None and not np.array_equal(a.ids, b.ids):
        return False
    if not (np.array_equal(a.means, b.means) and np.array_equal(a.scales, b.scales)):
        return False
    if not np.array_equal(a.opacities, b.opacities):
        return False
    # Quaternions are re-normalized and colors re-encoded (f_dc) on every trip: equal up to rounding.
    if not np.allclose(a.quats, b.quats, rtol=0, atol=1e-6):
        return False
    if (a.colors is None) != (b.colors is None):
        return False
    return a.colors is None or np.allclose(a.colors, b.colors, rtol=0, atol=1e-5)


def id_partners(old_ids: np.ndarray, new_ids: np.ndarray) -> np.ndarray:
    """(M,) int64: per new id the row of the same id in old_ids (N,), or -1 (both unique)."""
    out = np.full(len(new_ids), -1, np.int64)
    if not len(old_ids) or not len(new_ids):
        return out
    lo = int(min(old_ids.min(), new_ids.min()))
    span = int(max(old_ids.max(), new_ids.max())) - lo + 1
    if span <= _ID_TABLE_FACTOR * (len(old_ids) + len(new_ids)):
        table = np.full(span, -1, np.int64)
        table[old_ids - lo] = np.arange(len(old_ids))
        return table[new_ids - lo]
    order = np.argsort(old_ids)
    pos = np.searchsorted(old_ids, new_ids, sorter=order).clip(0, len(old_ids) - 1)
    cand = order[pos]
    hit = old_ids[cand] == new_ids
    out[hit] = cand[hit]
    return out


def removed_gaussians(old: GaussianMap, new: GaussianMap) -> tuple[int, int]:
    """(Gaussians of `old` that `new` removes, len(old)): by id when both maps have ids, else by count.
    Moved Gaussians are not removed, with or without ids (a loop closure keeps its map)."""
    if old.ids is not None and new.ids is not None:
        return int(np.count_nonzero(id_partners(new.ids, old.ids) < 0)), len(old)
    return max(0, len(old) - len(new)), len(old)


@numba.njit(cache=True, nogil=True, parallel=True)
def gather_rows(a, rows):  # pragma: no cover - numba
    """a[rows] for a 2D array (N, C), on every core (a random gather is memory-bound: 2x faster than numpy's)."""
    out = np.empty((rows.shape[0], a.shape[1]), a.dtype)
    for i in numba.prange(rows.shape[0]):
        for c in range(a.shape[1]):
            out[i, c] = a[rows[i], c]
    return out
