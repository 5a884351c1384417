"""Cutting one object out of a keyframe for embedding: hard (object only) or soft (dimmed context) masks.

MonoVoc found soft masks retrieve better: the surroundings tell the image encoder what the object is
(a cushion on a sofa), while dimming them keeps the object the most salient thing in the crop.
"""

from __future__ import annotations

from typing import Literal

import cv2
import numpy as np

CropMode = Literal["soft", "hard"]
# Neutral mid grey: what a hard mask leaves, and what a soft mask blends the context toward.
GREY = 127


def resize_mask(mask: np.ndarray, height: int, width: int) -> np.ndarray:
    """Nearest-neighbour resize of a boolean mask (labels must not be interpolated)."""
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"mask must be 2-D (H, W), got shape {mask.shape}")
    mask = mask.astype(bool)
    if mask.shape == (height, width):
        return mask
    resized = cv2.resize(mask.astype(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST)
    return resized.astype(bool)


def mask_bbox(mask: np.ndarray) -> tuple[int, int, int, int]:
    """(y0, x0, y1, x1) of the mask's True pixels, end-exclusive; ``ValueError`` for an empty mask."""
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        raise ValueError("mask is empty: the object is not visible in this view")
    return int(rows[0]), int(cols[0]), int(rows[-1]) + 1, int(cols[-1]) + 1


def crop_object(
    rgb: np.ndarray,
    mask: np.ndarray,
    mode: CropMode = "soft",
    *,
    context: float = 0.15,
    dim: float = 0.35,
) -> np.ndarray:
    """Crop the object under ``mask`` from ``rgb``.

    The crop is the mask's bounding box grown on each side by ``context`` times the box's height (top,
    bottom) or width (left, right), clipped to the image. Pixels outside the mask become grey
    (``mode="hard"``) or are blended toward grey by ``dim`` (``mode="soft"``: 0 keeps them, 1 is hard).
    ``mask`` may have another resolution than ``rgb``; it is resized nearest-neighbour.
    Returns an (h, w, 3) uint8 array.
    """
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be an (H, W, 3) uint8 image, got shape {rgb.shape} dtype {rgb.dtype}")
    if mode not in ("soft", "hard"):
        raise ValueError(f"mode must be 'soft' or 'hard', got {mode!r}")
    if not (np.isfinite(context) and context >= 0):
        raise ValueError(f"context must be a fraction >= 0, got {context}")
    if not (np.isfinite(dim) and 0.0 <= dim <= 1.0):
        raise ValueError(f"dim must be in [0, 1], got {dim}")
    height, width = rgb.shape[:2]
    mask = resize_mask(mask, height, width)
    y0, x0, y1, x1 = mask_bbox(mask)
    pad_y, pad_x = round(context * (y1 - y0)), round(context * (x1 - x0))
    y0, x0 = max(0, y0 - pad_y), max(0, x0 - pad_x)
    y1, x1 = min(height, y1 + pad_y), min(width, x1 + pad_x)

    crop = rgb[y0:y1, x0:x1].copy()
    outside = ~mask[y0:y1, x0:x1]
    if mode == "hard":
        crop[outside] = GREY
    else:
        blended = crop[outside].astype(np.float32) * (1.0 - dim) + GREY * dim
        crop[outside] = np.clip(np.rint(blended), 0, 255).astype(np.uint8)
    return crop
