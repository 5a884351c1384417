"""Spatial language in text queries (issue 26): a small deterministic grammar, no LLM, no network.

Read forms (case and a leading article do not matter; a trailing "?" or "." neither):

* ``X <relation> Y``: relations ``on`` / ``on top of``, ``above`` / ``over``, ``under`` / ``below`` / ``beneath`` /
  ``underneath``, ``in`` / ``inside``, ``next to`` / ``beside`` / ``near`` / ``close to``, ``left of`` /
  ``to the left of``, ``right of`` / ``to the right of``, ``in front of``, ``behind``; ``the closest X to Y``,
  ``the farthest X from Y``;
* ``X between A and B``;
* superlatives before the head: ``the biggest`` / ``largest`` / ``smallest`` / ``tallest`` / ``highest`` /
  ``lowest`` / ``closest`` / ``nearest`` / ``farthest`` / ``furthest`` X, alone or with a relation.

X, Y, A and B are open-vocabulary noun phrases, resolved as one object set each: the objects whose label
(given or a segmenter's, never a model's guess) names the phrase's head noun, when any does; otherwise the
objects whose embedding is within ``EMBEDDING_MARGIN`` of the best match to the phrase. Relations are
computed from each object's box in the map frame and the map's up vector: support (X's bottom within
``SUPPORT_GAP_M`` of Y's top, footprints overlapping), containment, distances between boxes (not centroids),
and for left / right / in front / behind the robot's viewpoint (the latest keyframe's camera pose, or one
given). Text that does not parse is ranked as today; a relation no object satisfies falls back to the head
phrase's ranking, saying so. Nothing here imports ROS.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from monovoc_ros.objects.labels import head_noun
from monovoc_ros.objects.records import ObjectRecord, QueryResult
from monovoc_ros.objects.upright import upright_rotation

# Relation phrases -> canonical relation; matched longest first, at the first word where one starts.
RELATION_WORDS: dict[str, str] = {
    "on top of": "on",
    "on": "on",
    "above": "above",
    "over": "above",
    "under": "under",
    "underneath": "under",
    "beneath": "under",
    "below": "under",
    "inside": "in",
    "in": "in",
    "within": "in",
    "next to": "near",
    "beside": "near",
    "near": "near",
    "close to": "near",
    "closest to": "near",
    "nearest to": "near",
    "by": "near",
    "farthest from": "far",
    "furthest from": "far",
    "to the left of": "left_of",
    "left of": "left_of",
    "to the right of": "right_of",
    "right of": "right_of",
    "in front of": "in_front_of",
    "behind": "behind",
    "between": "between",
}
SUPERLATIVE_WORDS: dict[str, str] = {
    "biggest": "biggest",
    "largest": "biggest",
    "smallest": "smallest",
    "tallest": "tallest",
    "highest": "highest",
    "lowest": "lowest",
    "closest": "closest",
    "nearest": "closest",
    "farthest": "farthest",
    "furthest": "farthest",
}
_ARTICLES = {"the", "a", "an", "some", "any"}
GENERIC_NOUNS = {"object", "thing", "item", "something", "one", "anything"}
STRUCTURE = {"floor", "wall", "ceiling"}  # not what "the biggest object" means
_QUESTION_LEADS = (("what", "is"), ("what's",), ("what", "are"), ("which", "is"), ("which", "object", "is"))
# Boxes are of Gaussian centres, which lie inside surfaces: a cup's bottom is a few cm below the table's top.
SUPPORT_GAP_M = 0.12
NEAR_M = 1.0  # box-to-box distance at which "near" has faded to half
EMBEDDING_MARGIN = 0.05  # objects this close to the best embedding score resolve a phrase together
MIN_OVERLAP = 0.3  # share of X's footprint over Y's for "on" and "under"
MIN_INSIDE = 0.6  # share of X's box inside Y's for "in"
# By appearance alone (no label), a phrase names something when its best match stands out from the other
# objects' scores by this many standard deviations (the synthetic room, ConSE: a mug 3.4, a couch 3.1, a
# television 3.7; a giraffe 2.2, an elephant 1.4, a bicycle 2.0; but a toilet 3.1: a weak witness).
APPEARANCE_MIN_Z = 2.5


@dataclass(frozen=True)
class SpatialQuery:
    head: str  # noun phrase of the object wanted
    relation: str | None = None  # a value of RELATION_WORDS, or "far" (the farthest X from Y)
    anchors: tuple[str, ...] = ()  # the reference phrase(s): one, two for "between"
    superlative: str | None = None  # a value of SUPERLATIVE_WORDS

    def reading(self) -> str:
        """How the text was read, for the answer's message."""
        head = f"the {self.superlative} {self.head!r}" if self.superlative else f"{self.head!r}"
        return f"{head} {self.relation_text()}" if self.relation else head

    def relation_text(self) -> str:
        """The relation and its anchors: "on 'table'", "between 'sofa' and 'tv'" ("" without a relation)."""
        if self.relation is None:
            return ""
        if self.relation == "between":
            return f"between {self.anchors[0]!r} and {self.anchors[1]!r}"
        return f"{self.relation.replace('_', ' ')} {self.anchors[0]!r}"


