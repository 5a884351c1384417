"""Object palette: the distinct colors of the segmentation masks, each color one object.

Object identity *is* the mask color, packed as ``r << 16 | g << 8 | b`` (a uint32 "object id"), so ids
do not depend on the order in which colors are discovered and two maps built from the same masks agree.
Pure white (``VOID_ID``) is void (unlabeled) and never a palette color; ``UNOBSERVED_ID`` (which no
24-bit color can take) marks Gaussians without evidence. This module owns that identity: packing
(`pack_rgb`, `unpack_rgb`), ids as people write them (`format_object_id`, `parse_object_id`) and the
class names of colors in labels.json files (`read_label_entries`, `labels_from_entries`, `read_labels`).

Masks with anti-aliased or resampled edges hold blended colors that are no object. Counting pixels does
not separate them: a blend of two objects' colors sits on every pixel of their shared boundary, in every
mask that shows it, so its count grows like a small object's. Shape does: blends lie on lines one pixel
wide along boundaries, objects form regions. `PaletteBuilder.build` therefore keeps a color when

1. it forms a region somewhere: at least `min_interior` pixels (over all masks) whose full 3x3
   neighbourhood is that same color (an object a few pixels wide has these; a blend line never), or
2. it is a thin real structure: at least `thin_min_pixels` pixels of which at most
   `thin_max_blend_fraction` lie between two opposite neighbours on the RGB segment joining those
   neighbours' colors (how a blended pixel looks; a real object's color is no mix of its neighbours).

and it has at least `min_pixels` pixels in all. Measured on Replica office_0 (81 masks, nearest-
downscaled so without blends): rule 1 alone keeps 34 of its 35 labeled colors; the 35th (a wall sliver
1-2 px wide, 887 px over 19 masks, none of them a blend) is kept by rule 2, so all 35 are kept and
nothing else. The same masks resampled with bilinear (to 616x344, 0.75x, 2x) or area (0.5x)
interpolation hold 415 to 26,022 blended colors (up to 22,576 px each, more than the smallest
objects); the rule keeps none of them and loses no labeled color that still forms a region (only the
sliver, which the resampling itself blends away). Rejected colors and their pixel counts are reported
in the `Palette`.

Speed: `update` takes ~4 ms for a 600x340 mask (pack 0.6 ms, np.unique 2 ms, the numba region/blend
kernel of `core.evidence.palette_kernels` 1 ms; its plain twin is `region_counts_reference`).
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from monovoc_ros.core.evidence.palette_kernels import region_counts

VOID_RGB = (255, 255, 255)
VOID_ID = 0xFFFFFF
UNOBSERVED_ID = 0xFFFFFFFF

# A pixel c is a blend of its two opposite neighbours a, b when its projection on the line a-b falls
# strictly between them and it lies within 1.5 (8-bit units) of that line: per-channel rounding moves a
# blend by at most sqrt(3)/2. Tested exactly in integers, as (|c-a|^2 |b-a|^2 - dot^2) / |b-a|^2 <= 9/4.
_BLEND_NUM, _BLEND_DEN = 9, 4
# Opposite-neighbour directions tested for blends: horizontal, vertical and both diagonals.
_DIRECTIONS = ((0, 1), (1, 0), (1, 1), (1, -1))

_COUNT_FIELDS = ("pixels", "interior", "blend", "masks")


def pack_rgb(rgb: np.ndarray) -> np.ndarray:
    """(..., 3) uint8 colors -> (...) uint32 ids ``r << 16 | g << 8 | b``."""
    rgb = np.asarray(rgb)
    if rgb.shape[-1:] != (3,) or rgb.dtype != np.uint8:
        raise ValueError(f"pack_rgb: expected (..., 3) uint8 colors, got shape {rgb.shape} dtype {rgb.dtype}")
    rgb = rgb.astype(np.uint32)
    return (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]


def unpack_rgb(ids: np.ndarray) -> np.ndarray:
    """(...) packed ids -> (..., 3) uint8 colors. Ids above 0xFFFFFF (e.g. UNOBSERVED_ID) raise."""
    ids = np.asarray(ids)
    if ids.dtype.kind not in "iu":
        raise ValueError(f"unpack_rgb: expected integer ids, got dtype {ids.dtype}")
    if ids.size and (ids.min() < 0 or ids.max() > 0xFFFFFF):
        raise ValueError("unpack_rgb: ids must be in [0, 0xFFFFFF] (UNOBSERVED_ID has no color)")
    ids = ids.astype(np.uint32)
    return np.stack([(ids >> 16) & 0xFF, (ids >> 8) & 0xFF, ids & 0xFF], axis=-1).astype(np.uint8)


_HEX_ID = re.compile(r"^(?:#|0x)?([0-9a-fA-F]{6})$")


def format_object_id(oid: int) -> str:
    """``#rrggbb``: how ids are shown to people (logs, answers, JSON reports, marker texts)."""
    return f"#{int(oid):06x}"


