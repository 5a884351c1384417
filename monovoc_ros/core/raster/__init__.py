"""The SCD rasterizer: per-Gaussian evidence sums (METHOD.md section 3) and plain rendering (section 2).

Three implementations share one definition (projection.py, constants.py) and one signature:
"numba" (the production CPU kernel), "torch" (vectorized, CPU or CUDA tensors) and "reference" (float64,
per pixel, tiny scenes only; the oracle the other two are tested against). Implementation modules are
imported on first use, so importing this package does not pull in numba or torch.
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from monovoc_ros.core.map.camera import Intrinsics
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.raster.inputs import (
    check_background,
    check_colors,
    check_labels,
    check_mask,
    check_valid,
    check_view,
)

IMPLEMENTATIONS = ("numba", "torch", "reference")
# Exponents k of the evidence weights w_ip^k. k = 1 is the paper's SCD (the exact minimizer of
# sum_p w_ip ||s - y_p||^2); larger k trusts the pixels a Gaussian dominates over those it shares with its
# neighbours, which shrinks the overlap bias at object boundaries (see README, "Choices"). Any k keeps the
# sums incremental, order independent and mergeable.
WEIGHT_POWERS = (1, 2, 3, 4)
_MODULES = {"numba": "numba_impl", "torch": "torch_impl", "reference": "reference"}

# Labels kept per Gaussian and keyframe by accumulate_votes (the rest is pooled as "other").
EVIDENCE_SLOTS = 8

__all__ = [
    "EVIDENCE_SLOTS",
    "IMPLEMENTATIONS",
    "WEIGHT_POWERS",
    "Evidence",
    "Rendering",
    "VoteEvidence",
    "accumulate",
    "accumulate_votes",
    "render",
]


@dataclass
class Evidence:
    color_sum: np.ndarray  # (N, 3) float64: sum_p w_ip^k * y_p
    weight_sum: np.ndarray  # (N,) float64: sum_p w_ip^k
    n_visible: int  # Gaussians that survived culling for this camera


@dataclass
class VoteEvidence:
    """One keyframe's votes, for the Gaussians it gave votes to (vote_tables has the exact definition)."""

    rows: np.ndarray  # (V,) int64 map index of each Gaussian with votes (ascending from the numba kernels)
    labels: np.ndarray  # (V, E) int32 keyframe label of each kept entry, -1 where unused
    weights: np.ndarray  # (V, E) float64 sum_p w_ip^k [label_p == label], heaviest first
    other: np.ndarray  # (V,) float64 votes for labels not kept
    n_visible: int  # Gaussians that survived culling for this camera (>= V: hidden ones get no votes)


@dataclass
class Rendering:
    image: np.ndarray  # (H, W, 3) float32: sum_i w_ip c_i + T_final b
    transmittance: np.ndarray  # (H, W) float32: T_final
    depth: np.ndarray  # (H, W) float32: sum_i w_ip z_i / (1 - T_final) where 1 - T_final > 1e-6, else 0


def _module(impl: str, device: str | None):
    if impl not in IMPLEMENTATIONS:
        raise ValueError(f"impl must be one of {IMPLEMENTATIONS}, got {impl!r}")
    if device is not None and impl != "torch":
        raise ValueError(f"device is only meaningful for impl='torch', got device={device!r} with impl={impl!r}")
    return importlib.import_module(f"monovoc_ros.core.raster.{_MODULES[impl]}")


def _device_kwargs(impl: str, device: str | None) -> dict:
    return {"device": device} if impl == "torch" else {}


