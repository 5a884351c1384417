"""The embedding-backend interface and the factory that picks an implementation by name."""

from __future__ import annotations

import importlib
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


# name -> (module, class): imported on first use (onnxruntime, tokenizers).
_IMPLEMENTATIONS = {
    "conse": ("monovoc_ros.embed.conse", "ConseBackend"),
    "clip_onnx": ("monovoc_ros.embed.clip_onnx", "ClipOnnxBackend"),
}
BACKENDS = tuple(_IMPLEMENTATIONS)


def backend_class(name: str) -> type:
    """The class of backend ``name``, its modules imported (no model loaded). Their import holds the interpreter
    0.1-0.3 s: a node does it before it serves (nodes/object_query.py), not while it answers queries."""
    if name not in _IMPLEMENTATIONS:
        raise ValueError(f"unknown embedding backend {name!r}; choose one of {', '.join(BACKENDS)}")
    module, cls = _IMPLEMENTATIONS[name]
    return getattr(importlib.import_module(module), cls)


def load_backend(name: str = "conse", **options) -> EmbeddingBackend:
    """Create a backend.

    - ``"conse"`` (default, offline): options ``model_dir``, ``threads``, ``top_k``, ``fit``
      (see :class:`monovoc_ros.embed.conse.ConseBackend`).
    - ``"clip_onnx"``: user-supplied CLIP-style ONNX files; options ``model_dir`` (required), ``threads``
      (see :class:`monovoc_ros.embed.clip_onnx.ClipOnnxBackend`).
    """
    cls = backend_class(name)
    if name == "clip_onnx" and "model_dir" not in options:
        raise ValueError("the clip_onnx backend needs model_dir=<directory with visual.onnx, textual.onnx, ...>")
    return cls(**options)
