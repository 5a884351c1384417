"""The segmenter (monovoc_ros.segment): letterbox, both YOLO-seg ONNX layouts held against the plain twin,
overlaps, options, and every kind of bad model file failing at load with one clear line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from segment_reference import random_raw, reference_decode, tiny_model

from monovoc_ros.segment.backend import SegmenterModelError, load_segmenter
from monovoc_ros.segment.letterbox import PAD_VALUE, Letterbox
from monovoc_ros.segment.model_files import DEFAULT_MODEL, resolve_model
from monovoc_ros.segment.options import SegmenterOptions, parse_class_map
from monovoc_ros.segment.yolo_decode import ModelLayoutError, detect_layout, nms

NAMES = ["chair", "couch", "potted plant", "tv", "dining table"]
M = 8  # mask coefficients of the tiny models
INPUT_HW = (64, 96)
PROTO_HW = (16, 24)  # stride 4, as YOLO's prototypes


@pytest.mark.parametrize("shape", [(340, 600), (480, 640), (640, 480), (37, 1000), (64, 96), (1, 5000), (5000, 1)])
def test_letterbox_round_trip(shape):
    h, w = shape
    for lb in (Letterbox.fit(h, w, *INPUT_HW), Letterbox.rect(h, w, 640, 32)):
        assert lb.input_h % 1 == 0 and lb.resized_h <= lb.input_h and lb.resized_w <= lb.input_w
        boxes = np.array([[0, 0, w, h], [w * 0.25, h * 0.1, w * 0.5, h * 0.9]])
        np.testing.assert_allclose(lb.boxes_to_image(lb.boxes_to_input(boxes)), boxes, atol=1e-9)
        full = lb.boxes_to_input(boxes[:1])[0]
        np.testing.assert_allclose(full, [lb.left, lb.top, lb.left + lb.resized_w, lb.top + lb.resized_h])
        image = np.full((h, w, 3), 7, np.uint8)
        tensor = lb.apply(image)
        assert tensor.shape == (1, 3, lb.input_h, lb.input_w) and tensor.dtype == np.float32
        inside = tensor[0, :, lb.top : lb.top + lb.resized_h, lb.left : lb.left + lb.resized_w]
        np.testing.assert_allclose(inside, 7 / 255, atol=1e-6)
        assert np.isclose(
            tensor.sum(), (7 * inside[0].size + PAD_VALUE * (tensor[0, 0].size - inside[0].size)) * 3 / 255, rtol=1e-4
        )
    rect = Letterbox.rect(340, 600, 640, 32)
    assert (rect.input_h, rect.input_w) == (384, 640)


@pytest.mark.parametrize("layout", ["yolov5", "yolov8"])
@pytest.mark.parametrize("agnostic", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_decode_matches_the_plain_twin(tmp_path, layout, agnostic, seed):
    rng = np.random.default_rng(seed)
    pred, proto = random_raw(rng, layout, 60, len(NAMES), M, INPUT_HW, PROTO_HW)
    path = tiny_model(tmp_path / "m.onnx", pred, proto, INPUT_HW, NAMES)
    options = SegmenterOptions(score_threshold=0.2, nms_iou=0.5, class_agnostic=agnostic, min_mask_area=5)
    seg = load_segmenter(model=str(path), options=options, prefer_cuda=False)
    assert seg.layout == layout
    image = rng.integers(0, 255, (45, 100, 3), dtype=np.uint8)
    got = seg.segment(image)
    ids, names, scores = reference_decode(pred, proto, layout, seg.letterbox(45, 100), NAMES, options)
    assert got.count >= 2, "the case must exercise several instances"
    assert got.names == names
    np.testing.assert_allclose(got.scores, scores, rtol=1e-6)
    assert np.mean(got.ids != ids) < 1e-3
    assert got.ids.shape == (45, 100) and got.ids.dtype == np.uint16
    assert int(got.ids.max()) == got.count


def test_nms_against_pairwise_loops():
    rng = np.random.default_rng(5)
    boxes = np.concatenate([rng.uniform(0, 50, (80, 2)), np.zeros((80, 2))], axis=1)
    boxes[:, 2:] = boxes[:, :2] + rng.uniform(5, 30, (80, 2))
    scores = rng.uniform(0, 1, 80)
    from segment_reference import iou

    kept = []
    for i in np.argsort(-scores, kind="stable"):
        if all(iou(boxes[k], boxes[i]) <= 0.4 for k in kept):
            kept.append(i)
    assert nms(boxes, scores, 0.4).tolist() == kept


def _two_boxes(layout: str, confs: tuple[float, float], classes=(0, 1)):
    """Two overlapping candidates whose masks fill their boxes (positive constant prototypes)."""
    boxes = [[40, 32, 40, 40], [56, 32, 40, 40]]  # cx, cy, w, h in the 64x96 input
    rows = []
    for box, conf, c in zip(boxes, confs, classes, strict=False):
        cls = np.zeros(len(NAMES))
        cls[c] = 1.0 if layout == "yolov5" else conf
        obj = [conf] if layout == "yolov5" else []
        rows.append([*box, *obj, *cls, *np.ones(M)])
    rows += [np.zeros(len(rows[0]))] * 40  # empty candidates, as a real model's many anchors
    pred = np.array(rows, np.float32)[None]
    if layout == "yolov8":
        pred = np.ascontiguousarray(pred.transpose(0, 2, 1))
    return pred, np.ones((1, M) + PROTO_HW, np.float32)


@pytest.mark.parametrize("layout", ["yolov5", "yolov8"])
def test_overlaps_go_to_the_highest_score(tmp_path, layout):
    for confs in ((0.9, 0.6), (0.6, 0.9)):
        pred, proto = _two_boxes(layout, confs)
        path = tiny_model(tmp_path / f"{confs[0]}.onnx", pred, proto, INPUT_HW, NAMES)
        seg = load_segmenter(model=str(path), options=SegmenterOptions(nms_iou=0.9), prefer_cuda=False)
        out = seg.segment(np.zeros(INPUT_HW + (3,), np.uint8))
        assert out.count == 2
        best = int(np.argmax(confs))
        assert out.names[0] == NAMES[best] and out.scores[0] == pytest.approx(max(confs))
        overlap = out.ids[12:52, 40:56]  # both boxes cover columns 36..60
        assert (overlap == 1).all(), "the more confident instance owns every shared pixel"
        assert (out.ids[12:52, 20:36] == (2 if best == 1 else 1)).all()


def test_options_class_map_max_instances_and_min_area(tmp_path):
    pred, proto = _two_boxes("yolov5", (0.9, 0.6))
    path = tiny_model(tmp_path / "m.onnx", pred, proto, INPUT_HW, NAMES)
    zero = np.zeros(INPUT_HW + (3,), np.uint8)

    def run(**kw):
        return load_segmenter(
            model=str(path),
            options=SegmenterOptions(**{"nms_iou": 0.9, "class_agnostic": False, **kw}),
            prefer_cuda=False,
        ).segment(zero)

    assert run(class_map={"chair": "seat"}).names == ("seat", "couch")
    assert run(class_map=["chair="]).names == ("couch",)  # dropped before suppression
    assert run(max_instances=1).names == ("chair",)
    assert run(score_threshold=0.7).names == ("chair",)
    # The weaker one keeps 16 x 40 visible pixels after the overlap: an area floor above that drops it.
    assert run(min_mask_area=16 * 40).count == 2 and run(min_mask_area=16 * 40 + 1).names == ("chair",)
    assert run(class_agnostic=True, nms_iou=0.3).names == ("chair",)  # IoU 0.43 across classes
    assert run(nms_iou=0.3).count == 2  # class-aware: different classes never suppress each other
    with pytest.raises(ValueError, match="class=new name"):
        parse_class_map(["chair"])
    with pytest.raises(ValueError, match="score_threshold"):
        SegmenterOptions(score_threshold=1.5)
    with pytest.raises(ValueError, match="class_agnostic"):
        SegmenterOptions(class_agnostic="yes")


def test_layouts_are_told_apart_by_shape():
    assert detect_layout([(1, 8400, 5 + 80 + 32), (1, 32, 160, 160)], 80)[0] == "yolov5"
    assert detect_layout([(1, 4 + 80 + 32, 8400), (1, 32, 160, 160)], 80)[0] == "yolov8"
    assert detect_layout([(1, 32, 160, 160), (1, 116, 8400)], None)[:2] == ("yolov8", 1)
    assert detect_layout([(1, 25200, 117), (1, 32, 160, 160)], None)[0] == "yolov5"
    for shapes, n in (
        ([(1, 8400, 100), (1, 32, 160, 160)], 80),
        ([(1, 100, 8400)], 80),
        ([(2, 8400, 117), (2, 32, 9, 9)], 80),
    ):
        with pytest.raises(ModelLayoutError):
            detect_layout(shapes, n)


def _one_line_error(tmp_path, model, **kw) -> str:
    with pytest.raises(SegmenterModelError) as info:
        load_segmenter(model=str(model), prefer_cuda=False, **kw)
    message = str(info.value)
    assert "\n" not in message and len(message) < 400
    return message


def test_bad_model_files_fail_at_load_with_one_line(tmp_path):
    assert "neither a file" in _one_line_error(tmp_path, tmp_path / "absent.onnx")
    (tmp_path / "empty.onnx").write_bytes(b"")
    assert "cannot be loaded" in _one_line_error(tmp_path, tmp_path / "empty.onnx")
    (tmp_path / "garbage.onnx").write_bytes(np.random.default_rng(0).bytes(4096))
    assert "cannot be loaded" in _one_line_error(tmp_path, tmp_path / "garbage.onnx")
    pred, proto = random_raw(np.random.default_rng(0), "yolov5", 20, len(NAMES), M, INPUT_HW, PROTO_HW)
    good = tiny_model(tmp_path / "good.onnx", pred, proto, INPUT_HW, NAMES)
    (tmp_path / "truncated.onnx").write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    assert "cannot be loaded" in _one_line_error(tmp_path, tmp_path / "truncated.onnx")
    # A valid graph that is not a YOLO-seg model: its layout is refused at load, not on the first image.
    wrong = tiny_model(tmp_path / "wrong.onnx", pred[:, :, :-3], proto, INPUT_HW, NAMES)
    assert "fit neither" in _one_line_error(tmp_path, wrong)
    # Class names that do not match the model's class count.
    names_file = tmp_path / "names.txt"
    names_file.write_text("a\nb\n")
    assert "fit neither" in _one_line_error(tmp_path, good, names_file=names_file)
    (tmp_path / "bad.yaml").write_text("names: {0: a, 5: b}\n")
    assert "indices" in _one_line_error(tmp_path, good, names_file=tmp_path / "bad.yaml")
    bad_meta = tiny_model(tmp_path / "meta.onnx", pred, proto, INPUT_HW, None)
    import onnx

    model = onnx.load(str(bad_meta))
    entry = model.metadata_props.add()
    entry.key, entry.value = "names", "{0: 'chair', 1: "
    onnx.save(model, str(bad_meta))
    assert "unreadable 'names'" in _one_line_error(tmp_path, bad_meta)


def test_names_from_a_file_and_without_names(tmp_path):
    pred, proto = _two_boxes("yolov5", (0.9, 0.6))
    unnamed = tiny_model(tmp_path / "unnamed.onnx", pred, proto, INPUT_HW, None)
    zero = np.zeros(INPUT_HW + (3,), np.uint8)
    opts = SegmenterOptions(nms_iou=0.9)
    assert load_segmenter(model=str(unnamed), options=opts, prefer_cuda=False).segment(zero).names == (
        "class_0",
        "class_1",
    )
    (tmp_path / "names.json").write_text('["seat", "sofa", "plant", "screen", "table"]')
    seg = load_segmenter(model=str(unnamed), options=opts, names_file=tmp_path / "names.json", prefer_cuda=False)
    assert seg.segment(zero).names == ("seat", "sofa")


def test_bad_images_are_refused(tmp_path):
    pred, proto = _two_boxes("yolov5", (0.9, 0.6))
    seg = load_segmenter(model=str(tiny_model(tmp_path / "m.onnx", pred, proto, INPUT_HW, NAMES)), prefer_cuda=False)
    for image in (np.zeros((0, 5, 3), np.uint8), np.zeros((10, 10), np.uint8), np.zeros((10, 10, 3), np.float32)):
        with pytest.raises(ValueError):
            seg.segment(image)


OFFICE = Path(__file__).resolve().parents[2] / "shared" / "data" / "replica_office0"


def test_the_default_model_segments_a_real_frame():
    """The installed default (exported by make install) on a real Replica frame: rectangular input, COCO
    names, the monitor found."""
    from monovoc_ros.core.evaluation.datasets import read_rgb

    resolve_model(DEFAULT_MODEL)  # raises with the export hint when the install step was skipped
    seg = load_segmenter(model=DEFAULT_MODEL, options=SegmenterOptions(score_threshold=0.25), prefer_cuda=False)
    assert len(seg.class_names) == 80 and seg.fixed_input is None
    if not OFFICE.is_dir():
        pytest.skip(f"{OFFICE} is missing (research-only data, read from ../shared)")
    rgb = read_rgb(sorted((OFFICE / "rgb").iterdir())[0])
    out = seg.segment(rgb)
    assert seg.letterbox(*rgb.shape[:2]).input_h == 384
    assert "tv" in out.names
    tv = out.names.index("tv") + 1
    assert (out.ids == tv).sum() > 5000  # the wall monitor spans ~40k pixels
