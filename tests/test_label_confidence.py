"""How sure an object's label is (core.segments.object_labels.ObjectLabel.confidence): the share of its segments'
class evidence, ranking text queries that name the label (objects.index.label_match), kept in objects.db."""

from __future__ import annotations

import json
import sqlite3

import numpy as np
import pytest

from monovoc_ros.core.segments.object_labels import SEGMENTS, ObjectLabel, resolve
from monovoc_ros.core.segments.segment_labels import LabelHistogram
from monovoc_ros.objects.database import DB_NAME, SCHEMA_VERSION, load_object_index, save_object_index
from monovoc_ros.objects.index import IndexConfig, ObjectIndex
from monovoc_ros.objects.labels import head_noun
from tests.object_room import backend, room, room_map


@pytest.mark.parametrize(
    ("phrase", "head"),
    [
        ("a chair", "chair"),
        ("the dark blue chairs", "chair"),
        ("a box of tissues", "box"),
        ("the large white board on wheels", "board"),
        ("the cup next to the sink", "cup"),
        ("the chair left of the table", "chair"),
        ("the left chair", "chair"),
        ("dining table", "table"),
        ("indoor-plant", "plant"),
        ("a chair?", "chair"),
        ("the built-in shelf", "shelf"),
        ("", ""),
        ("-", ""),
    ],
)
def test_head_noun_is_the_last_word_before_any_post_modifier(phrase, head):
    assert head_noun(phrase) == head


def test_a_label_is_as_sure_as_its_share_of_the_class_evidence():
    names = LabelHistogram()
    for name, score in [("chair", 0.6), ("chair", 0.58), ("dining table", 0.33), ("bed", 0.16)]:
        names.add(7, name, score)
    names.add(9, "chair", 0.9)
    assert names.leading() == {7: "chair", 9: "chair"}
    assert names.leading_share() == pytest.approx({7: 1.18 / 1.67, 9: 1.0})
    label = resolve(7, {}, names.leading(), None, names.leading_share())
    assert label.source == SEGMENTS and label.confidence == pytest.approx(0.7066, abs=1e-4)
    assert resolve(9, {9: "armchair"}, names.leading(), None, names.leading_share()).confidence == 1.0  # given
    with pytest.raises(ValueError, match="confidence"):
        ObjectLabel("chair", SEGMENTS, 1.5)


@pytest.fixture(scope="module")
def contested():
    """The room indexed with two objects named "chair" by a segmenter: the one the embedding ranks first for
    "a chair" only half sure of it, the other one sure."""
    mapper, _ = room_map()
    scene = room()
    index = ObjectIndex(backend(), IndexConfig(label_weight=0.0))
    for i in range(len(scene)):
        index.keyframe_listener(scene.keyframe(i), mapper)
    index.refresh(gaussians=mapper.gaussians, result=mapper.result(), segment_labels={})
    ranked = [r.id for r, _ in index.query("a chair", len(index))]
    first, other = ranked[0], ranked[len(ranked) // 2]
    names = {first: "chair", other: "chair"}
    index.refresh(gaussians=mapper.gaussians, result=mapper.result(), segment_labels=names,
                  label_confidence={first: 0.5, other: 1.0})  # fmt: skip
    return index, first, other, mapper


def test_a_text_naming_the_label_ranks_the_surer_object_first(contested):
    index, first, other, _ = contested
    by_embedding = [r.id for r, _ in index.query("a chair", len(index))]
    assert by_embedding.index(first) < by_embedding.index(other)  # label_weight 0: the embedding alone
    index.config.label_weight = 0.5
    try:
        for text in ("a chair", "the chairs", "the chair next to the sofa"):
            result = index.query(text, 2)
            assert [r.id for r, _ in result] == [other, first], text
            cosine = index.record(other).embedding @ index.backend.embed_texts([text])[0]
            assert result[0][1] == pytest.approx(float(cosine), abs=1e-5)  # the score stays the cosine
            assert "2 labelled 'chair' ranked by label confidence" in result.message
        # A text that does not name the label is ranked by the embedding alone.
        plain = [r.id for r, _ in index.query("a lamp", len(index))]
        index.config.label_weight = 0.0
        assert plain == [r.id for r, _ in index.query("a lamp", len(index))]
    finally:
        index.config.label_weight = 0.0


def test_objects_db_keeps_the_confidence_and_migrates_older_databases(contested, tmp_path):
    index, first, other, mapper = contested
    save_object_index(index, tmp_path, snapshot="snap-000001", map_version=0, keyframes=mapper.n_keyframes)
    loaded = load_object_index(tmp_path, backend=backend(), config=IndexConfig())
    assert loaded.labels()[first] == ObjectLabel("chair", SEGMENTS, 0.5)
    assert loaded.labels()[other] == ObjectLabel("chair", SEGMENTS, 1.0)
    assert [r.id for r, _ in loaded.query("a chair", 2)] == [other, first]  # default label_weight 0.5

    # A database written before label_confidence (schema 1) opens, every label counted sure.
    with sqlite3.connect(tmp_path / DB_NAME) as db:
        db.execute("ALTER TABLE objects DROP COLUMN label_confidence")
        db.execute("UPDATE meta SET value = '1' WHERE key = 'schema_version'")
    old = load_object_index(tmp_path, backend=backend(), config=IndexConfig())
    assert old.labels()[first] == ObjectLabel("chair", SEGMENTS, 1.0)
    assert np.array_equal(sorted(old.labels()), sorted(index.labels()))
    with sqlite3.connect(tmp_path / DB_NAME) as db:
        version = db.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()[0]
    assert json.loads(version) == SCHEMA_VERSION == 2
