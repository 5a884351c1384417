"""The plain twin of monovoc_ros.segment.yolo_decode: the same decoding written the obvious way (loops over
candidates and pairs, every pixel's bilinear sample gathered directly), for the tests to hold the fast one to.
It also builds tiny YOLO-seg ONNX models of both export layouts with onnx.helper."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from monovoc_ros.segment.letterbox import Letterbox
from monovoc_ros.segment.options import SegmenterOptions


def reference_decode(pred, proto, layout, lb: Letterbox, names, options: SegmenterOptions):
    """(ids (H, W) uint16, names, scores) the plain way. ``pred`` (1, N, 5+C+M) or (1, 4+C+M, N)."""
    pred = np.asarray(pred, np.float64)[0]
    proto = np.asarray(proto, np.float64)[0]
    m, ph, pw = proto.shape
    if layout == "yolov8":
        pred = pred.T
    rows = []
    for row in pred:
        box = row[:4]
        if layout == "yolov5":
            obj, cls, coef = row[4], row[5 : len(row) - m], row[len(row) - m :]
        else:
            obj, cls, coef = None, row[4 : len(row) - m], row[len(row) - m :]
        c = int(np.argmax(cls))
        if obj is None:
            conf = cls[c]
        elif options.class_agnostic:
            conf = obj
        else:
            conf = obj * cls[c]
        if conf < options.score_threshold or box[2] <= 0 or box[3] <= 0 or options.rename(names[c]) == "":
            continue
        x0, y0 = box[0] - box[2] / 2, box[1] - box[3] / 2
        named = cls[c] if obj is None else obj * cls[c]  # the class's confidence names the segment
        rows.append((float(conf), c, (x0, y0, x0 + box[2], y0 + box[3]), coef, float(named)))
    rows.sort(key=lambda r: -r[0])
    kept = []
    for r in rows:
        suppressed = False
        for k in kept:
            if not options.class_agnostic and k[1] != r[1]:
                continue
            if iou(k[2], r[2]) > options.nms_iou:
                suppressed = True
                break
        if not suppressed:
            kept.append(r)
    kept = kept[: options.max_instances]
    H, W = lb.image_h, lb.image_w
    owner = np.full((H, W), -1, np.int64)
    ys, xs = np.mgrid[0:H, 0:W]
    # Image pixel centre -> input coordinate -> prototype coordinate (pixel centres), clamped at the edges.
    u = np.clip(((xs + 0.5) * lb.resized_w / W + lb.left) * pw / lb.input_w - 0.5, 0, pw - 1)
    v = np.clip(((ys + 0.5) * lb.resized_h / H + lb.top) * ph / lb.input_h - 0.5, 0, ph - 1)
    u0, v0 = np.floor(u).astype(int), np.floor(v).astype(int)
    u1, v1 = np.minimum(u0 + 1, pw - 1), np.minimum(v0 + 1, ph - 1)
    fu, fv = u - u0, v - v0
    for index in range(len(kept) - 1, -1, -1):
        _, _, box, coef, _ = kept[index]
        logit = np.tensordot(coef, proto, axes=1)
        sample = (
            logit[v0, u0] * (1 - fu) * (1 - fv)
            + logit[v0, u1] * fu * (1 - fv)
            + logit[v1, u0] * (1 - fu) * fv
            + logit[v1, u1] * fu * fv
        )
        bx0 = (box[0] - lb.left) * W / lb.resized_w
        bx1 = (box[2] - lb.left) * W / lb.resized_w
        by0 = (box[1] - lb.top) * H / lb.resized_h
        by1 = (box[3] - lb.top) * H / lb.resized_h
        inside = (xs + 0.5 >= bx0) & (xs + 0.5 < bx1) & (ys + 0.5 >= by0) & (ys + 0.5 < by1)
        owner[inside & (sample > 0)] = index
    ids = np.zeros((H, W), np.uint16)
    out_names, out_scores = [], []
    for index, (_, c, _, _, named) in enumerate(kept):
        area = int((owner == index).sum())
        if area >= max(options.min_mask_area, 1):
            out_names.append(options.rename(names[c]))
            out_scores.append(named)
            ids[owner == index] = len(out_names)
    return ids, tuple(out_names), tuple(out_scores)


def iou(a, b) -> float:
    w = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    h = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = w * h
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else 0.0


def random_raw(rng, layout: str, n: int, num_classes: int, m: int, input_hw: tuple[int, int], proto_hw):
    """Random but realistic raw outputs: boxes inside the input, clustered so that suppression matters."""
    h, w = input_hw
    centres = rng.uniform([0.2 * w, 0.2 * h], [0.8 * w, 0.8 * h], (max(1, n // 4), 2))
    pick = centres[rng.integers(0, len(centres), n)] + rng.normal(0, 2.0, (n, 2))
    sizes = rng.uniform([0.15 * w, 0.15 * h], [0.6 * w, 0.6 * h], (n, 2))
    obj = rng.uniform(0, 1, (n, 1))
    cls = rng.uniform(0, 1, (n, num_classes)) ** 3
    coef = rng.normal(0, 1, (n, m))
    parts = [pick, sizes] + ([obj] if layout == "yolov5" else []) + [cls, coef]
    pred = np.concatenate(parts, axis=1).astype(np.float32)[None]
    if layout == "yolov8":
        pred = np.ascontiguousarray(pred.transpose(0, 2, 1))
    proto = rng.normal(0, 1, (1, m) + tuple(proto_hw)).astype(np.float32)
    return pred, proto


def tiny_model(
    path: Path, pred: np.ndarray, proto: np.ndarray, input_hw: tuple[int, int], names: list[str] | None, stride=None
) -> Path:
    """An ONNX model with a fixed (1, 3, H, W) input whose outputs are ``pred`` and ``proto`` (plus 0 x the
    input's mean, so the input is used)."""
    h, w = input_hw
    zero = numpy_helper.from_array(np.zeros((), np.float32), "zero")
    nodes = [
        helper.make_node("ReduceMean", ["images"], ["mean"], keepdims=0),
        helper.make_node("Mul", ["mean", "zero"], ["nothing"]),
        helper.make_node("Constant", [], ["pred_c"], value=numpy_helper.from_array(pred, "pred_v")),
        helper.make_node("Constant", [], ["proto_c"], value=numpy_helper.from_array(proto, "proto_v")),
        helper.make_node("Add", ["pred_c", "nothing"], ["output0"]),
        helper.make_node("Add", ["proto_c", "nothing"], ["output1"]),
    ]
    graph = helper.make_graph(
        nodes,
        "tiny_yolo_seg",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, h, w])],
        [
            helper.make_tensor_value_info("output0", TensorProto.FLOAT, list(pred.shape)),
            helper.make_tensor_value_info("output1", TensorProto.FLOAT, list(proto.shape)),
        ],
        initializer=[zero],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    if names is not None:
        entry = model.metadata_props.add()
        entry.key, entry.value = "names", str(dict(enumerate(names)))
    if stride is not None:
        entry = model.metadata_props.add()
        entry.key, entry.value = "stride", str(stride)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path
