"""Mask pixels to object labels for vote evidence (METHOD.md section 8).

A pixel whose color is a palette color votes for that object. A pixel whose color is not a palette
color (an anti-aliased boundary blend, a lossy-compression artefact) is snapped to the nearest
palette color with the configured metric (CMC by default: the paper's quantization, applied per
pixel) unless the two nearest palette colors are too close to decide (relative margin
``(d2 - d1) / (d2 + d1)`` below `min_snap_margin`), in which case it adds no evidence. Void (pure
white) pixels add no evidence. Colors are handled once per distinct color of the mask, not per pixel.
`mask_labels` takes the palette of the mask itself (core.evidence.palette's region and thin rules).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monovoc_ros.core.evidence.palette import VOID_ID, MaskColors, Palette, PaletteBuilder, mask_colors, unpack_rgb
from monovoc_ros.core.evidence.quantize import confidence, quantize

# A thin color (no 3x3 region in the mask) is an object of that mask from this many pixels on, when it
# is no blend of its neighbours (PaletteBuilder's thin rule, applied to one mask).
MASK_THIN_MIN_PIXELS = 20


@dataclass
class PixelLabels:
    labels: np.ndarray  # (H, W) int32 index into `objects`, -1 = no evidence
    objects: np.ndarray  # (L,) uint32 object ids (packed palette colors) of the labels
    snapped_pixels: int  # pixels of non-palette colors snapped to a palette color
    ambiguous_pixels: int  # pixels of non-palette colors left without evidence


def pixel_labels(
    mask: np.ndarray,
    palette: Palette,
    metric: str = "cmc",
    min_snap_margin: float = 0.5,
    *,
    include_void: bool = False,
    colors: MaskColors | None = None,
) -> PixelLabels:
    """Labels of one (H, W, 3) uint8 mask against `palette` (see the module docstring); with
    `include_void`, void pixels get a label of their own whose object id is VOID_ID."""
    distinct = colors or mask_colors(mask)
    colors, counts = distinct.ids, distinct.counts
    index = palette.index_of(colors)  # (C,) palette index of each distinct color, -1 if not a palette color
    foreign = (index < 0) & (colors != VOID_ID)
    snapped = ambiguous = 0
    if foreign.any() and len(palette):
        q = quantize(unpack_rgb(colors[foreign]) / 255.0, palette.colors, metric=metric)
        sure = confidence(q) >= min_snap_margin
        index[np.flatnonzero(foreign)[sure]] = q.index[sure]
        snapped = int(counts[foreign][sure].sum())
        ambiguous = int(counts[foreign][~sure].sum())
    elif foreign.any():
        ambiguous = int(counts[foreign].sum())
    present = np.unique(index[index >= 0])
    compact = np.full(len(palette) + 2, -1, np.int32)  # palette index -> label; index -1 stays -1
    compact[present] = np.arange(present.size, dtype=np.int32)
    objects = palette.ids[present]
    if include_void and (colors == VOID_ID).any():
        index[colors == VOID_ID] = len(palette)
        compact[len(palette)] = present.size
        objects = np.append(objects, np.uint32(VOID_ID))
    labels = compact[index][distinct.inverse()]
    return PixelLabels(labels, objects.astype(np.uint32), snapped, ambiguous)


def mask_labels(
    mask: np.ndarray,
    metric: str = "cmc",
    min_snap_margin: float = 0.5,
    *,
    include_void: bool = False,
    palette: Palette | None = None,
) -> tuple[PixelLabels, PaletteBuilder]:
    """Labels of a mask against `palette` (the known object colors) or, when None, against the mask's
    own palette; and that mask's palette counts.

    Labels come from the mask (and the fixed palette) alone, never from the masks before it, so a
    keyframe's votes do not depend on the order of keyframes and maps of the same scene merge exactly."""
    colors = mask_colors(mask)
    own = PaletteBuilder()
    own.update(mask, colors)
    if palette is None:
        palette = own.build(thin_min_pixels=MASK_THIN_MIN_PIXELS)
    return pixel_labels(mask, palette, metric, min_snap_margin, include_void=include_void, colors=colors), own
