"""Model cache: manifest integrity checks, idempotent export, and the export's own torch-vs-ONNX guard.

The full export (~12 s) runs once at install, not here; these tests check the installed result and the
pieces that decide whether it is trusted.
"""

import json
import subprocess
import sys
import time

import numpy as np
import pytest

from monovoc_ros.embed import conse_files as cf
from monovoc_ros.embed.export import ExportError, _check_match, is_up_to_date
from monovoc_ros.embed.model_store import (
    MANIFEST_NAME,
    ModelMissingError,
    default_model_dir,
    read_manifest,
    verify_model_dir,
    write_manifest,
)


def test_installed_export_is_complete_and_current():
    model_dir = default_model_dir()
    manifest = verify_model_dir(model_dir, cf.CONSE_FILES)
    assert set(manifest["files"]) == set(cf.CONSE_FILES)
    assert manifest["class_prompt"] == cf.CLASS_PROMPT
    assert is_up_to_date(model_dir)
    assert np.load(model_dir / cf.CLASS_EMBEDDINGS).shape == (1000, 384)


def test_export_is_a_fast_no_op_when_up_to_date():
    manifest_before = (default_model_dir() / MANIFEST_NAME).read_bytes()
    start = time.perf_counter()
    result = subprocess.run(
        [sys.executable, "-m", "monovoc_ros.embed.export", "--quiet"], capture_output=True, text=True, check=False
    )
    elapsed = time.perf_counter() - start
    assert result.returncode == 0, result.stderr
    assert result.stdout == "" and result.stderr == ""
    assert elapsed < 3.0  # includes interpreter start-up; the check itself is ~0.1 s
    assert (default_model_dir() / MANIFEST_NAME).read_bytes() == manifest_before


def test_manifest_round_trip_and_damage(tmp_path):
    (tmp_path / "a.bin").write_bytes(b"\x00" * 1000)
    (tmp_path / "b.txt").write_text("hello")
    write_manifest(tmp_path, ["a.bin", "b.txt"], {"note": "test"})
    manifest = verify_model_dir(tmp_path, ["a.bin"])
    assert manifest["note"] == "test" and manifest["files"]["a.bin"]["size"] == 1000

    with pytest.raises(ModelMissingError, match="does not list"):
        verify_model_dir(tmp_path, ["c.onnx"])
    (tmp_path / "b.txt").write_text("hellO")
    with pytest.raises(ModelMissingError, match="sha256"):
        verify_model_dir(tmp_path)
    (tmp_path / "b.txt").write_text("hello!")
    with pytest.raises(ModelMissingError, match="bytes"):
        verify_model_dir(tmp_path)
    (tmp_path / "b.txt").unlink()
    with pytest.raises(ModelMissingError, match="missing model file"):
        verify_model_dir(tmp_path)


@pytest.mark.parametrize(
    "content", ["{not json", json.dumps({"format": 999, "files": {}}), json.dumps({"format": 1, "files": {"x": 1}})]
)
def test_bad_manifest_is_reported(tmp_path, content):
    (tmp_path / MANIFEST_NAME).write_text(content)
    with pytest.raises(ModelMissingError, match=r"monovoc_ros\.embed\.export"):
        read_manifest(tmp_path)


def test_export_guard_rejects_a_mismatching_graph():
    expected = np.linspace(0, 1, 12, dtype=np.float32).reshape(3, 4)
    _check_match("ok.onnx", expected + 5e-6, expected)
    with pytest.raises(ExportError, match="differs"):
        _check_match("bad.onnx", expected + 1e-3, expected)
    with pytest.raises(ExportError, match="shape"):
        _check_match("bad.onnx", expected[:2], expected)
    with pytest.raises(ExportError):
        _check_match("nan.onnx", np.full_like(expected, np.nan), expected)


def test_class_names_are_the_imagenet_1k_order():
    names = cf.parse_class_names(cf.packaged_class_names_text())
    assert len(names) == 1000
    assert names[0] == "tench" and names[999] == "toilet paper"
    assert names[559] == "folding chair" and names[898] == "water bottle" and names[532] == "dining table"
    with pytest.raises(ValueError, match="1000"):
        cf.parse_class_names("# header\nchair\n")
