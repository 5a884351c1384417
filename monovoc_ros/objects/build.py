"""Building an object index offline, while mapping (as the live node does): ``map_with_objects`` passes
``index.keyframe_listener`` as the per-keyframe hook and calls ``index.refresh(mapper)`` at the end; then
``save_object_index(index, map_dir, ...)``.
"""

from __future__ import annotations

import sys

from tqdm import tqdm

from monovoc_ros.core.evidence.palette import labels_from_entries
from monovoc_ros.core.mapping import MapperConfig, SemanticMapper
from monovoc_ros.objects.index import IndexConfig, ObjectIndex, lazy_backend


def map_with_objects(
    sequence,
    mapper_config: MapperConfig | None = None,
    index_config: IndexConfig | None = None,
    backend: object | None = None,
    *,
    stride: int = 1,
    max_keyframes: int | None = None,
    use_labels: bool = True,
    progress: bool = False,
) -> tuple[SemanticMapper, ObjectIndex]:
    """Maps a ``core.evaluation.datasets.Sequence`` (every ``stride``-th keyframe) and indexes its objects as the
    live node does (views offered after each integration). ``use_labels``: take class names from the
    sequence's labels (labels.json) unless ``index_config`` has its own."""
    gaussians = sequence.load_gaussians()
    if gaussians is None:
        raise ValueError(f"{sequence.name}: the sequence has no Gaussian map")
    config = index_config or IndexConfig()
    if use_labels and config.labels is None:
        labels = labels_from_entries(sequence.labels())
        if labels:
            config = IndexConfig(**{**config.__dict__, "labels": labels})
    mapper = SemanticMapper(gaussians, mapper_config)
    index = ObjectIndex(backend if backend is not None else lazy_backend("conse"), config)
    frames = range(0, len(sequence), max(1, int(stride)))
    if max_keyframes is not None:
        frames = frames[: int(max_keyframes)]
    for i in tqdm(frames, desc="map+views", unit="kf", disable=not progress, file=sys.stderr):
        keyframe = sequence.keyframe(i)
        mapper.integrate(keyframe)
        index.keyframe_listener(keyframe, mapper)
    index.refresh(mapper)
    return mapper, index