def parse(text: str) -> SpatialQuery | None:
    """The spatial reading of `text`, or None when it holds no relation or superlative (a plain query)."""
    words = re.sub(r"[?.!,]", " ", text.lower()).split()
    for lead in _QUESTION_LEADS:  # "what is on the table": the thing on the table
        if words[: len(lead)] == list(lead):
            words = ["thing", *words[len(lead) :]]
            break
    while words and words[0] in _ARTICLES:
        words = words[1:]
    superlative = None
    if words and words[0] in SUPERLATIVE_WORDS:
        superlative = SUPERLATIVE_WORDS[words[0]]
        words = words[1:]
        # "the closest chair to the sofa" is the chair nearest the sofa, "the farthest chair from it" the other.
        links = [k for k, w in enumerate(words) if k > 0 and w in ("to", "from")]
        if superlative in ("closest", "farthest") and links:
            k = links[0]
            head, anchor = strip_articles(words[:k]), strip_articles(words[k + 1 :])
            if head and anchor:
                return SpatialQuery(head, "near" if superlative == "closest" else "far", (anchor,))
    phrases = sorted(RELATION_WORDS, key=lambda p: -len(p.split()))
    for i in range(1, len(words)):
        for phrase in phrases:
            n = len(phrase.split())
            if words[i : i + n] != phrase.split():
                continue
            head, rest = strip_articles(words[:i]), words[i + n :]
            relation = RELATION_WORDS[phrase]
            if relation == "between":
                if "and" not in rest:
                    continue
                k = rest.index("and")
                first, second = strip_articles(rest[:k]), strip_articles(rest[k + 1 :])
                if head and first and second:
                    return SpatialQuery(head, relation, (first, second), superlative)
                continue
            anchor = strip_articles(rest)
            if head and anchor:
                return SpatialQuery(head, relation, (anchor,), superlative)
    if superlative and words:
        return SpatialQuery(strip_articles(words), None, (), superlative)
    return None


def strip_articles(words: Sequence[str]) -> str:
    """A noun phrase without its leading articles: ["the", "red", "cup"] -> "red cup"."""
    words = list(words)
    while words and words[0] in _ARTICLES:
        words = words[1:]
    return " ".join(words)


# ---------------------------------------------------------------------------------------------- geometry


