"""Object-level geometry of a semantic map: one object per palette color (METHOD section 5).

Extents are robust: the box spans the 1st..99th percentile of the object's Gaussian centres on each
axis, so a handful of mislabeled Gaussians far away (floaters, boundary errors) do not inflate it.
The centroid is the opacity-weighted mean of the centres inside that box.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monovoc_ros.core.gaussians import GaussianMap
from monovoc_ros.core.palette import UNOBSERVED_ID, VOID_ID, unpack_rgb

_LOW, _HIGH = 1.0, 99.0


@dataclass
class ObjectSummary:
    id: int  # packed palette color r << 16 | g << 8 | b
    rgb: tuple[int, int, int]
    num_gaussians: int
    centroid: np.ndarray  # (3,) metres, map frame
    bbox_min: np.ndarray  # (3,)
    bbox_max: np.ndarray  # (3,)

    @property
    def extent(self) -> np.ndarray:
        return self.bbox_max - self.bbox_min


def summarize_objects(gaussians: GaussianMap, object_ids: np.ndarray) -> list[ObjectSummary]:
    """Summaries of every object with at least one Gaussian, sorted by id (void and unobserved skipped)."""
    object_ids = np.asarray(object_ids, np.uint32)
    if object_ids.shape != (len(gaussians),):
        raise ValueError(f"object_ids: expected shape ({len(gaussians)},), got {object_ids.shape}")
    keep = (object_ids != UNOBSERVED_ID) & (object_ids != VOID_ID)
    index = np.flatnonzero(keep)
    if index.size == 0:
        return []
    order = index[np.argsort(object_ids[index], kind="stable")]
    ids, starts = np.unique(object_ids[order], return_index=True)
    bounds = np.append(starts, order.size)
    out = []
    for k, oid in enumerate(ids):
        members = order[bounds[k] : bounds[k + 1]]
        pts = gaussians.means[members].astype(np.float64)
        lo, hi = np.percentile(pts, [_LOW, _HIGH], axis=0)
        inside = np.all((pts >= lo) & (pts <= hi), axis=1)
        w = gaussians.opacities[members][inside].astype(np.float64)
        centroid = (pts[inside] * w[:, None]).sum(0) / w.sum() if w.sum() > 0 else pts.mean(0)
        rgb = tuple(int(c) for c in unpack_rgb(np.uint32(oid)))
        out.append(ObjectSummary(int(oid), rgb, int(members.size), centroid, lo, hi))
    return out
