"""The embedding-backend interface and the factory that picks an implementation by name."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class EmbeddingBackend(Protocol):
    """Maps object crops and free text into one space where cosine similarity ranks matches.

    Both methods return float32 arrays of unit-norm rows, shape (n, dim); n may be 0.
    """

    name: str
    dim: int

    def embed_images(self, crops: Sequence[np.ndarray]) -> np.ndarray:
        """RGB uint8 (H, W, 3) crops of any size -> (n, dim)."""
        ...

    def embed_texts(self, texts: Sequence[str]) -> np.ndarray:
        """Free-text queries or descriptions -> (n, dim)."""
        ...


BACKENDS = ("conse", "clip_onnx")


def load_backend(name: str = "conse", **options) -> EmbeddingBackend:
    """Create a backend.

    - ``"conse"`` (default, offline): options ``model_dir``, ``threads``, ``top_k``, ``fit``
      (see :class:`monovoc_ros.embed.conse.ConseBackend`).
    - ``"clip_onnx"``: user-supplied CLIP-style ONNX files; options ``model_dir`` (required), ``threads``
      (see :class:`monovoc_ros.embed.clip_onnx.ClipOnnxBackend`).
    """
    if name == "conse":
        from monovoc_ros.embed.conse import ConseBackend

        return ConseBackend(**options)
    if name == "clip_onnx":
        from monovoc_ros.embed.clip_onnx import ClipOnnxBackend

        if "model_dir" not in options:
            raise ValueError("the clip_onnx backend needs model_dir=<directory with visual.onnx, textual.onnx, ...>")
        return ClipOnnxBackend(**options)
    raise ValueError(f"unknown embedding backend {name!r}; choose one of {', '.join(BACKENDS)}")
