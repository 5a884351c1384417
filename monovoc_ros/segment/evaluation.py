"""Scoring per-frame instance masks and a map's rendered objects against reference instances.

Both sides are scored the same way, on the same frames, over the reference's non-void pixels: an
instance's IoU is the mean over the frames where it is visible (at least ``min_visible`` pixels) of its
IoU there with the segment or object matched to it, 0 where nothing is matched. ``per_frame`` matches
one-to-one in every frame (Hungarian on IoU): what a segmenter is credited with. ``matched_once`` matches
one-to-one once over all frames (Hungarian on the IoU of the summed intersections and unions): a map
object keeps one identity everywhere.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
from scipy.optimize import linear_sum_assignment

# A reference instance counts as visible in a frame from 0.1% of a 600x340 image on.
DEFAULT_MIN_VISIBLE = 200


def frame_overlaps(pred: np.ndarray, ref: np.ndarray, instances: np.ndarray, void: int) -> tuple:
    """(pred ids (P,), inter (P, R), pred areas (P,), ref areas (R,)) over the frame's non-void reference
    pixels; ``pred`` (H, W) ids (``void`` = no segment), ``ref`` (H, W) ids, ``instances`` (R,) ref ids."""
    valid = ref != void
    p, r = pred[valid].astype(np.int64), ref[valid].astype(np.int64)
    col = np.searchsorted(instances, r)
    col = np.where((col < len(instances)) & (instances[np.minimum(col, len(instances) - 1)] == r), col, -1)
    pred_ids, p_index = np.unique(p, return_inverse=True)
    inter = np.zeros((len(pred_ids), len(instances)), np.int64)
    hit = col >= 0
    np.add.at(inter, (p_index[hit], col[hit]), 1)
    pred_area = np.bincount(p_index, minlength=len(pred_ids))
    ref_area = np.bincount(col[hit], minlength=len(instances))
    return pred_ids, inter, pred_area, ref_area


def _iou(inter: np.ndarray, pred_area: np.ndarray, ref_area: np.ndarray) -> np.ndarray:
    union = pred_area[:, None] + ref_area[None, :] - inter
    return np.divide(inter, union, out=np.zeros(inter.shape, np.float64), where=union > 0)


def per_frame(
    preds: Sequence[np.ndarray],
    refs: Sequence[np.ndarray],
    instances: Iterable[int],
    *,
    pred_void: int,
    ref_void: int,
    min_visible: int = DEFAULT_MIN_VISIBLE,
) -> dict[int, float]:
    """Instance -> mean IoU over its visible frames, matched anew in each frame."""
    inst = np.array(sorted(set(int(i) for i in instances)), np.int64)
    sums, counts = np.zeros(len(inst)), np.zeros(len(inst), np.int64)
    for pred, ref in zip(preds, refs, strict=True):
        pred_ids, inter, pred_area, ref_area = frame_overlaps(pred, ref, inst, ref_void)
        keep = pred_ids != pred_void
        iou = _iou(inter[keep], pred_area[keep], ref_area)
        visible = ref_area >= min_visible
        counts += visible
        if iou.size:
            rows, cols = linear_sum_assignment(-iou)
            got = np.zeros(len(inst))
            got[cols] = iou[rows, cols]
            sums += np.where(visible, got, 0.0)
    return {int(i): float(s / c) for i, s, c in zip(inst, sums, counts, strict=True) if c > 0}


def matched_once(
    preds: Sequence[np.ndarray],
    refs: Sequence[np.ndarray],
    instances: Iterable[int],
    *,
    pred_void: int,
    ref_void: int,
    min_visible: int = DEFAULT_MIN_VISIBLE,
) -> tuple[dict[int, float], dict[int, int]]:
    """(instance -> mean IoU over its visible frames, instance -> the map id matched to it once)."""
    inst = np.array(sorted(set(int(i) for i in instances)), np.int64)
    frames = [frame_overlaps(p, r, inst, ref_void) for p, r in zip(preds, refs, strict=True)]
    all_ids = np.unique(np.concatenate([f[0] for f in frames] + [np.zeros(0, np.int64)]))
    all_ids = all_ids[all_ids != pred_void]
    inter = np.zeros((len(all_ids), len(inst)))
    union = np.zeros((len(all_ids), len(inst)))
    for pred_ids, f_inter, pred_area, ref_area in frames:
        rows = np.searchsorted(all_ids, pred_ids)
        keep = pred_ids != pred_void
        inter[rows[keep]] += f_inter[keep]
        # Union summed over the frames where either side is present.
        union += ref_area[None, :]
        union[rows[keep]] += pred_area[keep, None] - f_inter[keep]
        # Frames where the object is absent still add its reference area: added above for every object.
    iou = np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)
    match: dict[int, int] = {}
    if iou.size:
        rows, cols = linear_sum_assignment(-iou)
        match = {int(inst[c]): int(all_ids[r]) for r, c in zip(rows, cols, strict=True) if iou[r, c] > 0}
    sums, counts = np.zeros(len(inst)), np.zeros(len(inst), np.int64)
    for pred_ids, f_inter, pred_area, ref_area in frames:
        visible = ref_area >= min_visible
        counts += visible
        for j, instance in enumerate(inst):
            if not visible[j] or int(instance) not in match:
                continue
            where = np.flatnonzero(pred_ids == match[int(instance)])
            if where.size:
                k = where[0]
                u = pred_area[k] + ref_area[j] - f_inter[k, j]
                sums[j] += f_inter[k, j] / u if u > 0 else 0.0
    scores = {int(i): float(s / c) for i, s, c in zip(inst, sums, counts, strict=True) if c > 0}
    return scores, match


def mean(scores: dict[int, float]) -> float:
    return float(np.mean(list(scores.values()))) if scores else 0.0
