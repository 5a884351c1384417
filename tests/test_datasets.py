"""Dataset loaders: the real plain-layout Replica sequence, round trips, NICE-SLAM and HI-SLAM2 folders."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from monovoc_ros.core.evaluation.datasets import (
    REPLICA_INTRINSICS,
    HiSlam2Sequence,
    NiceSlamSequence,
    PlainSequence,
    SequenceError,
    instance_palette,
    open_sequence,
    write_plain,
)
from monovoc_ros.core.map.camera import matrix_to_quat_wxyz
from monovoc_ros.core.map.ply import save_ply
from monovoc_ros.synthetic import SceneConfig, SyntheticScene, generate_scene

MASK_SIZE = (154, 86)


@pytest.fixture(scope="module")
def scene() -> SyntheticScene:
    # Masks at 154x86 with the Replica camera scaled down: the fake NICE-SLAM RGB is 2x that.
    k = REPLICA_INTRINSICS.scaled_to(*MASK_SIZE)
    cfg = SceneConfig(width=k.width, height=k.height, fx=k.fx, fy=k.fy, cx=k.cx, cy=k.cy)
    cfg.n_gaussians, cfg.n_keyframes = 1_500, 6
    return generate_scene(cfg)


def _bgr(rgb: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(rgb[:, :, ::-1])


# ------------------------------------------------------------------------------------------ plain layout


def test_real_replica_office0(replica_office0: Path) -> None:
    seq = open_sequence(replica_office0)
    assert isinstance(seq, PlainSequence) and len(seq) == 81
    k = seq.intrinsics
    assert (k.width, k.height, k.fx, k.fy, k.cx, k.cy) == (600, 340, 300.0, 300.0, 299.5, 169.5)
    assert np.allclose(seq.poses[0], np.eye(4), atol=1e-9)
    assert np.all(np.diff(seq.stamps_ns) == 100_000_000)
    kf = seq.keyframe(40)
    assert kf.mask.shape == (340, 600, 3) and kf.rgb.shape == (340, 600, 3)
    palette = {tuple(d["color"]) for d in seq.labels()}
    colors = {tuple(int(v) for v in c) for c in np.unique(kf.mask.reshape(-1, 3), axis=0)}
    assert len(colors) > 5 and colors <= palette | {(255, 255, 255)}
    assert {"chair", "sofa", "wall"} <= {d["class_name"] for d in seq.labels()}
    assert len(seq.load_gaussians()) == 204_266


def test_a_plain_folder_that_fails_halfway_is_removed_when_it_was_created(scene: SyntheticScene, tmp_path: Path):
    class Unreadable:  # the scene, whose third keyframe cannot be read (as an image that is no image)
        intrinsics = scene.intrinsics

        def __iter__(self):
            for kf in scene:
                if kf.index == 2:
                    raise SequenceError("rgb/000002.png: not an image")
                yield kf

        def labels(self):
            return scene.labels()

        def load_gaussians(self):
            return None

    with pytest.raises(SequenceError, match="not an image"):
        write_plain(Unreadable(), tmp_path / "new")
    assert not (tmp_path / "new").exists()
    (tmp_path / "mine").mkdir()  # a folder the caller made is kept, with what was written
    with pytest.raises(SequenceError, match="not an image"):
        write_plain(Unreadable(), tmp_path / "mine")
    assert sorted(p.name for p in (tmp_path / "mine" / "masks").iterdir()) == ["000000.png", "000001.png"]


def test_plain_round_trip_is_lossless(scene: SyntheticScene, tmp_path: Path) -> None:
    write_plain(scene, tmp_path / "seq")
    back = open_sequence(tmp_path / "seq")
    assert isinstance(back, PlainSequence) and len(back) == len(scene)
    assert back.intrinsics == scene.intrinsics
    assert np.array_equal(back.poses, scene.poses)  # bit for bit
    assert np.array_equal(back.stamps_ns, scene.stamps_ns)
    assert back.labels() == scene.labels()
    for i in range(len(scene)):
        a, b = scene.keyframe(i), back.keyframe(i)
        assert np.array_equal(a.mask, b.mask) and np.array_equal(a.rgb, b.rgb)
        assert a.stamp_ns == b.stamp_ns and np.array_equal(a.cam_to_world, b.cam_to_world)
    g = back.load_gaussians()
    assert np.array_equal(g.ids, scene.gaussians.ids) and np.array_equal(g.means, scene.gaussians.means)
    # Indexed (palette) PNGs, as segmentation tools write them, read as the same colors.
    labels = scene.object_index_map(1) + 1
    indexed = Image.fromarray(labels.astype(np.uint8), mode="P")
    indexed.putpalette(scene.lut.ravel().tolist())
    indexed.save(tmp_path / "seq" / "masks" / "000001.png")
    assert np.array_equal(open_sequence(tmp_path / "seq").keyframe(1).mask, scene.clean_mask(1))


def test_plain_write_options(scene: SyntheticScene, tmp_path: Path) -> None:
    out = tmp_path / "jpg"
    write_plain(scene, out, rgb_format="jpg")
    assert sorted(p.name for p in (out / "rgb").iterdir())[0] == "000000.jpg"
    back = open_sequence(out, layout="plain")
    assert np.abs(back.keyframe(2).rgb.astype(int) - scene.rgb(2)).mean() < 4
    assert np.array_equal(back.keyframe(2).mask, scene.clean_mask(2))
    with pytest.raises(SequenceError, match="not empty"):
        write_plain(scene, out)
    write_plain(scene, out, overwrite=True)  # replaces the JPEGs with PNGs
    assert sorted(p.suffix for p in (out / "rgb").iterdir()) == [".png"] * len(scene)
    with pytest.raises(SequenceError, match="rgb_format"):
        write_plain(scene, tmp_path / "x", rgb_format="bmp")


def _plain_copy(scene: SyntheticScene, tmp_path: Path) -> Path:
    out = tmp_path / "p"
    write_plain(scene, out)
    return out


def test_plain_layout_errors_name_the_path(scene: SyntheticScene, tmp_path: Path) -> None:
    assert issubclass(SequenceError, ValueError)
    root = _plain_copy(scene, tmp_path)
    traj = (root / "traj.txt").read_text().splitlines()

    (root / "traj.txt").write_text("\n".join(traj[:-1]) + "\n")
    with pytest.raises(SequenceError, match=r"traj\.txt: 5 poses but 6 masks"):
        open_sequence(root)
    (root / "traj.txt").write_text("\n".join(traj[:-1] + ["1 2 three"]) + "\n")
    with pytest.raises(SequenceError, match=r"traj\.txt:6: not a row of numbers"):
        open_sequence(root)
    (root / "traj.txt").write_text("\n".join(traj[:-1] + [" ".join(["1"] * 15)]) + "\n")
    with pytest.raises(SequenceError, match=r"traj\.txt:6: expected 16 numbers"):
        open_sequence(root)
    scaled = " ".join(str(v) for v in (np.diag([2.0, 2.0, 2.0, 1.0])).ravel())
    (root / "traj.txt").write_text("\n".join(traj[:-1] + [scaled]) + "\n")
    with pytest.raises(SequenceError, match=r"traj\.txt:6: rotation block is not orthonormal"):
        open_sequence(root)
    (root / "traj.txt").write_text("\n".join(traj) + "\n")

    (root / "stamps.txt").write_text("1\n2\n")
    with pytest.raises(SequenceError, match=r"stamps\.txt: 2 timestamps for 6 keyframes"):
        open_sequence(root)
    # Beyond int64 (OverflowError was a traceback), negative, repeated: refused as the live node refuses them.
    for stamps, problem in (
        (["99999999999999999999", *map(str, range(1, 6))], r"timestamp \(0 \.\. 2\^63-1\) per line"),
        (["-5", *map(str, range(1, 6))], "negative timestamps"),
        (["1", "2", "2", "3", "4", "5"], "timestamps decrease or repeat"),
    ):
        (root / "stamps.txt").write_text("\n".join(stamps) + "\n")
        with pytest.raises(SequenceError, match=problem):
            open_sequence(root)
    (root / "stamps.txt").unlink()
    assert np.array_equal(open_sequence(root).stamps_ns, np.arange(6) * 100_000_000)  # synthesized 10 Hz

    small = np.zeros((10, 10, 3), np.uint8)
    cv2.imwrite(str(root / "masks" / "000003.png"), small)
    with pytest.raises(SequenceError, match=r"masks/000003\.png: Keyframe\.mask is 10x10"):
        open_sequence(root).keyframe(3)
    (root / "rgb" / "000004.png").unlink()
    with pytest.raises(SequenceError, match=r"rgb: no RGB image for mask\(s\) \['000004\.png'\]"):
        open_sequence(root)
    shutil.rmtree(root / "rgb")  # RGB is optional
    assert open_sequence(root).keyframe(4).rgb is None
    (root / "intrinsics.json").write_text(json.dumps({"fx": 1}))
    with pytest.raises(SequenceError, match=r"intrinsics\.json"):
        PlainSequence(root)
    (root / "traj.txt").unlink()
    with pytest.raises(SequenceError, match="not a known layout"):
        open_sequence(root)
    with pytest.raises(SequenceError, match=r"traj\.txt: missing trajectory file"):
        open_sequence(root, layout="plain")
    with pytest.raises(SequenceError, match="no such sequence directory"):
        open_sequence(tmp_path / "absent")
    with pytest.raises(SequenceError, match="unknown layout"):
        open_sequence(root, layout="tum")
    with pytest.raises(SequenceError, match="takes no option"):
        open_sequence(root, layout="plain", masks="x")


# --------------------------------------------------------------------------------------------- NICE-SLAM


def _write_nice_slam(scene: SyntheticScene, root: Path) -> None:
    """NICE-SLAM's Replica layout: 2x-resolution frames and depth, one 4x4 per line in traj.txt."""
    (root / "results").mkdir(parents=True)
    w, h = 2 * MASK_SIZE[0], 2 * MASK_SIZE[1]
    for i in range(len(scene)):
        cv2.imwrite(str(root / "results" / f"frame{i:06d}.jpg"), _bgr(cv2.resize(scene.rgb(i), (w, h))))
        depth = cv2.resize(scene.depth(i), (w, h), interpolation=cv2.INTER_NEAREST)
        cv2.imwrite(str(root / "results" / f"depth{i:06d}.png"), np.round(depth * 6553.5).astype(np.uint16))
    (root / "traj.txt").write_text("".join(" ".join(f"{v:.17g}" for v in T.ravel()) + "\n" for T in scene.poses))


