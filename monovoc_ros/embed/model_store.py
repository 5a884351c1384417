"""Where the exported embedding models live and how their integrity is checked.

The model directory holds the ONNX files, tokenizer and cached class-prompt embeddings written by
``python -m monovoc_ros.embed.export`` plus ``manifest.json`` with the sha256 and size of each file.
Loading verifies the files against the manifest so that a half-written or stale cache fails loudly
instead of producing silently wrong embeddings.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable
from pathlib import Path

MANIFEST_NAME = "manifest.json"
# Bump when the exported files change meaning (graph inputs/outputs, prompt template, file set).
MANIFEST_FORMAT = 1

EXPORT_HINT = "run `python -m monovoc_ros.embed.export` (or `make install`) to create it"


class ModelMissingError(RuntimeError):
    """The exported embedding models are missing, incomplete or corrupt."""


def default_model_dir() -> Path:
    """``$MONOVOC_MODEL_DIR`` if set, else ``~/.cache/monovoc_ros/models``."""
    env = os.environ.get("MONOVOC_MODEL_DIR")
    if env:
        return Path(env).expanduser()
    return Path.home() / ".cache" / "monovoc_ros" / "models"


def sha256_file(path: Path, chunk_size: int = 1 << 20) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(chunk_size):
            digest.update(chunk)
    return digest.hexdigest()


def write_manifest(model_dir: Path, files: Iterable[str], info: dict) -> Path:
    """Hash ``files`` (paths relative to ``model_dir``) and write the manifest last, so that its presence
    marks a complete export."""
    entries = {}
    for name in sorted(files):
        path = model_dir / name
        entries[name] = {"sha256": sha256_file(path), "size": path.stat().st_size}
    manifest = {"format": MANIFEST_FORMAT, "files": entries, **info}
    tmp = model_dir / (MANIFEST_NAME + ".tmp")
    tmp.write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    tmp.replace(model_dir / MANIFEST_NAME)
    return model_dir / MANIFEST_NAME


def read_manifest(model_dir: Path, hint: str = EXPORT_HINT) -> dict:
    path = Path(model_dir) / MANIFEST_NAME
    if not path.is_file():
        raise ModelMissingError(f"no models in {model_dir} (missing {MANIFEST_NAME}): {hint}")
    try:
        manifest = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ModelMissingError(f"unreadable {path} ({exc}): {hint}") from exc
    if manifest.get("format") != MANIFEST_FORMAT or not isinstance(manifest.get("files"), dict):
        raise ModelMissingError(
            f"{path} has format {manifest.get('format')!r}, this version needs {MANIFEST_FORMAT}: {hint}"
        )
    for name, entry in manifest["files"].items():
        if not (
            isinstance(entry, dict) and isinstance(entry.get("sha256"), str) and isinstance(entry.get("size"), int)
        ):
            raise ModelMissingError(f"{path}: malformed entry for {name!r}: {hint}")
    return manifest


def verify_model_dir(model_dir: Path, required: Iterable[str] = (), hint: str = EXPORT_HINT) -> dict:
    """Check every manifest file's size and sha256; return the manifest or raise ``ModelMissingError``.

    Hashing all ~110 MB takes ~0.08 s (sha256 with CPU extensions, files in page cache), cheaper than
    creating the onnxruntime sessions, so every load re-checks rather than trusting a size/mtime cache.
    """
    model_dir = Path(model_dir)
    manifest = read_manifest(model_dir, hint)
    entries: dict = manifest["files"]
    missing_required = [name for name in required if name not in entries]
    if missing_required:
        raise ModelMissingError(f"{model_dir / MANIFEST_NAME} does not list {missing_required}: {hint}")
    for name, entry in entries.items():
        path = model_dir / name
        if not path.is_file():
            raise ModelMissingError(f"missing model file {path}: {hint}")
        size = path.stat().st_size
        if size != entry["size"]:
            raise ModelMissingError(
                f"model file {path} has {size} bytes, manifest says {entry['size']} (corrupt): {hint}"
            )
        if sha256_file(path) != entry["sha256"]:
            raise ModelMissingError(f"model file {path} does not match its sha256 (corrupt): {hint}")
    return manifest
