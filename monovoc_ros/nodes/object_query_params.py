"""The parameters the object component (nodes.object_query) adds to the node: one specification each
(nodes.param_spec), with the object index's own defaults (IndexConfig). `config/object_query.yaml` and
the README table list them (a test checks both)."""

from __future__ import annotations

from monovoc_ros.embed.backend import BACKENDS
from monovoc_ros.nodes.param_spec import Param
from monovoc_ros.objects.index import CROP_MODES, LIVE_OBJECTS_PER_REFRESH, UP_AXES, IndexConfig

_INDEX = IndexConfig()

# Order = order in config/object_query.yaml and in the README table.
PARAMETERS: tuple[Param, ...] = (
    Param("query.top_k", _INDEX.default_top_k, "objects returned when a TextQuery asks for top_k = 0", low=1),
    Param("query.max_text_chars", _INDEX.max_query_chars, "longer query texts are truncated (the answer's message says so)", low=1),
    Param("query.highlight", True, "publish query/highlight (Gaussians) and query/markers for answers"),
    Param("query.highlight_rate_hz", 5.0, "max highlight publications per second (the newest answer wins)", above=0),
    Param("objects.backend", "conse", "embedding backend: 'conse' (offline default) or 'clip_onnx' (user-supplied)", choices=BACKENDS),
    Param("objects.model_dir", "", "embedding model directory (empty: ~/.cache/monovoc_ros/models)"),
    Param("objects.crop_mode", _INDEX.crop_mode, "object crops: 'soft' (context dimmed) or 'hard' (object only)", choices=CROP_MODES),
    Param("objects.views_per_object", _INDEX.views_per_object, "best keyframe views kept per object (by mask pixel count)", low=1),
    Param("objects.description_weight", _INDEX.description_weight, "share of the attribute description in each object's embedding (0-1)", low=0, high=1),
    Param("objects.min_gaussians", _INDEX.min_gaussians, "objects with fewer Gaussians are not listed", low=1),
    Param("objects.up_axis", _INDEX.up_axis, "up direction for sizes and heights: +x..-z, or 'auto' (cameras + flat surfaces)", choices=UP_AXES),
    Param("objects.max_objects_per_refresh", LIVE_OBJECTS_PER_REFRESH, "objects (re-)embedded per chunk of work", low=1),
)  # fmt: skip