def parse_object_id(value: str | int) -> int:
    """A packed palette color from ``#rrggbb``, ``0xrrggbb``, ``rrggbb`` or a decimal integer.

    Six hex digits always read as a color (``"102030"`` is 0x102030), so decimals need another length."""
    if isinstance(value, bool):
        raise ValueError(f"not an object id: {value!r}")
    if isinstance(value, int):
        oid = value
    else:
        text = str(value).strip()
        match = _HEX_ID.match(text)
        if match:
            oid = int(match.group(1), 16)
        elif text.isdigit():
            oid = int(text)
        else:
            raise ValueError(f"not an object id (expected #rrggbb, 0xrrggbb or an integer): {value!r}")
    if not 0 <= oid <= 0xFFFFFF:
        raise ValueError(f"object id {value!r} is not a 24-bit palette color")
    return oid


def read_label_entries(path: str | os.PathLike) -> list[dict]:
    """The entries of a labels.json file (Replica / plain layout: ``[{color: [r, g, b], class_name, ...}]``),
    as written (sequences keep and forward every field)."""
    path = Path(path)
    try:
        entries = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: unreadable labels file ({exc})") from None
    if not isinstance(entries, list) or not all(isinstance(d, dict) and "color" in d for d in entries):
        raise ValueError(f"{path}: expected a JSON list of {{color, class_name}} entries")
    return entries


def labels_from_entries(entries: Iterable[Mapping]) -> dict[int, str]:
    """``{object id: class name}`` of labels.json-style entries; an entry without a class name gives ""."""
    out: dict[int, str] = {}
    for n, entry in enumerate(entries):
        try:
            rgb = list(entry["color"])
            name = str(entry.get("class_name", "")).strip()
        except (KeyError, TypeError) as exc:
            raise ValueError(f"labels entry {n}: expected color [r, g, b] and class_name ({exc})") from None
        if len(rgb) != 3 or not all(isinstance(c, int) and not isinstance(c, bool) and 0 <= c <= 255 for c in rgb):
            raise ValueError(f"labels entry {n}: color {rgb!r} is not three integers 0..255")
        out[int(pack_rgb(np.array(rgb, np.uint8)))] = name
    return out


def read_labels(path: str | os.PathLike) -> dict[int, str]:
    """``{object id: class name}`` of a labels.json file."""
    entries = read_label_entries(path)
    try:
        return labels_from_entries(entries)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def _check_mask(mask: np.ndarray) -> np.ndarray:
    mask = np.asarray(mask)
    if mask.ndim != 3 or mask.shape[2] != 3 or mask.dtype != np.uint8:
        raise ValueError(f"mask: expected (H, W, 3) uint8, got shape {mask.shape} dtype {mask.dtype}")
    return mask


