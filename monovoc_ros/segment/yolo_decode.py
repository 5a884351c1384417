"""Decoding a YOLO-seg network's raw outputs into one image's instances (NumPy).

Two export layouts are in common use, told apart by their shapes:

- YOLOv5-seg / YOLOv7-seg: predictions ``(1, N, 5 + C + M)`` rows ``cx, cy, w, h, objectness, C class
  scores, M mask coefficients``;
- YOLOv8 / YOLO11-seg (``yolo export format=onnx``): predictions ``(1, 4 + C + M, N)``, the same without
  objectness, one column per candidate.

Both come with prototypes ``(1, M, h, w)`` at a fixed stride of the input. An instance's mask is
``sigmoid(coefficients @ prototypes) > 0.5`` inside its box, the prototypes sampled bilinearly at each
image pixel's centre (mapped through the letterbox), so masks are decoded at the image's resolution
without ever building them at the input's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from monovoc_ros.segment.letterbox import Letterbox
from monovoc_ros.segment.options import SegmenterOptions
from monovoc_ros.segment.segmentation import Segmentation

# YOLO's cap on candidates entering suppression (boxes beyond it are the least confident).
MAX_NMS_CANDIDATES = 30000
# Class-aware suppression offsets each class's boxes by this much so that classes never overlap.
CLASS_OFFSET = 7680.0


class ModelLayoutError(ValueError):
    """The network's outputs are not a YOLO-seg layout this decoder knows."""


@dataclass(frozen=True)
class RawDetections:
    """Candidates of one image in the network's input coordinates."""

    boxes: np.ndarray  # (N, 4) float32 cx, cy, w, h
    objectness: np.ndarray | None  # (N,) float32, None in the YOLOv8 layout
    class_scores: np.ndarray  # (N, C) float32
    coefficients: np.ndarray  # (N, M) float32
    prototypes: np.ndarray  # (M, h, w) float32
    layout: str  # "yolov5" | "yolov8"


def detect_layout(shapes: list[tuple[int, ...]], num_classes: int | None) -> tuple[str, int, int]:
    """(layout, index of the predictions output, index of the prototypes output) for output shapes.

    ``num_classes`` (from the model's class names) resolves which axis holds the channels; without it the
    channels are the last axis in the YOLOv5 layout and the middle one in the YOLOv8 layout, the shorter
    of the two.
    """
    protos = [i for i, s in enumerate(shapes) if len(s) == 4]
    preds = [i for i, s in enumerate(shapes) if len(s) == 3]
    if len(protos) != 1 or len(preds) < 1:
        raise ModelLayoutError(
            f"expected a (1, N, C) prediction output and a (1, M, h, w) prototype output, got shapes {shapes}"
        )
    p, q = preds[0], protos[0]
    batch, a, b = shapes[p]
    m = shapes[q][1]
    if batch != 1 or shapes[q][0] != 1:
        raise ModelLayoutError(f"batch size must be 1, got output shapes {shapes}")
    if num_classes is not None:
        v5 = b == 5 + num_classes + m
        v8 = a == 4 + num_classes + m
        if v5 == v8:
            raise ModelLayoutError(
                f"predictions {shapes[p]} with {m} mask coefficients fit neither (1, N, 5 + {num_classes} + {m}) "
                f"(YOLOv5/v7-seg) nor (1, 4 + {num_classes} + {m}, N) (YOLOv8/11-seg) for {num_classes} class names"
            )
        return ("yolov5" if v5 else "yolov8"), p, q
    if b < a and b > 5 + m:
        return "yolov5", p, q
    if a < b and a > 4 + m:
        return "yolov8", p, q
    raise ModelLayoutError(f"cannot tell the layout of predictions {shapes[p]} with {m} mask coefficients")


def split_outputs(outputs: list[np.ndarray], num_classes: int | None) -> RawDetections:
    shapes = [tuple(int(d) for d in np.shape(o)) for o in outputs]
    layout, p, q = detect_layout(shapes, num_classes)
    pred = np.asarray(outputs[p], np.float32)[0]
    proto = np.asarray(outputs[q], np.float32)[0]
    m = proto.shape[0]
    if layout == "yolov8":
        pred = pred.T
        return RawDetections(pred[:, :4], None, pred[:, 4:-m], pred[:, -m:], proto, layout)
    return RawDetections(pred[:, :4], pred[:, 4], pred[:, 5:-m], pred[:, -m:], proto, layout)


