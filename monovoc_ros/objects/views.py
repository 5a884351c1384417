"""The best keyframe views of every object, kept as keyframes arrive (METHOD section 5).

An object's representative views are the keyframes where its palette color covers the most mask pixels
(its *prevalence*). Only the top ``views_per_object`` views are kept, so memory is bounded by the number
of objects, not the length of the sequence. A view stores what re-cropping needs in either mask mode:
the RGB of the object's box grown by the context margin and the object's boolean mask over that crop.
Cropping a stored view with ``crop_object(view.rgb, view.mask, mode, context=c)`` for any ``c`` up to the
stored margin gives exactly the crop of the full keyframe (same box, same padding, same image-edge
clipping), unless the view was downscaled to ``max_side``.

The mask may have another resolution than the RGB: mask labels are resized nearest-neighbour to the RGB
(as ``embed.crops.resize_mask`` does), while prevalence stays a count of mask pixels.

Every change of an object's view set bumps its ``version``; consumers (the object index) remember the
version they embedded and re-embed an object only when it moved on.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import cv2
import numpy as np

from monovoc_ros.core.evidence.palette import VOID_ID, pack_rgb
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.objects import views_kernels as vk


@dataclass
class ViewConfig:
    views_per_object: int = 3
    # Margin kept around the object's box, as a fraction of its height/width (crop_object's context):
    # re-crops with a context up to this are exact.
    context: float = 0.15
    # Fewer object pixels than this in a mask is no usable view (a few pixels embed as noise).
    min_pixels: int = 20
    # Crops longer than this are downscaled (area for RGB, nearest for the mask): an image encoder sees
    # 224-260 px anyway, and it bounds a view to ~0.8 MB even for a wall filling the frame.
    max_side: int = 448

    def __post_init__(self) -> None:
        if int(self.views_per_object) < 1:
            raise ValueError(f"views_per_object must be >= 1, got {self.views_per_object}")
        if not (np.isfinite(self.context) and self.context >= 0):
            raise ValueError(f"context must be a fraction >= 0, got {self.context}")
        if int(self.min_pixels) < 1:
            raise ValueError(f"min_pixels must be >= 1, got {self.min_pixels}")
        if int(self.max_side) < 16:
            raise ValueError(f"max_side must be >= 16, got {self.max_side}")


@dataclass(eq=False)
class ObjectView:
    object_id: int  # packed palette color
    stamp_ns: int  # keyframe stamp (unique per keyframe)
    keyframe_index: int
    prevalence: int  # object pixels in the keyframe's mask (mask resolution)
    rgb: np.ndarray  # (h, w, 3) uint8: the object's box grown by the context margin
    mask: np.ndarray  # (h, w) bool: the object's pixels in that crop
    # Per (crop mode, context, dim, backend) image embedding of this view: a view is embedded once.
    embeddings: dict[tuple, np.ndarray] = field(default_factory=dict, repr=False)

    @property
    def key(self) -> tuple[int, int]:
        return (self.object_id, self.stamp_ns)

    @property
    def nbytes(self) -> int:
        return int(self.rgb.nbytes + self.mask.nbytes + sum(e.nbytes for e in self.embeddings.values()))

    def pixels(self) -> np.ndarray:
        """(n, 3) uint8 RGB of the object's pixels in this view."""
        return self.rgb[self.mask]


