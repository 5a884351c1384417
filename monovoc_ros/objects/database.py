"""The object database: ``objects.db`` (SQLite, standard library) in the map directory.

Tables (values little endian; ids are packed palette colors r << 16 | g << 8 | b):

    meta            key -> JSON value: format, schema_version, backend (name, dim, options), embedding_model,
                    config (IndexConfig), floor, keyframes_seen, saved_unix, snapshot
    objects         one row per object: color, label, description, centroid / box / extent (metres, map
                    frame), counts, embedding + image_embedding (float32 BLOBs), embedding model + dim
    views           the objects' best keyframe views: stamp, prevalence, RGB crop and mask (PNG BLOBs),
                    the view's image embedding and the crop settings it was made with
    observations    per object id: keyframes whose mask showed it
    gaussian_index  the per-Gaussian object index of the map snapshot it belongs to: the distinct ids
                    (uint32) and per Gaussian the position of its id in them (uint8 / uint16 / uint32,
                    whichever fits), so 140k Gaussians of <= 255 objects take 140 kB

Every save is one transaction in WAL mode with ``synchronous=FULL``: a process killed at any moment
(SIGKILL included) leaves the database with the last committed save, and the next open replays or drops
the write-ahead log as SQLite does. Views are written incrementally (only new ones are PNG-encoded).
A file that is not such a database raises ``ObjectDatabaseError`` naming the file and the problem.
"""

from __future__ import annotations

import contextlib
import json
import os
import sqlite3
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from monovoc_ros.core.map.sorting import argsort_keys
from monovoc_ros.core.segments.object_labels import stored_source
from monovoc_ros.objects.index import IndexConfig, ObjectIndex, backend_identity, lazy_backend, model_name
from monovoc_ros.objects.records import ObjectRecord
from monovoc_ros.objects.views import ObjectView

