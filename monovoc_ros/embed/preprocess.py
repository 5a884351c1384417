"""Fitting object crops of any shape to an image encoder's fixed square input."""

from __future__ import annotations

from typing import Literal

import cv2
import numpy as np

FitMode = Literal["pad", "center_crop"]
# Neutral grey used to pad: it is also what the hard/soft crops fill the background with, and it maps
# to ~0 after EfficientNet-Lite's (x - 127) / 128 scaling.
PAD_VALUE = 127


def _resize(rgb: np.ndarray, width: int, height: int) -> np.ndarray:
    # INTER_AREA averages when shrinking (no aliasing); cubic when enlarging small crops, as CLIP does.
    shrinking = width * height < rgb.shape[0] * rgb.shape[1]
    return cv2.resize(rgb, (width, height), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_CUBIC)


def fit_square(rgb: np.ndarray, size: int, mode: FitMode = "pad") -> np.ndarray:
    """Return a (size, size, 3) uint8 image.

    ``pad`` keeps the whole crop (letterboxed with grey): object crops are tight, and cutting their ends
    off loses the object. ``center_crop`` resizes the short side and crops the middle, the usual
    ImageNet/CLIP evaluation transform.
    """
    if size < 1:
        raise ValueError(f"size must be >= 1, got {size}")
    h, w = rgb.shape[:2]
    if mode == "pad":
        scale = size / max(h, w)
        nh, nw = max(1, round(h * scale)), max(1, round(w * scale))
        resized = _resize(rgb, nw, nh)
        out = np.full((size, size, 3), PAD_VALUE, dtype=np.uint8)
        top, left = (size - nh) // 2, (size - nw) // 2
        out[top : top + nh, left : left + nw] = resized
        return out
    if mode == "center_crop":
        scale = size / min(h, w)
        nh, nw = max(size, round(h * scale)), max(size, round(w * scale))
        resized = _resize(rgb, nw, nh)
        top, left = (nh - size) // 2, (nw - size) // 2
        return np.ascontiguousarray(resized[top : top + size, left : left + size])
    raise ValueError(f"unknown fit mode {mode!r}; expected 'pad' or 'center_crop'")


def to_nchw(images: list[np.ndarray], mean: np.ndarray, std: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """Stack (S, S, 3) uint8 images into a float32 (B, 3, S, S) batch computing (x * scale - mean) / std."""
    batch = np.stack(images).astype(np.float32)
    batch = (batch * np.float32(scale) - mean.astype(np.float32)) / std.astype(np.float32)
    return np.ascontiguousarray(batch.transpose(0, 3, 1, 2))
