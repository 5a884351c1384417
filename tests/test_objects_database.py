"""objects.db: exact round trip, incremental view writes, crash safety under SIGKILL, clear errors, memory."""

import json
import os
import signal
import sqlite3
import subprocess
import textwrap

import numpy as np
import pytest

from monovoc_ros.objects.database import (
    DB_NAME,
    ObjectDatabase,
    ObjectDatabaseError,
    encode_positions,
    load_object_index,
    save_object_index,
)
from monovoc_ros.objects.index import IndexConfig, ObjectIndex
from monovoc_ros.objects.memory import TARGET_SEMANTIC_BYTES, measure_memory, semantic_memory
from monovoc_ros.ros_harness import wait_until
from tests.object_room import backend, room_labels, room_map
from tests.rosutil import REPO, VENV_PYTHON


def test_round_trip_is_exact(tmp_path):
    mapper, index = room_map()
    report = save_object_index(index, tmp_path, snapshot="snap-000001", map_version=0, keyframes=mapper.n_keyframes)
    assert report.objects == len(index) and report.views_written == len(index.views.all_views())
    assert report.gaussians == len(mapper.gaussians)
    loaded = load_object_index(tmp_path, backend=backend())
    assert loaded.config == index.config and loaded.config.labels == room_labels()
    assert len(loaded) == len(index)
    for a, b in zip(index.records(), loaded.records(), strict=True):
        for name, value in vars(a).items():
            other = getattr(b, name)
            if isinstance(value, np.ndarray):
                assert value.dtype == other.dtype, name
                np.testing.assert_array_equal(value, other, err_msg=name)
            else:
                assert value == other, name
    saved = {v.key: v for v in index.views.all_views()}
    restored = {v.key: v for v in loaded.views.all_views()}
    assert saved.keys() == restored.keys()
    for key, view in saved.items():
        np.testing.assert_array_equal(view.rgb, restored[key].rgb)
        np.testing.assert_array_equal(view.mask, restored[key].mask)
        assert (view.prevalence, view.keyframe_index) == (restored[key].prevalence, restored[key].keyframe_index)
    np.testing.assert_array_equal(loaded.object_ids, mapper.result().object_ids)
    assert loaded.views.observation_counts() == index.views.observation_counts()
    np.testing.assert_allclose(loaded.up_vector(), index.up_vector())
    # Same answers from the loaded index, and nothing to re-embed.
    a, b = index.query("a lamp", top_k=5), loaded.query("a lamp", top_k=5)
    assert [(r.id, s) for r, s in a] == [(r.id, s) for r, s in b]
    assert loaded.pending() == 0
    meta = ObjectDatabase(tmp_path).meta()
    assert meta["backend"]["name"] == "conse" and meta["embedding_model"].startswith("conse(")
    assert meta["snapshot"] == "snap-000001"


def test_saves_write_only_new_views_and_drop_replaced_ones(tmp_path):
    mapper, index = room_map()
    first = save_object_index(index, tmp_path)
    again = save_object_index(index, tmp_path)
    assert first.views_written > 0 and (again.views_written, again.views_deleted) == (0, 0)
    # Another index with one view fewer per object: the DB follows it.
    smaller = ObjectIndex(backend(), IndexConfig(views_per_object=2, labels=room_labels()))
    smaller.restore(index.records(), index.views.all_views())
    report = save_object_index(smaller, tmp_path)
    assert report.views_written == 0 and report.views_deleted == len(index.views.all_views()) - len(
        smaller.views.all_views()
    )
    assert len(ObjectDatabase(tmp_path).views()) == len(smaller.views.all_views())


def test_gaussian_index_takes_one_byte_per_gaussian_up_to_255_objects():
    ids = np.array([0xFFFFFFFF, 0x102030, 0x102030, 0xFFFFFF, 7], np.uint32)
    table, positions = encode_positions(ids)
    assert positions.dtype == np.uint8 and np.array_equal(table[positions], ids)
    many = np.arange(300, dtype=np.uint32)
    table, positions = encode_positions(many)
    assert positions.dtype == np.dtype("<u2") and np.array_equal(table[positions], many)
    rng = np.random.default_rng(0)
    for ids in (rng.choice(np.array([0, 5, 0xFFFFFF, 0xFFFFFFFF, 2**31], np.uint32), 10_000), np.zeros(0, np.uint32),
                rng.integers(0, 2**32, 70_000, dtype=np.uint32)):  # fmt: skip
        table, positions = encode_positions(ids)
        want_table, want_positions = np.unique(ids, return_inverse=True)  # its plain twin
        np.testing.assert_array_equal(table, want_table)
        np.testing.assert_array_equal(positions, want_positions)
        assert positions.dtype.itemsize == (1 if table.size <= 256 else 2 if table.size <= 65536 else 4)


WRITER = textwrap.dedent(
    """
    import sys
    import numpy as np
    from monovoc_ros.objects.database import ObjectDatabase, load_object_index
    index = load_object_index(sys.argv[1])  # the room's index: records, views, per-Gaussian ids
    big = np.tile(index.object_ids, 50)  # 2M ids per save: most of the loop's time is inside a transaction
    db = ObjectDatabase(sys.argv[2])
    for n in range(1, 10**6):
        index.object_ids = np.full_like(big, n)
        db.save(index, snapshot=f"gen-{n}", keyframes=n)
        print(f"committed {n}", flush=True)
    """
)


