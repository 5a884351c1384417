"""Class names from a segmenter, per segment and frame, gathered per map object.

A segmenter that names its segments (a detector with masks, an open-vocabulary segmenter) gives per
segment of one mask its color (or packed id) in that mask, a class name and a score. A keyframe
carries them as `Keyframe.segments`; dataset folders give them as ``segments/<mask stem>.json``
(``[{"color": [r, g, b], "class_name": "chair", "score": 0.9}, ...]``, or ``"id": 0xRRGGBB`` in
place of the color). The mapper adds each named segment's score to a per-object histogram under the
object the segment was integrated as (the segment's own color with global mask ids, its associated
object with per-frame ids; core.segments.association), and an object's label is its leading class. Merged
objects add their histograms.
"""

from __future__ import annotations

import json
from collections import defaultdict
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from monovoc_ros.core.evidence.palette import VOID_ID, pack_rgb


@dataclass(frozen=True)
class SegmentLabel:
    id: int  # the segment's packed color (0xRRGGBB) in its mask
    class_name: str
    score: float = 1.0

    def __post_init__(self) -> None:
        if not 0 <= int(self.id) <= 0xFFFFFF or int(self.id) == VOID_ID:
            raise ValueError(f"segment id must be a 24-bit color other than white, got {self.id!r}")
        if not str(self.class_name).strip():
            raise ValueError("segment class_name must not be empty")
        if not (np.isfinite(self.score) and 0.0 <= float(self.score) <= 1.0):
            raise ValueError(f"segment score must be in [0, 1], got {self.score!r}")


def segments_from_entries(entries: list[dict]) -> tuple[SegmentLabel, ...]:
    """Segment labels from JSON entries ({color | id, class_name, score?}); raises ValueError."""
    out = []
    for e in entries:
        if "color" in e:
            key = int(pack_rgb(np.array(e["color"], np.uint8).reshape(1, 3))[0])
        elif "id" in e:
            key = int(e["id"])
        else:
            raise ValueError(f"segment entry needs 'color' or 'id': {e!r}")
        out.append(SegmentLabel(key, str(e.get("class_name", "")), float(e.get("score", 1.0))))
    return tuple(out)


def read_segments(path: str | Path) -> tuple[SegmentLabel, ...]:
    entries = json.loads(Path(path).read_text())
    if not isinstance(entries, list):
        raise ValueError(f"{path}: expected a JSON list of segments")
    return segments_from_entries(entries)


def segments_to_entries(segments: tuple[SegmentLabel, ...], digits: int | None = None) -> list[dict]:
    """JSON entries ({id, class_name, score}) of segment labels (`segments_from_entries` reads them back);
    `digits` rounds the scores."""

    def score(s: SegmentLabel) -> float:
        return float(s.score) if digits is None else round(float(s.score), digits)

    return [{"id": int(s.id), "class_name": s.class_name, "score": score(s)} for s in segments]


def write_segments(path: str | Path, segments: tuple[SegmentLabel, ...]) -> None:
    Path(path).write_text(json.dumps(segments_to_entries(segments, digits=6)))


def leading_name(table: Mapping[str, float]) -> str:
    """The class of highest summed score in an object's non-empty table (ties: alphabetical)."""
    return min(table.items(), key=lambda kv: (-kv[1], kv[0]))[0]


class LabelHistogram:
    """Per object, the summed scores of the class names its segments were given."""

    def __init__(self) -> None:
        self.scores: dict[int, dict[str, float]] = defaultdict(dict)

    def add(self, object_id: int, class_name: str, score: float) -> None:
        table = self.scores[int(object_id)]
        table[class_name] = table.get(class_name, 0.0) + float(score)

    def add_keyframe(self, segments: tuple[SegmentLabel, ...], segment_objects: dict[int, int]) -> int:
        """Adds a keyframe's segment labels; `segment_objects` maps a segment id to its object id
        (segments without an object add nothing). Returns the labels added."""
        added = 0
        for s in segments:
            oid = segment_objects.get(s.id)
            if oid is not None and s.score > 0:
                self.add(oid, s.class_name, s.score)
                added += 1
        return added

    def merge_objects(self, keep: int, drop: int) -> None:
        for name, score in self.scores.pop(int(drop), {}).items():
            self.add(keep, name, score)

    def rename_objects(self, mapping: Mapping[int, int]) -> None:
        """Object ids renamed (old id -> new id; others stay); objects renamed onto one id add their scores."""
        scores, self.scores = self.scores, defaultdict(dict)
        for oid, table in scores.items():
            for name, score in table.items():
                self.add(mapping.get(oid, oid), name, score)

    def merged(self, other: LabelHistogram) -> LabelHistogram:
        """Both histograms' scores added (two maps of the same scene with global ids)."""
        out = LabelHistogram()
        for source in (self, other):
            for oid, table in source.scores.items():
                for name, score in table.items():
                    out.add(oid, name, score)
        return out

    def weakly_named(self, min_score: float) -> list[int]:
        """Objects whose names add up to less than ``min_score`` (objects never named are not listed)."""
        return [oid for oid, t in self.scores.items() if t and sum(t.values()) < min_score]

    def leading(self) -> dict[int, str]:
        """Object id -> its leading class."""
        return {oid: leading_name(t) for oid, t in self.scores.items() if t}

    def leading_share(self) -> dict[int, float]:
        """Object id -> the share of its summed scores that names its leading class (how unanimous its
        segments were: a table called "chair" in some frames and "dining table" in others is unsure)."""
        return {oid: max(t.values()) / sum(t.values()) for oid, t in self.scores.items() if t and sum(t.values()) > 0}

    def to_json(self) -> str:
        return json.dumps({str(k): v for k, v in sorted(self.scores.items())})

    @classmethod
    def from_json(cls, text: str) -> LabelHistogram:
        out = cls()
        for k, table in json.loads(text).items():
            out.scores[int(k)] = {str(n): float(s) for n, s in table.items()}
        return out


def palette_segments(mask: np.ndarray, names: dict[int, str], score: float = 1.0) -> tuple[SegmentLabel, ...]:
    """The segment labels a perfect segmenter would give a mask whose colors `names` names."""
    return tuple(
        SegmentLabel(int(c), names[int(c)], score) for c in np.unique(pack_rgb(mask)).tolist() if int(c) in names
    )


def relabel_segments(
    segments: tuple[SegmentLabel, ...], before: np.ndarray, after: np.ndarray
) -> tuple[SegmentLabel, ...]:
    """Segment labels of a recolored mask: each color of `after` ((H, W) packed) takes the label of the
    `before` color most of its pixels had (a renumbered, merged or split segment keeps its name)."""
    by_id = {s.id: s for s in segments}
    keys, counts = np.unique((after.astype(np.uint64) << np.uint64(32)) | before.astype(np.uint64), return_counts=True)
    best: dict[int, tuple[int, int]] = {}
    for key, c in zip(keys.tolist(), counts.tolist(), strict=True):
        a, b = key >> 32, key & 0xFFFFFFFF
        if a != VOID_ID and b in by_id and c > best.get(a, (0, -1))[0]:
            best[a] = (c, b)
    return tuple(SegmentLabel(a, by_id[b].class_name, by_id[b].score) for a, (_, b) in sorted(best.items()))
