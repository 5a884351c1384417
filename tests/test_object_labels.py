"""One label per object (core.segments.object_labels): the precedence and display rules, and the object index and
objects.db following them (given, segments and guessed labels, a round trip, databases of before)."""

from __future__ import annotations

import sqlite3

import pytest

from monovoc_ros.core.segments.object_labels import (
    GIVEN,
    GUESS,
    SEGMENTS,
    ObjectLabel,
    display,
    label_fields,
    resolve,
)
from monovoc_ros.embed.attributes import best_class_name
from monovoc_ros.objects.database import DB_NAME, load_object_index, save_object_index
from monovoc_ros.objects.index import IndexConfig, ObjectIndex
from tests.object_room import backend, room, room_labels, room_map


def test_given_beats_segments_beats_known_labels():
    given = {1: "sofa", 2: "", 5: "lamp"}
    segments = {1: "couch", 2: "chair", 3: "table"}
    known = {1: ObjectLabel("studio couch", GUESS), 3: ObjectLabel("desk", GUESS), 4: ObjectLabel("bed", GIVEN)}
    assert resolve(1, given, segments, known) == ObjectLabel("sofa", GIVEN)
    assert resolve(2, given, segments, known) == ObjectLabel("chair", SEGMENTS)  # an unnamed color names nothing
    assert resolve(3, given, segments, known) == ObjectLabel("table", SEGMENTS)  # the segmenter over a guess
    assert resolve(4, given, segments, known) == ObjectLabel("bed", GIVEN)  # a restored name keeps its source
    assert resolve(5, given, segments) == ObjectLabel("lamp", GIVEN)
    assert resolve(6, given, segments, known) is None
    assert [resolve(o, given, segments, known) for o in (6, 1, 4)] == [None, ObjectLabel("sofa", GIVEN), known[4]]


def test_a_guess_is_marked_and_an_unlabelled_object_has_empty_fields():
    assert ObjectLabel("couch", GUESS).display() == "couch?" and display(ObjectLabel("couch", GUESS)) == "couch?"
    assert ObjectLabel("sofa", GIVEN).display() == "sofa" and ObjectLabel("sofa", SEGMENTS).display() == "sofa"
    assert display(None) == "" and label_fields(None) == ("", "")
    assert label_fields(ObjectLabel("couch", GUESS)) == ("couch", "guess")
    with pytest.raises(ValueError, match="source"):
        ObjectLabel("couch", "imagenet")
    with pytest.raises(ValueError, match="name"):
        ObjectLabel("", GIVEN)


def test_stored_labels_of_older_databases_read_as_guesses():
    assert ObjectLabel.stored("toilet seat", "imagenet") == ObjectLabel("toilet seat", GUESS)
    assert ObjectLabel.stored("sofa", "given") == ObjectLabel("sofa", GIVEN)
    assert ObjectLabel.stored("", "imagenet") is None


@pytest.fixture(scope="module")
def mixed_index() -> tuple[ObjectIndex, dict[int, str], dict[int, str]]:
    """The room indexed as the node does, named by a labels file (some objects), a segmenter (others)
    and otherwise by the model's guess."""
    mapper, _ = room_map()
    scene = room()
    ids = sorted(room_labels())
    given = {oid: room_labels()[oid] for oid in ids[0::3]}
    segments = {oid: f"segment {room_labels()[oid]}" for oid in ids[1::3]}
    index = ObjectIndex(backend(), IndexConfig(labels=given))
    for i in range(len(scene)):
        index.keyframe_listener(scene.keyframe(i), mapper)
    index.refresh(gaussians=mapper.gaussians, result=mapper.result(), segment_labels=segments)
    assert index.pending() == 0 and len(index) >= 20
    return index, given, segments


def test_the_index_names_objects_by_the_rule(mixed_index):
    index, given, segments = mixed_index
    sources = {GIVEN: 0, SEGMENTS: 0, GUESS: 0}
    for r in index.records():
        sources[r.label_source] += 1
        if r.id in given:
            assert (r.label, r.label_source) == (given[r.id], GIVEN)
        elif r.id in segments:
            assert (r.label, r.label_source) == (segments[r.id], SEGMENTS)
        else:
            assert (r.label, r.label_source) == (best_class_name(r.image_embedding, backend()), GUESS)
            assert "object" in r.description  # a guess does not enter the description as a name
    assert min(sources.values()) >= 5, sources
    assert index.labels() == {r.id: ObjectLabel(r.label, r.label_source) for r in index.records()}


def test_objects_db_keeps_label_and_source(mixed_index, tmp_path):
    index, _, _ = mixed_index
    mapper, _ = room_map()
    save_object_index(index, tmp_path, snapshot="snap-000001", map_version=0, keyframes=mapper.n_keyframes)
    # Restored without the labels file or segments (a restart): the same label and source for every object,
    # also after the node's next refresh, which re-derives the guesses.
    loaded = load_object_index(tmp_path, backend=backend(), config=IndexConfig())
    assert loaded.labels() == index.labels()
    loaded.refresh(gaussians=mapper.gaussians, result=mapper.result(), segment_labels={})
    assert loaded.labels() == index.labels()

    # A database of before the sources were named stored a guess as "imagenet".
    with sqlite3.connect(tmp_path / DB_NAME) as db:
        assert db.execute("UPDATE objects SET label_source = 'imagenet' WHERE label_source = 'guess'").rowcount >= 5
    old = load_object_index(tmp_path, backend=backend(), config=IndexConfig())
    assert old.labels() == index.labels()
    assert {r.label_source for r in old.records()} == {GIVEN, SEGMENTS, GUESS}