def region_counts_reference(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plain twin of the update kernel: sorted ids, interior and blend pixel counts per id."""
    packed = pack_rgb(_check_mask(mask))
    ids = np.unique(packed)
    inner = packed[1:-1, 1:-1]
    interior = np.bincount(np.searchsorted(ids, inner[interior_mask(packed)]), minlength=ids.size)
    blend = np.bincount(np.searchsorted(ids, inner[blend_mask(mask, packed)]), minlength=ids.size)
    return ids, interior.astype(np.int64), blend.astype(np.int64)


def color_counts(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct packed colors of one mask (sorted, void included) and their pixel counts."""
    ids, counts = np.unique(pack_rgb(_check_mask(mask)), return_counts=True)
    return ids.astype(np.uint32), counts.astype(np.int64)


def interior_mask(packed: np.ndarray) -> np.ndarray:
    """(H-2, W-2) bool for the inner pixels: True where the whole 3x3 neighbourhood has one color."""
    centre = packed[1:-1, 1:-1]
    rows = (packed[:, 1:-1] == packed[:, :-2]) & (packed[:, 1:-1] == packed[:, 2:])  # row triples
    # Three uniform row triples whose middles agree make a uniform 3x3 block.
    return rows[1:-1] & rows[:-2] & rows[2:] & (centre == packed[:-2, 1:-1]) & (centre == packed[2:, 1:-1])


def blend_mask(mask: np.ndarray, packed: np.ndarray) -> np.ndarray:
    """(H-2, W-2) bool for the inner pixels: True where the color lies strictly between the colors of
    two opposite neighbours (both different from it and from each other), within rounding."""
    h, w = packed.shape
    out = np.zeros((max(h - 2, 0), max(w - 2, 0)), bool)
    if out.size == 0:
        return out
    centre = packed[1:-1, 1:-1]
    for dy, dx in _DIRECTIONS:
        pa = packed[1 - dy : h - 1 - dy, 1 - dx : w - 1 - dx]
        pb = packed[1 + dy : h - 1 + dy, 1 + dx : w - 1 + dx]
        # Only pixels unlike both neighbours can be blends: few, so the arithmetic runs on them alone.
        ys, xs = np.nonzero((pa != centre) & (pb != centre) & (pa != pb))
        if ys.size == 0:
            continue
        a = mask[ys + 1 - dy, xs + 1 - dx].astype(np.int64)
        b = mask[ys + 1 + dy, xs + 1 + dx].astype(np.int64)
        ca, ab = mask[ys + 1, xs + 1].astype(np.int64) - a, b - a
        dot, ab2, ca2 = (ca * ab).sum(1), (ab * ab).sum(1), (ca * ca).sum(1)
        near = (dot > 0) & (dot < ab2) & (_BLEND_DEN * (ca2 * ab2 - dot * dot) <= _BLEND_NUM * ab2)
        out[ys[near], xs[near]] = True
    return out


@dataclass(frozen=True, eq=False)
class MaskColors:
    """The distinct colors of one mask."""

    packed: np.ndarray  # (H, W) uint32 packed color of every pixel
    ids: np.ndarray  # (C,) uint32 distinct packed colors, ascending
    counts: np.ndarray  # (C,) int64 pixels of each

    def inverse(self) -> np.ndarray:
        """(H, W) index into `ids` of every pixel (a search, not a second sort)."""
        return np.searchsorted(self.ids, self.packed)


def mask_colors(mask: np.ndarray) -> MaskColors:
    packed = pack_rgb(_check_mask(mask))
    ids, counts = np.unique(packed, return_counts=True)
    return MaskColors(packed, ids.astype(np.uint32), counts.astype(np.int64))


@dataclass(frozen=True, eq=False)
class Palette:
    colors: np.ndarray  # (K, 3) uint8, sorted by packed id
    ids: np.ndarray  # (K,) uint32 packed colors (the object ids), ascending
    pixel_counts: np.ndarray  # (K,) int64 pixels over all masks
    mask_counts: np.ndarray  # (K,) int64 masks showing the color
    rejected_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint32))  # (R,) uint32
    rejected_pixels: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (R,) int64
    void_pixels: int = 0  # pure white pixels seen
    n_masks: int = 0  # masks counted

    def __post_init__(self) -> None:
        ids = np.asarray(self.ids, dtype=np.uint32)
        if ids.ndim != 1 or np.any(np.diff(ids.astype(np.int64)) <= 0):
            raise ValueError("Palette.ids must be a strictly ascending 1-D array")
        if np.any(ids > 0xFFFFFF) or np.any(ids == VOID_ID):
            raise ValueError("Palette.ids must be 24-bit colors other than void white")
        if not np.array_equal(pack_rgb(np.asarray(self.colors, np.uint8).reshape(-1, 3)), ids):
            raise ValueError("Palette.colors do not match Palette.ids")
        for name in ("pixel_counts", "mask_counts"):
            if np.asarray(getattr(self, name)).shape != ids.shape:
                raise ValueError(f"Palette.{name}: expected shape {ids.shape}")
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "colors", np.asarray(self.colors, np.uint8).reshape(-1, 3))

    @classmethod
    def from_colors(cls, colors: np.ndarray) -> Palette:
        """A palette of known colors (any order, duplicates and white dropped), without statistics."""
        ids = np.unique(pack_rgb(np.asarray(colors, np.uint8).reshape(-1, 3)))
        ids = ids[ids != VOID_ID]
        zeros = np.zeros(ids.size, np.int64)
        return cls(unpack_rgb(ids), ids, zeros, zeros.copy())

    def __len__(self) -> int:
        return self.ids.size

    def index_of(self, ids: np.ndarray) -> np.ndarray:
        """Palette index (int32) of each packed id, -1 for ids not in the palette."""
        ids = np.asarray(ids)
        if len(self) == 0:
            return np.full(ids.shape, -1, np.int32)
        pos = np.searchsorted(self.ids, ids).clip(0, len(self) - 1)
        return np.where(self.ids[pos] == ids, pos, -1).astype(np.int32)

    def labels(self, mask: np.ndarray) -> np.ndarray:
        """(H, W) int32 palette index of every pixel; -1 for void and colors not in the palette."""
        return self.index_of(pack_rgb(_check_mask(mask)))


