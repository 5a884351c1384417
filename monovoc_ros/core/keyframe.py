"""One keyframe as every part of monovoc_ros sees it, whatever it came from (files, bags, topics)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monovoc_ros.core.map.camera import Intrinsics


@dataclass
class Keyframe:
    index: int  # position in its sequence (0-based)
    stamp_ns: int  # acquisition time, nanoseconds
    cam_to_world: np.ndarray  # (4, 4) float64, OpenCV optical camera frame (see core.map.camera)
    intrinsics: Intrinsics  # for the mask's resolution
    mask: np.ndarray  # (H, W, 3) uint8 palette-colored segmentation; (255, 255, 255) = void
    rgb: np.ndarray | None = None  # (H', W', 3) uint8 RGB image, may differ in size from the mask
    # Class names a segmenter gave the mask's segments (core.segments.segment_labels.SegmentLabel), if any.
    segments: tuple | None = None

    def __post_init__(self) -> None:
        if self.mask.ndim != 3 or self.mask.shape[2] != 3 or self.mask.dtype != np.uint8:
            raise ValueError(f"Keyframe.mask: expected (H, W, 3) uint8, got {self.mask.shape} {self.mask.dtype}")
        h, w = self.mask.shape[:2]
        if (w, h) != (self.intrinsics.width, self.intrinsics.height):
            raise ValueError(
                f"Keyframe.mask is {w}x{h} but intrinsics are for {self.intrinsics.width}x{self.intrinsics.height}"
            )
