"""One image's segmentation: per-pixel instance ids numbered per frame, each with a class name and score."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Instance ids travel as mono16 masks: at most this many instances per image.
MAX_INSTANCES = 65535


@dataclass(frozen=True)
class Segmentation:
    """``ids`` (H, W) uint16: 0 is void, instance k (1..K) is named ``names[k - 1]`` with ``scores[k - 1]``.

    Ids are numbered per image by descending detection confidence, without gaps; ``scores`` are the
    confidences in the class names; they carry no identity across
    images (the mapper associates them with its objects).
    """

    ids: np.ndarray  # (H, W) uint16
    names: tuple[str, ...]
    scores: tuple[float, ...]

    def __post_init__(self) -> None:
        ids = self.ids
        if not (isinstance(ids, np.ndarray) and ids.ndim == 2 and ids.dtype == np.uint16):
            raise ValueError(f"ids must be an (H, W) uint16 array, got {getattr(ids, 'shape', None)}")
        if len(self.names) != len(self.scores):
            raise ValueError(f"{len(self.names)} names but {len(self.scores)} scores")
        if len(self.names) > MAX_INSTANCES:
            raise ValueError(f"at most {MAX_INSTANCES} instances per image, got {len(self.names)}")
        if ids.size and int(ids.max()) > len(self.names):
            raise ValueError(f"ids reach {int(ids.max())} but only {len(self.names)} instances are named")

    @property
    def count(self) -> int:
        return len(self.names)

    def entries(self) -> list[tuple[int, str, float]]:
        """(instance id, class name, score) of every instance, in id order."""
        return [
            (k + 1, name, float(score)) for k, (name, score) in enumerate(zip(self.names, self.scores, strict=True))
        ]

    def labels(self) -> tuple:
        """The instances as core SegmentLabels keyed by instance id (a mono16 mask's values)."""
        from monovoc_ros.core.segments.segment_labels import SegmentLabel

        return tuple(SegmentLabel(k, name, min(1.0, max(0.0, score))) for k, name, score in self.entries())
