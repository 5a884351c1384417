"""Export a CLIP-style model you own into a directory the ``clip_onnx`` backend loads.

For open_clip models (needs ``pip install open_clip_torch`` and your weights file; nothing is
downloaded when ``--pretrained`` is a local path)::

    # tokenizer.json for open_clip's CLIP BPE, saved once from a local copy of the Hugging Face files:
    #   from transformers import CLIPTokenizerFast
    #   tok = CLIPTokenizerFast.from_pretrained("<local openai/clip-vit-base-patch32 dir>")
    #   tok.backend_tokenizer.save("tokenizer.json")
    python -m monovoc_ros.embed.clip_export --model ViT-B-32 --pretrained /path/to/open_clip_model.bin \\
        --tokenizer-json tokenizer.json --out ~/models/clip_vit_b32
    # then: load_backend("clip_onnx", model_dir="~/models/clip_vit_b32")

Any other model works through :func:`export_clip_onnx` if it has ``encode_image(images)`` and
``encode_text(token_ids)`` methods (Perception Encoder's open_clip-style CLIP class has both); write the
matching :class:`~monovoc_ros.embed.clip_onnx.ClipConfig` for its preprocessing and tokens.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import warnings
from pathlib import Path

import numpy as np

from monovoc_ros.embed.clip_onnx import CONFIG_JSON, TEXTUAL_ONNX, TOKENIZER_JSON, VISUAL_ONNX, ClipConfig
from monovoc_ros.embed.export import OPSET, ExportError

# Transformers exported in float32 reproduce torch to ~1e-6 relative; allow headroom for deep ViTs.
RELATIVE_TOLERANCE = 1e-4


def export_clip_onnx(model, out_dir: str | Path, tokenizer_json: str | Path, config: ClipConfig | dict) -> Path:
    """Write visual.onnx, textual.onnx, tokenizer.json and clip_config.json into ``out_dir`` and check that
    onnxruntime reproduces ``model.encode_image`` / ``model.encode_text``; raise ``ExportError`` if not."""
    import torch

    config = config if isinstance(config, ClipConfig) else ClipConfig.from_dict(config)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    model = model.eval()

    class Visual(torch.nn.Module):
        def __init__(self, clip: torch.nn.Module) -> None:
            super().__init__()
            self.clip = clip

        def forward(self, images: torch.Tensor) -> torch.Tensor:
            return self.clip.encode_image(images)

    class Textual(torch.nn.Module):
        def __init__(self, clip: torch.nn.Module) -> None:
            super().__init__()
            self.clip = clip

        def forward(self, token_ids: torch.Tensor) -> torch.Tensor:
            return self.clip.encode_text(token_ids)

    size, length = config.image_size, config.context_length
    images = torch.from_numpy(np.random.default_rng(0).normal(size=(2, 3, size, size)).astype(np.float32))
    shutil.copyfile(tokenizer_json, out_dir / TOKENIZER_JSON)
    (out_dir / CONFIG_JSON).write_text(json.dumps(config.to_dict(), indent=2) + "\n")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # legacy-exporter deprecation and tracer chatter; checked numerically below
        torch.onnx.export(
            Visual(model).eval(),
            (images,),
            str(out_dir / VISUAL_ONNX),
            input_names=["images"],
            output_names=["embedding"],
            dynamic_axes={"images": {0: "batch"}, "embedding": {0: "batch"}},
            opset_version=OPSET,
            dynamo=False,
        )
        # Any ids trace the same graph (fixed length L); real tokenized texts are checked below.
        tokens = torch.zeros((2, length), dtype=torch.int64)
        torch.onnx.export(
            Textual(model).eval(),
            (tokens,),
            str(out_dir / TEXTUAL_ONNX),
            input_names=["token_ids"],
            output_names=["embedding"],
            dynamic_axes={"token_ids": {0: "batch"}, "embedding": {0: "batch"}},
            opset_version=OPSET,
            dynamo=False,
        )
    from monovoc_ros.embed.clip_onnx import ClipOnnxBackend

    backend = ClipOnnxBackend(out_dir)
    token_ids = backend.token_ids(["a photo of a chair", "the red mug on the kitchen table", "lamp"])
    with torch.no_grad():
        expected_image = model.encode_image(images).numpy()
        expected_text = model.encode_text(torch.from_numpy(token_ids)).numpy()
    got_image = backend._run_visual(images.numpy())
    got_text = backend._run_textual(token_ids)
    for name, got, expected in ((VISUAL_ONNX, got_image, expected_image), (TEXTUAL_ONNX, got_text, expected_text)):
        scale = max(1e-6, float(np.max(np.abs(expected))))
        err = float(np.max(np.abs(got - expected))) / scale
        if got.shape != expected.shape or not err <= RELATIVE_TOLERANCE:
            raise ExportError(f"{name}: onnxruntime differs from torch (relative error {err:.3g}, shapes {got.shape})")
    return out_dir


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m monovoc_ros.embed.clip_export",
        description="Export an open_clip model you own to ONNX for the clip_onnx embedding backend.",
    )
    parser.add_argument("--model", required=True, help="open_clip architecture name, e.g. ViT-B-32")
    parser.add_argument("--pretrained", required=True, help="local weights file (nothing is downloaded)")
    parser.add_argument("--tokenizer-json", required=True, type=Path, help="the model's tokenizer in tokenizers format")
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--sot-id", type=int, default=49406, help="start-of-text id (CLIP BPE: 49406)")
    parser.add_argument("--eot-id", type=int, default=49407, help="end-of-text id (CLIP BPE: 49407)")
    args = parser.parse_args(argv)
    try:
        import open_clip
    except ImportError:
        print("clip_export needs open_clip: pip install open_clip_torch", file=sys.stderr)
        return 1
    model, _, _ = open_clip.create_model_and_transforms(args.model, pretrained=str(args.pretrained))
    preprocess = getattr(model.visual, "preprocess_cfg", {})
    size = preprocess.get("size", model.visual.image_size)
    size = size[0] if isinstance(size, list | tuple) else size
    config = ClipConfig(
        image_size=int(size),
        image_mean=tuple(preprocess.get("mean", open_clip.OPENAI_DATASET_MEAN)),
        image_std=tuple(preprocess.get("std", open_clip.OPENAI_DATASET_STD)),
        context_length=int(model.context_length),
        sot_id=args.sot_id,
        eot_id=args.eot_id,
    )
    try:
        export_clip_onnx(model, args.out, args.tokenizer_json, config)
    except ExportError as exc:
        print(f"clip_export failed: {exc}", file=sys.stderr)
        return 1
    print(f"exported {args.model} to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