def test_nice_slam_layout_with_palette_and_vmap_masks(scene: SyntheticScene, tmp_path: Path) -> None:
    root = tmp_path / "room0"
    _write_nice_slam(scene, root)
    palette_dir, vmap_dir = tmp_path / "palette", tmp_path / "vmap" / "semantic_instance"
    palette_dir.mkdir()
    vmap_dir.mkdir(parents=True)
    for i in range(len(scene)):
        cv2.imwrite(str(palette_dir / f"frame{i:06d}.png"), _bgr(scene.clean_mask(i)))
        ids = (scene.object_index_map(i) + 1).astype(np.uint8)  # vMAP-style instance ids, 0 = void
        cv2.imwrite(str(vmap_dir / f"semantic_instance_{i}.png"), ids)
    save_ply(tmp_path / "map.ply", scene.gaussians)
    rgb_camera = REPLICA_INTRINSICS.scaled_to(2 * MASK_SIZE[0], 2 * MASK_SIZE[1])

    seq = open_sequence(root, masks=palette_dir, intrinsics=rgb_camera, gaussians=tmp_path / "map.ply")
    assert isinstance(seq, NiceSlamSequence) and len(seq) == len(scene)
    k = seq.intrinsics  # the RGB camera rescaled to the masks
    assert (k.width, k.height) == MASK_SIZE
    assert np.allclose([k.fx, k.fy, k.cx, k.cy], [scene.intrinsics.fx, scene.intrinsics.fy, scene.intrinsics.cx,
                                                   scene.intrinsics.cy], atol=1e-9)  # fmt: skip
    assert np.array_equal(seq.poses, scene.poses)
    kf = seq.keyframe(3)
    assert np.array_equal(kf.mask, scene.clean_mask(3)) and kf.rgb.shape == (2 * MASK_SIZE[1], 2 * MASK_SIZE[0], 3)
    depth = seq.depth(3)
    assert depth.shape == kf.rgb.shape[:2] and np.abs(depth[::2, ::2] - scene.depth(3)).max() < 1e-3
    assert np.array_equal(seq.load_gaussians().ids, scene.gaussians.ids)

    vm = open_sequence(root, masks=vmap_dir.parent, intrinsics=rgb_camera, stride=2)
    assert len(vm) == 3 and np.array_equal(vm.poses, scene.poses[::2])
    assert np.array_equal(vm.stamps_ns, np.array([0, 2, 4]) * 100_000_000)
    assert np.array_equal(vm.keyframe(1).mask, instance_palette(scene.object_index_map(2) + 1))

    default = open_sequence(root, masks=palette_dir)
    assert default.rgb_intrinsics == REPLICA_INTRINSICS
    with pytest.raises(SequenceError, match="pass masks="):
        open_sequence(root)
    (palette_dir / "frame000004.png").unlink()
    with pytest.raises(SequenceError, match="no mask for frame 4"):
        open_sequence(root, masks=palette_dir)
    (root / "traj.txt").write_text("".join(" ".join(map(str, np.eye(4).ravel())) + "\n" for _ in range(3)))
    with pytest.raises(SequenceError, match="3 poses but frames up to 5"):
        open_sequence(root, masks=vmap_dir)


