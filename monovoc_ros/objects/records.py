"""What the object index knows about one object, and what a text query returns."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from monovoc_ros.core.evidence.palette import format_object_id, unpack_rgb
from monovoc_ros.core.segments.object_labels import GUESS
from monovoc_ros.objects.labels import head_noun


class QueryError(ValueError):
    """A query that cannot be answered (empty text, bad arguments, no embedding models); the message
    says why in words a user can act on."""


@dataclass(eq=False)
class ObjectRecord:
    id: int  # packed palette color r << 16 | g << 8 | b
    # The object's one label (core.segments.object_labels): labels_file, a segmenter's class, a restored name, else
    # the embedding model's best class for its image embedding.
    label: str
    label_source: str  # "given", "segments" or "guess" (core.segments.object_labels.SOURCES)
    description: str  # attribute description, e.g. "a blue chair, 0.97 m tall"
    color_name: str  # dominant basic color term of the object's pixels in its views
    centroid: np.ndarray  # (3,) float64, map frame, metres
    bbox_min: np.ndarray  # (3,) float64
    bbox_max: np.ndarray  # (3,) float64
    num_gaussians: int
    num_observations: int  # keyframes whose mask shows the object
    embedding: np.ndarray  # (d,) float32 unit: THE language embedding of the object
    image_embedding: np.ndarray  # (d,) float32 unit: normalized mean of its views' image embeddings
    updated_unix: float = 0.0
    num_views: int = 0
    # Size in a gravity-aligned frame (two horizontal sizes, then the height) and the height of the
    # object's lowest point above the floor, metres: what the description quotes.
    upright_extent: np.ndarray = field(default_factory=lambda: np.zeros(3))
    height_above_floor: float = 0.0
    label_confidence: float = 1.0  # core.segments.object_labels.ObjectLabel.confidence

    @property
    def rgb(self) -> tuple[int, int, int]:
        r, g, b = unpack_rgb(np.array(self.id)).tolist()
        return (r, g, b)

    @property
    def hex(self) -> str:
        return format_object_id(self.id)

    @property
    def extent(self) -> np.ndarray:
        return self.bbox_max - self.bbox_min

    def labelled(self, noun: str) -> bool:
        """Whether its label (given or a segmenter's, never the model's guess) has `noun` as its head noun."""
        return bool(self.label) and self.label_source != GUESS and head_noun(self.label) == noun

    def to_dict(self) -> dict:
        """Plain JSON-able values (no embeddings)."""
        return {
            "id": self.id,
            "hex": self.hex,
            "label": self.label,
            "label_source": self.label_source,
            "label_confidence": round(float(self.label_confidence), 4),
            "description": self.description,
            "color_name": self.color_name,
            "centroid": [float(v) for v in self.centroid],
            "bbox_min": [float(v) for v in self.bbox_min],
            "bbox_max": [float(v) for v in self.bbox_max],
            "extent": [float(v) for v in self.extent],
            "num_gaussians": self.num_gaussians,
            "num_observations": self.num_observations,
            "num_views": self.num_views,
            "upright_extent": [float(v) for v in self.upright_extent],
            "height_above_floor": float(self.height_above_floor),
        }


@dataclass
class QueryResult:
    """Matches best first; iterating yields ``(record, score)`` pairs."""

    text: str  # the text actually embedded (whitespace collapsed, maybe truncated)
    matches: list[tuple[ObjectRecord, float]] = field(default_factory=list)
    message: str = ""
    n_objects: int = 0  # objects that were ranked
    truncation: str = ""  # the note on a truncated text, which every answer's message keeps ("": not truncated)

    @property
    def truncated(self) -> bool:
        return bool(self.truncation)

    @property
    def answered(self) -> bool:
        """False when there was nothing to rank (no objects yet)."""
        return self.n_objects > 0

    def __iter__(self) -> Iterator[tuple[ObjectRecord, float]]:
        return iter(self.matches)

    def __len__(self) -> int:
        return len(self.matches)

    def __getitem__(self, i: int) -> tuple[ObjectRecord, float]:
        return self.matches[i]