def nms(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Greedy non-maximum suppression: indices kept, by descending score. ``boxes`` (n, 4) xyxy."""
    x1, y1, x2, y2 = (boxes[:, i].astype(np.float64) for i in range(4))
    areas = np.maximum(x2 - x1, 0.0) * np.maximum(y2 - y1, 0.0)
    order = np.argsort(-scores, kind="stable")
    keep = []
    while order.size:
        i = order[0]
        keep.append(i)
        rest = order[1:]
        w = np.maximum(np.minimum(x2[i], x2[rest]) - np.maximum(x1[i], x1[rest]), 0.0)
        h = np.maximum(np.minimum(y2[i], y2[rest]) - np.maximum(y1[i], y1[rest]), 0.0)
        inter = w * h
        union = areas[i] + areas[rest] - inter
        iou = np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)
        order = rest[iou <= iou_threshold]
    return np.asarray(keep, np.int64)


def xywh_to_xyxy(boxes: np.ndarray) -> np.ndarray:
    cx, cy, w, h = boxes[:, 0], boxes[:, 1], boxes[:, 2], boxes[:, 3]
    return np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], axis=1)


def select(
    raw: RawDetections, class_names: tuple[str, ...], options: SegmenterOptions
) -> tuple[np.ndarray, np.ndarray]:
    """Candidates kept after thresholds, the class map and suppression: (K,) indices, best first, and (N,)
    every candidate's class index."""
    scores, classes = confidences(raw, options)
    allowed = np.array([options.rename(n) != "" for n in class_names], bool)
    named = allowed[classes] if class_names else np.ones(len(scores), bool)
    finite = np.isfinite(raw.boxes).all(axis=1) & np.isfinite(scores) & (raw.boxes[:, 2] > 0) & (raw.boxes[:, 3] > 0)
    candidates = np.flatnonzero(finite & (scores >= options.score_threshold) & named)
    if candidates.size > MAX_NMS_CANDIDATES:
        top = np.argsort(-scores[candidates], kind="stable")[:MAX_NMS_CANDIDATES]
        candidates = candidates[top]
    boxes = xywh_to_xyxy(raw.boxes[candidates].astype(np.float64))
    if not options.class_agnostic:
        boxes = boxes + classes[candidates, None] * CLASS_OFFSET
    kept = candidates[nms(boxes, scores[candidates], options.nms_iou)]
    return kept[: options.max_instances], classes


def confidences(raw: RawDetections, options: SegmenterOptions) -> tuple[np.ndarray, np.ndarray]:
    """(N,) confidence and (N,) class index of every candidate."""
    n = raw.boxes.shape[0]
    if raw.class_scores.shape[1] == 0:
        return (raw.objectness if raw.objectness is not None else np.zeros(n, np.float32)), np.zeros(n, np.int64)
    classes = np.argmax(raw.class_scores, axis=1)
    best = raw.class_scores[np.arange(n), classes]
    if raw.objectness is None:
        return best, classes
    if options.class_agnostic:
        return raw.objectness, classes
    return raw.objectness * best, classes


def class_confidences(raw: RawDetections, classes: np.ndarray) -> np.ndarray:
    """(N,) confidence in each candidate's class: objectness x class score (YOLOv5 layout) or the class
    score. What a segment's name is worth, also where candidates were selected by objectness alone."""
    n = raw.boxes.shape[0]
    best = raw.class_scores[np.arange(n), classes] if raw.class_scores.shape[1] else np.ones(n, np.float32)
    return best if raw.objectness is None else raw.objectness * best


def bilinear_weights(n_out: int, start: int, a: float, b: float, n_src: int) -> tuple[np.ndarray, int]:
    """Interpolation matrix (n_out, span) and its first source column for output pixels start..start+n_out-1
    sampled at source coordinate ``u = a * x + b`` (pixel centres, edges clamped)."""
    u = a * np.arange(start, start + n_out, dtype=np.float64) + b
    u = np.clip(u, 0.0, n_src - 1)
    i0 = np.floor(u).astype(np.int64)
    i1 = np.minimum(i0 + 1, n_src - 1)
    f = u - i0
    first = int(i0.min()) if n_out else 0
    span = (int(i1.max()) - first + 1) if n_out else 0
    weights = np.zeros((n_out, span), np.float64)
    rows = np.arange(n_out)
    np.add.at(weights, (rows, i0 - first), 1.0 - f)
    np.add.at(weights, (rows, i1 - first), f)
    return weights, first


def pixel_box(box: np.ndarray, height: int, width: int) -> tuple[int, int, int, int]:
    """Image pixels whose centres lie in the box [x0, x1) x [y0, y1): (row0, row1, col0, col1)."""
    x0, y0, x1, y1 = box
    c0 = int(np.clip(np.ceil(x0 - 0.5), 0, width))
    c1 = int(np.clip(np.ceil(x1 - 0.5), 0, width))
    r0 = int(np.clip(np.ceil(y0 - 0.5), 0, height))
    r1 = int(np.clip(np.ceil(y1 - 0.5), 0, height))
    return r0, r1, c0, c1


def instance_masks(
    raw: RawDetections, kept: np.ndarray, lb: Letterbox
) -> list[tuple[tuple[int, int, int, int], np.ndarray]]:
    """Per kept candidate its pixel box and (rows, cols) bool mask inside it, at the image's resolution."""
    m, ph, pw = raw.prototypes.shape
    # Image pixel centre x -> input x = (x + 0.5) * scale + left -> prototype u = input x / stride - 0.5.
    stride_x, stride_y = lb.input_w / pw, lb.input_h / ph
    ax, bx = lb.scale_x / stride_x, (0.5 * lb.scale_x + lb.left) / stride_x - 0.5
    ay, by = lb.scale_y / stride_y, (0.5 * lb.scale_y + lb.top) / stride_y - 0.5
    boxes = lb.boxes_to_image(xywh_to_xyxy(raw.boxes[kept].astype(np.float64)))
    protos = raw.prototypes.reshape(m, ph * pw)
    logits = (raw.coefficients[kept].astype(np.float32) @ protos).reshape(len(kept), ph, pw)
    out = []
    for k in range(len(kept)):
        r0, r1, c0, c1 = pixel_box(boxes[k], lb.image_h, lb.image_w)
        if r1 <= r0 or c1 <= c0:
            out.append(((r0, r0, c0, c0), np.zeros((0, 0), bool)))
            continue
        wy, fy = bilinear_weights(r1 - r0, r0, ay, by, ph)
        wx, fx = bilinear_weights(c1 - c0, c0, ax, bx, pw)
        patch = logits[k, fy : fy + wy.shape[1], fx : fx + wx.shape[1]].astype(np.float64)
        out.append(((r0, r1, c0, c1), (wy @ patch @ wx.T) > 0.0))
    return out


def resolve_overlaps(
    masks: list[tuple[tuple[int, int, int, int], np.ndarray]], height: int, width: int, min_area: int
) -> tuple[np.ndarray, np.ndarray]:
    """One instance per pixel, the most confident (masks come best first): (H, W) uint16 ids numbered
    1..K in that order after dropping instances with fewer than ``min_area`` visible pixels, and (K,)
    the index in ``masks`` of each id."""
    order = np.zeros((height, width), np.int32)  # 1 + index of the winning mask, 0 = void
    for k in range(len(masks) - 1, -1, -1):  # least confident first: better ones paint over it
        (r0, r1, c0, c1), mask = masks[k]
        if mask.size:
            view = order[r0:r1, c0:c1]
            view[mask] = k + 1
    areas = np.bincount(order.ravel(), minlength=len(masks) + 1)[1:]
    survivors = np.flatnonzero(areas >= max(min_area, 1))
    relabel = np.zeros(len(masks) + 1, np.uint16)
    relabel[survivors + 1] = np.arange(1, len(survivors) + 1, dtype=np.uint16)
    return relabel[order], survivors


def decode(
    outputs: list[np.ndarray], lb: Letterbox, class_names: tuple[str, ...], options: SegmenterOptions
) -> Segmentation:
    """Raw YOLO-seg outputs of one letterboxed image -> its :class:`Segmentation` at the image's size."""
    raw = split_outputs(outputs, len(class_names) if class_names else None)
    if class_names and raw.class_scores.shape[1] != len(class_names):
        raise ModelLayoutError(f"the model scores {raw.class_scores.shape[1]} classes but has {len(class_names)} names")
    kept, classes = select(raw, class_names, options)
    scores = class_confidences(raw, classes)
    masks = instance_masks(raw, kept, lb)
    ids, survivors = resolve_overlaps(masks, lb.image_h, lb.image_w, options.min_mask_area)
    chosen = kept[survivors]
    names = tuple(options.rename(class_name(class_names, int(c))) for c in classes[chosen])
    return Segmentation(ids, names, tuple(float(s) for s in scores[chosen]))


def class_name(class_names: tuple[str, ...], index: int) -> str:
    return class_names[index] if index < len(class_names) else f"class_{index}"