# ---------------------------------------------------------------------------------------------- HI-SLAM2


def _write_hislam2(scene: SyntheticScene, root: Path, frames: list[float]) -> None:
    root.mkdir(parents=True)
    rows = []
    for t, T in zip(frames, scene.poses, strict=True):
        w, x, y, z = matrix_to_quat_wxyz(T[:3, :3])
        rows.append([t, *T[:3, 3], x, y, z, w])  # lietorch order: tx ty tz qx qy qz qw
    np.savetxt(root / "traj_kf.txt", np.array(rows))
    k = SceneConfig.default_intrinsics()  # HI-SLAM2 tracks Replica at 616x344
    np.save(root / "intrinsics.npy", np.array([k.fx, k.fy, k.cx, k.cy], dtype=np.float32))
    save_ply(root / "3dgs_final.ply", scene.gaussians)


def test_hislam2_layout_matches_keyframes_by_name(scene: SyntheticScene, tmp_path: Path) -> None:
    frames = [0, 7, 15, 22, 31, 40]  # keyframes picked by the tracker out of 45 frames
    root = tmp_path / "out"
    _write_hislam2(scene, root, frames)
    masks, rgb = tmp_path / "masks", tmp_path / "rgb"
    masks.mkdir()
    rgb.mkdir()
    for f in range(45):  # every frame has files; non-keyframes get a decoy mask
        kf = frames.index(f) if f in frames else None
        mask = scene.clean_mask(kf) if kf is not None else np.zeros((MASK_SIZE[1], MASK_SIZE[0], 3), np.uint8)
        cv2.imwrite(str(masks / f"frame{f:06d}.png"), _bgr(mask))
        cv2.imwrite(str(rgb / f"frame{f:06d}.jpg"), _bgr(scene.rgb(kf) if kf is not None else mask))

    seq = open_sequence(root, masks=masks, rgb=rgb)
    assert isinstance(seq, HiSlam2Sequence) and len(seq) == len(scene)
    assert np.allclose(seq.poses, scene.poses, atol=1e-12)  # xyzw order handled
    assert np.array_equal(seq.stamps_ns, np.array(frames) * 100_000_000)
    k = seq.intrinsics  # intrinsics.npy is for 616x344, rescaled to the masks
    assert (k.width, k.height) == MASK_SIZE
    assert seq.slam_intrinsics.scaled_to(*MASK_SIZE) == k
    for i in (0, 3, 5):
        assert np.array_equal(seq.keyframe(i).mask, scene.clean_mask(i))
    assert np.array_equal(seq.load_gaussians().means, scene.gaussians.means)

    with pytest.raises(SequenceError, match="45 images for 6 keyframes"):
        open_sequence(root, masks=masks, match="order")
    with pytest.raises(SequenceError, match="pass masks="):
        open_sequence(root)
    (masks / "frame000022.png").unlink()
    with pytest.raises(SequenceError, match="no image named with keyframe stamp 22"):
        open_sequence(root, masks=masks)


