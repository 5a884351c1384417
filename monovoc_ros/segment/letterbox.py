"""Letterboxing an image into a detector's input and mapping the detector's coordinates back."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

# YOLO's letterbox fill (gray 114), which the published weights were trained with.
PAD_VALUE = 114


@dataclass(frozen=True)
class Letterbox:
    """How an (image_h, image_w) image sits in an (input_h, input_w) network input.

    The image is resized to (resized_h, resized_w) and placed at (left, top); the rest is padding.
    Input coordinates (continuous, pixel edges at integers) map to image coordinates by
    ``x_img = (x_in - left) * image_w / resized_w`` (and the same for y).
    """

    image_h: int
    image_w: int
    input_h: int
    input_w: int
    resized_h: int
    resized_w: int
    top: int
    left: int

    @classmethod
    def fit(cls, image_h: int, image_w: int, input_h: int, input_w: int) -> Letterbox:
        """The largest aspect-preserving fit of the image into the input, centred (YOLO's rounding)."""
        if min(image_h, image_w, input_h, input_w) <= 0:
            raise ValueError(f"empty image or input: image {image_h}x{image_w}, input {input_h}x{input_w}")
        r = min(input_h / image_h, input_w / image_w)
        resized_w = max(1, min(input_w, int(round(image_w * r))))
        resized_h = max(1, min(input_h, int(round(image_h * r))))
        left = int(round((input_w - resized_w) / 2 - 0.1))
        top = int(round((input_h - resized_h) / 2 - 0.1))
        return cls(image_h, image_w, input_h, input_w, resized_h, resized_w, top, left)

    @classmethod
    def rect(cls, image_h: int, image_w: int, size: int, stride: int) -> Letterbox:
        """Long side to ``size``, each input side the smallest multiple of ``stride`` that holds the image
        (YOLO's rectangular inference: a 600x340 frame at 640 runs as 640x384, not 640x640)."""
        if min(image_h, image_w) <= 0:
            raise ValueError(f"empty image: {image_h}x{image_w}")
        r = size / max(image_h, image_w)
        # At least one stride a side: a thin strip (1x5000) would round to an empty input.
        input_h = max(stride, int(np.ceil(round(image_h * r) / stride) * stride))
        input_w = max(stride, int(np.ceil(round(image_w * r) / stride) * stride))
        return cls.fit(image_h, image_w, input_h, input_w)

    @property
    def scale_x(self) -> float:
        return self.resized_w / self.image_w

    @property
    def scale_y(self) -> float:
        return self.resized_h / self.image_h

    def apply(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 image -> (1, 3, input_h, input_w) float32 in [0, 1]."""
        if rgb.shape[:2] != (self.image_h, self.image_w):
            raise ValueError(f"image is {rgb.shape[:2]}, letterbox made for {(self.image_h, self.image_w)}")
        resized = rgb
        if (self.resized_h, self.resized_w) != (self.image_h, self.image_w):
            resized = cv2.resize(rgb, (self.resized_w, self.resized_h), interpolation=cv2.INTER_LINEAR)
        canvas = np.full((self.input_h, self.input_w, 3), PAD_VALUE, np.uint8)
        canvas[self.top : self.top + self.resized_h, self.left : self.left + self.resized_w] = resized
        return (canvas.transpose(2, 0, 1)[None].astype(np.float32)) * np.float32(1.0 / 255.0)

    def boxes_to_image(self, xyxy: np.ndarray) -> np.ndarray:
        """(n, 4) boxes in input coordinates -> (n, 4) float64 in image coordinates, clipped to the image."""
        out = np.asarray(xyxy, np.float64).copy()
        out[:, [0, 2]] = np.clip((out[:, [0, 2]] - self.left) / self.scale_x, 0.0, self.image_w)
        out[:, [1, 3]] = np.clip((out[:, [1, 3]] - self.top) / self.scale_y, 0.0, self.image_h)
        return out

    def boxes_to_input(self, xyxy: np.ndarray) -> np.ndarray:
        """(n, 4) boxes in image coordinates -> input coordinates (the inverse of ``boxes_to_image``)."""
        out = np.asarray(xyxy, np.float64).copy()
        out[:, [0, 2]] = out[:, [0, 2]] * self.scale_x + self.left
        out[:, [1, 3]] = out[:, [1, 3]] * self.scale_y + self.top
        return out