def accumulate(
    gmap: GaussianMap,
    mask: np.ndarray,
    intrinsics: Intrinsics,
    cam_to_world: np.ndarray,
    *,
    valid: np.ndarray | None = None,
    background: Sequence[float] | None = None,
    weight_power: int = 1,
    max_depth: float = math.inf,
    impl: str = "numba",
    device: str | None = None,
) -> Evidence:
    """SCD evidence of one keyframe: per Gaussian, sum_p w_ip^k y_p and sum_p w_ip^k with y_p = C_p - T_p b
    and k = `weight_power` (1 is the paper's SCD; see WEIGHT_POWERS).

    `mask` is (H, W, 3) uint8 (color = value / 255) or float in [0, 1]; pixels where `valid` is False add
    nothing (they still occlude as usual). Gaussians deeper than `max_depth` metres in the camera take nothing
    and hide nothing. Returns float64 NumPy arrays whatever the implementation.
    """
    if isinstance(weight_power, bool) or weight_power not in WEIGHT_POWERS:
        raise ValueError(f"weight_power must be one of {WEIGHT_POWERS}, got {weight_power!r}")
    module = _module(impl, device)
    view = check_view(gmap, intrinsics, cam_to_world, max_depth)
    mask = check_mask(mask, intrinsics)
    valid = check_valid(valid, intrinsics)
    bg = check_background(background)
    color_sum, weight_sum, n_visible = module.accumulate(
        gmap, mask, view, valid, bg, int(weight_power), **_device_kwargs(impl, device)
    )
    return Evidence(color_sum, weight_sum, int(n_visible))


def accumulate_votes(
    gmap: GaussianMap,
    labels: np.ndarray,
    intrinsics: Intrinsics,
    cam_to_world: np.ndarray,
    *,
    weight_power: int = 1,
    slots: int = EVIDENCE_SLOTS,
    max_depth: float = math.inf,
    impl: str = "numba",
    device: str | None = None,
) -> VoteEvidence:
    """Vote evidence of one keyframe in one rasterization pass: per Gaussian i and label o,
    sum_p w_ip^k [label_p == o] (METHOD.md section 8). `labels` is (H, W) integer, -1 = no evidence.
    Gaussians deeper than `max_depth` metres in the camera take no votes and hide nothing."""
    if isinstance(weight_power, bool) or weight_power not in WEIGHT_POWERS:
        raise ValueError(f"weight_power must be one of {WEIGHT_POWERS}, got {weight_power!r}")
    if int(slots) < 1:
        raise ValueError(f"slots must be >= 1, got {slots}")
    module = _module(impl, device)
    view = check_view(gmap, intrinsics, cam_to_world, max_depth)
    labels = check_labels(labels, intrinsics)
    rows, top_labels, top_weights, other, n_visible = module.accumulate_votes(
        gmap, labels, view, int(weight_power), int(slots), **_device_kwargs(impl, device)
    )
    # Only the Gaussians with votes go on: in a building most of a view's frustum is hidden behind walls (office_0
    # tiled to 1M: 850k Gaussians in view, 120k with any weight), and every later step is linear in the rows.
    voted = np.flatnonzero((top_weights[:, 0] > 0) | (other > 0)) if len(rows) else rows
    if len(voted) < len(rows):
        rows, top_labels, top_weights, other = rows[voted], top_labels[voted], top_weights[voted], other[voted]
    return VoteEvidence(rows, top_labels, top_weights, other, int(n_visible))


def render(
    gmap: GaussianMap,
    colors: np.ndarray,
    intrinsics: Intrinsics,
    cam_to_world: np.ndarray,
    *,
    background: Sequence[float] | None = None,
    impl: str = "numba",
    device: str | None = None,
) -> Rendering:
    """Forward rendering of per-Gaussian `colors` (N, 3) with the same weights as `accumulate`."""
    module = _module(impl, device)
    view = check_view(gmap, intrinsics, cam_to_world)
    colors = check_colors(colors, len(gmap))
    bg = check_background(background)
    image, trans, depth = module.render(gmap, colors, view, bg, **_device_kwargs(impl, device))
    return Rendering(
        np.asarray(image, dtype=np.float32), np.asarray(trans, dtype=np.float32), np.asarray(depth, dtype=np.float32)
    )
