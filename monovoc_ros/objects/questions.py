"""Questions about the map (issue 26), answered from the object index without an LLM: counting, what is in
a relation to something, where something is, and whether something is there.

Forms (case, articles and a trailing "?" do not matter):

* ``how many X (are there) [<relation> Y]`` -> a count;
* ``what is / what's / what are <relation> Y`` -> the objects in that relation, nearest first;
* ``where is X`` -> X's place relative to a larger object next to it and to the robot, in metres;
* ``is there / are there X [<relation> Y]`` -> yes or no, with the count.

Noun phrases resolve as in queries (objects.spatial): by label where labels name their head noun, exactly;
for objects known only by appearance (no label) a count takes those within ``COUNT_MARGIN`` of the best
embedding score, and only when the best stands out from the rest (``spatial.APPEARANCE_MIN_Z``); the answer says it
is by appearance. Calibrated on the synthetic room without labels (ConSE): appearance alone finds the right
objects poorly (margin 0.02: precision 0.18, recall 0.29), so the margin is kept small and the answer says
so. Anything else gets an answer that lists the forms understood.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from monovoc_ros.objects.labels import head_noun
from monovoc_ros.objects.records import ObjectRecord, QueryError
from monovoc_ros.objects.spatial import (
    STRUCTURE,
    Scene,
    SpatialQuery,
    Viewpoint,
    box_distance,
    default_view,
    parse,
    relation_grade,
    strip_articles,
)

COUNT_MARGIN = 0.02  # appearance-only counting: objects this close to the best embedding score
FORMS = "how many X are there, what is on / next to / ... Y, where is X, is there an X"
_RELATIONS_FOR_WHERE = ("on", "in", "under", "above", "near")


@dataclass
class Answer:
    success: bool
    answer: str  # one sentence for people
    count: int | None = None  # None when the question counts nothing
    objects: list[tuple[ObjectRecord, float]] = field(default_factory=list)  # what the answer is about


def ask(index, question: str, view: Viewpoint | None = None) -> Answer:
    """Answers `question` about `index`'s objects (objects.index.ObjectIndex); `view`: the robot's viewpoint
    (default the latest keyframe's). Raises QueryError for an empty question or missing models."""
    if not isinstance(question, str) or not question.strip():
        raise QueryError("empty question: ask e.g. 'how many chairs are there'")
    # Counted as a query's text is (whitespace runs as one space); refused, not cut: a cut question asks something
    # else (a 200 kB question held the service's handler 0.5 s).
    limit, length = index.config.max_query_chars, len(" ".join(question.split()))
    if length > limit:
        raise QueryError(f"a question of {length} characters (at most {limit}: query.max_text_chars)")
    words = re.sub(r"[?.!,]", " ", question.lower()).split()
    text = " ".join(words)
    if not index.records():
        return Answer(False, "there are no objects in the map yet")
    scene = Scene(index, default_view(index, view))
    for pattern, handler in (
        (r"^how many (.+?)(?: are there| is there| do you see| can you see)?$", _how_many),
        (r"^(?:what is|what's|what are|which objects are|which things are) (.+)$", _what_is),
        (r"^(?:where is|where's|where are) (.+)$", _where_is),
        (r"^(?:is there|are there|do you see|can you see) (.+)$", _is_there),
    ):
        match = re.match(pattern, text)
        if match:
            return handler(scene, match.group(1))
    return Answer(False, f"I cannot answer that kind of question; I understand: {FORMS}")


def _phrase_objects(scene: Scene, text: str) -> tuple[list[tuple[ObjectRecord, float]], SpatialQuery, str]:
    """The objects `text` (a noun phrase, maybe with a relation) names, with their grades; its reading; and
    how they were found."""
    text = " ".join(w for w in text.split() if w not in ("are", "is", "there"))  # "chairs are next to the table"
    if not strip_articles(text.split()):  # "where is the", "is there a": the query's "empty query" would puzzle
        raise QueryError(f"the question names no object; I understand: {FORMS}")
    query = parse(text) or SpatialQuery(strip_articles(text.split()))
    margin = 0.0 if query.superlative else COUNT_MARGIN
    heads = scene.named(query.head, margin=margin)
    how = "by label"
    if not scene.by_label(query.head):
        how = "by appearance only (no label names it)"
        if not scene.stands_out(query.head):
            heads = []  # nothing stands out from the rest: what the phrase names is not in the map
    if query.relation is None:
        return [(h, 1.0) for h in heads], query, how
    if not all(scene.stands_out(p) for p in query.anchors):
        return [], query, how
    grades, _ = scene.grades(query, heads)
    # "next to" in a question is a yes or no: within NEAR_M (a grade of 0.5), "far from" beyond it.
    least = 0.5 if query.relation in ("near", "far") else 0.0
    found = sorted(((h, g) for h, g in grades.items() if g > least), key=lambda hg: -hg[1])
    by_id = {r.id: r for r in heads}
    return [(by_id[i], g) for i, g in found], query, how


def _how_many(scene: Scene, text: str) -> Answer:
    found, query, how = _phrase_objects(scene, strip_articles(text.split()))
    noun = query.head if len(found) != 1 else _singular_phrase(query.head)
    where = f" {query.relation_text()}" if query.relation else ""
    return Answer(True, f"{len(found)} {noun}{where} ({how})", len(found), found)


def _is_there(scene: Scene, text: str) -> Answer:
    found, query, how = _phrase_objects(scene, strip_articles(text.split()))
    if not found:
        return Answer(True, f"no, I see no {query.reading()}", 0, [])
    return Answer(True, f"yes, {len(found)}: {_names(found)} ({how})", len(found), found)


def _what_is(scene: Scene, text: str) -> Answer:
    query = parse("thing " + text)
    if query is None or query.relation is None:
        return Answer(False, f"I cannot answer that kind of question; I understand: {FORMS}")
    found, _, _ = _phrase_objects(scene, "thing " + text)
    if not found:
        return Answer(True, f"nothing {query.relation_text()}", 0, [])
    return Answer(True, f"{query.relation_text()}: {_names(found)}", len(found), found)


def _where_is(scene: Scene, text: str) -> Answer:
    phrase = strip_articles(text.split())
    found, _, _ = _phrase_objects(scene, phrase)
    if not found:
        return Answer(True, f"I see no {phrase}", None, [])
    target = found[0][0]
    box = scene.boxes[target.id]
    parts = []
    landmark = _landmark(scene, target)
    if landmark is not None:
        other, relation = landmark
        gap = box_distance(box, scene.boxes[other.id])
        words = {"on": "on", "in": "in", "under": "under", "above": "above", "near": "next to"}[relation]
        away = f" ({gap:.1f} m away)" if gap > 0.05 else ""
        parts.append(f"{words} the {other.label or 'object ' + other.hex}{away}")
    if scene.view is not None:
        position, right, forward = scene.view
        offset = box.centre - position
        distance = box.distance_to(position)
        side = "to your right" if offset @ right > 0.3 else "to your left" if offset @ right < -0.3 else "ahead"
        if offset @ forward < -0.3:
            side = "behind you" if side == "ahead" else side + ", behind you"
        parts.append(f"{distance:.1f} m from you, {side}")
    name = target.label or f"object {target.hex}"
    at = f"at ({', '.join(f'{v:.2f}' for v in target.centroid)}) in the map frame"
    where = ", ".join(parts) if parts else at
    return Answer(True, f"the {name} is {where}", None, [(target, 1.0)])


def _landmark(scene: Scene, target: ObjectRecord) -> tuple[ObjectRecord, str] | None:
    """The larger object that best places `target`: one it stands on, is in, under or above, else the nearest."""
    box = scene.boxes[target.id]
    candidates = [
        r for r in scene.records
        if r.id != target.id and head_noun(r.label) not in STRUCTURE and scene.boxes[r.id].volume > box.volume
    ]  # fmt: skip
    best = None
    for relation in _RELATIONS_FOR_WHERE:
        graded = [(relation_grade(relation, box, [scene.boxes[r.id]], None), r) for r in candidates]
        graded = [(g, r) for g, r in graded if g > 0]
        if graded and relation != "near":
            return max(graded, key=lambda gr: gr[0])[1], relation
        if relation == "near" and graded:
            best = (max(graded, key=lambda gr: gr[0])[1], relation)
    return best


def _names(found: list[tuple[ObjectRecord, float]]) -> str:
    names = [r.label or f"object {r.hex}" for r, _ in found]
    return names[0] if len(names) == 1 else ", ".join(names[:-1]) + " and " + names[-1]


def _singular_phrase(phrase: str) -> str:
    words = phrase.split()
    return " ".join([*words[:-1], head_noun(words[-1])]) if words else phrase
