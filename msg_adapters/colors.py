"""Colors as messages give them -> packed 0x00RRGGBB uint32 (the object id and RViz's ``rgb``; core.evidence.palette
unpacks them)."""

from __future__ import annotations

import numpy as np

from monovoc_ros.core.evidence.palette import pack_rgb
from msg_adapters.errors import AdapterError


def rgb_to_packed(rgb: np.ndarray, what: str = "rgb") -> np.ndarray:
    """Packed (N,) uint32 0x00RRGGBB from (N, 3) integers in [0, 255], (N, 3) float in [0, 1], or (N,) packed."""
    rgb = np.asarray(rgb)
    if rgb.ndim == 1:
        if rgb.dtype.kind not in "ui" or (rgb.size and (rgb.min() < 0 or rgb.max() > 0xFFFFFF)):
            raise AdapterError(f"{what}: packed colors must be integers in [0, 0xFFFFFF]")
        return rgb.astype(np.uint32)
    if rgb.ndim != 2 or rgb.shape[1] != 3:
        raise AdapterError(f"{what}: expected (N, 3) colors or (N,) packed colors, got shape {rgb.shape}")
    if rgb.dtype.kind in "ui":
        if rgb.size and (rgb.min() < 0 or rgb.max() > 255):
            raise AdapterError(f"{what}: integer colors must be in [0, 255]")
        c = rgb.astype(np.uint8)
    elif rgb.dtype.kind == "f":
        if not np.all(np.isfinite(rgb)) or (rgb.size and (rgb.min() < 0 or rgb.max() > 1)):
            raise AdapterError(f"{what}: float colors must be finite and in [0, 1]")
        c = np.rint(rgb * 255.0).astype(np.uint8)
    else:
        raise AdapterError(f"{what}: (N, 3) colors must be integers or floats in [0, 1], got {rgb.dtype}")
    return pack_rgb(c)
