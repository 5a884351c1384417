"""``sensor_msgs/CameraInfo`` <-> ``Intrinsics``.

Which image the intrinsics describe: the image as published, i.e. after the driver's ROI crop and
binning (REP-104: K is for the full-resolution sensor; ``roi`` is in full-resolution pixels; binning
0 or 1 means none), optionally resampled to a target resolution (e.g. the segmentation masks).
Crop is a pure shift; binning and resampling keep pixel centres (``Intrinsics.scaled_to``).

Distortion: MonoVoc projects with a pure pinhole model. By default a CameraInfo with any non-zero
distortion coefficient is rejected, because its K does not describe the raw image exactly. For a
rectified image (``image_rect``) pass ``rectified=True``: the pinhole is then the left 3x3 block of
P, and D does not apply. ``allow_distortion=True`` uses K and ignores D (check
``has_distortion`` to warn): only sensible when the distortion is negligible.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from monovoc_ros.core.map.camera import Intrinsics
from msg_adapters.errors import AdapterError
from msg_adapters.stamps import make_header

# Plausibility bounds: a camera outside them is a corrupt or hostile message, not a lens. fx = fy = 1e-30
# projected everything onto one pixel (garbage evidence); a 2^32 x 2^32 camera asked for 2^64-pixel images.
MAX_IMAGE_SIDE = 16384
FOCAL_RANGE = (0.05, 50.0)  # focal length / image width: ~175 degrees to ~1 degree of horizontal field of view


def has_distortion(msg: Any) -> bool:
    """True when the CameraInfo lists any non-zero distortion coefficient."""
    d = np.asarray(msg.d, dtype=np.float64).reshape(-1)
    return bool(np.any(d != 0.0))


def _effective_size_and_matrix(msg: Any, rectified: bool) -> tuple[np.ndarray, int, int]:
    width, height = int(msg.width), int(msg.height)
    if width <= 0 or height <= 0:
        raise AdapterError(f"CameraInfo: invalid image size {width}x{height}")
    if width > MAX_IMAGE_SIDE or height > MAX_IMAGE_SIDE:
        raise AdapterError(f"CameraInfo: image size {width}x{height} exceeds {MAX_IMAGE_SIDE} pixels per side")
    if rectified:
        P = np.asarray(msg.p, dtype=np.float64).reshape(-1)
        if P.size != 12:
            raise AdapterError(f"CameraInfo: p has {P.size} values, expected 12")
        K = P.reshape(3, 4)[:, :3].copy()
        what = "P"
    else:
        K = np.asarray(msg.k, dtype=np.float64).reshape(-1)
        if K.size != 9:
            raise AdapterError(f"CameraInfo: k has {K.size} values, expected 9")
        K = K.reshape(3, 3).copy()
        what = "K"
    if not np.all(np.isfinite(K)):
        raise AdapterError(f"CameraInfo: {what} contains NaN or infinite values")
    if not np.any(K):
        raise AdapterError(f"CameraInfo: {what} is all zero (uncalibrated camera)")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[0, 1] != 0 or not np.allclose(K[2], (0.0, 0.0, 1.0)):
        raise AdapterError(f"CameraInfo: {what} is not a pinhole matrix with positive focal lengths: {K.tolist()}")
    lo, hi = FOCAL_RANGE
    for name, f in (("fx", K[0, 0]), ("fy", K[1, 1])):
        if not lo * width <= f <= hi * width:
            raise AdapterError(
                f"CameraInfo: {name} = {f:g} is implausible for a {width} pixel wide image "
                f"(expected {lo:g}..{hi:g} x width = {lo * width:g}..{hi * width:g})"
            )

    roi = msg.roi
    x0, y0, rw, rh = int(roi.x_offset), int(roi.y_offset), int(roi.width), int(roi.height)
    if rw or rh or x0 or y0:
        if rw == 0 or rh == 0:
            raise AdapterError(f"CameraInfo: roi {rw}x{rh}+{x0}+{y0} has a zero width or height")
        if x0 + rw > width or y0 + rh > height:
            raise AdapterError(f"CameraInfo: roi {rw}x{rh}+{x0}+{y0} exceeds the {width}x{height} sensor")
        K[0, 2] -= x0
        K[1, 2] -= y0
        width, height = rw, rh
    bx, by = max(int(msg.binning_x), 1), max(int(msg.binning_y), 1)
    if bx > 1 or by > 1:
        if width % bx or height % by:
            raise AdapterError(f"CameraInfo: {width}x{height} is not divisible by binning {bx}x{by}")
        binned = Intrinsics.from_K(K, width, height).scaled_to(width // bx, height // by)
        K, width, height = binned.K, binned.width, binned.height
    return K, width, height


def camera_info_to_intrinsics(
    msg: Any,
    width: int | None = None,
    height: int | None = None,
    *,
    rectified: bool = False,
    allow_distortion: bool = False,
) -> Intrinsics:
    """Pinhole intrinsics of the published image, rescaled to ``width`` x ``height`` when given.

    Raises AdapterError for uncalibrated or malformed CameraInfo, and for non-zero distortion unless
    ``rectified`` or ``allow_distortion`` (see the module docstring).
    """
    if not rectified and not allow_distortion and has_distortion(msg):
        d = np.round(np.asarray(msg.d, dtype=np.float64).reshape(-1), 6).tolist()
        raise AdapterError(
            f"CameraInfo: non-zero distortion ({msg.distortion_model or 'unnamed model'}, d={d}); "
            "use the rectified image with rectified=True, or allow_distortion=True to ignore it"
        )
    K, w, h = _effective_size_and_matrix(msg, rectified)
    intrinsics = Intrinsics.from_K(K, w, h)
    if (width is None) != (height is None):
        raise AdapterError("camera_info_to_intrinsics: give both width and height, or neither")
    if width is not None and (int(width), int(height)) != (w, h):
        if int(width) <= 0 or int(height) <= 0:
            raise AdapterError(f"camera_info_to_intrinsics: invalid target size {width}x{height}")
        intrinsics = intrinsics.scaled_to(int(width), int(height))
    return intrinsics


def intrinsics_to_camera_info(intrinsics: Intrinsics, *, frame_id: str = "", stamp: Any = 0):
    """A ``sensor_msgs.msg.CameraInfo`` for an undistorted pinhole camera (plumb_bob, D = 0, R = I)."""
    from sensor_msgs.msg import CameraInfo

    K = intrinsics.K
    P = np.zeros((3, 4))
    P[:, :3] = K
    msg = CameraInfo(header=make_header(frame_id, stamp), width=intrinsics.width, height=intrinsics.height)
    msg.distortion_model = "plumb_bob"
    msg.d = [0.0] * 5
    msg.k = K.reshape(-1).tolist()
    msg.r = np.eye(3).reshape(-1).tolist()
    msg.p = P.reshape(-1).tolist()
    return msg
