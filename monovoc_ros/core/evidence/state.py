"""The incremental SCD accumulators of one Gaussian map (METHOD section 3).

Per Gaussian i the state holds ``color_sum[i] = sum_p w_ip y_p`` and ``weight_sum[i] = sum_p w_ip``
over every pixel of every keyframe integrated so far, plus the stamps of those keyframes. The
deblended color is their ratio. Because both are plain sums, integration order does not matter and
two states of the same map (two halves of a bag, two robots) merge by adding them; the only cost is
float64 addition order (differences of a few ulp).

Keyframes are identified by their stamp: adding a stamp twice would count its evidence twice, so it
raises, and merging two states that share a stamp raises for the same reason.

When the SLAM front-end publishes a new map, `carried_over` gives the new map's Gaussians the rows
of the old evidence that core.follow.map_follow chose for them (by id, else by the map's estimated motion).

Evidence is kept even for keyframes that are later re-posed: SCD weights depend on the pose used at
integration time, and re-rendering old keyframes is the caller's choice, not this store's.
"""

from __future__ import annotations

import copy
import os
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Self

import numpy as np

from monovoc_ros.core.map.gaussians import all_distinct, gather_rows, id_partners

# Written into every saved file (beside the store's FORMAT) so that a foreign .npz is recognised as such.
_FORMAT_VERSION = 1


def _as_ids(ids: np.ndarray | None, n: int, what: str) -> np.ndarray | None:
    if ids is None:
        return None
    ids = np.asarray(ids)
    if ids.shape != (n,):
        raise ValueError(f"{what}: expected shape ({n},), got {ids.shape}")
    if ids.dtype.kind not in "iu":
        raise ValueError(f"{what}: expected integer ids, got dtype {ids.dtype}")
    ids = ids.astype(np.int64)
    if not all_distinct(ids):
        raise ValueError(f"{what}: ids must be unique")
    return ids


