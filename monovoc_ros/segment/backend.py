"""The segmenter interface and the factory that picks an implementation by name."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from monovoc_ros.segment.segmentation import Segmentation


class SegmenterModelError(ValueError):
    """The segmenter's model is missing, corrupt or not a layout the backend knows (one line, at start)."""


@runtime_checkable
class Segmenter(Protocol):
    """RGB uint8 (H, W, 3) image -> its instances, numbered per image."""

    name: str

    def segment(self, rgb: np.ndarray) -> Segmentation: ...


BACKENDS = ("yolo_onnx",)


def load_segmenter(name: str = "yolo_onnx", **options) -> Segmenter:
    """Create a backend.

    - ``"yolo_onnx"`` (default): a YOLO-seg ONNX model (YOLOv5/v7-seg or YOLOv8/11-seg export layout) run by
      onnxruntime; options of :class:`monovoc_ros.segment.yolo_onnx.YoloSegOnnx`.
    """
    if name == "yolo_onnx":
        from monovoc_ros.segment.yolo_onnx import YoloSegOnnx

        return YoloSegOnnx(**options)
    raise ValueError(f"unknown segmenter backend {name!r}; choose one of {', '.join(BACKENDS)}")
