"""Language embeddings for objects: pluggable image/text backends, object crops, attributes, retrieval.

Importing this package loads neither torch nor onnxruntime; backends load theirs when created.
"""

from monovoc_ros.embed.attributes import combine, describe, dominant_color_name
from monovoc_ros.embed.backend import BACKENDS, EmbeddingBackend, load_backend
from monovoc_ros.embed.crops import crop_object
from monovoc_ros.embed.model_store import ModelMissingError, default_model_dir
from monovoc_ros.embed.retrieval import rank, topk_accuracy

__all__ = [
    "BACKENDS",
    "EmbeddingBackend",
    "ModelMissingError",
    "combine",
    "crop_object",
    "default_model_dir",
    "describe",
    "dominant_color_name",
    "load_backend",
    "rank",
    "topk_accuracy",
]