class GaussianEvidence:
    """What every per-Gaussian evidence store shares: per-Gaussian arrays (`ARRAYS`, first axis N),
    optional stable Gaussian ids, the stamps of the integrated keyframes, atomic .npz files, and
    carrying the evidence over to a new map."""

    FORMAT: ClassVar[str]
    WHAT: ClassVar[str]
    ARRAYS: ClassVar[tuple[str, ...]]
    ids: np.ndarray | None
    stamps_ns: np.ndarray

    def _init_common(self, n: int) -> None:
        stamps = np.zeros(0, np.int64) if self.stamps_ns is None else np.array(self.stamps_ns, dtype=np.int64)
        name = type(self).__name__
        if stamps.ndim != 1:
            raise ValueError(f"{name}.stamps_ns: expected shape (K,), got {stamps.shape}")
        if not all_distinct(stamps):
            raise ValueError(f"{name}.stamps_ns: duplicate keyframe stamps")
        self.ids = _as_ids(self.ids, n, f"{name}.ids")
        self.stamps_ns = stamps

    def empty_like(self, n: int, ids: np.ndarray | None) -> GaussianEvidence:
        """A store of the same kind (and shape per Gaussian) for `n` Gaussians without evidence."""
        raise NotImplementedError

    @classmethod
    def _built(cls, ids: np.ndarray | None, stamps_ns: np.ndarray, **arrays: np.ndarray) -> Self:
        """A store of arrays made here, valid by construction (`ARRAYS` by name, `ids` unique int64 or None):
        without the constructor's copies and checks, which for an empty 1M-Gaussian vote state touched 130 MB
        of fresh pages (~0.5 s) where the arrays alone take 56 MB."""
        out = cls.__new__(cls)
        for name in cls.ARRAYS:
            setattr(out, name, arrays[name])
        out.ids = ids
        out.stamps_ns = stamps_ns
        return out

    @classmethod
    def _zeros(cls, n: int, ids: np.ndarray | None, **arrays: np.ndarray) -> Self:
        """An empty store of the given arrays for `n` Gaussians, its `ids` checked as the constructor checks them."""
        return cls._built(_as_ids(ids, n, f"{cls.__name__}.ids"), np.zeros(0, np.int64), **arrays)

    def __len__(self) -> int:
        return getattr(self, self.ARRAYS[0]).shape[0]

    def has_stamp(self, stamp_ns: int) -> bool:
        return bool(np.any(self.stamps_ns == np.int64(stamp_ns)))

    def _check_new_stamp(self, stamp_ns: int) -> None:
        if self.has_stamp(stamp_ns):
            raise ValueError(f"keyframe stamp {int(stamp_ns)} was already integrated")

    def _aligned_rows(self, other: GaussianEvidence) -> np.ndarray:
        """Row of `other` for each row of this store (by id when both have ids, else by position);
        raises when the two cannot be merged."""
        if len(self) != len(other):
            raise ValueError(f"cannot merge states of {len(self)} and {len(other)} Gaussians")
        shared = np.intersect1d(self.stamps_ns, other.stamps_ns)
        if shared.size:
            raise ValueError(f"cannot merge: {shared.size} keyframe stamps are in both states (e.g. {shared[0]})")
        take = np.arange(len(self))
        if self.ids is not None and other.ids is not None and len(self):
            take = id_partners(other.ids, self.ids)
            if np.any(take < 0):
                raise ValueError("cannot merge: the states have different Gaussian ids (reindex one first)")
        return take

    def copy(self) -> GaussianEvidence:
        """A store holding this one's evidence as it is now, sharing no array with it (a snapshot written on
        another thread while this one takes more keyframes: core.map_store.capture_snapshot)."""
        out = copy.copy(self)
        for name in self.ARRAYS:
            setattr(out, name, getattr(self, name).copy())
        out.stamps_ns = self.stamps_ns.copy()
        out.ids = None if self.ids is None else self.ids.copy()
        return out

    @property
    def total_weight(self) -> np.ndarray:
        """(N,) float64 sum of every evidence weight a Gaussian received."""
        raise NotImplementedError

    @property
    def evidence_nbytes(self) -> int:
        """Bytes of the per-Gaussian evidence arrays alone."""
        return sum(getattr(self, name).nbytes for name in self.ARRAYS)

    @property
    def nbytes(self) -> int:
        ids = 0 if self.ids is None else self.ids.nbytes
        return self.evidence_nbytes + self.stamps_ns.nbytes + ids

    def save(self, path: str | os.PathLike) -> None:
        """Writes an .npz atomically: a reader sees the old file or the new one, never a partial one."""
        path = Path(path)
        arrays = {
            "format": np.array(self.FORMAT),
            "format_version": np.array(_FORMAT_VERSION, np.int64),
            "stamps_ns": self.stamps_ns,
        }
        arrays.update({name: getattr(self, name) for name in self.ARRAYS})
        if self.ids is not None:
            arrays["ids"] = self.ids
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as fh:
                np.savez(fh, **arrays)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        _fsync_dir(path.parent)

    @classmethod
    def load(cls, path: str | os.PathLike):
        """Reads a file written by `save` (bit-exact). A missing file raises FileNotFoundError; a corrupt
        or foreign file (another kind of evidence included) raises ValueError naming the file."""
        path = Path(path)
        what = f"{path}: unreadable {cls.WHAT}"
        try:
            data = np.load(path, allow_pickle=False)
        except FileNotFoundError:
            raise
        except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
            raise ValueError(f"{what} ({exc})") from exc
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise ValueError(f"{path}: not a {cls.WHAT} file (not an .npz archive)")
        try:
            with data:
                if "format" not in data.files or str(data["format"]) != cls.FORMAT:
                    found = str(data["format"]) if "format" in data.files else None
                    raise ValueError(f"not a {cls.WHAT} file (format {found!r}, expected {cls.FORMAT!r})")
                version = int(data["format_version"]) if "format_version" in data.files else None
                if version != _FORMAT_VERSION:
                    raise ValueError(f"unsupported format_version {version} (expected {_FORMAT_VERSION})")
                missing = {*cls.ARRAYS, "stamps_ns"} - set(data.files)
                if missing:
                    raise ValueError(f"missing arrays {sorted(missing)}")
                arrays = {k: data[k] for k in (*cls.ARRAYS, "stamps_ns")}
                ids = data["ids"] if "ids" in data.files else None
        except (ValueError, OSError, EOFError, KeyError, zipfile.BadZipFile) as exc:
            raise ValueError(f"{what} ({exc})") from exc
        try:
            return cls(**arrays, ids=ids)
        except ValueError as exc:
            raise ValueError(f"{path}: inconsistent {cls.WHAT} ({exc})") from exc

    def carried_over(self, source_rows: np.ndarray, new_ids: np.ndarray | None) -> GaussianEvidence:
        """A store for a new map whose Gaussian j takes this store's row source_rows[j] (-1: none).
        `new_ids`: the new map's ids (unique, as a GaussianMap's are) or None.

        Built by one gather per array, without re-validating (the rows come from a valid store): at 1M
        Gaussians this is 0.05 s where constructing a store takes 0.2 s."""
        source_rows = np.asarray(source_rows, np.int64)
        rows = np.maximum(source_rows, 0)
        miss = np.flatnonzero(source_rows < 0)
        template = self.empty_like(1, None)  # the values of a Gaussian without evidence
        arrays = {}
        for name in self.ARRAYS:
            empty_row = getattr(template, name)[0]
            if len(self):
                arrays[name] = _gathered(getattr(self, name), rows)
                arrays[name][miss] = empty_row
            else:
                arrays[name] = np.repeat(getattr(template, name), len(rows), axis=0)
        ids = None if new_ids is None else np.asarray(new_ids, np.int64)
        return self._built(ids, self.stamps_ns.copy(), **arrays)


