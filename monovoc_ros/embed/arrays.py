"""Input checks and normalisation shared by the backends (no onnxruntime import: cheap for callers)."""

from __future__ import annotations

import numpy as np


def l2_normalize(x: np.ndarray, axis: int = -1) -> np.ndarray:
    """Unit-norm rows in float32; an all-zero row stays zero rather than becoming NaN."""
    x = np.asarray(x, dtype=np.float32)
    norm = np.linalg.norm(x, axis=axis, keepdims=True)
    return (x / np.maximum(norm, 1e-12)).astype(np.float32, copy=False)


def check_rgb_crops(crops) -> list[np.ndarray]:
    """Validate a sequence of RGB uint8 (H, W, 3) images; raise ``ValueError`` naming the bad one."""
    if isinstance(crops, np.ndarray) and crops.ndim == 3:
        raise ValueError("embed_images takes a sequence of (H, W, 3) images, got a single array; wrap it in a list")
    checked = []
    for i, crop in enumerate(crops):
        crop = np.asarray(crop)
        if crop.ndim != 3 or crop.shape[2] != 3 or crop.shape[0] < 1 or crop.shape[1] < 1:
            raise ValueError(f"crop {i}: expected an RGB image of shape (H, W, 3), got {crop.shape}")
        if crop.dtype != np.uint8:
            raise ValueError(f"crop {i}: expected dtype uint8, got {crop.dtype}")
        checked.append(crop)
    return checked


def check_texts(texts) -> list[str]:
    if isinstance(texts, str):
        raise ValueError("embed_texts takes a sequence of strings, got a single str; wrap it in a list")
    checked = []
    for i, text in enumerate(texts):
        if not isinstance(text, str):
            raise ValueError(f"text {i}: expected str, got {type(text).__name__}")
        checked.append(text)
    return checked