def test_a_writer_killed_mid_write_leaves_the_last_commit(tmp_path):
    mapper, index = room_map()
    source = tmp_path / "source"
    save_object_index(index, source)
    target = tmp_path / "target"
    out = tmp_path / "writer.out"
    with open(out, "w") as fh:
        proc = subprocess.Popen(
            [str(VENV_PYTHON), "-c", WRITER, str(source), str(target)],
            cwd=REPO,
            stdout=fh,
            stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONPATH": str(REPO)},
        )
    try:
        wait_until(lambda: out.read_text().count("committed") >= 3, 60.0, "three committed saves")
    finally:
        proc.send_signal(signal.SIGKILL)  # anywhere in the loop: most of its time is inside a save
        proc.wait(10)
    last = max(int(line.split()[1]) for line in out.read_text().splitlines() if line.startswith("committed"))
    db = ObjectDatabase(target, create=False)
    assert db.integrity_check() == "ok"
    gaussians = db.gaussian_index()
    n = gaussians.keyframes
    assert n in (last, last + 1)  # killed after printing, or between commit and print
    assert gaussians.snapshot == f"gen-{n}" and np.all(gaussians.object_ids == n)
    assert len(db.records()) == len(index) and len(db.views()) == len(index.views.all_views())


def test_unreadable_files_raise_a_clear_error(tmp_path):
    garbage = tmp_path / "garbage" / DB_NAME
    garbage.parent.mkdir()
    garbage.write_bytes(b"this is not a database at all" * 100)
    with pytest.raises(ObjectDatabaseError, match=r"garbage/objects.db: not a readable MonoVoc object database"):
        load_object_index(garbage.parent)
    other = tmp_path / "other.db"
    with sqlite3.connect(other) as db:
        db.execute("CREATE TABLE something (x)")
    with pytest.raises(ObjectDatabaseError, match="other tables"):
        ObjectDatabase(other)
    with pytest.raises(ObjectDatabaseError, match="no object database"):
        load_object_index(tmp_path / "missing")
    (tmp_path / "folder" / DB_NAME).mkdir(parents=True)  # a directory in its place: said so, not "missing"
    with pytest.raises(ObjectDatabaseError, match="objects.db: not a file"):
        load_object_index(tmp_path / "folder")
    # A real database cut in half (a disk full or a copy gone wrong).
    mapper, index = room_map()
    whole = tmp_path / "whole"
    save_object_index(index, whole)
    ObjectDatabase(whole).integrity_check()  # folds the WAL into the main file
    data = (whole / DB_NAME).read_bytes()
    cut = tmp_path / "cut"
    cut.mkdir()
    (cut / DB_NAME).write_bytes(data[: len(data) // 2])
    with pytest.raises(ObjectDatabaseError, match="cut/objects.db"):
        load_object_index(cut)
    # A future schema.
    with sqlite3.connect(whole / DB_NAME) as db:
        db.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'", (json.dumps(99),))
    with pytest.raises(ObjectDatabaseError, match="schema version 99"):
        load_object_index(whole)


def test_another_backend_reembeds_from_the_stored_views(tmp_path):
    mapper, index = room_map()
    save_object_index(index, tmp_path)
    meta_backend = ObjectDatabase(tmp_path).meta()["backend"]
    assert meta_backend["top_k"] == backend().top_k

    class OtherTopK:  # the same models with other ConSE options: embeddings are not comparable
        name, dim, top_k, fit = "conse", backend().dim, 3, "pad"
        class_names, class_embeddings = backend().class_names, backend().class_embeddings

        def embed_images(self, crops):
            return backend().embed_images(crops)

        def embed_texts(self, texts):
            return backend().embed_texts(texts)

    loaded = load_object_index(tmp_path, backend=OtherTopK())
    assert len(loaded) == 0 and loaded.pending() == len(index)  # geometry and views kept, no embeddings
    loaded.refresh()
    assert len(loaded) == len(index)


def test_semantic_memory_per_scene():
    report = semantic_memory(140_000, 100, 384)
    assert report.semantic_bytes < TARGET_SEMANTIC_BYTES
    assert report.object_index_bytes == 140_000 + 4 * 101  # one byte per Gaussian
    assert report.accumulator_bytes == 140_000 * 56  # 4 x (uint32 id + float64 votes) + float64 other
    assert report.to_dict()["ratio_to_paper"] < 0.05  # vs MonoVoc's 14 MB per 140k-Gaussian scene
    assert semantic_memory(140_000, 300).object_index_bytes == 2 * 140_000 + 4 * 301
    mapper, index = room_map()
    measured = measure_memory(index, mapper)
    assert measured.n_gaussians == len(mapper.gaussians) and measured.n_objects == len(index)
    assert measured.object_index_bytes == len(mapper.gaussians) + 4 * np.unique(mapper.result().object_ids).size
    assert measured.semantic_bytes < semantic_memory(len(mapper.gaussians), len(index)).semantic_bytes * 1.5
    assert measured.view_bytes > 0


def test_a_restored_index_keeps_given_labels_when_it_re_embeds(tmp_path):
    """A node resumed without the labels file keeps the names its database was written with, also
    after re-embedding (before, every object fell back to its ImageNet class a few seconds after start)."""
    from tests.object_room import CountingBackend

    mapper, index = room_map()
    save_object_index(index, tmp_path, snapshot="snap-000001", map_version=0, keyframes=mapper.n_keyframes)
    other = CountingBackend(backend())
    other.top_k += 1  # another embedding identity: the stored embeddings are invalid, all are re-embedded
    loaded = load_object_index(tmp_path, backend=other, config=IndexConfig())
    assert loaded.config.labels is None and loaded.pending() == len(index)
    loaded.refresh(mapper)
    assert other.images > 0 and loaded.pending() == 0
    names = {r.id: (r.label, r.label_source) for r in loaded.records()}
    assert names == {r.id: (r.label, "given") for r in index.records()}
