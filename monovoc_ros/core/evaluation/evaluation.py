"""Evaluation as in the paper (METHOD section 6): render the labeled point cloud, compare to the masks.

`render_point_labels` projects the Gaussian centres into a camera, drops points closer than the near
plane (z <= 0.2 m, the rasterizer's near plane, which also removes everything behind the camera),
sorts by depth and draws each point as a disc of world size `point_size` (projected radius
``fx * point_size / z`` pixels, covering the pixel centres within it and at least the pixel its centre
falls in); the nearest point wins every pixel. Gaussians labeled ``UNOBSERVED_ID`` are not drawn, and
pixels no point covers keep `background` (void by default, so they match void reference pixels).

`render_splat_labels` is the second protocol: the semantic map rendered the way the SLAM system
renders the map itself, through the Gaussians (alpha compositing, METHOD section 2). Each pixel takes
the label whose Gaussians carry the largest summed compositing weight there; unlabeled Gaussians and
the background (final transmittance) compete as "void". Disc rendering of centres has an error floor
of its own at object edges (discs of 5 cm spill over silhouettes); splatting measures what a robot
rendering the semantic map would see.

`SegmentationEvaluator` accumulates pixel counts over frames. ``mismatch_all`` is the share of pixels
whose label differs from the reference; ``mismatch_nonwhite`` the same over pixels whose reference is
not void. IoU is per object, objects being the ids seen in the references; void reference pixels are
ignored for IoU (a prediction there is neither right nor wrong), and IoUs are computed from counts
summed over all frames (dataset-level IoU), then averaged over objects (``miou``). Predictions of
another size are resized to the reference with nearest-neighbour sampling at pixel centres (no
interpolation, so no blended labels).
"""

from __future__ import annotations

import numpy as np

from monovoc_ros.core.evaluation.evaluation_kernels import splat_discs
from monovoc_ros.core.evidence.palette import UNOBSERVED_ID, VOID_ID
from monovoc_ros.core.map.camera import Intrinsics, invert_pose, resize_nearest, validate_pose
from monovoc_ros.core.map.gaussians import GaussianMap

NEAR_PLANE = 0.2  # metres; the rasterizer's near plane (METHOD section 2)


