"""Questions about the map (issue 26): counting and "what is on" exact on the synthetic room with given labels,
"where is" in metres, "is there", unknown forms, and the offline `monovoc ask`."""

from __future__ import annotations

import collections
import json

import pytest

from monovoc_ros.cli import main as cli_main
from monovoc_ros.objects.questions import ask
from monovoc_ros.objects.records import QueryError
from tests.object_room import room, room_directory, room_map


def hexes(answer) -> set[str]:
    return {r.hex for r, _ in answer.objects}


def test_every_class_is_counted_exactly_with_given_labels():
    _, index = room_map()
    indexed = {r.id for r in index.records()}
    truth = collections.Counter(o.class_name for o in room().objects if _id(o) in indexed)
    for name, n in truth.items():
        plural = name + "s" if not name.endswith("s") else name
        answer = ask(index, f"how many {plural} are there?")
        assert answer.success and answer.count == n, (name, answer.answer)
        assert "by label" in answer.answer


def _id(o) -> int:
    r, g, b = (int(c) for c in o.palette_rgb)
    return (r << 16) | (g << 8) | b


@pytest.mark.parametrize(
    ("question", "expected"),
    [
        ("what is on the table", {"#333300", "#66ccff", "#330000"}),
        ("What's on the cabinet?", {"#cc9999"}),
        ("what is in the shelf", {"#00ffcc", "#006633"}),
        ("what is above the tv stand", {"#000033"}),
    ],
)
def test_what_is_on_lists_exactly_what_the_reference_has_there(question, expected):
    answer = ask(room_map()[1], question)
    assert answer.success and hexes(answer) == expected and answer.count == len(expected), answer.answer


def test_counts_with_relations_and_is_there():
    _, index = room_map()
    assert ask(index, "how many books are on the table").count == 1
    assert ask(index, "how many chairs are next to the table").count == 2
    yes = ask(index, "is there a plant?")
    assert yes.success and yes.count == 1 and yes.answer.startswith("yes") and hexes(yes) == {"#ff0000"}
    no = ask(index, "is there a cup on the sofa")
    assert no.success and no.count == 0 and no.answer.startswith("no")
    giraffe = ask(index, "is there a giraffe")  # by appearance, nothing stands out
    assert giraffe.count == 0 and giraffe.answer.startswith("no")


def test_where_is_places_an_object_by_a_larger_one_and_by_the_robot():
    answer = ask(room_map()[1], "where is the cup")
    assert answer.success and answer.count is None and hexes(answer) == {"#330000"}
    assert answer.answer.startswith("the cup is on the table") and "m from you" in answer.answer


def test_unknown_questions_say_what_is_understood():
    _, index = room_map()
    answer = ask(index, "why is the sky blue")
    assert not answer.success and "I understand: how many" in answer.answer and answer.count is None
    with pytest.raises(QueryError, match="empty question"):
        ask(index, "  ")
    for question in ("where is the", "is there a", "how many are there?"):
        with pytest.raises(QueryError, match="the question names no object; I understand: how many"):
            ask(index, question)
    limit = index.config.max_query_chars
    assert ask(index, "how many chairs are there" + " " * (5 * limit) + "?").success  # a run of spaces counts one
    with pytest.raises(QueryError, match=f"a question of {limit + 1} characters \\(at most {limit}"):
        ask(index, "how many " + "x" * (limit - 15) + " chairs")


def test_offline_monovoc_ask(capsys):
    assert cli_main(["ask", "--map", str(room_directory()), "how many chairs are there", "--json"]) == 0
    answer = json.loads(capsys.readouterr().out)
    assert answer["success"] and answer["count"] == 2 and len(answer["objects"]) == 2
    assert {o["label"] for o in answer["objects"]} == {"chair"} and "centroid" in answer["objects"][0]
    assert cli_main(["ask", "--map", str(room_directory()), "where is the sofa", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["count"] is None
    assert cli_main(["ask", "--map", str(room_directory()), "tell me a joke"]) == 1
    assert "I cannot answer" in capsys.readouterr().out


def test_next_to_in_a_question_means_within_a_metre_and_the_sentence_reads_well():
    _, index = room_map()
    near = ask(index, "what is next to the vase")
    assert near.success and "#ff0066" in hexes(near) and "#cc99ff" not in hexes(near)  # the cabinet, not the sofa
    books = ask(index, "how many red books are on the table")
    assert books.answer.startswith("1 red book on 'table'"), books.answer