def test_hislam2_order_matching_and_second_stamps(scene: SyntheticScene, tmp_path: Path) -> None:
    stamps = [1305031102.175304 + 0.5 * i for i in range(len(scene))]  # TUM-style names: seconds
    root = tmp_path / "tum"
    _write_hislam2(scene, root, stamps)
    masks = tmp_path / "m"
    masks.mkdir()
    for i, t in enumerate(stamps):
        cv2.imwrite(str(masks / f"{t:.6f}.png"), _bgr(scene.clean_mask(i)))
    by_name = open_sequence(root, masks=masks)
    assert np.array_equal(by_name.stamps_ns, np.round(np.array(stamps) * 1e9).astype(np.int64))
    assert np.array_equal(by_name.keyframe(4).mask, scene.clean_mask(4))
    by_order = open_sequence(root, masks=masks, match="order")
    assert [p.name for p in by_order.mask_files] == [p.name for p in by_name.mask_files]


def test_hislam2_rejects_bad_files(scene: SyntheticScene, tmp_path: Path) -> None:
    root = tmp_path / "bad"
    _write_hislam2(scene, root, list(range(len(scene))))
    masks = tmp_path / "m"
    masks.mkdir()
    for i in range(len(scene)):
        cv2.imwrite(str(masks / f"{i:06d}.png"), _bgr(scene.clean_mask(i)))
    rows = (root / "traj_kf.txt").read_text().splitlines()
    (root / "traj_kf.txt").write_text("\n".join(rows[:2] + ["2 0 0 0 0 0 0 2"] + rows[3:]) + "\n")
    with pytest.raises(SequenceError, match=r"traj_kf\.txt:3: quaternion norm 2\.000000 is not 1"):
        open_sequence(root, masks=masks)
    (root / "traj_kf.txt").write_text("\n".join(rows[:2] + ["2 0 0 0 0 0 1"] + rows[3:]) + "\n")
    with pytest.raises(SequenceError, match=r"traj_kf\.txt:3: expected 8 numbers"):
        open_sequence(root, masks=masks)
    (root / "traj_kf.txt").write_text("\n".join(rows) + "\n")
    np.save(root / "intrinsics.npy", np.array([1.0, 2.0, 3.0]))
    with pytest.raises(SequenceError, match=r"intrinsics\.npy: expected 4 finite values"):
        open_sequence(root, masks=masks)
    with pytest.raises(SequenceError, match="match must be"):
        HiSlam2Sequence(root, masks=masks, match="nearest")


def test_instance_palette_is_deterministic_and_distinct() -> None:
    ids = np.arange(0, 2000)
    colors = instance_palette(ids)
    assert tuple(colors[0]) == (255, 255, 255)
    rest = colors[1:]
    assert len(np.unique(rest, axis=0)) == len(rest) and not np.any(np.all(rest == 255, axis=1))
    assert np.array_equal(instance_palette(ids.reshape(40, 50)), colors.reshape(40, 50, 3))
    with pytest.raises(SequenceError):
        instance_palette(np.array([-1]))