def _project(
    points: np.ndarray,
    labels: np.ndarray,
    intrinsics: Intrinsics,
    cam_to_world: np.ndarray,
    point_size: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pixel coordinates, radii, labels and depths of the points to draw, nearest first."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points: expected shape (N, 3), got {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("points: contains NaN or infinite values")
    labels = np.asarray(labels)
    if labels.shape != (points.shape[0],) or labels.dtype.kind not in "iu":
        raise ValueError(f"labels: expected ({points.shape[0]},) integer ids, got {labels.shape} {labels.dtype}")
    if labels.size and (labels.min() < 0 or labels.max() > UNOBSERVED_ID):
        raise ValueError("labels: ids must fit in uint32")
    if not (np.isfinite(point_size) and point_size > 0):
        raise ValueError(f"point_size must be > 0, got {point_size}")
    world_to_cam = invert_pose(validate_pose(cam_to_world, what="cam_to_world"))
    cam = points @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
    z = cam[:, 2]
    keep = (z > NEAR_PLANE) & (labels != UNOBSERVED_ID)
    cam, z, labels = cam[keep], z[keep], labels[keep].astype(np.uint32)
    u = intrinsics.fx * cam[:, 0] / z + intrinsics.cx
    v = intrinsics.fy * cam[:, 1] / z + intrinsics.cy
    r = intrinsics.fx * point_size / z
    # Discs wholly off the image (centre pixel included) cannot draw anything.
    w, h = intrinsics.width, intrinsics.height
    reach = np.maximum(r, 0.5)
    on = (u + reach >= -0.5) & (u - reach <= w - 0.5) & (v + reach >= -0.5) & (v - reach <= h - 0.5)
    u, v, r, labels, z = u[on], v[on], r[on], labels[on], z[on]
    order = np.argsort(z, kind="stable")  # equal depths: the lower point index wins
    return u, v, r, labels, order


def render_point_labels(
    points: np.ndarray,
    labels: np.ndarray,
    intrinsics: Intrinsics,
    cam_to_world: np.ndarray,
    *,
    point_size: float = 0.05,
    background: int = VOID_ID,
) -> np.ndarray:
    """(H, W) uint32 label image of the point cloud `points` (N, 3) labeled `labels` (N,) seen from
    `cam_to_world` (OpenCV optical frame) with `intrinsics`."""
    u, v, r, labels, order = _project(points, labels, intrinsics, cam_to_world, point_size)
    return splat_discs(u, v, r, labels, order, intrinsics.height, intrinsics.width, np.uint32(background))


def render_point_labels_reference(
    points: np.ndarray,
    labels: np.ndarray,
    intrinsics: Intrinsics,
    cam_to_world: np.ndarray,
    *,
    point_size: float = 0.05,
    background: int = VOID_ID,
) -> np.ndarray:
    """Plain twin of `render_point_labels`: painter's algorithm, farthest first, nearer discs overwrite."""
    u, v, r, labels, order = _project(points, labels, intrinsics, cam_to_world, point_size)
    h, w = intrinsics.height, intrinsics.width
    image = np.full((h, w), background, np.uint32)
    ys, xs = np.mgrid[0:h, 0:w]
    for i in order[::-1]:
        x0, x1 = max(int(np.ceil(u[i] - r[i])), 0), min(int(np.floor(u[i] + r[i])), w - 1)
        y0, y1 = max(int(np.ceil(v[i] - r[i])), 0), min(int(np.floor(v[i] + r[i])), h - 1)
        if x0 <= x1 and y0 <= y1:
            box = (slice(y0, y1 + 1), slice(x0, x1 + 1))
            inside = (xs[box] - u[i]) ** 2 + (ys[box] - v[i]) ** 2 <= r[i] * r[i]
            image[box][inside] = labels[i]
        px, py = int(np.floor(u[i] + 0.5)), int(np.floor(v[i] + 0.5))
        if 0 <= px < w and 0 <= py < h:
            image[py, px] = labels[i]
    return image


def render_splat_labels(
    gmap: GaussianMap,
    labels: np.ndarray,
    intrinsics: Intrinsics,
    cam_to_world: np.ndarray,
    *,
    impl: str = "numba",
    background: int = VOID_ID,
) -> np.ndarray:
    """(H, W) uint32 label image of the Gaussians `gmap` labeled `labels` (N,), alpha-composited.

    Labels are rendered three at a time as one-hot colors through `core.raster.render`, so the
    per-label weights are exactly the rasterizer's w_ip summed per label.
    """
    from monovoc_ros.core.raster import render  # deferred: the rasterizer pulls in numba at import

    labels = np.asarray(labels, np.uint32)
    if labels.shape != (len(gmap),):
        raise ValueError(f"labels: expected shape ({len(gmap)},), got {labels.shape}")
    known = (labels != UNOBSERVED_ID) & (labels != background)
    classes, index = np.unique(labels[known], return_inverse=True)
    slot = np.full(len(gmap), -1, np.int64)
    slot[known] = index
    weights = np.zeros((intrinsics.height, intrinsics.width, len(classes) + 1), np.float32)
    for first in range(0, max(len(classes), 1), 3):
        onehot = np.zeros((len(gmap), 3), np.float32)
        for c in range(3):
            onehot[slot == first + c, c] = 1.0
        rendering = render(gmap, onehot, intrinsics, cam_to_world, impl=impl)
        n = min(3, len(classes) - first)
        weights[..., first : first + n] = rendering.image[..., :n]
    # Partition of unity: what the labels leave is the unlabeled Gaussians' weight plus the final
    # transmittance (the background), which compete together as void.
    weights[..., -1] = 1.0 - weights[..., :-1].sum(axis=2)
    table = np.append(classes, np.uint32(background)).astype(np.uint32)
    return table[np.argmax(weights, axis=2)]


class SegmentationEvaluator:
    """Accumulates rendered-vs-reference label agreement over frames (see the module docstring)."""

    def __init__(self, void_id: int = VOID_ID) -> None:
        self.void_id = int(void_id)
        self.frames = 0
        self.pixels = 0
        self.pixels_nonvoid = 0
        self.mismatched = 0
        self.mismatched_nonvoid = 0
        self.ref_pixels: dict[int, int] = {}  # per object: reference pixels
        self.pred_pixels: dict[int, int] = {}  # per id: predicted pixels where the reference is not void
        self.intersection: dict[int, int] = {}  # per object: pixels where both agree

    def update(self, pred: np.ndarray, ref: np.ndarray) -> dict:
        """Adds one frame (`pred`, `ref`: (H, W) integer label images, e.g. packed colors) and returns
        that frame's mismatch ratios."""
        pred, ref = np.asarray(pred), np.asarray(ref)
        for name, image in (("pred", pred), ("ref", ref)):
            if image.ndim != 2 or image.dtype.kind not in "iu" or image.size == 0:
                raise ValueError(
                    f"{name}: expected a non-empty (H, W) integer label image, got {image.shape} {image.dtype}"
                )
        if pred.shape != ref.shape:
            pred = resize_nearest(pred, *ref.shape)
        if min(pred.min(), ref.min()) < 0 or max(pred.max(), ref.max()) > UNOBSERVED_ID:
            raise ValueError("pred and ref labels must fit in uint32")
        pred, ref = pred.astype(np.uint32, copy=False), ref.astype(np.uint32, copy=False)
        wrong = pred != ref
        valid = ref != self.void_id
        n_wrong, n_valid = int(wrong.sum()), int(valid.sum())
        n_wrong_valid = int((wrong & valid).sum())
        self.frames += 1
        self.pixels += ref.size
        self.pixels_nonvoid += n_valid
        self.mismatched += n_wrong
        self.mismatched_nonvoid += n_wrong_valid
        # One pass over (reference, prediction) pairs gives all three per-id counts.
        pairs, counts = np.unique(
            (ref[valid].astype(np.uint64) << 32) | pred[valid].astype(np.uint64), return_counts=True
        )
        for key, count in zip(pairs.tolist(), counts.tolist(), strict=True):
            r, p = key >> 32, key & 0xFFFFFFFF
            self.ref_pixels[r] = self.ref_pixels.get(r, 0) + count
            self.pred_pixels[p] = self.pred_pixels.get(p, 0) + count
            if r == p:
                self.intersection[r] = self.intersection.get(r, 0) + count
        return {
            "mismatch_all": n_wrong / ref.size,
            "mismatch_nonwhite": n_wrong_valid / n_valid if n_valid else float("nan"),
        }

    def result(self) -> dict:
        """Ratios over all frames so far (NaN where nothing was counted) and per-object IoU."""
        iou = {}
        for obj, ref_count in sorted(self.ref_pixels.items()):
            inter = self.intersection.get(obj, 0)
            iou[obj] = inter / (ref_count + self.pred_pixels.get(obj, 0) - inter)
        nan = float("nan")
        return {
            "frames": self.frames,
            "pixels": self.pixels,
            "pixels_nonwhite": self.pixels_nonvoid,
            "mismatched": self.mismatched,
            "mismatched_nonwhite": self.mismatched_nonvoid,
            "mismatch_all": self.mismatched / self.pixels if self.pixels else nan,
            "mismatch_nonwhite": self.mismatched_nonvoid / self.pixels_nonvoid if self.pixels_nonvoid else nan,
            "iou": iou,
            "miou": float(np.mean(list(iou.values()))) if iou else nan,
            "object_pixels": dict(sorted(self.ref_pixels.items())),
        }
