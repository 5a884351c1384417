"""semantic.ply: what other readers (plyfile) see, -1 for unobserved, and older uint files still read."""

from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData

from monovoc_ros.core.evidence.palette import UNOBSERVED_ID, VOID_ID
from monovoc_ros.core.map_store import read_semantic_ply, save_semantic_ply

IDS = np.array([0x00CC99, UNOBSERVED_ID, 0xFF0000, VOID_ID, 0, UNOBSERVED_ID], np.uint32)


def cloud(n: int = len(IDS)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(3)
    points = rng.normal(size=(n, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, (n, 3)).astype(np.uint8)
    confidence = rng.uniform(0, 1, n).astype(np.float32)
    return points, rgb, confidence


def test_plyfile_reads_int32_object_ids_with_minus_one_for_unobserved(tmp_path):
    points, rgb, confidence = cloud()
    path = tmp_path / "semantic.ply"
    save_semantic_ply(path, points, rgb, IDS, confidence)
    vertex = PlyData.read(str(path))["vertex"]
    kinds = {p.name: p.val_dtype for p in vertex.properties}
    # Open3D's PLY reader skips 'uint' properties ("unsupported datatype") and loads 'int'.
    assert kinds == {
        "x": "f4", "y": "f4", "z": "f4", "red": "u1", "green": "u1", "blue": "u1",
        "object_id": "i4", "confidence": "f4",
    }  # fmt: skip
    assert b"property int object_id" in path.read_bytes()[:400]
    assert vertex["object_id"].tolist() == [0x00CC99, -1, 0xFF0000, 0xFFFFFF, 0, -1]
    np.testing.assert_array_equal(np.stack([vertex["x"], vertex["y"], vertex["z"]], 1), points)
    np.testing.assert_array_equal(np.stack([vertex["red"], vertex["green"], vertex["blue"]], 1), rgb)
    np.testing.assert_array_equal(vertex["confidence"], confidence)
    back = read_semantic_ply(path)
    np.testing.assert_array_equal(back["object_id"], IDS)
    assert back["object_id"].dtype == np.uint32
    np.testing.assert_array_equal(back["points"], points)
    np.testing.assert_array_equal(back["rgb"], rgb)
    np.testing.assert_array_equal(back["confidence"], confidence)


def test_older_uint_files_still_read(tmp_path):
    """Files written before the int32 change (object_id uint, unobserved 0xFFFFFFFF), here by plyfile."""
    from plyfile import PlyElement

    points, rgb, _ = cloud()
    table = np.empty(len(IDS), [("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"),
                                ("blue", "u1"), ("object_id", "u4")])  # fmt: skip
    for k, name in enumerate("xyz"):
        table[name] = points[:, k]
    for k, name in enumerate(("red", "green", "blue")):
        table[name] = rgb[:, k]
    table["object_id"] = IDS
    path = tmp_path / "old.ply"
    PlyData([PlyElement.describe(table, "vertex")]).write(str(path))
    assert b"property uint object_id" in path.read_bytes()[:400]
    back = read_semantic_ply(path)
    np.testing.assert_array_equal(back["object_id"], IDS)
    assert "confidence" not in back


def test_bad_ids_and_non_semantic_files_are_refused(tmp_path):
    points, rgb, _ = cloud(2)
    with pytest.raises(ValueError, match="packed colors"):
        save_semantic_ply(tmp_path / "x.ply", points, rgb, np.array([0x1000000, 1], np.uint32))
    assert not (tmp_path / "x.ply").exists()
    save_semantic_ply(tmp_path / "ok.ply", points, rgb, np.array([1, 2], np.uint32))
    text = (tmp_path / "ok.ply").read_bytes().replace(b"object_id", b"other_one")
    (tmp_path / "bad.ply").write_bytes(text)
    with pytest.raises(ValueError, match=r"bad.ply: not a semantic PLY, missing vertex properties \['object_id'\]"):
        read_semantic_ply(tmp_path / "bad.ply")
