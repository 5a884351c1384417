"""Shared by the test_objects_* and test_query* files (no tests here): the embedding backend, a small
synthetic room mapped and indexed once per session, and a saved map directory of it."""

from __future__ import annotations

import atexit
import functools
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np

from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.camera import Intrinsics
from monovoc_ros.core.map_store import save_snapshot
from monovoc_ros.synthetic import SceneConfig, SyntheticScene, generate_scene

# 40k Gaussians, 20 keyframes at 462x258: ~10 s to generate, map and index, and every class query of
# config/queries/synthetic_room.json still has views of its object.
ROOM = {"n_gaussians": 40_000, "n_keyframes": 20}
ROOM_SIZE = (462, 258)
SYNTHETIC_QUERIES = Path(__file__).resolve().parents[1] / "config" / "queries" / "synthetic_room.json"
REPLICA_QUERIES = Path(__file__).resolve().parents[1] / "config" / "queries" / "replica_office0.json"


@functools.lru_cache(maxsize=1)
def backend():
    """The default conse backend (missing models fail the tests that need it, with the export hint)."""
    from monovoc_ros.embed import load_backend

    return load_backend("conse")


class CountingBackend:
    """The real backend, counting what goes through it (to check that refreshes embed only what changed)."""

    def __init__(self, inner) -> None:
        self.inner = inner
        self.name, self.dim = inner.name, inner.dim
        self.top_k, self.fit = inner.top_k, inner.fit
        self.class_names, self.class_embeddings = inner.class_names, inner.class_embeddings
        self.images = 0
        self.texts = 0

    def embed_images(self, crops):
        self.images += len(crops)
        return self.inner.embed_images(crops)

    def embed_texts(self, texts):
        self.texts += len(texts)
        return self.inner.embed_texts(texts)


@functools.lru_cache(maxsize=1)
def room() -> SyntheticScene:
    return generate_scene(SceneConfig.at_resolution(*ROOM_SIZE, **ROOM))


def room_labels() -> dict[int, str]:
    from monovoc_ros.core.evidence.palette import labels_from_entries

    return labels_from_entries(room().labels())


def room_id(class_name: str, nth: int = 0) -> int:
    """The object id (packed palette color) of the nth object of a class in the room."""
    matches = [o for o in room().objects if o.class_name == class_name]
    r, g, b = (int(c) for c in matches[nth].palette_rgb)
    return (r << 16) | (g << 8) | b


@functools.lru_cache(maxsize=1)
def room_map():
    """(mapper, index) of the room, views offered after each keyframe as the live node does, with labels."""
    from monovoc_ros.objects.build import map_with_objects

    return map_with_objects(room(), backend=backend())


@functools.lru_cache(maxsize=1)
def room_directory() -> Path:
    """A saved map directory of the room: snapshot, objects.db and labels.json (read-only for tests)."""
    from monovoc_ros.objects.database import save_object_index

    mapper, index = room_map()
    directory = Path(tempfile.mkdtemp(prefix="monovoc-room-"))
    atexit.register(shutil.rmtree, directory, True)
    info = save_snapshot(mapper, directory, export_cloud=False)
    save_object_index(index, directory, snapshot=info.path.name, keyframes=mapper.n_keyframes)
    (directory / "labels.json").write_text(json.dumps(room().labels()))
    return directory


def copy_directory(source: Path, target: Path) -> Path:
    shutil.copytree(source, target)
    return target


def make_keyframe(index: int, mask: np.ndarray, rgb: np.ndarray | None, stamp_ns: int | None = None) -> Keyframe:
    """A keyframe with an identity pose and a plain pinhole camera for the mask's size."""
    h, w = mask.shape[:2]
    intrinsics = Intrinsics(float(w), float(w), (w - 1) / 2, (h - 1) / 2, w, h)
    stamp = index * 100_000_000 if stamp_ns is None else stamp_ns
    return Keyframe(index, stamp, np.eye(4), intrinsics, mask, rgb)