@dataclass(frozen=True)
class UprightBox:
    """An object's box in the upright frame (objects.upright.upright_rotation: x, y horizontal, z up, metres):
    its height span from the upright geometry the descriptions quote (the floor plus its height above it,
    and its height), its footprint centred on its centroid with its two horizontal sizes."""

    lo: np.ndarray  # (3,) float64
    hi: np.ndarray  # (3,) float64

    @property
    def bottom(self) -> float:
        return float(self.lo[2])

    @property
    def top(self) -> float:
        return float(self.hi[2])

    @property
    def height(self) -> float:
        return self.top - self.bottom

    @property
    def centre(self) -> np.ndarray:
        return (self.lo + self.hi) / 2

    @property
    def volume(self) -> float:
        return float(np.prod(np.maximum(self.hi - self.lo, 0.0)))

    def distance_to(self, point: np.ndarray) -> float:
        """Euclidean distance from `point` (3,) to the box (0 inside)."""
        return float(np.linalg.norm(np.maximum(np.maximum(self.lo - point, point - self.hi), 0.0)))


def upright_box(record: ObjectRecord, rotation: np.ndarray, floor: float) -> UprightBox:
    """`record`'s box in the upright frame of `rotation` (3, 3) (rows: two horizontal directions, up)."""
    centre = rotation @ np.asarray(record.centroid, np.float64)
    half = np.asarray(record.upright_extent, np.float64)[:2] / 2
    bottom = floor + float(record.height_above_floor)
    top = bottom + float(record.upright_extent[2])
    return UprightBox(
        np.array([centre[0] - half[0], centre[1] - half[1], bottom]),
        np.array([centre[0] + half[0], centre[1] + half[1], top]),
    )


def _footprint_overlap(a: UprightBox, b: UprightBox, of_smaller: bool = False, grow: float = 0.0) -> float:
    """Share of a's footprint over b's grown by `grow` metres on every side, or of the smaller footprint (a
    footprint without area counts by its centre)."""
    if grow:
        b = UprightBox(b.lo - [grow, grow, 0.0], b.hi + [grow, grow, 0.0])
    inter = np.maximum(np.minimum(a.hi[:2], b.hi[:2]) - np.maximum(a.lo[:2], b.lo[:2]), 0.0)
    areas = [float(np.prod(np.maximum(box.hi[:2] - box.lo[:2], 0.0))) for box in (a, b)]
    area = min(areas) if of_smaller else areas[0]
    if area <= 1e-9:
        small = a if not of_smaller or areas[0] <= areas[1] else b
        other = b if small is a else a
        centre = small.centre[:2]
        return float(np.all(centre >= other.lo[:2]) and np.all(centre <= other.hi[:2]))
    return float(inter[0] * inter[1]) / area


def box_distance(a: UprightBox, b: UprightBox) -> float:
    """Euclidean gap between two boxes (0 when they touch or overlap)."""
    return float(np.linalg.norm(np.maximum(np.maximum(a.lo - b.hi, b.lo - a.hi), 0.0)))


def _inside(a: UprightBox, b: UprightBox) -> float:
    """Share of a's box inside b's (flat boxes count by their extent along the other axes)."""
    share = 1.0
    for k in range(3):
        span = a.hi[k] - a.lo[k]
        if span <= 1e-6:
            share *= float(b.lo[k] - 1e-6 <= a.lo[k] <= b.hi[k] + 1e-6)
        else:
            share *= max(min(a.hi[k], b.hi[k]) - max(a.lo[k], b.lo[k]), 0.0) / span
    return share