DB_NAME = "objects.db"
FORMAT = "monovoc_objects"
SCHEMA_VERSION = 2
# Version 1 lacked objects.label_confidence: opening one adds the column (every label counted sure, as then).
_MIGRATIONS = {1: "ALTER TABLE objects ADD COLUMN label_confidence REAL NOT NULL DEFAULT 1.0"}

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS objects (
    id INTEGER PRIMARY KEY,
    r INTEGER NOT NULL, g INTEGER NOT NULL, b INTEGER NOT NULL,
    label TEXT NOT NULL, label_source TEXT NOT NULL, description TEXT NOT NULL, color_name TEXT NOT NULL,
    cx REAL NOT NULL, cy REAL NOT NULL, cz REAL NOT NULL,
    min_x REAL NOT NULL, min_y REAL NOT NULL, min_z REAL NOT NULL,
    max_x REAL NOT NULL, max_y REAL NOT NULL, max_z REAL NOT NULL,
    ex REAL NOT NULL, ey REAL NOT NULL, ez REAL NOT NULL,
    upright_w REAL NOT NULL, upright_d REAL NOT NULL, upright_h REAL NOT NULL, height_above_floor REAL NOT NULL,
    num_gaussians INTEGER NOT NULL, num_observations INTEGER NOT NULL, num_views INTEGER NOT NULL,
    embedding BLOB NOT NULL, image_embedding BLOB NOT NULL,
    embedding_model TEXT NOT NULL, embedding_dim INTEGER NOT NULL,
    updated_unix REAL NOT NULL,
    label_confidence REAL NOT NULL DEFAULT 1.0
);
CREATE TABLE IF NOT EXISTS views (
    object_id INTEGER NOT NULL, stamp_ns INTEGER NOT NULL,
    keyframe_index INTEGER NOT NULL, prevalence INTEGER NOT NULL,
    width INTEGER NOT NULL, height INTEGER NOT NULL,
    rgb_png BLOB NOT NULL, mask_png BLOB NOT NULL,
    embedding BLOB, embedding_key TEXT,
    PRIMARY KEY (object_id, stamp_ns)
);
CREATE TABLE IF NOT EXISTS observations (object_id INTEGER PRIMARY KEY, keyframes INTEGER NOT NULL);
CREATE TABLE IF NOT EXISTS gaussian_index (
    slot INTEGER PRIMARY KEY CHECK (slot = 0),
    snapshot TEXT, map_version INTEGER, keyframes INTEGER,
    n_gaussians INTEGER NOT NULL, ids BLOB NOT NULL, positions BLOB NOT NULL, position_bytes INTEGER NOT NULL,
    updated_unix REAL NOT NULL
);
"""
_F32 = np.dtype("<f4")
_U32 = np.dtype("<u4")
_POSITION_DTYPES = {1: np.dtype("u1"), 2: np.dtype("<u2"), 4: np.dtype("<u4")}


class ObjectDatabaseError(ValueError):
    """An object database that cannot be read or written; the message names the file and the problem."""


@dataclass
class SaveReport:
    path: Path
    objects: int
    views_written: int
    views_deleted: int
    gaussians: int  # per-Gaussian index entries written (0 when the index had none)
    seconds: float


@dataclass(frozen=True)
class PreparedSave:
    """What ObjectDatabase.save writes, taken from an index at one moment (`prepare_save`)."""

    objects: list[tuple]  # the objects table's rows
    views: list[ObjectView]  # their images are encoded when written (only those the file lacks)
    view_key: tuple | None  # the embeddings stored with the views
    observations: list[tuple[int, int]]  # (object id, masks seen in)
    object_ids: np.ndarray | None  # (N,) per-Gaussian object index
    meta: dict
    snapshot: str | None
    map_version: int | None
    keyframes: int | None
    seconds: float  # the time taken to prepare it


@dataclass
class GaussianIndex:
    """The per-Gaussian object ids of one map snapshot."""

    object_ids: np.ndarray  # (N,) uint32
    snapshot: str | None
    map_version: int | None
    keyframes: int | None


def database_path(location: str | os.PathLike) -> Path:
    """``location`` itself when it names a file (or a path ending in .db), else ``location/objects.db``."""
    location = Path(location)
    if location.suffix == ".db" or location.is_file():
        return location
    return location / DB_NAME


def encode_positions(object_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distinct ids uint32 ascending, per-element position in them in the smallest unsigned type): numpy's
    unique(return_inverse=True) by the radix argsort (1M ids: numpy's sort took ~100 ms of each objects.db write)."""
    flat = np.asarray(object_ids, np.uint32).reshape(-1)
    order = argsort_keys(flat)
    ordered = flat[order]
    first = np.empty(flat.size, bool)
    first[:1] = True
    np.not_equal(ordered[1:], ordered[:-1], out=first[1:])
    ids = ordered[first]
    size = 1 if ids.size <= 0x100 else 2 if ids.size <= 0x10000 else 4
    positions = np.empty(flat.size, _POSITION_DTYPES[size])
    positions[order] = np.cumsum(first) - 1
    return ids.astype(_U32), positions


def _png(image: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".png", image)
    if not ok:
        raise ObjectDatabaseError(f"could not PNG-encode an image of shape {image.shape}")
    return data.tobytes()


def _unpng(blob: bytes, flags: int) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(blob, np.uint8), flags)
    if image is None:
        raise ObjectDatabaseError("a stored view is not a readable PNG")
    return image


def _vector(blob: bytes | None) -> np.ndarray | None:
    return None if blob is None else np.frombuffer(blob, _F32).astype(np.float32)


