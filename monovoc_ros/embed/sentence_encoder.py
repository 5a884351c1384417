"""all-MiniLM-L6-v2 sentence embeddings with onnxruntime + tokenizers (no torch/transformers at run time).

The exported graph already contains sentence-transformers' pipeline for this model (modules.json:
Transformer -> mean Pooling over the attention mask -> Normalize), so it returns unit (B, 384) vectors.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from tokenizers import Tokenizer

from monovoc_ros.embed.arrays import check_texts, l2_normalize
from monovoc_ros.embed.onnx_session import DEFAULT_THREADS, make_session

# sentence_bert_config.json of all-MiniLM-L6-v2; the tokenizer.json itself says 128 with fixed padding,
# which is not what sentence-transformers runs.
MAX_SEQ_LENGTH = 256
PAD_ID = 0
# Batches are padded to their longest text; chunking bounds memory for long lists (the 1000 prompts).
TEXT_BATCH = 64


def load_sentence_tokenizer(path: Path) -> Tokenizer:
    tokenizer = Tokenizer.from_file(str(path))
    tokenizer.no_padding()
    tokenizer.enable_padding(pad_id=PAD_ID, pad_token="[PAD]")
    tokenizer.enable_truncation(max_length=MAX_SEQ_LENGTH)
    return tokenizer


class SentenceEncoder:
    """Texts -> unit-norm float32 embeddings."""

    def __init__(self, onnx_path: Path, tokenizer_path: Path, threads: int = DEFAULT_THREADS) -> None:
        self.session = make_session(onnx_path, threads)
        self.tokenizer = load_sentence_tokenizer(tokenizer_path)
        self.dim = int(self.session.get_outputs()[0].shape[-1])

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        texts = check_texts(texts)
        if not texts:
            return np.zeros((0, self.dim), dtype=np.float32)
        out = []
        for start in range(0, len(texts), TEXT_BATCH):
            encodings = self.tokenizer.encode_batch(texts[start : start + TEXT_BATCH])
            ids = np.array([e.ids for e in encodings], dtype=np.int64)
            mask = np.array([e.attention_mask for e in encodings], dtype=np.int64)
            (emb,) = self.session.run(None, {"input_ids": ids, "attention_mask": mask})
            out.append(emb)
        # The graph normalises already; renormalising float32 output costs nothing and guards user exports.
        return l2_normalize(np.concatenate(out))