@dataclass(frozen=True)
class Viewpoint:
    """Where the robot looks from: a camera pose (cam_to_world, OpenCV optical: x right, z forward)."""

    cam_to_world: np.ndarray  # (4, 4) float64, map frame

    def in_frame(self, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(position, right, forward) in the upright frame of `rotation`; right and forward horizontal."""
        pose = np.asarray(self.cam_to_world, np.float64)
        position = rotation @ pose[:3, 3]
        forward = rotation @ pose[:3, 2]
        if np.linalg.norm(forward[:2]) < 1e-6:  # looking straight down or up: the camera's -y is ahead
            forward = -(rotation @ pose[:3, 1])
        forward = np.array([forward[0], forward[1], 0.0]) / np.linalg.norm(forward[:2])
        right = np.cross(forward, np.array([0.0, 0.0, 1.0]))
        return position, right, forward


def relation_grade(
    relation: str,
    x: UprightBox,
    anchors: Sequence[UprightBox],
    view: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
) -> float:
    """How well X stands in `relation` to the anchor box(es), 0 (not at all) .. 1."""
    y = anchors[0]
    if relation == "on":
        # Supported by Y's top, or held by Y (a book on a shelf board, a picture on a wall: inside Y's box).
        inside = _inside(x, y)
        # Held, not standing beside Y's base: a bin under a desk is inside the desk's box too, on the floor.
        raised = x.bottom - y.bottom > SUPPORT_GAP_M
        held = 0.9 * inside if inside >= MIN_INSIDE and x.volume <= y.volume and raised else 0.0
        gap = x.bottom - y.top
        if not (-SUPPORT_GAP_M <= gap <= SUPPORT_GAP_M and x.top > y.top):
            return held
        overlap = _footprint_overlap(x, y)
        return max(held, overlap * (1.0 - abs(gap) / (2 * SUPPORT_GAP_M)) if overlap >= MIN_OVERLAP else 0.0)
    if relation == "under":  # below Y's top, under its footprint: a bin under a desk, a cabinet under a vase
        if not x.top <= y.top - 0.02:
            return 0.0
        overlap = _footprint_overlap(x, y, of_smaller=True, grow=SUPPORT_GAP_M)
        return overlap if overlap >= MIN_OVERLAP else 0.0
    if relation == "above":  # over Y's footprint at any height: a tv over its stand, a lamp over a table
        gap = x.bottom - y.top
        if gap < -SUPPORT_GAP_M:
            return 0.0
        # Grown: a wall-mounted tv's thin footprint lies a few cm behind its stand's.
        overlap = _footprint_overlap(x, y, of_smaller=True, grow=SUPPORT_GAP_M)
        return overlap / (1.0 + max(gap, 0.0)) if overlap >= MIN_OVERLAP else 0.0
    if relation == "in":
        inside = _inside(x, y)
        return inside if inside >= MIN_INSIDE and x.volume <= y.volume else 0.0
    if relation == "near":  # graded, never 0: the nearest one is "the X next to the Y"
        return 1.0 / (1.0 + box_distance(x, y) / NEAR_M)
    if relation == "far":  # "the farthest X from the Y"
        distance = box_distance(x, y)
        return distance / (distance + NEAR_M)
    if relation == "between":
        a, b = anchors[0].centre, anchors[1].centre
        ab = b - a
        length = float(np.linalg.norm(ab))
        if length < 1e-6:
            return 0.0
        t = float((x.centre - a) @ ab) / length**2
        off = float(np.linalg.norm(x.centre - (a + t * ab)))
        limit = max(0.5, 0.3 * length)
        return (1.0 - off / limit) if 0.05 <= t <= 0.95 and off < limit else 0.0
    if relation in ("left_of", "right_of", "in_front_of", "behind"):
        if view is None:
            return 0.0
        _, right, forward = view
        d = x.centre - y.centre
        side = {"left_of": -d @ right, "right_of": d @ right, "in_front_of": -d @ forward, "behind": d @ forward}
        along = float(side[relation])
        if along <= 0.05:
            return 0.0
        return min(1.0, along / 0.5) / (1.0 + box_distance(x, y))
    raise ValueError(f"unknown relation {relation!r}")


def superlative_key(superlative: str, box: UprightBox, view: tuple[np.ndarray, np.ndarray, np.ndarray] | None) -> float:
    """A value to maximise: the biggest has the largest volume, the closest the smallest distance, ..."""
    if superlative == "biggest":
        return box.volume
    if superlative == "smallest":
        return -box.volume
    if superlative == "tallest":
        return box.height
    if superlative == "highest":
        return box.top
    if superlative == "lowest":
        return -box.bottom
    if view is None:
        return 0.0
    distance = box.distance_to(view[0])
    return -distance if superlative == "closest" else distance


# ---------------------------------------------------------------------------------------------- answers


class Scene:
    """An index's objects as the relations see them: records, boxes in the upright frame, the viewpoint in
    that frame, and noun phrases resolved to objects (each phrase ranked once)."""

    def __init__(self, index, view: Viewpoint | None) -> None:
        self.index = index
        self.records = index.records()
        rotation = upright_rotation(index.up_vector())
        self.boxes = {r.id: upright_box(r, rotation, index.floor_height()) for r in self.records}
        self.view = view.in_frame(rotation) if view is not None else None
        self._ranked: dict[str, QueryResult] = {}

    def ranked(self, phrase: str) -> QueryResult:
        """Every object of this scene ranked by embedding similarity to `phrase` (an object the index listed
        after this scene was taken is left out: the index changes while mapping)."""
        if phrase not in self._ranked:
            result = self.index.query(phrase, len(self.records))
            result.matches = [(r, s) for r, s in result.matches if r.id in self.boxes]
            self._ranked[phrase] = result
        return self._ranked[phrase]

    def stands_out(self, phrase: str) -> bool:
        """Whether `phrase` names something here: through a label, or a best embedding match standing out from
        the others' scores by APPEARANCE_MIN_Z standard deviations."""
        if self.by_label(phrase):
            return True
        scores = np.array([s for _, s in self.ranked(phrase).matches])
        spread = float(scores.std()) if len(scores) > 1 else 0.0
        return spread > 0 and (scores[0] - scores.mean()) / spread >= APPEARANCE_MIN_Z

    def named(self, phrase: str, margin: float = EMBEDDING_MARGIN) -> list[ObjectRecord]:
        """The objects a noun phrase names, best first: every object but the room's structure for a generic
        noun ("object", "thing"); by label where labels name its head noun; else the embedding's best (all
        within `margin` of the top score)."""
        ranked = self.ranked(phrase)
        noun = head_noun(phrase)
        if noun in GENERIC_NOUNS:
            return [r for r, _ in ranked.matches if head_noun(r.label) not in STRUCTURE]
        labelled = self._labelled(noun)
        if labelled:
            return [r for r, _ in ranked.matches if r.id in labelled]
        if not ranked.matches:
            return []
        best = ranked.matches[0][1]
        return [r for r, s in ranked.matches if s >= best - margin]

    def by_label(self, phrase: str) -> bool:
        """Whether `phrase` resolves through labels (or is generic) rather than by appearance."""
        noun = head_noun(phrase)
        return noun in GENERIC_NOUNS or bool(self._labelled(noun))

    def _labelled(self, noun: str) -> set[int]:
        """Ids of the objects whose label (given or a segmenter's, never a guess) has `noun` as head noun."""
        return {r.id for r in self.records if r.labelled(noun)}

    def grades(self, query: SpatialQuery, heads: Sequence[ObjectRecord]) -> tuple[dict[int, float], str]:
        """Each head's relation grade (its best over the anchors' objects), and what the anchors resolved to."""
        anchor_sets = [self.named(p) for p in query.anchors]
        grades = {}
        for h in heads:
            grades[h.id] = max(
                (
                    relation_grade(query.relation, self.boxes[h.id], [self.boxes[a.id] for a in combo], self.view)
                    for combo in _combinations(anchor_sets, exclude=h.id)
                ),
                default=0.0,
            )
        return grades, ", ".join(f"{p!r}: {len(s)}" for p, s in zip(query.anchors, anchor_sets, strict=True))


def spatial_answer(
    query: SpatialQuery, scene: Scene, top_k: int
) -> tuple[list[tuple[ObjectRecord, float]] | None, str, int]:
    """Objects best first for a parsed query, each with its score (relation grade, or the head's embedding
    score when no relation holds); a message saying how the text was read and what was found; and how many
    of the first objects answer the relation or superlative (the rest follow by embedding). None instead of
    the objects when no object satisfies the relation or an anchor names nothing here (the caller ranks the
    whole text)."""
    head_ranked = scene.ranked(query.head)
    heads = scene.named(query.head)
    embedding = {r.id: s for r, s in head_ranked.matches}
    notes = [f"read as {query.reading()}"]
    if query.relation in ("left_of", "right_of", "in_front_of", "behind") or query.superlative in (
        "closest",
        "farthest",
    ):
        notes.append("from the robot's viewpoint" if scene.view is not None else "no robot viewpoint known")
    grades: dict[int, float] = {}
    if query.relation is not None:
        unknown = [p for p in query.anchors if not scene.stands_out(p)]
        if unknown:  # "the board on wheels": no object is "wheels", so this is no relation
            notes.append(f"no object stands out as {unknown[0]!r}: ranked by the whole text")
            return None, "; ".join(notes), 0
        grades, anchors_found = scene.grades(query, heads)
        satisfied = [h for h in heads if grades[h.id] > 0]
        if not satisfied:
            notes.append(f"no {query.head!r} satisfies it ({anchors_found}): ranked by the whole text")
            return None, "; ".join(notes), 0
        notes.append(f"{len(satisfied)} of {len(heads)} {query.head!r} satisfy it ({anchors_found})")
        pool = satisfied
    else:
        pool = heads
    if query.superlative is not None:
        key = query.superlative
        ordered = sorted(
            pool, key=lambda r: (-superlative_key(key, scene.boxes[r.id], scene.view), -grades.get(r.id, 0.0))
        )
    else:
        ordered = sorted(pool, key=lambda r: (-grades.get(r.id, 0.0), -embedding.get(r.id, -1.0)))
    chosen = {r.id for r in ordered}
    rest = [r for r, _ in head_ranked.matches if r.id not in chosen]
    answer = [(r, grades.get(r.id) or embedding.get(r.id, 0.0)) for r in ordered]
    answer += [(r, embedding.get(r.id, 0.0)) for r in rest]
    return answer[: top_k or len(answer)], "; ".join(notes), len(ordered)


def default_view(index, view: Viewpoint | None) -> Viewpoint | None:
    """`view`, else the index's latest keyframe pose (the robot's viewpoint), else None."""
    if view is None and index.viewpoint is not None:
        return Viewpoint(index.viewpoint)
    return view


def answer(index, text: str, top_k: int = 0, min_score: float = -1.0, view: Viewpoint | None = None) -> QueryResult:
    """`index.query` (objects.index.ObjectIndex) with spatial language: the head object first and the reading
    in the message for relational text, today's ranking (and its errors) for everything else. `view`: the
    robot's viewpoint; default the index's latest keyframe pose."""
    plain = index.query(text, top_k, min_score)
    query = parse(plain.text)
    if query is None or not plain.matches:
        return plain
    scene = Scene(index, default_view(index, view))
    ranked, message, answers = spatial_answer(query, scene, len(scene.records))
    if ranked is None:
        return QueryResult(plain.text, plain.matches, f"{plain.message}; {message}", plain.n_objects, plain.truncation)
    # min_score is a cosine bound: it filters the objects ranked by embedding, not the relation's answers.
    kept = [(r, s) for k, (r, s) in enumerate(ranked) if k < answers or s >= min_score]
    kept = kept[: top_k or index.config.default_top_k]
    notes = [f"{len(kept)} of {len(scene.records)} objects", *([plain.truncation] if plain.truncated else []), message]
    return QueryResult(plain.text, kept, "; ".join(notes), len(scene.records), plain.truncation)


def _combinations(sets: list[list[ObjectRecord]], exclude: int) -> list[tuple[ObjectRecord, ...]]:
    if len(sets) == 1:
        return [(a,) for a in sets[0] if a.id != exclude]
    return [(a, b) for a in sets[0] for b in sets[1] if exclude not in (a.id, b.id) and a.id != b.id]