@dataclass(eq=False)
class SemanticState(GaussianEvidence):
    color_sum: np.ndarray  # (N, 3) float64, sum_p w_ip y_p
    weight_sum: np.ndarray  # (N,) float64, sum_p w_ip
    ids: np.ndarray | None = None  # (N,) int64 stable Gaussian ids (None when the map has none)
    stamps_ns: np.ndarray | None = None  # (K,) int64 stamps of the integrated keyframes, in order of arrival

    FORMAT: ClassVar[str] = "monovoc_semantic_state"
    WHAT: ClassVar[str] = "semantic state"
    ARRAYS: ClassVar[tuple[str, ...]] = ("color_sum", "weight_sum")

    def __post_init__(self) -> None:
        color_sum = np.array(self.color_sum, dtype=np.float64)  # a copy: the state owns its arrays
        weight_sum = np.array(self.weight_sum, dtype=np.float64)
        if color_sum.ndim != 2 or color_sum.shape[1] != 3:
            raise ValueError(f"SemanticState.color_sum: expected shape (N, 3), got {color_sum.shape}")
        n = color_sum.shape[0]
        if weight_sum.shape != (n,):
            raise ValueError(f"SemanticState.weight_sum: expected shape ({n},), got {weight_sum.shape}")
        self.color_sum = color_sum
        self.weight_sum = weight_sum
        self._init_common(n)

    @classmethod
    def zeros(cls, n: int, ids: np.ndarray | None = None) -> SemanticState:
        """An empty state for a map of `n` Gaussians."""
        if int(n) < 0:
            raise ValueError(f"SemanticState.zeros: n must be >= 0, got {n}")
        n = int(n)
        return cls._zeros(n, ids, color_sum=np.zeros((n, 3)), weight_sum=np.zeros(n))

    def empty_like(self, n: int, ids: np.ndarray | None) -> SemanticState:
        return SemanticState.zeros(n, ids)

    def add(self, evidence, stamp_ns: int) -> None:
        """Adds one keyframe's evidence (any object with `color_sum` (N, 3) and `weight_sum` (N,)).

        Everything is checked before anything changes, so a rejected keyframe leaves the state as it was.
        """
        n = len(self)
        color = np.asarray(evidence.color_sum, dtype=np.float64)
        weight = np.asarray(evidence.weight_sum, dtype=np.float64)
        if color.shape != (n, 3):
            raise ValueError(f"evidence.color_sum: expected shape ({n}, 3), got {color.shape}")
        if weight.shape != (n,):
            raise ValueError(f"evidence.weight_sum: expected shape ({n},), got {weight.shape}")
        # A single NaN would poison the accumulator for good, so bad evidence is refused up front.
        if not (np.isfinite(color).all() and np.isfinite(weight).all()):
            raise ValueError("evidence contains NaN or infinite values")
        if np.any(weight < 0):
            raise ValueError("evidence.weight_sum has negative weights")
        self._check_new_stamp(stamp_ns)
        self.color_sum += color
        self.weight_sum += weight
        self.stamps_ns = np.append(self.stamps_ns, np.int64(stamp_ns))

    def merged(self, other: SemanticState) -> SemanticState:
        """The state holding both states' evidence (same map).

        When both have ids they are aligned by id (the id sets must be equal; the result keeps this
        state's order); otherwise by position (sizes must be equal). Shared stamps raise: that
        keyframe's evidence would be counted twice.
        """
        take = self._aligned_rows(other)
        ids = self.ids if self.ids is not None else other.ids
        return SemanticState(
            self.color_sum + other.color_sum[take],
            self.weight_sum + other.weight_sum[take],
            None if ids is None else ids.copy(),
            np.concatenate([self.stamps_ns, other.stamps_ns]),
        )

    @property
    def observed(self) -> np.ndarray:
        """(N,) bool: Gaussians with any evidence."""
        return self.weight_sum > 0

    @property
    def total_weight(self) -> np.ndarray:
        return self.weight_sum

    def colors(self) -> np.ndarray:
        """(N, 3) float64 deblended colors s_hat = color_sum / weight_sum; NaN rows where unobserved."""
        out = np.full_like(self.color_sum, np.nan)
        seen = self.observed
        out[seen] = self.color_sum[seen] / self.weight_sum[seen, None]
        return out


def _gathered(a: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """a[rows] for a 1D or 2D array (the parallel gather of core.map.gaussians)."""
    out = gather_rows(np.ascontiguousarray(a).reshape(len(a), -1), rows)
    return out.reshape((len(rows), *a.shape[1:]))


def _fsync_dir(directory: Path) -> None:
    # Makes the rename itself durable; not every platform can open a directory.
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