class ObjectDatabase:
    """One objects.db file. Each call opens its own short connection (safe from any thread)."""

    def __init__(self, location: str | os.PathLike, *, create: bool = True) -> None:
        self.path = database_path(location)
        if not create and self.path.exists() and not self.path.is_file():
            raise ObjectDatabaseError(f"{self.path}: not a file (an object database is one SQLite file)")
        if not create and not self.path.is_file():
            raise ObjectDatabaseError(f"{self.path}: no object database (build the map's objects first)")
        if create:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        with self._connect() as db:
            self._check_or_init(db, create)

    # ------------------------------------------------------------------ connections

    @contextlib.contextmanager
    def _connect(self) -> Iterator[sqlite3.Connection]:
        try:
            db = sqlite3.connect(self.path, timeout=30.0, isolation_level=None)
        except sqlite3.Error as exc:
            raise ObjectDatabaseError(f"{self.path}: cannot open ({exc})") from exc
        try:
            db.execute("PRAGMA journal_mode=WAL")
            db.execute("PRAGMA synchronous=FULL")
            yield db
        except sqlite3.DatabaseError as exc:
            if isinstance(exc, sqlite3.OperationalError) and "locked" in str(exc):
                raise ObjectDatabaseError(f"{self.path}: busy, another process holds a write lock ({exc})") from exc
            # Deleting it is the remedy only for a map's own objects.db, not for another file given in its place.
            remedy = "; delete it to rebuild the objects" if self.path.name == DB_NAME else ""
            raise ObjectDatabaseError(f"{self.path}: not a readable MonoVoc object database ({exc}){remedy}") from exc
        finally:
            db.close()

    @contextlib.contextmanager
    def _transaction(self, write: bool) -> Iterator[sqlite3.Connection]:
        with self._connect() as db:
            db.execute("BEGIN IMMEDIATE" if write else "BEGIN")
            try:
                yield db
            except BaseException:
                db.execute("ROLLBACK")
                raise
            db.execute("COMMIT")

    def _migrate(self, db: sqlite3.Connection, version: int) -> int:
        """Brings an older schema up to date under the write lock (another process may have just done it) and
        returns the version now; a file this process may not write stays as it is (it is read as it is)."""
        try:
            db.execute("BEGIN IMMEDIATE")
        except sqlite3.OperationalError:  # read-only file or directory
            return version
        try:
            row = db.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
            version = json.loads(row[0]) if row else version
            while version in _MIGRATIONS:
                db.execute(_MIGRATIONS[version])
                version += 1
            db.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'", (json.dumps(version),))
            db.execute("COMMIT")
        except sqlite3.OperationalError:  # read-only: the migration is left to a writer
            db.execute("ROLLBACK")
            return json.loads(db.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()[0])
        return version

    def _check_or_init(self, db: sqlite3.Connection, create: bool) -> None:
        tables = {row[0] for row in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if "meta" in tables:
            meta = dict(db.execute("SELECT key, value FROM meta").fetchall())
            fmt = json.loads(meta.get("format", "null"))
            if fmt != FORMAT:
                raise ObjectDatabaseError(f"{self.path}: an SQLite file, but not a MonoVoc object database")
            version = json.loads(meta.get("schema_version", "null"))
            if version in _MIGRATIONS:
                version = self._migrate(db, version)
            if version != SCHEMA_VERSION and version not in _MIGRATIONS:
                raise ObjectDatabaseError(
                    f"{self.path}: schema version {version}, this version reads {SCHEMA_VERSION}; rebuild the objects"
                )
            return
        if tables:
            raise ObjectDatabaseError(f"{self.path}: an SQLite file with other tables, not a MonoVoc object database")
        if not create:
            raise ObjectDatabaseError(f"{self.path}: empty file, not a MonoVoc object database")
        db.execute("BEGIN IMMEDIATE")
        for statement in filter(str.strip, _SCHEMA.split(";")):
            db.execute(statement)
        db.executemany(
            "INSERT INTO meta (key, value) VALUES (?, ?)",
            [("format", json.dumps(FORMAT)), ("schema_version", json.dumps(SCHEMA_VERSION))],
        )
        db.execute("COMMIT")

    # ------------------------------------------------------------------ writing

    def save(
        self,
        index: ObjectIndex,
        *,
        snapshot: str | None = None,
        map_version: int | None = None,
        keyframes: int | None = None,
    ) -> SaveReport:
        """Writes the index (records, views, observations, per-Gaussian ids, settings) in one transaction."""
        return self.write(prepare_save(index, snapshot=snapshot, map_version=map_version, keyframes=keyframes))

    def write(self, prepared: PreparedSave) -> SaveReport:
        """Writes what `prepare_save` took, in one transaction: only the views the file lacks are encoded."""
        start = time.perf_counter()
        view_key = prepared.view_key
        gaussians = 0
        with self._transaction(write=True) as db:
            stored = set(db.execute("SELECT object_id, stamp_ns FROM views").fetchall())
            wanted = {v.key: v for v in prepared.views}
            stale = [key for key in stored if key not in wanted]
            fresh = [v for key, v in wanted.items() if key not in stored]
            db.executemany("DELETE FROM views WHERE object_id = ? AND stamp_ns = ?", stale)
            db.executemany(
                "INSERT INTO views VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)", [_view_row(v, view_key) for v in fresh]
            )
            # Views kept from an earlier save may have been embedded since: store their embeddings too.
            db.executemany(
                "UPDATE views SET embedding = ?, embedding_key = ? WHERE object_id = ? AND stamp_ns = ?",
                [
                    (v.embeddings[view_key].astype(_F32).tobytes(), json.dumps(view_key), *v.key)
                    for key, v in wanted.items()
                    if key in stored and view_key is not None and view_key in v.embeddings
                ],
            )
            db.execute("DELETE FROM objects")
            db.executemany(f"INSERT INTO objects VALUES ({', '.join('?' * 33)})", prepared.objects)
            db.execute("DELETE FROM observations")
            db.executemany("INSERT INTO observations VALUES (?, ?)", prepared.observations)
            if prepared.object_ids is not None:
                ids, positions = encode_positions(prepared.object_ids)
                db.execute(
                    "INSERT OR REPLACE INTO gaussian_index VALUES (0, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (
                        prepared.snapshot,
                        prepared.map_version,
                        prepared.keyframes,
                        int(positions.size),
                        ids.tobytes(),
                        positions.tobytes(),
                        positions.dtype.itemsize,
                        time.time(),
                    ),
                )
                gaussians = int(positions.size)
            db.executemany(
                "INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)",
                [(k, json.dumps(v)) for k, v in prepared.meta.items()],
            )
        seconds = prepared.seconds + time.perf_counter() - start
        return SaveReport(self.path, len(prepared.objects), len(fresh), len(stale), gaussians, seconds)

    # ------------------------------------------------------------------ reading

    def meta(self) -> dict:
        with self._connect() as db:
            return {k: json.loads(v) for k, v in db.execute("SELECT key, value FROM meta")}

    def records(self) -> list[ObjectRecord]:
        with self._connect() as db:
            db.row_factory = sqlite3.Row
            rows = db.execute("SELECT * FROM objects ORDER BY id").fetchall()
        return [_record(row) for row in rows]

    def views(self) -> list[ObjectView]:
        with self._connect() as db:
            rows = db.execute(
                "SELECT object_id, stamp_ns, keyframe_index, prevalence, rgb_png, mask_png, embedding, embedding_key"
                " FROM views ORDER BY object_id, prevalence DESC, stamp_ns"
            ).fetchall()
        out = []
        for oid, stamp, kf, prevalence, rgb_png, mask_png, emb, key in rows:
            rgb = cv2.cvtColor(_unpng(rgb_png, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
            mask = _unpng(mask_png, cv2.IMREAD_GRAYSCALE) > 127
            view = ObjectView(int(oid), int(stamp), int(kf), int(prevalence), rgb, mask)
            if emb is not None and key is not None:
                view.embeddings[tuple(json.loads(key))] = _vector(emb)
            out.append(view)
        return out

    def observations(self) -> dict[int, int]:
        with self._connect() as db:
            return {int(k): int(v) for k, v in db.execute("SELECT object_id, keyframes FROM observations")}

    def gaussian_index(self) -> GaussianIndex | None:
        with self._connect() as db:
            row = db.execute(
                "SELECT snapshot, map_version, keyframes, n_gaussians, ids, positions, position_bytes"
                " FROM gaussian_index WHERE slot = 0"
            ).fetchone()
        if row is None:
            return None
        snapshot, map_version, keyframes, n, ids_blob, pos_blob, size = row
        if size not in _POSITION_DTYPES:
            raise ObjectDatabaseError(f"{self.path}: gaussian_index has position size {size}")
        ids = np.frombuffer(ids_blob, _U32)
        positions = np.frombuffer(pos_blob, _POSITION_DTYPES[size])
        if positions.size != n or (positions.size and int(positions.max()) >= ids.size):
            raise ObjectDatabaseError(f"{self.path}: gaussian_index is inconsistent ({positions.size} of {n} entries)")
        return GaussianIndex(ids[positions].astype(np.uint32), snapshot, map_version, keyframes)

    def integrity_check(self) -> str:
        with self._connect() as db:
            return str(db.execute("PRAGMA integrity_check").fetchone()[0])


def _object_row(r: ObjectRecord, model: str, dim: int) -> tuple:
    red, green, blue = r.rgb
    return (
        r.id,
        red,
        green,
        blue,
        r.label,
        r.label_source,
        r.description,
        r.color_name,
        *(float(v) for v in r.centroid),
        *(float(v) for v in r.bbox_min),
        *(float(v) for v in r.bbox_max),
        *(float(v) for v in r.extent),
        *(float(v) for v in r.upright_extent),
        float(r.height_above_floor),
        int(r.num_gaussians),
        int(r.num_observations),
        int(r.num_views),
        np.asarray(r.embedding, _F32).tobytes(),
        np.asarray(r.image_embedding, _F32).tobytes(),
        model,
        dim or int(np.asarray(r.embedding).size),
        float(r.updated_unix),
        float(r.label_confidence),
    )


def _record(row: sqlite3.Row) -> ObjectRecord:
    return ObjectRecord(
        id=int(row["id"]),
        label=row["label"],
        label_source=stored_source(row["label_source"]),
        description=row["description"],
        color_name=row["color_name"],
        centroid=np.array([row["cx"], row["cy"], row["cz"]], np.float64),
        bbox_min=np.array([row["min_x"], row["min_y"], row["min_z"]], np.float64),
        bbox_max=np.array([row["max_x"], row["max_y"], row["max_z"]], np.float64),
        num_gaussians=int(row["num_gaussians"]),
        num_observations=int(row["num_observations"]),
        embedding=_vector(row["embedding"]),
        image_embedding=_vector(row["image_embedding"]),
        updated_unix=float(row["updated_unix"]),
        label_confidence=float(row["label_confidence"]) if "label_confidence" in row.keys() else 1.0,  # schema 1
        num_views=int(row["num_views"]),
        upright_extent=np.array([row["upright_w"], row["upright_d"], row["upright_h"]], np.float64),
        height_above_floor=float(row["height_above_floor"]),
    )


def _view_row(v: ObjectView, view_key: tuple | None) -> tuple:
    emb = v.embeddings.get(view_key) if view_key is not None else None
    return (
        v.object_id,
        v.stamp_ns,
        v.keyframe_index,
        v.prevalence,
        int(v.rgb.shape[1]),
        int(v.rgb.shape[0]),
        _png(cv2.cvtColor(v.rgb, cv2.COLOR_RGB2BGR)),  # viewers see true colors
        _png(v.mask.astype(np.uint8) * 255),
        None if emb is None else np.asarray(emb, _F32).tobytes(),
        None if emb is None else json.dumps(view_key),
    )


def _same_backend(stored: dict, backend: object) -> bool:
    """Whether embeddings made by the ``stored`` backend identity are valid for ``backend`` (an instance,
    or a ``lazy_backend`` factory, judged by its name and options without loading any model)."""
    if hasattr(backend, "embed_texts"):
        current = backend_identity(backend)
    elif hasattr(backend, "backend_name"):
        current = {"name": backend.backend_name, **backend.backend_options}
        current.pop("model_dir", None)
        current.pop("threads", None)
    else:
        return True  # an opaque factory: trust the caller
    return all(stored.get(k) == v for k, v in current.items())


# ---------------------------------------------------------------------- map directory helpers


def prepare_save(
    index: ObjectIndex,
    *,
    snapshot: str | None = None,
    map_version: int | None = None,
    keyframes: int | None = None,
) -> PreparedSave:
    """What ObjectDatabase.save writes, taken from the index now (cheap: the views' images are encoded by
    ObjectDatabase.write, which a live node runs beside its worker while the index goes on changing)."""
    start = time.perf_counter()
    info = index.backend_info
    model = model_name(info) if info else ""
    meta = {
        "backend": info,
        "embedding_model": model,
        "config": index.config.to_dict(),
        "floor": index.floor_height(),
        "up": [float(v) for v in index.up_vector()],
        "viewpoint": None if index.viewpoint is None else [float(v) for v in index.viewpoint.ravel()],
        "keyframes_seen": index.views.keyframes,
        "saved_unix": time.time(),
        "snapshot": snapshot,
    }
    return PreparedSave(
        objects=[_object_row(r, model, int(info["dim"]) if info else 0) for r in index.records()],
        views=index.views.all_views(),
        view_key=index.view_key(info) if info else None,
        observations=sorted(index.views.observation_counts().items()),
        object_ids=index.object_ids,
        meta=meta,
        snapshot=snapshot,
        map_version=map_version,
        keyframes=keyframes,
        seconds=time.perf_counter() - start,
    )


def save_object_index(index: ObjectIndex, location: str | os.PathLike, **kwargs) -> SaveReport:
    """Saves ``index`` into ``location`` (a map directory: its objects.db; or a .db path)."""
    return ObjectDatabase(location).save(index, **kwargs)


def load_object_index(
    location: str | os.PathLike,
    backend: object | None = None,
    config: IndexConfig | None = None,
) -> ObjectIndex:
    """An index restored from ``location``'s objects.db; queries work at once.

    ``backend``: an embedding backend (or a zero-argument factory); by default a lazily loaded backend
    like the one the database was built with. A backend whose identity differs from the stored one
    gets the views and geometry only: its first ``refresh()`` re-embeds every object.
    ``config``: overrides the stored IndexConfig.
    """
    db = ObjectDatabase(location, create=False)
    meta = db.meta()
    stored = meta.get("backend")
    if config is None:
        try:
            config = IndexConfig.from_dict(meta.get("config") or {})
        except (TypeError, ValueError) as exc:
            raise ObjectDatabaseError(f"{db.path}: stored index configuration is invalid ({exc})") from exc
    if backend is None:
        if not stored:
            backend = lazy_backend("conse")
        else:
            options = {k: stored[k] for k in ("top_k", "fit", "model_dir") if k in stored}
            if stored["name"] == "clip_onnx":
                options = {k: v for k, v in options.items() if k == "model_dir"}
            backend = lazy_backend(stored["name"], **options)
        valid = True
    else:
        valid = stored is None or _same_backend(stored, backend)
    index = ObjectIndex(backend, config)
    gaussian_index = db.gaussian_index()
    index.restore(
        db.records(),
        db.views(),
        observations=db.observations(),
        object_ids=None if gaussian_index is None else gaussian_index.object_ids,
        floor=float(meta.get("floor") or 0.0),
        up=meta.get("up"),
        viewpoint=meta.get("viewpoint"),
        backend_info=stored,
        embeddings_valid=valid,
    )
    index.views.keyframes = int(meta.get("keyframes_seen") or 0)
    return index
