"""Sources of keyframes: one ``Sequence`` interface over datasets on disk and generated scenes, and views
of a sequence (``SequenceView``): ``CorruptedMasks`` (its masks through core.segments.segment_noise) and
``PaletteSegments`` (the class names a perfect segmenter would give).

Layouts read by ``open_sequence`` (conventions in core.map.camera: poses are camera-to-world, OpenCV axes):

``plain`` (what ``write_plain`` writes; ``../shared/data/replica_office0`` is one)
    rgb/NNNNNN.(jpg|png)   optional; any size (the RGB camera is the mask camera rescaled)
    masks/NNNNNN.png       palette-colored instance masks, (255, 255, 255) = void; RGB or indexed PNG
    traj.txt               one row-major 4x4 camera-to-world matrix per line, one line per mask
    intrinsics.json        {width, height, fx, fy, cx, cy} of the masks
    stamps.txt             optional: one integer timestamp in nanoseconds per line (else 10 Hz from 0)
    labels.json            optional: [{color: [r, g, b], instance_id, class_name, ...}, ...]
    gaussians.ply          optional: standard 3DGS PLY
    Frames are the mask files in sorted order; an RGB file must share its mask's stem.

``nice-slam`` (NICE-SLAM's Replica folders: ``results/frame%06d.jpg``, ``results/depth%06d.png``, ``traj.txt``)
    The RGB camera defaults to Replica's 1200x680, fx = fy = 600, cx 599.5, cy 339.5 (option ``intrinsics``).
    Masks are not part of it: option ``masks`` names a directory of palette PNGs named like the frames
    (``frame%06d.png`` or ``%06d.png``) or of vMAP ``semantic_instance_%d.png`` id images (or its parent),
    which are colorized with ``instance_palette`` (id 0 = void). Masks may have another size than the
    RGB; keyframe intrinsics are then the RGB camera's ``scaled_to`` the mask size. Option ``stride``
    keeps every n-th frame, ``gaussians`` names a PLY. Stamps: frame number at ``frame_rate`` Hz (10).

``hislam2`` (HI-SLAM2's output folder: ``3dgs_final.ply``, ``traj_kf.txt``, ``intrinsics.npy``)
    ``traj_kf.txt`` rows are ``t tx ty tz qx qy qz qw`` (camera-to-world, quaternion xyzw as written by
    lietorch) where ``t`` is the last number in the keyframe image's file name (HI-SLAM2 writes it so).
    ``intrinsics.npy`` holds fx fy cx cy for the image size HI-SLAM2 tracked at, 616x344 for Replica
    (option ``image_size=(w, h)`` otherwise). HI-SLAM2 stores no images: options ``masks`` (required)
    and ``rgb`` (optional) name directories; option ``match`` says how files pair with keyframes:
    ``"name"`` (default): the file whose last number in its name is nearest ``t``, at most ``tolerance``
    (default 1e-3) away;
    ``"order"``: the k-th file in sorted order is keyframe k (counts must match).
    Stamps: ``t`` in seconds when any ``t`` is fractional or above 1e6, else ``t`` is a frame number at
    ``frame_rate`` Hz.
"""

from __future__ import annotations

import functools
import json
import os
import re
import shutil
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from monovoc_ros.core.evidence.color import srgb_to_lab
from monovoc_ros.core.evidence.palette import labels_from_entries, pack_rgb, read_label_entries
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.camera import Intrinsics, pose_from_translation_quat, validate_pose
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.map.ply import load_ply, save_ply
from monovoc_ros.core.segments.segment_noise import NoiseRates, segment_noise, shuffle_ids

LAYOUTS = ("plain", "nice-slam", "hislam2")
REPLICA_INTRINSICS = Intrinsics(600.0, 600.0, 599.5, 339.5, 1200, 680)
HISLAM2_REPLICA_SIZE = (616, 344)
DEFAULT_FRAME_RATE = 10.0
NICE_SLAM_DEPTH_SCALE = 6553.5  # Replica depth PNG units per metre
_IMAGE_EXTS = (".png", ".jpg", ".jpeg")


