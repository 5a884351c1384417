"""A CLIP-style backend over user-supplied ONNX encoders (open_clip, Perception Encoder, ...).

No CLIP-family weights ship in any package usable offline, so users export the model they own once
(see :mod:`monovoc_ros.embed.clip_export`) into a directory holding:

- ``visual.onnx``: float32 images (B, 3, S, S), already normalised -> (B, D)
- ``textual.onnx``: int64 token ids (B, L) -> (B, D)
- ``tokenizer.json``: the text tokenizer in Hugging Face ``tokenizers`` format
- ``clip_config.json``: how to feed them, e.g. for open_clip ViT-B-32::

    {"image_size": 224,
     "image_mean": [0.48145466, 0.4578275, 0.40821073],
     "image_std": [0.26862954, 0.26130258, 0.27577711],
     "image_fit": "center_crop",
     "context_length": 77,
     "sot_id": 49406, "eot_id": 49407, "pad_id": 0,
     "lowercase": true,
     "tokenizer_adds_special_tokens": false}

Token ids are built as ``[sot] + tokenizer ids + [eot]`` (each only when not null), cut to
``context_length`` keeping ``eot`` last (open_clip does the same: its text tower pools at the
highest id, the eot), then padded with ``pad_id``. Set ``tokenizer_adds_special_tokens`` when the
tokenizer.json's own post-processor should add them instead.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import MISSING, asdict, dataclass, fields
from pathlib import Path

import numpy as np
from tokenizers import Tokenizer

from monovoc_ros.embed.arrays import check_rgb_crops, check_texts, l2_normalize
from monovoc_ros.embed.model_store import ModelMissingError
from monovoc_ros.embed.onnx_session import DEFAULT_THREADS, make_session
from monovoc_ros.embed.preprocess import fit_square, to_nchw

VISUAL_ONNX = "visual.onnx"
TEXTUAL_ONNX = "textual.onnx"
TOKENIZER_JSON = "tokenizer.json"
CONFIG_JSON = "clip_config.json"
CLIP_FILES = (VISUAL_ONNX, TEXTUAL_ONNX, TOKENIZER_JSON, CONFIG_JSON)
BATCH = 16


@dataclass(frozen=True)
class ClipConfig:
    image_size: int
    image_mean: tuple[float, float, float]
    image_std: tuple[float, float, float]
    context_length: int
    image_fit: str = "center_crop"
    sot_id: int | None = None
    eot_id: int | None = None
    pad_id: int = 0
    lowercase: bool = True
    tokenizer_adds_special_tokens: bool = False

    def __post_init__(self) -> None:
        if int(self.image_size) < 1 or int(self.context_length) < 2:
            raise ValueError(f"invalid image_size {self.image_size} or context_length {self.context_length}")
        for key in ("image_mean", "image_std"):
            value = getattr(self, key)
            if len(value) != 3 or not all(np.isfinite(value)):
                raise ValueError(f"{key} must be 3 finite numbers (RGB, for pixels scaled to [0, 1]), got {value}")
            object.__setattr__(self, key, tuple(float(v) for v in value))
        if min(self.image_std) <= 0:
            raise ValueError(f"image_std must be positive, got {self.image_std}")
        if self.image_fit not in ("center_crop", "pad"):
            raise ValueError(f"image_fit must be 'center_crop' or 'pad', got {self.image_fit!r}")

    @classmethod
    def from_dict(cls, data: dict) -> ClipConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown {CONFIG_JSON} keys {unknown}; known keys: {sorted(known)}")
        missing = sorted(f.name for f in fields(cls) if f.default is MISSING and f.name not in data)
        if missing:
            raise ValueError(f"{CONFIG_JSON} lacks required keys {missing}")
        return cls(**data)

    def to_dict(self) -> dict:
        data = asdict(self)
        data["image_mean"], data["image_std"] = list(self.image_mean), list(self.image_std)
        return data


class ClipOnnxBackend:
    name = "clip_onnx"

    def __init__(self, model_dir: str | Path, *, threads: int = DEFAULT_THREADS) -> None:
        self.model_dir = Path(model_dir).expanduser()
        missing = [name for name in CLIP_FILES if not (self.model_dir / name).is_file()]
        if missing:
            raise ModelMissingError(
                f"clip_onnx model directory {self.model_dir} lacks {', '.join(missing)}; it needs "
                f"{', '.join(CLIP_FILES)} (see monovoc_ros/embed/clip_onnx.py and "
                "`python -m monovoc_ros.embed.clip_export --help`)"
            )
        try:
            self.config = ClipConfig.from_dict(json.loads((self.model_dir / CONFIG_JSON).read_text()))
        except (json.JSONDecodeError, TypeError, ValueError) as exc:
            raise ValueError(f"invalid {self.model_dir / CONFIG_JSON}: {exc}") from exc
        self.tokenizer = Tokenizer.from_file(str(self.model_dir / TOKENIZER_JSON))
        # Padding and truncation are done by _token_ids, which knows where eot must go.
        self.tokenizer.no_padding()
        self.tokenizer.no_truncation()
        self.visual = make_session(self.model_dir / VISUAL_ONNX, threads)
        self.textual = make_session(self.model_dir / TEXTUAL_ONNX, threads)
        self._visual_input = self.visual.get_inputs()[0].name
        self._textual_input = self.textual.get_inputs()[0].name
        self._check_inputs()
        self.dim = self._check_output_dims()

    def _check_inputs(self) -> None:
        size, length = self.config.image_size, self.config.context_length
        vshape = self.visual.get_inputs()[0].shape
        if len(vshape) != 4 or (isinstance(vshape[1], int) and vshape[1] != 3):
            raise ValueError(f"{VISUAL_ONNX} must take (B, 3, S, S) images, its input is {vshape}")
        for axis in (2, 3):
            if isinstance(vshape[axis], int) and vshape[axis] != size:
                raise ValueError(f"{VISUAL_ONNX} takes {vshape[2]}x{vshape[3]} images but image_size is {size}")
        tinput = self.textual.get_inputs()[0]
        if len(tinput.shape) != 2 or tinput.type != "tensor(int64)":
            raise ValueError(
                f"{TEXTUAL_ONNX} must take (B, L) int64 token ids, its input is {tinput.type} {tinput.shape}"
            )
        if isinstance(tinput.shape[1], int) and tinput.shape[1] != length:
            raise ValueError(f"{TEXTUAL_ONNX} takes {tinput.shape[1]} tokens but context_length is {length}")

    def _check_output_dims(self) -> int:
        # Probe with one dummy input each: exported output shapes are often symbolic.
        image_dim = self._run_visual(np.zeros((1, 3, self.config.image_size, self.config.image_size), np.float32))
        text_dim = self._run_textual(self.token_ids([""]))
        if image_dim.ndim != 2 or text_dim.ndim != 2:
            raise ValueError(f"encoders must return (B, D), got {image_dim.shape} and {text_dim.shape}")
        if image_dim.shape[1] != text_dim.shape[1]:
            raise ValueError(
                f"mismatched embedding dims: {VISUAL_ONNX} returns {image_dim.shape[1]}, "
                f"{TEXTUAL_ONNX} returns {text_dim.shape[1]}"
            )
        return int(image_dim.shape[1])

    def _run_visual(self, pixels: np.ndarray) -> np.ndarray:
        return np.asarray(self.visual.run(None, {self._visual_input: pixels})[0], dtype=np.float32)

    def _run_textual(self, ids: np.ndarray) -> np.ndarray:
        return np.asarray(self.textual.run(None, {self._textual_input: ids})[0], dtype=np.float32)

    def token_ids(self, texts: Sequence[str]) -> np.ndarray:
        """(n, context_length) int64 ids exactly as fed to the text encoder."""
        cfg = self.config
        texts = check_texts(texts)
        if cfg.lowercase:
            texts = [" ".join(t.split()).lower() for t in texts]
        out = np.full((len(texts), cfg.context_length), cfg.pad_id, dtype=np.int64)
        for row, encoding in enumerate(
            self.tokenizer.encode_batch(texts, add_special_tokens=cfg.tokenizer_adds_special_tokens)
        ):
            ids = list(encoding.ids)
            if cfg.sot_id is not None:
                ids.insert(0, cfg.sot_id)
            if cfg.eot_id is not None:
                ids.append(cfg.eot_id)
            if len(ids) > cfg.context_length:
                ids = ids[: cfg.context_length]
                if cfg.eot_id is not None:
                    ids[-1] = cfg.eot_id
            out[row, : len(ids)] = ids
        return out

    def embed_images(self, crops: Sequence[np.ndarray]) -> np.ndarray:
        crops = check_rgb_crops(crops)
        if not crops:
            return np.zeros((0, self.dim), dtype=np.float32)
        cfg = self.config
        mean, std = np.array(cfg.image_mean), np.array(cfg.image_std)
        out = []
        for start in range(0, len(crops), BATCH):
            fitted = [fit_square(c, cfg.image_size, cfg.image_fit) for c in crops[start : start + BATCH]]
            out.append(self._run_visual(to_nchw(fitted, mean, std, scale=1.0 / 255.0)))
        return l2_normalize(np.concatenate(out))

    def embed_texts(self, texts: Sequence[str]) -> np.ndarray:
        ids = self.token_ids(texts)
        if len(ids) == 0:
            return np.zeros((0, self.dim), dtype=np.float32)
        return l2_normalize(np.concatenate([self._run_textual(ids[i : i + BATCH]) for i in range(0, len(ids), BATCH)]))
