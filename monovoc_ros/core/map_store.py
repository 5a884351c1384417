"""Crash-safe persistence of a semantic map directory.

Layout of a map directory:
    CURRENT               name of the newest complete snapshot (replaced atomically)
    snap-000007/          one complete snapshot: gaussians.npz, state.npz, palette.npz, meta.json (and
                          deferred_keyframes.npz: keyframes a stopping node had not integrated yet)
    semantic.ply          the latest quantized cloud (x y z rgb object_id confidence), for viewers
                          (save_semantic_ply / read_semantic_ply)

A snapshot is written into a fresh directory, fsynced, and only then published by atomically replacing
CURRENT. A process killed at any moment (SIGKILL included) therefore leaves CURRENT naming a complete
snapshot: at most the keyframes integrated since that snapshot are lost, and nothing is ever half
written. The two newest snapshots are kept; older ones are removed after publishing.
The map is stored as raw activated float32 arrays (not PLY, whose log/logit encoding does not round-trip
bit-exactly), so a resumed mapper continues exactly where the saved one stopped.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from monovoc_ros.core.deferred_keyframes import FILE_NAME as DEFERRED_FILE
from monovoc_ros.core.deferred_keyframes import load_keyframes, save_keyframes
from monovoc_ros.core.evidence.palette import UNOBSERVED_ID, PaletteBuilder
from monovoc_ros.core.evidence.state import GaussianEvidence, SemanticState
from monovoc_ros.core.evidence.votes import VoteState
from monovoc_ros.core.follow.keyframe_log import KeyframeLog
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.gaussians import ARRAY_FIELDS, GaussianMap
from monovoc_ros.core.map.ply import PlyError, read_ply_vertices, write_ply_vertices
from monovoc_ros.core.mapping import MapperConfig, SemanticMapper, SemanticResult, evidence_mismatch
from monovoc_ros.core.segments.association import Associator
from monovoc_ros.core.segments.segment_labels import LabelHistogram

FORMAT_VERSION = 1
_KEEP = 2


class MapStoreError(ValueError):
    """A map directory that cannot be read; the message names the directory and the problem."""


@dataclass
class SnapshotInfo:
    path: Path
    keyframes: int
    gaussians: int
    seconds: float


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_file(path: Path) -> None:
    with open(path, "rb") as fh:
        os.fsync(fh.fileno())


def _snapshots(map_dir: Path) -> list[Path]:
    return sorted(p for p in map_dir.glob("snap-*") if p.is_dir() and not p.name.endswith(".partial"))


def _save_map(path: Path, gmap: GaussianMap) -> None:
    arrays = {name: getattr(gmap, name) for name in ARRAY_FIELDS if getattr(gmap, name) is not None}
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)


def _load_map(path: Path, stamp_ns: int = 0) -> GaussianMap:
    with np.load(path, allow_pickle=False) as arrays:
        return GaussianMap(**{name: arrays[name] for name in ARRAY_FIELDS if name in arrays}, stamp_ns=stamp_ns)


def current_snapshot(map_dir: str | os.PathLike) -> Path | None:
    """The snapshot CURRENT points to, or None for a directory without a saved map."""
    map_dir = Path(map_dir)
    try:
        name = (map_dir / "CURRENT").read_text().strip()
    except FileNotFoundError:
        return None
    snap = map_dir / name
    if not name.startswith("snap-") or not (snap / "meta.json").is_file():
        raise MapStoreError(f"{map_dir}: CURRENT names {name!r}, which is not a complete snapshot")
    return snap


@dataclass(frozen=True, eq=False)
class SnapshotContent:
    """What a snapshot holds, captured from a mapper at one moment (`capture_snapshot`): nothing in it changes
    afterwards, so a live node writes it on another thread while the mapper takes more keyframes."""

    gaussians: GaussianMap  # immutable
    map_version: int
    keyframes: int
    config: MapperConfig
    state: GaussianEvidence  # a copy
    palette: dict[str, np.ndarray]  # PaletteBuilder.to_arrays (new arrays)
    association: str | None  # Associator.to_json, per-frame mask ids only
    segment_labels: str | None  # LabelHistogram.to_json, when there are segment labels
    keyframe_log: KeyframeLog  # a copy
    result: SemanticResult  # immutable: the labels of semantic.ply
    deferred: tuple[Keyframe, ...]


def capture_snapshot(mapper: SemanticMapper, deferred: Sequence[Keyframe] = ()) -> SnapshotContent:
    """The mapper's full state as `write_snapshot` writes it; `deferred`: keyframes received but not integrated
    (a stopping node's queue), integrated first on resume (`load_deferred`)."""
    return SnapshotContent(
        gaussians=mapper.gaussians,
        map_version=mapper.map_version,
        keyframes=mapper.n_keyframes,
        config=mapper.config,
        state=mapper.state.copy(),
        palette=mapper.palette_builder.to_arrays(),
        association=mapper.associator.to_json() if mapper.associator is not None else None,
        segment_labels=mapper.segment_labels.to_json() if mapper.segment_labels.scores else None,
        keyframe_log=mapper.keyframe_log.copy(),
        result=mapper.result(),
        deferred=tuple(deferred),
    )


def save_snapshot(
    mapper: SemanticMapper,
    map_dir: str | os.PathLike,
    *,
    export_cloud: bool = True,
    deferred: Sequence[Keyframe] = (),
) -> SnapshotInfo:
    """Writes the mapper's full state as a new snapshot and publishes it atomically (`capture_snapshot`, then
    `write_snapshot`)."""
    start = time.perf_counter()
    info = write_snapshot(capture_snapshot(mapper, deferred), map_dir, export_cloud=export_cloud)
    return replace(info, seconds=time.perf_counter() - start)


def write_snapshot(content: SnapshotContent, map_dir: str | os.PathLike, *, export_cloud: bool = True) -> SnapshotInfo:
    """Writes a captured state as a new snapshot of `map_dir` and publishes it atomically (one writer per
    directory at a time: the caller's to ensure)."""
    start = time.perf_counter()
    map_dir = Path(map_dir)
    map_dir.mkdir(parents=True, exist_ok=True)
    previous = current_snapshot(map_dir)
    existing = _snapshots(map_dir)
    number = int(existing[-1].name[5:]) + 1 if existing else 1
    final = map_dir / f"snap-{number:06d}"
    partial = map_dir / f"snap-{number:06d}.partial"
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir()

    # The map is the bulk of a snapshot: hard-link it from the previous one when it is the same map (by its
    # bytes: map_version restarts at a reset or a load, and a new map may have as many Gaussians).
    prev_meta = json.loads((previous / "meta.json").read_text()) if previous else None
    digest = content.gaussians.digest
    if prev_meta and prev_meta.get("map_digest") == digest:
        os.link(previous / "gaussians.npz", partial / "gaussians.npz")
    else:
        _save_map(partial / "gaussians.npz", content.gaussians)
    content.state.save(partial / "state.npz")
    palette_path = partial / "palette.npz"
    with open(palette_path, "wb") as fh:
        np.savez(fh, **content.palette)
    if content.association is not None:  # per-frame mask ids: issued object ids and pair statistics
        (partial / "association.json").write_text(content.association)
    if content.segment_labels is not None:
        (partial / "segment_labels.json").write_text(content.segment_labels)
    content.keyframe_log.save(partial / "keyframe_log.npz")
    if content.deferred:
        save_keyframes(partial / DEFERRED_FILE, content.deferred)
    meta = {
        "format_version": FORMAT_VERSION,
        "created_unix": time.time(),
        "keyframes": content.keyframes,
        "gaussians": len(content.gaussians),
        "map_version": content.map_version,
        "map_digest": digest,
        "map_stamp_ns": int(content.gaussians.stamp_ns),  # the SLAM's stamp of the map (core.follow.map_frames)
        "deferred_keyframes": len(content.deferred),
        "config": asdict(content.config),
    }
    (partial / "meta.json").write_text(json.dumps(meta, indent=1))
    for f in partial.iterdir():
        _fsync_file(f)
    _fsync_dir(partial)
    os.replace(partial, final)
    _fsync_dir(map_dir)

    tmp = map_dir / "CURRENT.tmp"
    tmp.write_text(final.name + "\n")
    _fsync_file(tmp)
    os.replace(tmp, map_dir / "CURRENT")
    _fsync_dir(map_dir)

    for old in _snapshots(map_dir)[:-_KEEP]:
        shutil.rmtree(old, ignore_errors=True)
    if export_cloud:
        result = content.result
        points = content.gaussians.means
        save_semantic_ply(map_dir / "semantic.ply", points, result.object_rgb(), result.object_ids, result.confidence)
    return SnapshotInfo(final, content.keyframes, len(content.gaussians), time.perf_counter() - start)


def load_deferred(map_dir: str | os.PathLike) -> list[Keyframe]:
    """The keyframes the newest snapshot of `map_dir` deferred (see `save_snapshot`); [] when none."""
    snap = current_snapshot(map_dir)
    if snap is None or not (snap / DEFERRED_FILE).is_file():
        return []
    try:
        return load_keyframes(snap / DEFERRED_FILE)
    except ValueError as exc:
        raise MapStoreError(str(exc)) from exc


def load_snapshot(map_dir: str | os.PathLike, config: MapperConfig | None = None) -> SemanticMapper:
    """A mapper restored from the newest complete snapshot of `map_dir`.

    `config` overrides the saved configuration (e.g. another rasterizer implementation); the saved
    one is used when it is None. Evidence accumulated with another weight_power raises MapStoreError.
    Every file is read and checked before the mapper is built, and any failure (a truncated or
    byte-flipped archive, meta.json that is not an object, a missing key, arrays of the wrong shape)
    raises MapStoreError naming the snapshot and the problem: never another exception type.
    """
    map_dir = Path(map_dir)
    try:
        snap = current_snapshot(map_dir)
    except OSError as exc:
        raise MapStoreError(f"{map_dir}: unreadable CURRENT ({exc})") from exc
    if snap is None:
        raise MapStoreError(f"{map_dir}: no saved map (no CURRENT file)")
    try:
        return _read_snapshot(snap, config)
    except MapStoreError:
        raise
    except Exception as exc:  # any defect of the files is "an unreadable snapshot"
        raise MapStoreError(f"{snap}: unreadable snapshot ({type(exc).__name__}: {exc})") from exc


def _read(path: Path, read):
    """read(path), any failure as MapStoreError naming the file."""
    try:
        return read(path)
    except MapStoreError:
        raise
    except Exception as exc:  # see load_snapshot
        raise MapStoreError(f"{path}: unreadable snapshot file ({type(exc).__name__}: {exc})") from exc


def _read_palette(path: Path) -> PaletteBuilder:
    with np.load(path, allow_pickle=False) as arrays:
        return PaletteBuilder.from_arrays(dict(arrays))


def _read_snapshot(snap: Path, config: MapperConfig | None) -> SemanticMapper:
    meta = _read(snap / "meta.json", lambda p: json.loads(p.read_text()))
    if not isinstance(meta, dict):
        raise MapStoreError(f"{snap}: meta.json holds a {type(meta).__name__}, not an object")
    if meta.get("format_version") != FORMAT_VERSION:
        raise MapStoreError(f"{snap}: unsupported format_version {meta.get('format_version')}")
    if not isinstance(meta.get("config"), dict):
        raise MapStoreError(f"{snap}: meta.json has no 'config' object")
    stamp = meta.get("map_stamp_ns", 0)  # 0: unknown (snapshots from before it)
    if isinstance(stamp, bool) or not isinstance(stamp, int) or stamp < 0:
        raise MapStoreError(f"{snap}: meta.json's map_stamp_ns is {stamp!r}, not a stamp in ns")
    gaussians = _read(snap / "gaussians.npz", lambda p: _load_map(p, stamp))
    # Snapshots from before semantic_mode used SCD, before weight_power the paper's k = 1, before max_depth_m no limit.
    saved = {"weight_power": 1, "semantic_mode": "scd", "max_depth_m": 0.0, **meta["config"]}
    try:
        saved_config = MapperConfig(**saved)  # checked even when `config` overrides it
    except (TypeError, ValueError) as exc:
        raise MapStoreError(f"{snap}: invalid saved config ({exc})") from exc
    store = VoteState if saved_config.semantic_mode == "vote" else SemanticState
    state = _read(snap / "state.npz", store.load)
    builder = _read(snap / "palette.npz", _read_palette)
    path = snap / "association.json"
    association = _read(path, lambda p: Associator.from_json(p.read_text())) if path.exists() else None
    path = snap / "segment_labels.json"
    segment_labels = (
        _read(path, lambda p: LabelHistogram.from_json(p.read_text())) if path.exists() else LabelHistogram()
    )
    path = snap / "keyframe_log.npz"
    keyframe_log = _read(path, KeyframeLog.load) if path.exists() else None  # older snapshots have none
    if len(state) != len(gaussians):
        raise MapStoreError(f"{snap}: state has {len(state)} Gaussians, map has {len(gaussians)}")
    if "gaussians" in meta and meta["gaussians"] != len(gaussians):
        raise MapStoreError(f"{snap}: meta.json says {meta['gaussians']} Gaussians, gaussians.npz has {len(gaussians)}")
    if isinstance(state, VoteState) and state.slots != saved_config.vote_slots:
        raise MapStoreError(f"{snap}: state.npz has {state.slots} vote slots, meta.json says {saved_config.vote_slots}")
    name, mine, theirs = evidence_mismatch(config, saved_config) if config is not None else ("", None, None)
    if name and len(state.stamps_ns):
        raise MapStoreError(
            f"{snap}: its evidence was accumulated with {name} {theirs!r}, not {mine!r}: "
            f"the two cannot be mixed (reset the map or keep {name})"
        )
    mapper = SemanticMapper(gaussians, config or saved_config)
    if len(state.stamps_ns):  # else the mapper's own empty state, of the configuration in force
        mapper.state = state
    mapper.palette_builder = builder
    mapper.segment_labels = segment_labels
    if keyframe_log is not None:
        keyframe_log.max_bytes = mapper.config.keyframe_log_bytes
        mapper.keyframe_log = keyframe_log
    else:  # a snapshot from before the log: none of its keyframes can be re-integrated
        mapper.keyframe_log.dropped = mapper.n_keyframes
    if mapper.associator is not None and association is not None:
        mapper.associator = association
        association.config.render_scale = mapper.config.association_scale  # a rendering setting only
    mapper.map_version = int(meta.get("map_version", 0))
    return mapper


SEMANTIC_UNOBSERVED = -1  # object_id of a Gaussian with no evidence in semantic.ply (palette.UNOBSERVED_ID)


def save_semantic_ply(
    path: str | os.PathLike,
    points: np.ndarray,
    rgb: np.ndarray,
    object_id: np.ndarray,
    confidence: np.ndarray | None = None,
) -> None:
    """A colored point cloud viewable in any PLY viewer: x y z red green blue object_id [confidence].

    ``object_id`` (N,) uint32 packed palette colors, ``UNOBSERVED_ID`` (0xFFFFFFFF) for unobserved
    Gaussians. It is written as ``int`` (int32), with -1 for unobserved: Open3D skips ``uint``
    properties, and every id that is a color (<= 0xFFFFFF) fits in int32 unchanged.
    """
    points = np.asarray(points, np.float32)  # (N, 3)
    rgb = np.asarray(rgb, np.uint8)  # (N, 3)
    ids = np.asarray(object_id, np.int64)  # (N,)
    unobserved = ids == UNOBSERVED_ID
    bad = ~unobserved & ((ids < 0) | (ids > 0xFFFFFF))
    if bad.any():
        raise ValueError(f"{path}: object ids must be packed colors 0..0xFFFFFF or UNOBSERVED_ID, got {ids[bad][:3]}")
    cols: dict[str, np.ndarray] = {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2]}
    cols.update(red=rgb[:, 0], green=rgb[:, 1], blue=rgb[:, 2])
    cols["object_id"] = np.where(unobserved, SEMANTIC_UNOBSERVED, ids).astype(np.int32)
    if confidence is not None:
        cols["confidence"] = np.asarray(confidence, np.float32)
    write_ply_vertices(Path(path), cols, comment="monovoc_ros semantic map")


def read_semantic_ply(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """A semantic.ply back as ``points`` (N, 3) float32, ``rgb`` (N, 3) uint8, ``object_id`` (N,) uint32
    (UNOBSERVED_ID for unobserved) and ``confidence`` (N,) float32 when present.

    Reads both layouts: ``int`` object_id with -1 (written since Open3D compatibility) and the older
    ``uint`` one with 0xFFFFFFFF.
    """
    v = read_ply_vertices(path)
    missing = [n for n in ("x", "y", "z", "red", "green", "blue", "object_id") if n not in v.dtype.names]
    if missing:
        raise PlyError(f"{path}: not a semantic PLY, missing vertex properties {missing}")
    ids = v["object_id"].astype(np.int64)
    ids[ids == SEMANTIC_UNOBSERVED] = UNOBSERVED_ID
    out = {
        "points": np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float32),
        "rgb": np.stack([v["red"], v["green"], v["blue"]], axis=1).astype(np.uint8),
        "object_id": ids.astype(np.uint32),
    }
    if "confidence" in v.dtype.names:
        out["confidence"] = v["confidence"].astype(np.float32)
    return out
