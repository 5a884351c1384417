"""Evaluation: point-label rendering (kernel vs reference, geometry by hand) and segmentation scores."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from monovoc_ros.core.evaluation.evaluation import (
    SegmentationEvaluator,
    render_point_labels,
    render_point_labels_reference,
    render_splat_labels,
)
from monovoc_ros.core.evidence.palette import UNOBSERVED_ID, VOID_ID, pack_rgb
from monovoc_ros.core.map.camera import Intrinsics, invert_pose, pose_from_translation_quat, resize_nearest

CAM = Intrinsics(100.0, 100.0, 10.0, 10.0, 21, 21)
EYE = np.eye(4)


def look_along_world_x() -> np.ndarray:
    """Camera at (0, 0, 1) whose optical axis is world +x (image x = world -y, image y = world -z)."""
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    T[:3, 3] = (0, 0, 1)
    return T


def test_disc_covers_pixel_centres_within_the_projected_radius():
    img = render_point_labels(np.array([[0.0, 0.0, 2.0]]), np.array([7], np.uint32), CAM, EYE)
    # r = fx * 0.05 / z = 2.5 px around pixel (10, 10): the 5x5 block without its 4 corners.
    ys, xs = np.nonzero(img == 7)
    assert len(ys) == 21
    assert ((xs - 10) ** 2 + (ys - 10) ** 2 <= 6.25).all()
    assert (img[img != 7] == VOID_ID).all() and img.dtype == np.uint32
    big = render_point_labels(np.array([[0.0, 0.0, 2.0]]), np.array([7], np.uint32), CAM, EYE, point_size=0.2)
    assert (big == 7).sum() == sum((x * x + y * y <= 100) for x in range(-10, 11) for y in range(-10, 11))


def test_tiny_discs_still_draw_their_centre_pixel():
    # z = 100 m: r = 0.05 px; the point at x = 0.0349 m lands at u = 10.0349 + ... -> pixel floor(u + 0.5).
    pts = np.array([[0.0, 0.0, 100.0], [0.6, -0.45, 100.0]])
    img = render_point_labels(pts, np.array([1, 2], np.uint32), CAM, EYE, background=0)
    assert img[10, 10] == 1
    assert img[round(10 - 0.45), round(10 + 0.6)] == 2  # u = 10.6 -> 11, v = 9.55 -> 10
    assert np.count_nonzero(img) == 2


def test_nearest_point_wins_and_hidden_points_are_dropped():
    near, far = [0.0, 0.0, 1.0], [0.0, 0.0, 3.0]
    for pts, labels in (([near, far], [1, 2]), ([far, near], [2, 1])):
        img = render_point_labels(np.array(pts), np.array(labels, np.uint32), CAM, EYE)
        assert img[10, 10] == 1
    # Equal depths: the lower point index wins.
    img = render_point_labels(np.array([near, near]), np.array([5, 6], np.uint32), CAM, EYE)
    assert img[10, 10] == 5
    # Behind the camera, in front of the near plane (z <= 0.2 m) and unobserved: nothing drawn.
    hidden = np.array([[0.0, 0.0, -2.0], [0.0, 0.0, 0.15], [0.0, 0.0, 0.2], [0.0, 0.0, 2.0]])
    labels = np.array([1, 2, 3, UNOBSERVED_ID], np.uint32)
    assert (render_point_labels(hidden, labels, CAM, EYE) == VOID_ID).all()


def test_pose_is_camera_to_world_in_optical_axes():
    T = look_along_world_x()
    pts = np.array([[3.0, 0.0, 1.0], [3.0, -0.3, 1.0], [3.0, 0.0, 0.7], [-3.0, 0.0, 1.0]])
    img = render_point_labels(pts, np.array([1, 2, 3, 4], np.uint32), CAM, T, point_size=0.001)
    assert img[10, 10] == 1  # straight ahead
    assert img[10, 20] == 2  # world -y is image right: u = 10 + 100 * 0.3 / 3
    assert img[20, 10] == 3  # world -z is image down
    assert not (img == 4).any()  # behind


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_kernel_matches_reference(seed):
    rng = np.random.default_rng(seed)
    intr = Intrinsics(60.0, 55.0, 31.5, 23.5, 64, 48)
    poses = [np.eye(4), pose_from_translation_quat(np.array([0.3, -1.0, 2.0]), np.array([0.9, 0.2, -0.3, 0.1]))]
    pose = (poses + [look_along_world_x()])[seed]
    n = 3000
    z = np.where(rng.random(n) < 0.1, rng.uniform(-1, 0.2, n), rng.uniform(2, 10, n))
    cam = np.column_stack([rng.uniform(-4, 4, n) * z / 4, rng.uniform(-3, 3, n) * z / 4, z])
    cam[:300, 2] = np.round(cam[:300, 2], 0)  # many exact depth ties
    points = cam @ pose[:3, :3].T + pose[:3, 3]
    labels = rng.integers(0, 40, n).astype(np.uint32)
    labels[rng.random(n) < 0.1] = UNOBSERVED_ID
    for size in (0.05, 0.003, 0.3):
        fast = render_point_labels(points, labels, intr, pose, point_size=size)
        slow = render_point_labels_reference(points, labels, intr, pose, point_size=size)
        np.testing.assert_array_equal(fast, slow)
        assert len(np.unique(fast)) > (10 if size < 0.1 else 3)


def test_render_bad_input():
    with pytest.raises(ValueError, match="points"):
        render_point_labels(np.zeros((3, 2)), np.zeros(3, np.uint32), CAM, EYE)
    with pytest.raises(ValueError, match="labels"):
        render_point_labels(np.zeros((3, 3)), np.zeros(2, np.uint32), CAM, EYE)
    with pytest.raises(ValueError, match="labels"):
        render_point_labels(np.zeros((3, 3)), np.zeros(3, np.float32), CAM, EYE)
    with pytest.raises(ValueError, match="point_size"):
        render_point_labels(np.zeros((3, 3)), np.zeros(3, np.uint32), CAM, EYE, point_size=0)
    with pytest.raises(ValueError, match="cam_to_world"):
        render_point_labels(np.zeros((3, 3)), np.zeros(3, np.uint32), CAM, np.eye(3))
    with pytest.raises(ValueError, match="NaN"):
        render_point_labels(np.full((1, 3), np.nan), np.zeros(1, np.uint32), CAM, EYE)


def test_evaluator_exact_counts():
    A, B, C, V = 0x112233, 0x445566, 0x778899, VOID_ID
    ref = np.array([[A, A, B, V], [A, A, B, V], [B, B, B, V], [C, V, V, V]], np.uint32)
    pred = np.array([[A, B, B, V], [A, A, B, A], [B, B, V, V], [V, V, B, C]], np.uint32)
    ev = SegmentationEvaluator()
    frame = ev.update(pred, ref)
    # Wrong: (0,1) A->B, (1,3) V->A, (2,2) B->V, (3,0) C->V, (3,2) V->B, (3,3) V->C.
    assert frame["mismatch_all"] == 6 / 16
    assert frame["mismatch_nonwhite"] == 3 / 10  # non-void reference: 4 A, 5 B, 1 C
    r = ev.result()
    assert (r["pixels"], r["pixels_nonwhite"], r["mismatched"], r["mismatched_nonwhite"]) == (16, 10, 6, 3)
    # IoU over non-void reference pixels: A: inter 3, ref 4, pred 3 -> 3/4; B: inter 4, ref 5, pred 5
    # -> 4/6; C: inter 0 -> 0. Predictions on void reference pixels (A, B, C there) do not count.
    assert r["iou"] == {A: 3 / 4, B: 4 / 6, C: 0.0}
    assert r["miou"] == pytest.approx((3 / 4 + 4 / 6) / 3)
    assert r["object_pixels"] == {A: 4, B: 5, C: 1}

    # A second frame accumulates counts (not ratios): a perfect frame with only A.
    ev.update(np.full((2, 2), A, np.uint32), np.full((2, 2), A, np.uint32))
    r = ev.result()
    assert r["frames"] == 2 and r["mismatch_all"] == 6 / 20 and r["mismatch_nonwhite"] == 3 / 14
    assert r["iou"][A] == 7 / 8


def test_evaluator_resizes_predictions_with_nearest():
    pred = np.array([[1, 2], [3, 4]], np.uint32)
    ref = np.kron(pred, np.ones((3, 2), np.uint32))
    np.testing.assert_array_equal(resize_nearest(pred, 6, 4), ref)
    ev = SegmentationEvaluator()
    assert ev.update(pred, ref) == {"mismatch_all": 0.0, "mismatch_nonwhite": 0.0}
    assert ev.result()["miou"] == 1.0
    # Downsampling picks the source pixel under each destination pixel centre.
    np.testing.assert_array_equal(resize_nearest(np.arange(6).reshape(1, 6), 1, 3), [[1, 3, 5]])


def test_evaluator_empty_and_bad_input():
    r = SegmentationEvaluator().result()
    assert r["frames"] == 0 and np.isnan(r["mismatch_all"]) and np.isnan(r["miou"]) and r["iou"] == {}
    ev = SegmentationEvaluator()
    all_void = ev.update(np.zeros((2, 2), np.uint32), np.full((2, 2), VOID_ID, np.uint32))
    assert all_void["mismatch_all"] == 1.0 and np.isnan(all_void["mismatch_nonwhite"])
    with pytest.raises(ValueError, match="pred"):
        ev.update(np.zeros((2, 2, 3), np.uint8), np.zeros((2, 2), np.uint32))
    with pytest.raises(ValueError, match="ref"):
        ev.update(np.zeros((2, 2), np.uint32), np.zeros((2, 2), np.float32))
    with pytest.raises(ValueError, match="uint32"):
        ev.update(np.full((2, 2), -1, np.int64), np.zeros((2, 2), np.uint32))


def test_replica_protocol_separates_right_from_wrong_labels(replica_office0):
    """Label each Gaussian centre with the mask pixel it projects to in the even keyframes, render it
    into odd keyframes: the error is the protocol's own floor (0.05 m discs bleed over edges), far
    below what shuffled labels give. Also pins the pose and pixel-centre conventions on real data."""
    from monovoc_ros.core.map.ply import load_ply

    intr = json.loads((replica_office0 / "intrinsics.json").read_text())
    intr = Intrinsics(intr["fx"], intr["fy"], intr["cx"], intr["cy"], intr["width"], intr["height"])
    poses = np.loadtxt(replica_office0 / "traj.txt").reshape(-1, 4, 4)
    points = load_ply(replica_office0 / "gaussians.ply").means.astype(np.float64)

    def mask(i: int) -> np.ndarray:
        return pack_rgb(cv2.imread(str(replica_office0 / "masks" / f"{i:06d}.png"))[:, :, ::-1].copy())

    labels = np.full(len(points), UNOBSERVED_ID, np.uint32)
    for i in range(0, 81, 6):
        w2c = invert_pose(poses[i])
        cam = points @ w2c[:3, :3].T + w2c[:3, 3]
        z = np.where(cam[:, 2] > 0.2, cam[:, 2], np.inf)
        u = np.floor(intr.fx * cam[:, 0] / z + intr.cx + 0.5).astype(np.int64)
        v = np.floor(intr.fy * cam[:, 1] / z + intr.cy + 0.5).astype(np.int64)
        ok = np.isfinite(z) & (u >= 0) & (u < intr.width) & (v >= 0) & (v < intr.height) & (labels == UNOBSERVED_ID)
        labels[ok] = mask(i)[v[ok], u[ok]]
    assert (labels != UNOBSERVED_ID).mean() > 0.95

    shuffled = labels.copy()
    np.random.default_rng(0).shuffle(shuffled)
    right, wrong = SegmentationEvaluator(), SegmentationEvaluator()
    for i in range(3, 81, 16):
        ref = mask(i)
        right.update(render_point_labels(points, labels, intr, poses[i]), ref)
        wrong.update(render_point_labels(points, shuffled, intr, poses[i]), ref)
    good, bad = right.result(), wrong.result()
    assert good["mismatch_nonwhite"] < 0.15 and good["miou"] > 0.45
    assert bad["mismatch_nonwhite"] > 0.6 and bad["miou"] < 0.2


def test_render_splat_labels_matches_argmax_of_reference_weights():
    """Each pixel takes the label with the largest summed compositing weight (void = the rest)."""
    from monovoc_ros.core.map.gaussians import GaussianMap
    from monovoc_ros.core.raster.reference import pixel_weights

    rng = np.random.default_rng(3)
    n = 120
    gmap = GaussianMap(
        means=np.column_stack([rng.uniform(-0.6, 0.6, n), rng.uniform(-0.4, 0.4, n), rng.uniform(1.5, 3.0, n)]),
        scales=rng.uniform(0.02, 0.12, (n, 3)),
        quats=rng.normal(size=(n, 4)),
        opacities=rng.uniform(0.3, 0.95, n),
    )
    intr = Intrinsics(60.0, 60.0, 31.5, 23.5, 64, 48)
    pose = np.eye(4)
    palette = np.array([0x102030, 0x405060, 0x708090, 0xA0B0C0, 0x00FF00], np.uint32)
    labels = palette[rng.integers(0, len(palette), n)]
    labels[:15] = UNOBSERVED_ID
    out = render_splat_labels(gmap, labels, intr, pose)

    W, T = pixel_weights(gmap, intr, pose)
    classes = np.unique(labels[labels != UNOBSERVED_ID])
    per_class = np.stack([W[:, labels == c].sum(1) for c in classes] + [1.0 - W[:, labels != UNOBSERVED_ID].sum(1)], 1)
    expect = np.append(classes, VOID_ID)[per_class.argmax(1)].reshape(48, 64)
    # Ties within float32 rounding may pick either label; they are vanishingly rare on random scenes.
    assert (out == expect).mean() > 0.999
    assert set(np.unique(out)) - set(classes) <= {VOID_ID}
    assert (out == VOID_ID).any() and (out != VOID_ID).any()
