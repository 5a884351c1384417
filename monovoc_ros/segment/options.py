"""The segmenter's options: one declaration each, with its default, description and range.

The node declares its ROS parameters from :data:`OPTION_SPECS` and ``monovoc segment`` its flags, so a
default or a range lives here only.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields
from types import MappingProxyType


@dataclass(frozen=True)
class OptionSpec:
    name: str
    description: str
    low: float | None = None
    high: float | None = None


OPTION_SPECS: tuple[OptionSpec, ...] = (
    OptionSpec("score_threshold", "lowest detection confidence kept", 0.0, 1.0),
    OptionSpec("nms_iou", "box IoU above which the weaker of two detections is suppressed", 0.0, 1.0),
    OptionSpec(
        "class_agnostic",
        "suppress overlapping detections across classes and, where the model has an objectness output "
        "(YOLOv5/v7 layout), select them by objectness instead of objectness x class (a segment's score "
        "stays its class confidence)",
    ),
    OptionSpec("max_instances", "most instances kept per image (highest confidence first)", 1, 65535),
    OptionSpec("min_mask_area", "instances with fewer visible pixels (after overlaps) are dropped", 0, 1 << 24),
    OptionSpec("input_size", "network input's long side in pixels (a dynamic-shape model runs rectangular)", 32, 4096),
)


def parse_class_map(items: Iterable[str] | Mapping[str, str]) -> dict[str, str]:
    """``["dining table=table", "person="]`` -> {"dining table": "table", "person": ""} (empty = drop)."""
    if isinstance(items, Mapping):
        pairs = list(items.items())
    else:
        pairs = []
        for item in items:
            if "=" not in item:
                raise ValueError(f"class map entry {item!r} must read 'class=new name' ('class=' drops the class)")
            old, new = item.split("=", 1)
            pairs.append((old, new))
    out = {}
    for old, new in pairs:
        old, new = str(old).strip(), str(new).strip()
        if not old:
            raise ValueError("class map entry with an empty class name")
        out[old] = new
    return out


@dataclass(frozen=True)
class SegmenterOptions:
    # Class-agnostic at a low threshold: what the camera-to-map benchmark measured best (README; docs/results.md):
    # recall matters more than the class, which the map's objects sum over many frames.
    score_threshold: float = 0.1
    nms_iou: float = 0.45
    class_agnostic: bool = True
    max_instances: int = 100
    min_mask_area: int = 64
    input_size: int = 640
    # Renames classes; a class renamed to "" is dropped before suppression.
    class_map: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for spec in OPTION_SPECS:
            value = getattr(self, spec.name)
            if isinstance(value, bool) or spec.low is None:
                if not isinstance(value, bool):
                    raise ValueError(f"{spec.name} must be true or false, got {value!r}")
                continue
            if not (spec.low <= value <= spec.high):
                raise ValueError(f"{spec.name} must lie in [{spec.low}, {spec.high}], got {value!r}")
        object.__setattr__(self, "class_map", MappingProxyType(parse_class_map(self.class_map)))

    def rename(self, name: str) -> str:
        """The class's name after the class map ("" = dropped)."""
        return self.class_map.get(name, name)


def option_defaults() -> dict[str, object]:
    return {f.name: getattr(SegmenterOptions(), f.name) for f in fields(SegmenterOptions) if f.name != "class_map"}
