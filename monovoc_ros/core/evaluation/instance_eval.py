"""Scoring a map whose object ids are its own (built with per-frame mask ids) against reference instances.

The map's rendered labels and the reference masks of the evaluated frames give joint pixel counts
N[p, r] (map object p, reference instance r, over pixels whose reference is not void). Map objects
and reference instances are matched one to one by IoU (Hungarian, scipy linear_sum_assignment;
pairs without overlap never match); each matched map object is then renamed to its reference
instance and the frames are scored as usual (core.evaluation.evaluation.SegmentationEvaluator: matched mIoU
over the reference instances, an unmatched instance scoring its IoU with nothing, 0). Reported
beside it:

- merges: reference instances left unmatched whose pixels are mostly (> 50%) rendered as a map
  object matched to another instance (two instances became one object);
- splits: map objects left unmatched whose pixels mostly lie on an instance matched to another map
  object (one instance became several objects);
- objects: map objects leading at least one evaluated pixel, against `reference_objects`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monovoc_ros.core.evaluation.evaluation import SegmentationEvaluator
from monovoc_ros.core.evidence.palette import UNOBSERVED_ID, VOID_ID
from monovoc_ros.core.map.camera import resize_nearest

UNMATCHED_ID = 0xFFFFFFFE  # a map object matched to no reference instance (not a 24-bit color)


@dataclass
class InstanceMatch:
    mapping: dict[int, int]  # map object id -> reference instance id
    merges: int
    splits: int
    objects: int  # map objects leading at least one evaluated pixel
    reference_objects: int  # reference instances in the evaluated frames


def joint_counts(preds: list[np.ndarray], refs: list[np.ndarray]) -> dict[tuple[int, int], int]:
    """Pixel counts per (map id, reference id) over pixels whose reference is not void."""
    counts: dict[tuple[int, int], int] = {}
    for pred, ref in zip(preds, refs, strict=True):
        if pred.shape != ref.shape:
            pred = resize_nearest(pred, *ref.shape)
        valid = ref != VOID_ID
        keys, n = np.unique(
            (pred[valid].astype(np.uint64) << np.uint64(32)) | ref[valid].astype(np.uint64), return_counts=True
        )
        for key, c in zip(keys.tolist(), n.tolist(), strict=True):
            pair = (key >> 32, key & 0xFFFFFFFF)
            counts[pair] = counts.get(pair, 0) + c
    return counts


def match_instances(preds: list[np.ndarray], refs: list[np.ndarray]) -> InstanceMatch:
    """One-to-one matching of rendered map objects (`preds`, (H, W) ids) to reference instances."""
    from scipy.optimize import linear_sum_assignment

    counts = joint_counts(preds, refs)
    background = {VOID_ID, UNOBSERVED_ID}
    pred_ids = sorted({p for p, _ in counts} - background)
    ref_ids = sorted({r for _, r in counts})
    pi = {p: i for i, p in enumerate(pred_ids)}
    ri = {r: i for i, r in enumerate(ref_ids)}
    inter = np.zeros((len(pred_ids), len(ref_ids)), np.int64)
    pred_total = np.zeros(len(pred_ids), np.int64)
    ref_total = np.zeros(len(ref_ids), np.int64)
    for (p, r), c in counts.items():
        ref_total[ri[r]] += c
        if p in pi:
            pred_total[pi[p]] += c
            inter[pi[p], ri[r]] += c
    mapping: dict[int, int] = {}
    matched_pred = np.zeros(len(pred_ids), bool)
    matched_ref = np.full(len(ref_ids), -1, np.int64)  # index of the map object matched to each instance
    if len(pred_ids) and len(ref_ids):
        union = pred_total[:, None] + ref_total[None, :] - inter
        iou = np.divide(inter, union, out=np.zeros(inter.shape), where=union > 0)
        rows, cols = linear_sum_assignment(-iou)
        for p, r in zip(rows.tolist(), cols.tolist(), strict=True):
            if inter[p, r] > 0:
                mapping[pred_ids[p]] = ref_ids[r]
                matched_pred[p] = True
                matched_ref[r] = p
    merges = 0
    for r in np.flatnonzero(matched_ref < 0):
        if len(pred_ids) and ref_total[r]:
            p = int(np.argmax(inter[:, r]))
            merges += int(matched_pred[p] and inter[p, r] > 0.5 * ref_total[r])
    splits = 0
    for p in np.flatnonzero(~matched_pred):
        if len(ref_ids) and pred_total[p]:
            r = int(np.argmax(inter[p]))
            splits += int(matched_ref[r] >= 0 and matched_ref[r] != p and inter[p, r] > 0.5 * pred_total[p])
    shown = {int(p) for pred in preds for p in np.unique(pred).tolist()} - background
    return InstanceMatch(mapping, merges, splits, len(shown), len(ref_ids))


def renamed(pred: np.ndarray, mapping: dict[int, int]) -> np.ndarray:
    """`pred` with matched map objects renamed to their instances and the others to UNMATCHED_ID."""
    ids, inverse = np.unique(pred, return_inverse=True)
    table = np.array(
        [mapping.get(int(i), int(i) if int(i) in (VOID_ID, UNOBSERVED_ID) else UNMATCHED_ID) for i in ids.tolist()],
        np.uint32,
    )
    return table[inverse].reshape(pred.shape)


def score_matched(preds: list[np.ndarray], refs: list[np.ndarray]) -> tuple[dict, InstanceMatch]:
    """SegmentationEvaluator's result over the matched renaming, and the match."""
    match = match_instances(preds, refs)
    evaluator = SegmentationEvaluator()
    for pred, ref in zip(preds, refs, strict=True):
        evaluator.update(renamed(pred, match.mapping), ref)
    return evaluator.result(), match
