"""Spatial language in queries (issue 26): the grammar, the relations, and the relational query set of
tests/data/relational_queries.json on the synthetic room and Replica office_0 with given labels."""

from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np
import pytest

from monovoc_ros.objects import spatial
from monovoc_ros.objects.spatial import SpatialQuery, Viewpoint, parse

QUERIES = json.loads((Path(__file__).parent / "data" / "relational_queries.json").read_text())


@pytest.mark.parametrize(
    ("text", "reading"),
    [
        ("the mug on the table", SpatialQuery("mug", "on", ("table",))),
        ("A book on top of the shelf?", SpatialQuery("book", "on", ("shelf",))),
        ("the chair in front of the sofa", SpatialQuery("chair", "in_front_of", ("sofa",))),
        ("the chair to the left of the table", SpatialQuery("chair", "left_of", ("table",))),
        ("the lamp between the sofa and the tv", SpatialQuery("lamp", "between", ("sofa", "tv"))),
        ("the biggest chair", SpatialQuery("chair", None, (), "biggest")),
        ("the largest chair next to the table", SpatialQuery("chair", "near", ("table",), "biggest")),
        ("the nearest chair to the sofa", SpatialQuery("chair", "near", ("sofa",))),
        ("the farthest chair from the sofa", SpatialQuery("chair", "far", ("sofa",))),
        ("what is on the table", SpatialQuery("thing", "on", ("table",))),
        ("the bin underneath the desk", SpatialQuery("bin", "under", ("desk",))),
    ],
)
def test_the_grammar_reads_relations_and_superlatives(text, reading):
    assert parse(text) == reading


@pytest.mark.parametrize("text", ["a chair", "the gray sofa", "on", "the chair on", "between the table and"])
def test_text_without_a_relation_is_a_plain_query(text):
    assert parse(text) is None


@functools.lru_cache(maxsize=1)
def office_index():
    from monovoc_ros.core.evaluation.datasets import open_sequence
    from monovoc_ros.objects.build import map_with_objects
    from tests.conftest import REPLICA_OFFICE0
    from tests.object_room import backend

    sequence = open_sequence(REPLICA_OFFICE0)
    mapper, index = map_with_objects(sequence, backend=backend())
    return index, Viewpoint(sequence.keyframe(len(sequence) - 1).cam_to_world), mapper


def room_index():
    from tests.object_room import room, room_map

    return room_map()[1], Viewpoint(room().keyframe(len(room()) - 1).cam_to_world)


def top1(index, view, queries) -> tuple[float, list[str]]:
    misses = []
    for q in queries:
        result = spatial.answer(index, q["text"], 3, view=view)
        got = result.matches[0][0].hex if result.matches else None
        if got not in q["expected"]:
            misses.append(f"{q['text']!r}: {got} ({result.message})")
    return 1.0 - len(misses) / len(queries), misses


def test_relational_queries_on_the_synthetic_room():
    index, view = room_index()
    accuracy, misses = top1(index, view, QUERIES["synthetic_room"])
    assert accuracy >= 0.9, misses


def test_relational_queries_on_replica_office0(replica_office0):
    index, view, _ = office_index()
    accuracy, misses = top1(index, view, QUERIES["replica_office0"])
    assert accuracy >= 0.9, misses


def test_the_query_set_is_large_enough_and_names_real_objects():
    from tests.object_room import room_labels

    room = {f"#{i:06x}" for i in room_labels()}
    assert len(QUERIES["synthetic_room"]) + len(QUERIES["replica_office0"]) >= 40
    assert all(set(q["expected"]) <= room for q in QUERIES["synthetic_room"])


def test_a_relation_nothing_satisfies_falls_back_to_the_whole_text():
    index, view = room_index()
    plain = index.query("the sofa on the ceiling", 3)
    answer = spatial.answer(index, "the sofa on the ceiling", 3, view=view)
    assert [r.id for r, _ in answer.matches] == [r.id for r, _ in plain.matches]
    assert "no 'sofa' satisfies it" in answer.message and "ranked by the whole text" in answer.message


def test_the_answer_says_how_it_read_the_text_and_keeps_plain_queries_as_they_were():
    index, view = room_index()
    answer = spatial.answer(index, "the book on the table", 3, view=view)
    assert "read as 'book' on 'table'" in answer.message and "1 of 3 'book' satisfy it" in answer.message
    plain = spatial.answer(index, "a sofa", 3, view=view)
    assert [r.id for r, _ in plain.matches] == [r.id for r, _ in index.query("a sofa", 3).matches]
    # By default the robot's viewpoint is the latest keyframe's camera (what the node and objects.db keep).
    default = spatial.answer(index, "the chair left of the table", 3)
    assert np.array_equal(index.viewpoint, view.cam_to_world) and "from the robot's viewpoint" in default.message
    assert default.matches[0][0].hex == "#66ff33"


def test_a_relational_answer_keeps_the_note_that_the_text_was_truncated():
    index, view = room_index()
    text = "the chair next to the sofa " * 100  # 2699 characters once its whitespace is collapsed
    answer = spatial.answer(index, text, 3, view=view)
    assert "satisfy it" in answer.message and "ranked by the whole text" not in answer.message  # by the relation
    assert answer.truncated and "query truncated from 2699 to 1000 characters" in answer.message, answer.message


def test_support_and_under_are_directional():
    cup = spatial.UprightBox(np.array([0.0, 0.0, 0.75]), np.array([0.1, 0.1, 0.85]))
    table = spatial.UprightBox(np.array([-0.5, -0.5, 0.0]), np.array([0.5, 0.5, 0.75]))
    assert spatial.relation_grade("on", cup, [table], None) > 0.9
    assert spatial.relation_grade("on", table, [cup], None) == 0
    assert spatial.relation_grade("under", table, [cup], None) > 0.9


def test_an_anchor_that_names_nothing_here_leaves_the_query_plain():
    """No object stands out as "giraffe", so the text is ranked as it always was."""
    index, view = room_index()
    text = "the lamp next to the giraffe"
    answer = spatial.answer(index, text, 3, view=view)
    assert "no object stands out as 'giraffe'" in answer.message, answer.message
    assert [r.id for r, _ in answer.matches] == [r.id for r, _ in index.query(text, 3).matches]


def test_containment_counts_as_on_only_when_held_above_the_anchors_base():
    desk = spatial.UprightBox(np.array([0.0, 0.0, 0.0]), np.array([1.2, 0.6, 0.75]))
    bin_under = spatial.UprightBox(np.array([0.2, 0.1, 0.0]), np.array([0.5, 0.4, 0.35]))
    shelf = spatial.UprightBox(np.array([0.0, 0.0, 0.0]), np.array([0.4, 1.0, 1.8]))
    book_in = spatial.UprightBox(np.array([0.05, 0.4, 0.63]), np.array([0.25, 0.45, 0.88]))
    assert spatial.relation_grade("on", bin_under, [desk], None) == 0
    assert spatial.relation_grade("under", bin_under, [desk], None) > 0.9
    assert spatial.relation_grade("on", book_in, [shelf], None) > 0.8