class SequenceView:
    """A sequence seen through a change of its keyframes (`keyframe(i)`, e.g. corrupted masks or segment
    names); everything else is the wrapped sequence's, and `clean_mask(i)` is the original mask."""

    def __init__(self, sequence) -> None:
        self._seq = sequence

    def __getattr__(self, name):
        return getattr(self._seq, name)

    def __len__(self) -> int:
        return len(self._seq)

    def keyframe(self, i: int) -> Keyframe:
        return self._seq.keyframe(i)

    def clean_mask(self, i: int) -> np.ndarray:
        clean = getattr(self._seq, "clean_mask", None)
        return clean(i) if clean else self._seq.keyframe(i).mask


class CorruptedMasks(SequenceView):
    """A sequence whose keyframe masks went through `segment_noise` and then (with `shuffled`) a per-frame
    renumbering, deterministically per keyframe index and `seed`; `clean_mask` is the original."""

    def __init__(self, sequence, *, shuffled: bool = True, rates: NoiseRates | None = None, seed: int = 0) -> None:
        super().__init__(sequence)
        self.shuffled, self.rates, self.seed = bool(shuffled), rates or NoiseRates(), int(seed)

    def keyframe(self, i: int):
        kf = self._seq.keyframe(i)
        rng = np.random.default_rng([self.seed, i])
        mask = kf.mask
        if self.rates.any:
            mask, _ = segment_noise(mask, self.rates, rng)
        if self.shuffled:
            mask = shuffle_ids(mask, rng)
        segments = kf.segments
        if segments:  # the segmenter's names follow the renumbered, merged and split segments
            from monovoc_ros.core.segments.segment_labels import relabel_segments

            segments = relabel_segments(segments, pack_rgb(kf.mask), pack_rgb(mask))
        return replace(kf, mask=mask, segments=segments)


class PaletteSegments(SequenceView):
    """A sequence whose keyframes carry the segment labels a perfect segmenter would give: every mask
    color that the sequence's labels.json names gets its class name (score 1)."""

    def __init__(self, sequence) -> None:
        super().__init__(sequence)
        self.names = {oid: name for oid, name in labels_from_entries(sequence.labels()).items() if name}

    def keyframe(self, i: int):
        from monovoc_ros.core.segments.segment_labels import palette_segments

        kf = self._seq.keyframe(i)
        return replace(kf, segments=palette_segments(kf.mask, self.names))


class SequenceError(ValueError):
    """A sequence that cannot be read as asked; the message names the offending path."""


class Sequence:
    """Keyframes with poses, mask intrinsics, and optionally a Gaussian map and palette labels.

    Subclasses set ``name``, ``intrinsics`` (of the masks), ``poses`` ((K, 4, 4) camera-to-world) and
    ``stamps_ns`` ((K,) int64) and implement ``keyframe``.
    """

    name: str
    intrinsics: Intrinsics
    poses: np.ndarray
    stamps_ns: np.ndarray

    def __len__(self) -> int:
        return len(self.poses)

    def keyframe(self, i: int) -> Keyframe:
        raise NotImplementedError

    def __iter__(self) -> Iterator[Keyframe]:
        for i in range(len(self)):
            yield self.keyframe(i)

    def load_gaussians(self) -> GaussianMap | None:
        return None

    def labels(self) -> list[dict]:
        return []

    def _index(self, i: int) -> int:
        n = len(self)
        if not isinstance(i, int | np.integer) or not -n <= i < n:
            raise IndexError(f"{self.name}: keyframe index {i} out of range for {n} keyframes")
        return int(i) % n

    def __repr__(self) -> str:
        k = self.intrinsics
        return f"{type(self).__name__}({self.name!r}, {len(self)} keyframes, masks {k.width}x{k.height})"


# ---------------------------------------------------------------------------------------- file helpers


def _require_file(path: Path, what: str) -> Path:
    if not path.is_file():
        raise SequenceError(f"{path}: missing {what}")
    return path


def _require_dir(path: Path, what: str) -> Path:
    if not path.is_dir():
        raise SequenceError(f"{path}: missing {what} directory")
    return path


def _rigid(T: np.ndarray, where: str) -> np.ndarray:
    try:
        return validate_pose(T, what=where)
    except ValueError as exc:
        raise SequenceError(str(exc)) from None


