"""A sequence seen through the segmenter: each keyframe's mask and segment names replaced by the
segmenter's on its RGB image, as ``monovoc segment`` writes them and ``--mask-ids per-frame`` maps them."""

from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from monovoc_ros.core.evaluation.datasets import SequenceError, SequenceView, instance_palette, write_plain
from monovoc_ros.core.evidence.palette import pack_rgb
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.segments.segment_labels import SegmentLabel
from monovoc_ros.segment.backend import Segmenter
from monovoc_ros.segment.segmentation import Segmentation


def colored_segments(
    segmentation: Segmentation, height: int, width: int
) -> tuple[np.ndarray, tuple[SegmentLabel, ...]]:
    """(H, W, 3) uint8 mask with a fresh color per instance (white void) at the mask's size, and the
    instances' names keyed by their colors."""
    ids = segmentation.ids
    if ids.shape != (height, width):  # the mask's resolution is the intrinsics'; the image may differ
        ids = cv2.resize(ids, (width, height), interpolation=cv2.INTER_NEAREST)
    mask = instance_palette(ids)
    colors = pack_rgb(instance_palette(np.arange(1, segmentation.count + 1)))
    present = np.zeros(segmentation.count + 1, bool)
    present[np.unique(ids)] = True
    labels = tuple(
        SegmentLabel(int(colors[k - 1]), name, min(1.0, max(0.0, score)))
        for k, name, score in segmentation.entries()
        if present[k]
    )
    return mask, labels


class SegmentedSequence(SequenceView):
    """Keyframes whose masks are the segmenter's per-frame instances; ``clean_mask`` keeps the original
    (the reference of the benchmark), ``labels()`` is empty (per-frame colors name nothing)."""

    def __init__(self, sequence, segmenter: Segmenter) -> None:
        super().__init__(sequence)
        self.segmenter = segmenter
        self.seconds: list[float] = []  # segmenter time per keyframe

    def keyframe(self, i: int) -> Keyframe:
        kf = self._seq.keyframe(i)
        if kf.rgb is None:
            raise SequenceError(f"keyframe {i} has no RGB image: the segmenter needs one")
        t0 = time.perf_counter()
        segmentation = self.segmenter.segment(kf.rgb)
        self.seconds.append(time.perf_counter() - t0)
        mask, labels = colored_segments(segmentation, *kf.mask.shape[:2])
        return replace(kf, mask=mask, segments=labels)

    def __iter__(self) -> Iterator[Keyframe]:
        return (self.keyframe(i) for i in range(len(self)))

    def labels(self) -> list[dict]:
        return []


def segment_sequence(sequence, segmenter: Segmenter, out_dir: str | Path, *, overwrite: bool = False) -> dict:
    """Write ``sequence`` in the plain layout with the segmenter's masks (``masks/``) and names
    (``segments/``); returns a summary."""
    view = SegmentedSequence(sequence, segmenter)
    write_plain(view, out_dir, overwrite=overwrite)
    seconds = np.asarray(view.seconds)
    return {
        "out": str(out_dir),
        "keyframes": int(seconds.size),
        "segmenter_ms_median": round(float(np.median(seconds)) * 1e3, 1) if seconds.size else None,
    }