def _label_image(mask: np.ndarray, palette_ids: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(ids, labels): the object ids considered and an (H, W) int32 index into them, -1 elsewhere."""
    if palette_ids is None:
        packed = pack_rgb(mask)
        ids, inverse = np.unique(packed, return_inverse=True)
        labels = inverse.reshape(packed.shape).astype(np.int32)
        void = np.searchsorted(ids, VOID_ID)
        if void < ids.size and ids[void] == VOID_ID:
            labels[labels == void] = -1
            labels[labels > void] -= 1
            ids = np.delete(ids, void)
        return ids.astype(np.uint32), labels
    ids = np.unique(np.asarray(palette_ids, dtype=np.uint32))
    ids = ids[ids != VOID_ID]
    labels = np.empty(mask.shape[:2], np.int32)
    vk.label_image(np.ascontiguousarray(mask), ids, labels)
    return ids, labels


def warm_up_views() -> float:
    """Runs both view kernels once on a tiny mask (compiled into numba's cache, or loaded); returns seconds."""
    import time

    start = time.perf_counter()
    mask = np.zeros((4, 4, 3), np.uint8)
    mask[:, 2:] = 255
    ids, labels = _label_image(mask, np.array([0, VOID_ID], np.uint32))
    vk.label_boxes(labels, ids.size)
    return time.perf_counter() - start


def label_image_reference(mask: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Plain twin of views_kernels.label_image: (H, W) int32 index of each pixel's color in ``ids``, -1."""
    packed = pack_rgb(mask)
    if ids.size == 0:
        return np.full(packed.shape, -1, np.int32)
    pos = np.searchsorted(ids, packed).clip(0, ids.size - 1)
    return np.where(ids[pos] == packed, pos, -1).astype(np.int32)


def boxes_reference(labels: np.ndarray, wanted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(len(wanted), 4) end-exclusive (y0, x0, y1, x1) boxes of the wanted labels and whether each is
    present at all, from row/column presence tables (labels x rows, labels x columns): no per-pixel
    Python, no sort."""
    h, w = labels.shape
    k = int(labels.max()) + 2 if labels.size else 1
    slot = labels + 1  # -1 (nothing) -> row 0 of the tables
    rows = np.zeros((k, h), bool)
    cols = np.zeros((k, w), bool)
    rows[slot, np.arange(h)[:, None]] = True
    cols[slot, np.arange(w)[None, :]] = True
    rows, cols = rows[wanted + 1], cols[wanted + 1]
    y0 = rows.argmax(1)
    y1 = h - rows[:, ::-1].argmax(1)
    x0 = cols.argmax(1)
    x1 = w - cols[:, ::-1].argmax(1)
    return np.stack([y0, x0, y1, x1], axis=1), rows.any(1)


class ObjectViews:
    """Top-k views per object by prevalence; thread-safe (observe on one thread, read on others)."""

    def __init__(self, config: ViewConfig | None = None) -> None:
        self.config = config or ViewConfig()
        self._views: dict[int, list[ObjectView]] = {}  # best first
        self._versions: dict[int, int] = {}
        self._observations: dict[int, int] = {}  # keyframes in which the object had >= min_pixels
        self._lock = threading.Lock()
        self.keyframes = 0

    # ------------------------------------------------------------------ reading

    def object_ids(self) -> list[int]:
        with self._lock:
            return sorted(self._views)

    def views(self, object_id: int) -> list[ObjectView]:
        """The object's views, highest prevalence first (a copy of the list; views are shared)."""
        with self._lock:
            return list(self._views.get(int(object_id), ()))

    def version(self, object_id: int) -> int:
        """Bumped whenever the object's view set changes; 0 for an object never seen."""
        with self._lock:
            return self._versions.get(int(object_id), 0)

    def versions(self) -> dict[int, int]:
        with self._lock:
            return dict(self._versions)

    def observations(self, object_id: int) -> int:
        with self._lock:
            return self._observations.get(int(object_id), 0)

    def observation_counts(self) -> dict[int, int]:
        with self._lock:
            return dict(self._observations)

    def all_views(self) -> list[ObjectView]:
        with self._lock:
            return [v for oid in sorted(self._views) for v in self._views[oid]]

    def nbytes(self) -> int:
        with self._lock:
            return sum(v.nbytes for vs in self._views.values() for v in vs)

    def __len__(self) -> int:
        with self._lock:
            return len(self._views)

    # ------------------------------------------------------------------ writing

    def observe(self, keyframe: Keyframe, palette_ids: np.ndarray | None = None) -> list[int]:
        """Offers this keyframe's view of every object in it; returns the ids whose view set changed.

        ``palette_ids``: the object ids to consider (e.g. the mapper's palette after integrating this
        keyframe); colors outside it (blends, noise) are ignored. ``None`` takes every non-void color.
        Keyframes without RGB count observations only.
        """
        cfg = self.config
        ids, labels = _label_image(keyframe.mask, palette_ids)
        counts, boxes = vk.label_boxes(labels, ids.size)
        present = np.flatnonzero(counts >= cfg.min_pixels)
        with self._lock:
            self.keyframes += 1
            for oid in ids[present].tolist():
                self._observations[oid] = self._observations.get(oid, 0) + 1
            if keyframe.rgb is None or present.size == 0:
                return []
            # Candidates: objects with a free slot or beating their weakest stored view.
            floor = [self._entry_floor(int(ids[i])) for i in present]  # -1 when a slot is free
            stamp = int(keyframe.stamp_ns)
            candidates = [
                int(i)
                for i, f in zip(present, floor, strict=True)
                if counts[i] > f and not any(v.stamp_ns == stamp for v in self._views.get(int(ids[i]), ()))
            ]
        if not candidates:
            return []
        rgb = keyframe.rgb
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ValueError(f"keyframe rgb must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
        height, width = rgb.shape[:2]
        pixels = counts
        if labels.shape != (height, width):
            labels = cv2.resize(labels, (width, height), interpolation=cv2.INTER_NEAREST)
            pixels, boxes = vk.label_boxes(labels, ids.size)
        wanted = np.array(candidates, dtype=np.int64)
        boxes, visible = boxes[wanted], pixels[wanted] > 0  # a tiny object may vanish when resized
        new_views = []
        for i, (y0, x0, y1, x1) in zip(wanted[visible].tolist(), boxes[visible].tolist(), strict=True):
            pad_y, pad_x = round(cfg.context * (y1 - y0)), round(cfg.context * (x1 - x0))
            y0, x0 = max(0, y0 - pad_y), max(0, x0 - pad_x)
            y1, x1 = min(height, y1 + pad_y), min(width, x1 + pad_x)
            crop = np.ascontiguousarray(rgb[y0:y1, x0:x1])
            mask = labels[y0:y1, x0:x1] == i
            crop, mask = _bound_size(crop, mask, cfg.max_side)
            oid = int(ids[i])
            new_views.append(ObjectView(oid, stamp, int(keyframe.index), int(counts[i]), crop, mask))
        changed = []
        with self._lock:
            for view in new_views:
                if self._insert(view):
                    changed.append(view.object_id)
        return changed

    def _entry_floor(self, oid: int) -> int:
        views = self._views.get(oid, ())
        return -1 if len(views) < self.config.views_per_object else views[-1].prevalence

    def _insert(self, view: ObjectView) -> bool:
        views = self._views.setdefault(view.object_id, [])
        if len(views) >= self.config.views_per_object and view.prevalence <= views[-1].prevalence:
            return False
        views.append(view)
        # Stable: among equal prevalences the earlier view stays ahead (deterministic for a replay).
        views.sort(key=lambda v: -v.prevalence)
        del views[self.config.views_per_object :]
        self._versions[view.object_id] = self._versions.get(view.object_id, 0) + 1
        return True

    def restore(self, views: list[ObjectView], observations: dict[int, int] | None = None) -> None:
        """Puts saved views back (e.g. from the object database), replacing what is held."""
        with self._lock:
            self._views.clear()
            for view in sorted(views, key=lambda v: (v.object_id, -v.prevalence)):
                self._views.setdefault(view.object_id, []).append(view)
            for oid, vs in self._views.items():
                del vs[self.config.views_per_object :]
                self._versions[oid] = self._versions.get(oid, 0) + 1
            if observations is not None:
                self._observations = {int(k): int(v) for k, v in observations.items()}

    def clear(self) -> None:
        with self._lock:
            self._views.clear()
            self._observations.clear()
            # Versions keep counting so that a consumer never mistakes new views for old ones.
            for oid in self._versions:
                self._versions[oid] += 1
            self.keyframes = 0


def _bound_size(crop: np.ndarray, mask: np.ndarray, max_side: int) -> tuple[np.ndarray, np.ndarray]:
    h, w = mask.shape
    if max(h, w) <= max_side:
        return crop, mask
    scale = max_side / max(h, w)
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    small = cv2.resize(crop, size, interpolation=cv2.INTER_AREA)
    small_mask = cv2.resize(mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST).astype(bool)
    if not small_mask.any():  # a sliver can vanish under nearest: keep its strongest pixel
        ys, xs = np.nonzero(mask)
        small_mask[min(int(ys[0] * scale), size[1] - 1), min(int(xs[0] * scale), size[0] - 1)] = True
    return small, small_mask