def read_traj(path: str | os.PathLike) -> np.ndarray:
    """(K, 4, 4) camera-to-world poses from a file of one row-major 4x4 matrix (16 numbers) per line."""
    path = _require_file(Path(path), "trajectory file")
    poses = []
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        try:
            values = np.array([float(x) for x in line.split()])
        except ValueError:
            raise SequenceError(f"{path}:{n}: not a row of numbers: {line[:80]!r}") from None
        if values.size != 16:
            raise SequenceError(f"{path}:{n}: expected 16 numbers (a row-major 4x4 matrix), got {values.size}")
        poses.append(_rigid(values.reshape(4, 4), f"{path}:{n}"))
    if not poses:
        raise SequenceError(f"{path}: no poses")
    return np.stack(poses)


def read_tum_traj(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(stamps (K,), poses (K, 4, 4)) from ``t tx ty tz qx qy qz qw`` lines (camera-to-world, xyzw)."""
    path = _require_file(Path(path), "trajectory file")
    stamps, poses = [], []
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        try:
            v = np.array([float(x) for x in line.split()])
        except ValueError:
            raise SequenceError(f"{path}:{n}: not a row of numbers: {line[:80]!r}") from None
        if v.size != 8:
            raise SequenceError(f"{path}:{n}: expected 8 numbers 't tx ty tz qx qy qz qw', got {v.size}")
        if not np.all(np.isfinite(v)):
            raise SequenceError(f"{path}:{n}: contains NaN or infinite values")
        norm = np.linalg.norm(v[4:8])
        if abs(norm - 1.0) > 1e-3:
            raise SequenceError(f"{path}:{n}: quaternion norm {norm:.6f} is not 1 (not a rotation)")
        stamps.append(v[0])
        poses.append(_rigid(pose_from_translation_quat(v[1:4], v[[7, 4, 5, 6]]), f"{path}:{n}"))
    if not poses:
        raise SequenceError(f"{path}: no poses")
    return np.array(stamps), np.stack(poses)


def _read_image(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise SequenceError(f"{path}: cannot be read as an image")
    return img


def read_rgb(path: str | os.PathLike) -> np.ndarray:
    """(H, W, 3) uint8 RGB of an 8-bit color image file."""
    path = Path(path)
    img = _read_image(path)
    if img.dtype != np.uint8:
        raise SequenceError(f"{path}: expected an 8-bit image, got {img.dtype}")
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2)
    return np.ascontiguousarray(img[:, :, 2::-1])


def read_mask(path: str | os.PathLike) -> np.ndarray:
    """(H, W, 3) uint8 palette mask (RGB or indexed PNG; an alpha channel is dropped)."""
    path = Path(path)
    img = _read_image(path)
    if img.ndim != 3 or img.dtype != np.uint8:
        raise SequenceError(f"{path}: expected an 8-bit color mask, got shape {img.shape} {img.dtype}")
    return np.ascontiguousarray(img[:, :, 2::-1])


def write_mask(path: str | os.PathLike, mask: np.ndarray) -> None:
    mask = np.asarray(mask)
    if mask.ndim != 3 or mask.shape[2] != 3 or mask.dtype != np.uint8:
        raise SequenceError(f"{path}: a mask must be (H, W, 3) uint8, got {mask.shape} {mask.dtype}")
    if not cv2.imwrite(str(path), np.ascontiguousarray(mask[:, :, ::-1])):
        raise SequenceError(f"{path}: could not write")


@functools.cache
def _palette_table() -> np.ndarray:
    # Colors on a grid of multiples of 36 (0..252), in farthest-first order in CIELAB from pure red.
    levels = np.arange(0, 253, 36)
    grid = np.stack(np.meshgrid(levels, levels, levels, indexing="ij"), -1).reshape(-1, 3)
    lab = srgb_to_lab(grid)
    grid, lab = grid[lab[:, 0] < 95], lab[lab[:, 0] < 95]
    start = int(np.argmin(np.abs(grid - (252, 0, 0)).sum(axis=1)))
    order, dist = [start], np.linalg.norm(lab - lab[start], axis=1)
    for _ in range(254):
        k = int(np.argmax(dist))
        order.append(k)
        dist = np.minimum(dist, np.linalg.norm(lab - lab[k], axis=1))
    return grid[order].astype(np.uint8)


def instance_palette(ids: np.ndarray) -> np.ndarray:
    """Deterministic distinct colors (..., 3) uint8 for instance ids; id 0 is void (white).

    Ids 1..255 get well separated colors (multiples of 36 per channel, farthest first in CIELAB);
    larger ids (up to 2^18 + 255) get channel values of the form 4k + 1, so the two sets never collide.
    """
    ids = np.asarray(ids, dtype=np.int64)
    if ids.size and (ids.min() < 0 or ids.max() >= 255 + 64**3):
        raise SequenceError(f"instance ids must lie in 0..{254 + 64**3}, got {ids.min()}..{ids.max()}")
    table = _palette_table()
    out = np.full(ids.shape + (3,), 255, np.uint8)
    small = (ids >= 1) & (ids <= 255)
    out[small] = table[ids[small] - 1]
    big = ids > 255
    j = ids[big] - 256
    out[big] = (np.stack([(j >> 12) & 63, (j >> 6) & 63, j & 63], axis=-1) * 4 + 1).astype(np.uint8)
    return out


def _last_number(name: str) -> float | None:
    # HI-SLAM2 stamps a keyframe with the last number in its image's file name.
    found = re.findall(r"[+]?(?:\d*\.\d+|\d+)", Path(name).stem)
    return float(found[-1]) if found else None


def _images_in(directory: Path, exts: tuple[str, ...]) -> list[Path]:
    return sorted(p for p in directory.iterdir() if p.suffix.lower() in exts and p.is_file())


def _mask_intrinsics(camera: Intrinsics, first_mask: Path) -> Intrinsics:
    h, w = _read_image(first_mask).shape[:2]
    return camera if (w, h) == (camera.width, camera.height) else camera.scaled_to(w, h)


def _load_mask_any(path: Path) -> np.ndarray:
    """A palette mask, or an instance-id image (single channel, 8 or 16 bit) colorized by ``instance_palette``."""
    img = _read_image(path)
    if img.ndim == 2:
        if img.dtype not in (np.uint8, np.uint16):
            raise SequenceError(f"{path}: id images must be 8 or 16 bit, got {img.dtype}")
        return instance_palette(img)
    if img.dtype != np.uint8:
        raise SequenceError(f"{path}: expected an 8-bit color mask, got {img.dtype}")
    return np.ascontiguousarray(img[:, :, 2::-1])


def _make_keyframe(
    index: int, stamp: int, pose: np.ndarray, k: Intrinsics, mask: np.ndarray, rgb: np.ndarray | None, where: Path
) -> Keyframe:
    try:
        return Keyframe(index, int(stamp), pose.copy(), k, mask, rgb)
    except ValueError as exc:
        raise SequenceError(f"{where}: {exc}") from None


def _check_options(layout: str, options: dict, allowed: set[str]) -> None:
    unknown = set(options) - allowed
    if unknown:
        raise SequenceError(f"layout {layout!r} takes no option(s) {sorted(unknown)}; it takes {sorted(allowed)}")


def _stamps_from_frames(frames: np.ndarray, frame_rate: float) -> np.ndarray:
    return np.round(np.asarray(frames, dtype=np.float64) * 1e9 / frame_rate).astype(np.int64)


def _maybe_ply(path: Path | None) -> GaussianMap | None:
    return None if path is None else load_ply(_require_file(path, "Gaussian PLY"))


# ------------------------------------------------------------------------------------------- layouts


class PlainSequence(Sequence):
    """The ``plain`` layout (see the module docstring)."""

    def __init__(self, root: str | os.PathLike) -> None:
        self.root = _require_dir(Path(root), "sequence")
        self.name = self.root.name
        mask_dir = _require_dir(self.root / "masks", "masks")
        self.mask_files = _images_in(mask_dir, (".png",))
        if not self.mask_files:
            raise SequenceError(f"{mask_dir}: no PNG masks")
        self.rgb_files: list[Path] | None = None
        if (self.root / "rgb").is_dir():
            by_stem = {p.stem: p for p in _images_in(self.root / "rgb", _IMAGE_EXTS)}
            missing = [m.name for m in self.mask_files if m.stem not in by_stem]
            if missing:
                raise SequenceError(f"{self.root / 'rgb'}: no RGB image for mask(s) {missing[:5]}")
            self.rgb_files = [by_stem[m.stem] for m in self.mask_files]
        self.poses = read_traj(self.root / "traj.txt")
        if len(self.poses) != len(self.mask_files):
            raise SequenceError(
                f"{self.root / 'traj.txt'}: {len(self.poses)} poses but {len(self.mask_files)} masks in {mask_dir}"
            )
        self.intrinsics = read_intrinsics_json(self.root / "intrinsics.json")
        stamps_path = self.root / "stamps.txt"
        if stamps_path.exists():
            self.stamps_ns = read_stamps(stamps_path, len(self.poses))
        else:
            self.stamps_ns = _stamps_from_frames(np.arange(len(self.poses)), DEFAULT_FRAME_RATE)
        self._labels = []
        if (self.root / "labels.json").exists():
            try:
                self._labels = read_label_entries(self.root / "labels.json")
            except ValueError as exc:
                raise SequenceError(str(exc)) from None
        self.gaussians_path = self.root / "gaussians.ply" if (self.root / "gaussians.ply").exists() else None

    def keyframe(self, i: int) -> Keyframe:
        i = self._index(i)
        rgb = read_rgb(self.rgb_files[i]) if self.rgb_files is not None else None
        mask_path = self.mask_files[i]
        keyframe = _make_keyframe(
            i, self.stamps_ns[i], self.poses[i], self.intrinsics, read_mask(mask_path), rgb, mask_path
        )
        segments_path = self.root / "segments" / f"{mask_path.stem}.json"
        if segments_path.exists():  # a segmenter's class names per segment (core.segments.segment_labels)
            from monovoc_ros.core.segments.segment_labels import read_segments

            try:
                keyframe = replace(keyframe, segments=read_segments(segments_path))
            except (ValueError, KeyError, TypeError) as exc:
                raise SequenceError(f"{segments_path}: {exc}") from None
        return keyframe

    def load_gaussians(self) -> GaussianMap | None:
        return _maybe_ply(self.gaussians_path)

    def labels(self) -> list[dict]:
        return [dict(d) for d in self._labels]


def read_intrinsics_json(path: str | os.PathLike) -> Intrinsics:
    path = _require_file(Path(path), "intrinsics file")
    try:
        d = json.loads(path.read_text())
        return Intrinsics.from_dict(d)
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise SequenceError(f"{path}: expected {{width, height, fx, fy, cx, cy}}: {exc}") from None


def read_stamps(path: str | os.PathLike, count: int) -> np.ndarray:
    path = Path(path)
    lines = [s for s in path.read_text().split() if s]
    try:
        stamps = np.array([int(s) for s in lines], dtype=np.int64)
    except (ValueError, OverflowError):  # OverflowError: beyond int64
        raise SequenceError(f"{path}: expected one integer nanosecond timestamp (0 .. 2^63-1) per line") from None
    if len(stamps) != count:
        raise SequenceError(f"{path}: {len(stamps)} timestamps for {count} keyframes")
    if len(stamps) and stamps.min() < 0:
        raise SequenceError(f"{path}: negative timestamps")
    # A keyframe's stamp names it (the live node refuses a stamp it has integrated already).
    if np.any(np.diff(stamps) <= 0):
        raise SequenceError(f"{path}: timestamps decrease or repeat")
    return stamps


class NiceSlamSequence(Sequence):
    """NICE-SLAM's Replica layout with masks from elsewhere (see the module docstring)."""

    def __init__(
        self,
        root: str | os.PathLike,
        masks: str | os.PathLike | None = None,
        gaussians: str | os.PathLike | None = None,
        intrinsics: Intrinsics | dict | None = None,
        stride: int = 1,
        frame_rate: float = DEFAULT_FRAME_RATE,
    ) -> None:
        self.root = _require_dir(Path(root), "sequence")
        self.name = self.root.name
        results = _require_dir(self.root / "results", "results")
        if masks is None:
            raise SequenceError(f"{self.root}: the nice-slam layout has no masks; pass masks=DIRECTORY")
        if int(stride) < 1:
            raise SequenceError(f"{self.root}: stride must be >= 1, got {stride}")
        frames = {}
        for p in _images_in(results, (".jpg", ".png")):
            m = re.fullmatch(r"frame(\d+)", p.stem)
            if m:
                frames[int(m.group(1))] = p
        if not frames:
            raise SequenceError(f"{results}: no frame%06d.jpg images")
        traj = read_traj(self.root / "traj.txt")
        numbers = sorted(frames)[:: int(stride)]
        if numbers[-1] >= len(traj):
            raise SequenceError(
                f"{self.root / 'traj.txt'}: {len(traj)} poses but frames up to {numbers[-1]} in {results}"
            )
        self.frame_numbers = np.array(numbers)
        self.rgb_files = [frames[f] for f in numbers]
        self.poses = traj[self.frame_numbers]
        self.stamps_ns = _stamps_from_frames(self.frame_numbers, frame_rate)
        self.mask_files = [_find_mask(Path(masks), f) for f in numbers]
        camera = _as_intrinsics(intrinsics) if intrinsics is not None else REPLICA_INTRINSICS
        self.rgb_intrinsics = camera
        self.intrinsics = _mask_intrinsics(camera, self.mask_files[0])
        self.gaussians_path = Path(gaussians) if gaussians is not None else None

    def keyframe(self, i: int) -> Keyframe:
        i = self._index(i)
        mask = _load_mask_any(self.mask_files[i])
        rgb = read_rgb(self.rgb_files[i])
        return _make_keyframe(i, self.stamps_ns[i], self.poses[i], self.intrinsics, mask, rgb, self.mask_files[i])

    def depth(self, i: int) -> np.ndarray:
        """(H, W) float32 depth in metres of keyframe ``i`` at RGB resolution (Replica's 16-bit PNG / 6553.5)."""
        i = self._index(i)
        path = self.root / "results" / f"depth{self.frame_numbers[i]:06d}.png"
        img = _read_image(_require_file(path, "depth image"))
        if img.ndim != 2:
            raise SequenceError(f"{path}: expected a single-channel depth image")
        return img.astype(np.float32) / np.float32(NICE_SLAM_DEPTH_SCALE)

    def load_gaussians(self) -> GaussianMap | None:
        return _maybe_ply(self.gaussians_path)


def _find_mask(directory: Path, frame: int) -> Path:
    names = (f"frame{frame:06d}.png", f"{frame:06d}.png", f"semantic_instance_{frame}.png")
    for d in (directory, directory / "semantic_instance"):
        for name in names:
            if (d / name).is_file():
                return d / name
    if not directory.is_dir():
        raise SequenceError(f"{directory}: missing masks directory")
    raise SequenceError(f"{directory}: no mask for frame {frame} (looked for {', '.join(names)})")


def _as_intrinsics(value: Intrinsics | dict) -> Intrinsics:
    if isinstance(value, Intrinsics):
        return value
    try:
        return Intrinsics.from_dict(value)
    except (KeyError, TypeError) as exc:
        raise SequenceError(
            f"intrinsics option: expected Intrinsics or {{width, height, fx, fy, cx, cy}}: {exc}"
        ) from None


class HiSlam2Sequence(Sequence):
    """HI-SLAM2's output folder with keyframe masks (and RGB) from elsewhere (see the module docstring)."""

    def __init__(
        self,
        root: str | os.PathLike,
        masks: str | os.PathLike | None = None,
        rgb: str | os.PathLike | None = None,
        match: str = "name",
        image_size: tuple[int, int] = HISLAM2_REPLICA_SIZE,
        gaussians: str | os.PathLike | None = None,
        frame_rate: float = DEFAULT_FRAME_RATE,
        tolerance: float = 1e-3,
    ) -> None:
        self.root = _require_dir(Path(root), "sequence")
        self.name = self.root.name
        if masks is None:
            raise SequenceError(f"{self.root}: HI-SLAM2 stores no images; pass masks=DIRECTORY (and rgb=DIRECTORY)")
        if match not in ("name", "order"):
            raise SequenceError(f"{self.root}: match must be 'name' or 'order', got {match!r}")
        stamps, self.poses = read_tum_traj(self.root / "traj_kf.txt")
        path = _require_file(self.root / "intrinsics.npy", "intrinsics.npy")
        try:
            k = np.load(path, allow_pickle=False).astype(np.float64).ravel()
        except (ValueError, OSError) as exc:
            raise SequenceError(f"{path}: not a NumPy array: {exc}") from None
        if k.size != 4 or not np.all(np.isfinite(k)):
            raise SequenceError(f"{path}: expected 4 finite values fx fy cx cy, got {k.tolist()}")
        w, h = image_size
        try:
            self.slam_intrinsics = Intrinsics(k[0], k[1], k[2], k[3], w, h)
        except ValueError as exc:
            raise SequenceError(f"{path}: {exc}") from None
        self.mask_files = _match_files(_require_dir(Path(masks), "masks"), (".png",), stamps, match, tolerance)
        self.rgb_files = None
        if rgb is not None:
            self.rgb_files = _match_files(_require_dir(Path(rgb), "rgb"), _IMAGE_EXTS, stamps, match, tolerance)
        self.intrinsics = _mask_intrinsics(self.slam_intrinsics, self.mask_files[0])
        fractional = np.any(np.abs(stamps - np.round(stamps)) > 1e-9) or np.any(np.abs(stamps) > 1e6)
        if fractional:
            self.stamps_ns = np.round(stamps * 1e9).astype(np.int64)
        else:
            self.stamps_ns = _stamps_from_frames(stamps, frame_rate)
        default_ply = self.root / "3dgs_final.ply"
        self.gaussians_path = (
            Path(gaussians) if gaussians is not None else (default_ply if default_ply.exists() else None)
        )

    def keyframe(self, i: int) -> Keyframe:
        i = self._index(i)
        mask = _load_mask_any(self.mask_files[i])
        rgb = read_rgb(self.rgb_files[i]) if self.rgb_files is not None else None
        return _make_keyframe(i, self.stamps_ns[i], self.poses[i], self.intrinsics, mask, rgb, self.mask_files[i])

    def load_gaussians(self) -> GaussianMap | None:
        return _maybe_ply(self.gaussians_path)


def _match_files(directory: Path, exts: tuple[str, ...], stamps: np.ndarray, match: str, tol: float) -> list[Path]:
    files = _images_in(directory, exts)
    if not files:
        raise SequenceError(f"{directory}: no {'/'.join(exts)} images")
    if match == "order":
        if len(files) != len(stamps):
            raise SequenceError(f"{directory}: {len(files)} images for {len(stamps)} keyframes (match='order')")
        return files
    numbered = [(n, p) for p in files if (n := _last_number(p.name)) is not None]
    if not numbered:
        raise SequenceError(f"{directory}: no image has a number in its name to match keyframes by")
    keys = np.array([n for n, _ in numbered])
    out = []
    for t in stamps:
        j = int(np.argmin(np.abs(keys - t)))
        if abs(keys[j] - t) > tol:
            raise SequenceError(
                f"{directory}: no image named with keyframe stamp {t:g} (nearest: {numbered[j][1].name})"
            )
        out.append(numbered[j][1])
    return out


def open_sequence(path: str | os.PathLike, layout: str = "auto", **options) -> Sequence:
    """Opens a sequence folder in one of ``LAYOUTS`` ("auto" recognises them by their files)."""
    path = Path(path)
    if not path.is_dir():
        raise SequenceError(f"{path}: no such sequence directory")
    if layout == "auto":
        if (path / "traj_kf.txt").is_file():
            layout = "hislam2"
        elif (path / "results").is_dir() and (path / "traj.txt").is_file():
            layout = "nice-slam"
        elif (path / "masks").is_dir() and (path / "traj.txt").is_file():
            layout = "plain"
        else:
            raise SequenceError(
                f"{path}: not a known layout (plain: masks/ + traj.txt; nice-slam: results/ + traj.txt; "
                "hislam2: traj_kf.txt)"
            )
    if layout == "plain":
        _check_options(layout, options, set())
        return PlainSequence(path)
    if layout == "nice-slam":
        _check_options(layout, options, {"masks", "gaussians", "intrinsics", "stride", "frame_rate"})
        return NiceSlamSequence(path, **options)
    if layout == "hislam2":
        allowed = {"masks", "rgb", "match", "image_size", "gaussians", "frame_rate", "tolerance"}
        _check_options(layout, options, allowed)
        return HiSlam2Sequence(path, **options)
    raise SequenceError(f"unknown layout {layout!r}; expected 'auto' or one of {LAYOUTS}")


def write_plain(
    sequence: Sequence,
    out_dir: str | os.PathLike,
    gaussians: GaussianMap | None = None,
    rgb_format: str = "png",
    *,
    overwrite: bool = False,
) -> None:
    """Writes ``sequence`` in the plain layout; ``open_sequence`` reads it back with identical masks and poses.

    ``gaussians`` defaults to the sequence's own map (``load_gaussians()``), if any. Masks are lossless
    RGB PNGs; RGB is PNG (lossless) or JPEG (quality 95). Poses and intrinsics are written with 17
    significant digits, so float64 values read back bit for bit. Refuses a non-empty ``out_dir`` unless
    ``overwrite``, which then replaces the files of the layout. A folder it created is removed when writing fails
    (`monovoc segment` stopped by an unreadable image left a half-written one).
    """
    if rgb_format not in ("png", "jpg"):
        raise SequenceError(f"rgb_format must be 'png' or 'jpg', got {rgb_format!r}")
    out = Path(out_dir)
    created = not out.exists()
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise SequenceError(f"{out}: exists and is not empty (pass overwrite=True to replace its sequence)")
        for sub in ("rgb", "masks", "segments"):
            if (out / sub).is_dir():
                for p in (out / sub).iterdir():
                    if p.is_file() and re.fullmatch(r"\d{6}\.(png|jpg|json)", p.name):
                        p.unlink()
        for name in ("stamps.txt", "labels.json", "gaussians.ply"):
            (out / name).unlink(missing_ok=True)
    try:
        _write_plain_files(sequence, out, gaussians, rgb_format)
    except BaseException:
        if created:  # a half-written folder would take overwrite=True to be written again
            shutil.rmtree(out, ignore_errors=True)
        raise


def _write_plain_files(sequence: Sequence, out: Path, gaussians: GaussianMap | None, rgb_format: str) -> None:
    (out / "masks").mkdir(parents=True, exist_ok=True)
    poses, stamps = [], []
    for kf in sequence:
        if kf.intrinsics != sequence.intrinsics:
            raise SequenceError(f"{out}: keyframe {kf.index} has intrinsics {kf.intrinsics}, not the sequence's")
        write_mask(out / "masks" / f"{kf.index:06d}.png", kf.mask)
        if kf.segments:  # a segmenter's names, read back by PlainSequence.keyframe
            from monovoc_ros.core.segments.segment_labels import write_segments

            (out / "segments").mkdir(exist_ok=True)
            write_segments(out / "segments" / f"{kf.index:06d}.json", kf.segments)
        if kf.rgb is not None:
            (out / "rgb").mkdir(exist_ok=True)
            params = [cv2.IMWRITE_JPEG_QUALITY, 95] if rgb_format == "jpg" else []
            path = out / "rgb" / f"{kf.index:06d}.{rgb_format}"
            if not cv2.imwrite(str(path), np.ascontiguousarray(kf.rgb[:, :, ::-1]), params):
                raise SequenceError(f"{path}: could not write")
        poses.append(np.asarray(kf.cam_to_world, dtype=np.float64))
        stamps.append(int(kf.stamp_ns))
    if not poses:
        raise SequenceError(f"{out}: the sequence has no keyframes")
    (out / "traj.txt").write_text("".join(" ".join(f"{v:.17g}" for v in T.ravel()) + "\n" for T in poses))
    (out / "stamps.txt").write_text("".join(f"{s}\n" for s in stamps))
    (out / "intrinsics.json").write_text(json.dumps(sequence.intrinsics.to_dict(), indent=1) + "\n")
    labels = sequence.labels()
    if labels:
        (out / "labels.json").write_text(json.dumps(labels, indent=1) + "\n")
    gmap = gaussians if gaussians is not None else sequence.load_gaussians()
    if gmap is not None:
        save_ply(out / "gaussians.ply", gmap)
