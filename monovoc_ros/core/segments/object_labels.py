"""One label per object, and where it came from: the rule every output follows (no ROS import).

Sources, strongest first:

* ``given``: ``labels_file`` (labels.json) names the object's color;
* ``segments``: the leading class a segmenter gave the object's segments (core.segments.segment_labels);
* a name restored from objects.db (it was ``given`` or ``segments`` when the database was written, so a
  restart without the labels file keeps it, with its source);
* ``guess``: the embedding model's best class for the object's image embedding (ImageNet for conse),
  known only once the object is embedded.

The objects topic, its markers, the query answers and objects.db all apply ``resolve`` to the same
inputs, so they name an object alike. A guess is never shown as a name: ``display`` marks it
("couch?") and ``SemanticObject.label_source`` says "guess".
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

GIVEN = "given"
SEGMENTS = "segments"
GUESS = "guess"
SOURCES = (GIVEN, SEGMENTS, GUESS)
# objects.db written before the sources were named: the model's guess was stored as "imagenet"
# (and segment labels as "given": they cannot be told apart and stay "given").
_LEGACY_SOURCES = {"imagenet": GUESS}
GUESS_MARK = "?"


@dataclass(frozen=True)
class ObjectLabel:
    name: str
    source: str  # one of SOURCES
    # How sure the source is of the name: for ``segments`` the share of the object's class evidence that names
    # it (a segmenter that called it a chair in half its detections: 0.5); 1 for ``given``; unused for guesses.
    # Not part of equality: a label is the same name from the same source (outputs republish on a change).
    confidence: float = field(default=1.0, compare=False)

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise ValueError(f"label source must be one of {SOURCES}, got {self.source!r}")
        if not self.name:
            raise ValueError("an object label needs a name (no label: None)")
        if not 0.0 <= self.confidence <= 1.0:
            raise ValueError(f"label confidence must be in [0, 1], got {self.confidence!r}")

    @property
    def is_guess(self) -> bool:
        return self.source == GUESS

    def display(self) -> str:
        """The text for people (RViz markers, tables): a guess carries a question mark."""
        return f"{self.name}{GUESS_MARK}" if self.is_guess else self.name

    @classmethod
    def stored(cls, name: str, source: str, confidence: float = 1.0) -> ObjectLabel | None:
        """A label read back from storage (objects.db, a message): legacy sources mapped, "" -> None."""
        if not name:
            return None
        return cls(name, stored_source(source), float(min(1.0, max(0.0, confidence))))


def stored_source(source: str) -> str:
    """A label source as written by any version (objects.db of before the sources were named)."""
    return _LEGACY_SOURCES.get(source, source)


def label_fields(label: ObjectLabel | None) -> tuple[str, str]:
    """(name, source) for messages and databases; ("", "") for an unlabelled object."""
    return ("", "") if label is None else (label.name, label.source)


def display(label: ObjectLabel | None) -> str:
    """``ObjectLabel.display``, "" for an unlabelled object."""
    return "" if label is None else label.display()


def resolve(
    object_id: int,
    given: Mapping[int, str],
    segments: Mapping[int, str],
    known: Mapping[int, ObjectLabel] | None = None,
    segment_confidence: Mapping[int, float] | None = None,
) -> ObjectLabel | None:
    """The label of one object: ``given`` (labels_file) > ``segments`` (with ``segment_confidence``, the share
    of the object's class evidence naming it; 1 when not given) > ``known`` (names restored from objects.db,
    then the model's guesses; the object index passes what it has) > None. Empty names (an unnamed
    labels.json color) name nothing."""
    name = given.get(object_id)
    if name:
        return ObjectLabel(name, GIVEN)
    name = segments.get(object_id)
    if name:
        return ObjectLabel(name, SEGMENTS, float((segment_confidence or {}).get(object_id, 1.0)))
    return (known or {}).get(object_id)