class PaletteBuilder:
    """Counts mask colors as keyframes arrive; `build` gives the palette seen so far at any time.

    Per color it keeps the pixel count, the interior-pixel count, the blend-pixel count and the number
    of masks that show it. Builders merge (`merged`) and round-trip through plain arrays (`to_arrays`,
    `from_arrays`) for .npz snapshots.
    """

    def __init__(self) -> None:
        self.ids = np.zeros(0, np.uint32)
        self.counts = {name: np.zeros(0, np.int64) for name in _COUNT_FIELDS}
        self.n_masks = 0

    def update(self, mask: np.ndarray, colors: MaskColors | None = None) -> None:
        """Counts one (H, W, 3) uint8 mask (`colors`: its mask_colors, when the caller has them)."""
        mask = _check_mask(mask)
        colors = colors or mask_colors(mask)
        interior, blend = region_counts(np.ascontiguousarray(mask), colors.packed, colors.ids)
        self._add(colors.ids, colors.counts, interior, blend, np.ones(colors.ids.size, np.int64))
        self.n_masks += 1

    def _add(self, ids: np.ndarray, *counts: np.ndarray) -> None:
        all_ids = np.union1d(self.ids, ids).astype(np.uint32)
        old_at, new_at = np.searchsorted(all_ids, self.ids), np.searchsorted(all_ids, ids)
        for name, add in zip(_COUNT_FIELDS, counts, strict=True):
            total = np.zeros(all_ids.size, np.int64)
            total[old_at] = self.counts[name]
            total[new_at] += add
            self.counts[name] = total
        self.ids = all_ids

    def absorb(self, other: PaletteBuilder) -> None:
        """Adds `other`'s counts to this builder, in place."""
        self._add(other.ids, *(other.counts[name] for name in _COUNT_FIELDS))
        self.n_masks += other.n_masks

    def merged(self, other: PaletteBuilder) -> PaletteBuilder:
        """A builder holding both builders' counts (e.g. two bags of the same scene)."""
        out = PaletteBuilder.from_arrays(self.to_arrays())
        out.absorb(other)
        return out

    def merge_ids(self, keep: int, drop: int) -> None:
        """Counts of color `drop` move to color `keep` (two objects found to be one; `drop` disappears).
        The mask count is the sum, so a mask that showed both counts twice."""
        at = np.searchsorted(self.ids, np.uint32(drop))
        if at >= self.ids.size or self.ids[at] != drop:
            return
        moved = {name: self.counts[name][at : at + 1].copy() for name in _COUNT_FIELDS}
        self.ids = np.delete(self.ids, at)
        for name in _COUNT_FIELDS:
            self.counts[name] = np.delete(self.counts[name], at)
        self._add(np.array([keep], np.uint32), *(moved[name] for name in _COUNT_FIELDS))

    def rename_ids(self, mapping: Mapping[int, int]) -> None:
        """Colors renamed (old id -> new id; others stay), their counts with them; colors renamed onto one
        id add up, as merge_ids does (a rebuilt map taking its predecessor's ids, core.segments.object_match)."""
        if not mapping:
            return
        ids = np.array([mapping.get(int(i), int(i)) for i in self.ids.tolist()], np.uint32)  # (C,)
        all_ids, at = np.unique(ids, return_inverse=True)
        for name in _COUNT_FIELDS:
            total = np.zeros(all_ids.size, np.int64)
            np.add.at(total, at, self.counts[name])
            self.counts[name] = total
        self.ids = all_ids.astype(np.uint32)

    def build(
        self,
        min_pixels: int = 1,
        min_interior: int = 1,
        thin_min_pixels: int = 100,
        thin_max_blend_fraction: float = 0.01,
    ) -> Palette:
        """The palette of the masks counted so far (see the module docstring for the rule)."""
        pixels, interior, blend = (self.counts[k] for k in ("pixels", "interior", "blend"))
        region = interior >= min_interior
        thin = (pixels >= thin_min_pixels) & (blend <= thin_max_blend_fraction * pixels)
        keep = (pixels >= min_pixels) & (region | thin) & (self.ids != VOID_ID)
        rejected = ~keep & (self.ids != VOID_ID)
        void = self.ids == VOID_ID
        return Palette(
            colors=unpack_rgb(self.ids[keep]),
            ids=self.ids[keep],
            pixel_counts=pixels[keep].copy(),
            mask_counts=self.counts["masks"][keep].copy(),
            rejected_ids=self.ids[rejected],
            rejected_pixels=pixels[rejected].copy(),
            void_pixels=int(pixels[void].sum()),
            n_masks=self.n_masks,
        )

    def to_arrays(self) -> dict[str, np.ndarray]:
        arrays = {"palette_ids": self.ids.copy(), "palette_n_masks": np.array(self.n_masks, np.int64)}
        arrays.update({f"palette_{name}": self.counts[name].copy() for name in _COUNT_FIELDS})
        return arrays

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> PaletteBuilder:
        """The builder saved by `to_arrays`; raises ValueError when arrays are missing or inconsistent."""
        names = ["palette_ids", "palette_n_masks"] + [f"palette_{name}" for name in _COUNT_FIELDS]
        missing = [name for name in names if name not in arrays]
        if missing:
            raise ValueError(f"palette builder arrays missing: {missing}")
        ids = np.asarray(arrays["palette_ids"])
        if ids.ndim != 1 or ids.dtype.kind not in "iu" or np.any(np.diff(ids.astype(np.int64)) <= 0):
            raise ValueError("palette_ids must be strictly ascending integers")
        out = cls()
        out.ids = ids.astype(np.uint32)
        for name in _COUNT_FIELDS:
            counts = np.asarray(arrays[f"palette_{name}"])
            if counts.shape != ids.shape or counts.dtype.kind not in "iu":
                raise ValueError(f"palette_{name}: expected {ids.shape} integer counts, got {counts.shape}")
            out.counts[name] = counts.astype(np.int64)
        out.n_masks = int(arrays["palette_n_masks"])
        return out
