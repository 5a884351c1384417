"""Checks and normalizes what callers hand the rasterizer, once, before any implementation runs."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from monovoc_ros.core.map.camera import Intrinsics, invert_pose, validate_pose
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.raster.constants import NEAR_PLANE


@dataclass(frozen=True)
class View:
    """One camera: intrinsics, the world-to-camera transform (float64 4x4) and the far plane (metres of
    camera-space depth; Gaussians beyond it are culled like those before the near plane)."""

    intrinsics: Intrinsics
    world_to_cam: np.ndarray
    far: float = math.inf

    @property
    def width(self) -> int:
        return self.intrinsics.width

    @property
    def height(self) -> int:
        return self.intrinsics.height


def check_view(
    gmap: GaussianMap, intrinsics: Intrinsics, cam_to_world: np.ndarray, max_depth: float = math.inf
) -> View:
    if not isinstance(gmap, GaussianMap):
        raise ValueError(f"gmap: expected a GaussianMap, got {type(gmap).__name__}")
    if not isinstance(intrinsics, Intrinsics):
        raise ValueError(f"intrinsics: expected an Intrinsics, got {type(intrinsics).__name__}")
    pose = validate_pose(cam_to_world, what="cam_to_world")
    far = float(max_depth)
    if not far > NEAR_PLANE:  # NaN too
        raise ValueError(f"max_depth must be beyond the near plane ({NEAR_PLANE} m) or inf, got {max_depth!r}")
    return View(intrinsics, invert_pose(pose), far)


def check_mask(mask: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """The mask as a C-contiguous (H, W, 3) uint8 or float32 array (float64 is converted)."""
    mask = np.asarray(mask)
    if mask.ndim != 3 or mask.shape[2] != 3:
        raise ValueError(f"mask: expected an (H, W, 3) array, got shape {mask.shape}")
    h, w = mask.shape[:2]
    if (w, h) != (intrinsics.width, intrinsics.height):
        raise ValueError(f"mask is {w}x{h} but intrinsics are for {intrinsics.width}x{intrinsics.height}")
    if mask.dtype == np.uint8:
        return np.ascontiguousarray(mask)
    if mask.dtype not in (np.float32, np.float64):
        raise ValueError(f"mask: expected uint8 or float32 values, got dtype {mask.dtype}")
    mask = np.ascontiguousarray(mask, dtype=np.float32)
    if mask.size and not (np.isfinite(mask).all() and mask.min() >= 0.0 and mask.max() <= 1.0):
        raise ValueError("mask: float values must be finite and in [0, 1]")
    return mask


def check_labels(labels: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """The labels as a C-contiguous (H, W) int32 array (-1 = no evidence)."""
    labels = np.asarray(labels)
    if labels.ndim != 2 or labels.dtype.kind not in "iu":
        raise ValueError(f"labels: expected an (H, W) integer array, got shape {labels.shape} dtype {labels.dtype}")
    h, w = labels.shape
    if (w, h) != (intrinsics.width, intrinsics.height):
        raise ValueError(f"labels are {w}x{h} but intrinsics are for {intrinsics.width}x{intrinsics.height}")
    if labels.size and (labels.min() < -1 or labels.max() >= 1 << 24):
        raise ValueError("labels: values must be in [-1, 2^24)")
    return np.ascontiguousarray(labels, dtype=np.int32)


def check_valid(valid: np.ndarray | None, intrinsics: Intrinsics) -> np.ndarray | None:
    if valid is None:
        return None
    valid = np.asarray(valid)
    if valid.dtype != np.bool_:
        raise ValueError(f"valid: expected a bool array, got dtype {valid.dtype}")
    if valid.shape != (intrinsics.height, intrinsics.width):
        raise ValueError(
            f"valid: expected shape {(intrinsics.height, intrinsics.width)} (H, W) from the intrinsics, "
            f"got {valid.shape}"
        )
    return np.ascontiguousarray(valid)


def check_background(background: Sequence[float] | None) -> np.ndarray | None:
    """The background as 3 float32 values, or None when absent or all zeros (the fast path)."""
    if background is None:
        return None
    b = np.asarray(background, dtype=np.float64)
    if b.shape != (3,) or not np.isfinite(b).all():
        raise ValueError(f"background: expected 3 finite values, got {np.asarray(background).tolist()}")
    if not b.any():
        return None
    return b.astype(np.float32)


def check_colors(colors: np.ndarray, n: int) -> np.ndarray:
    colors = np.asarray(colors)
    if colors.shape != (n, 3):
        raise ValueError(f"colors: expected shape ({n}, 3) for a map of {n} Gaussians, got {colors.shape}")
    if not np.issubdtype(colors.dtype, np.floating):
        raise ValueError(f"colors: expected float values in [0, 1], got dtype {colors.dtype}")
    colors = np.ascontiguousarray(colors, dtype=np.float32)
    if not np.isfinite(colors).all():
        raise ValueError("colors: contains NaN or infinite values")
    return colors
