"""``monovoc_interfaces/SegmentArray``: a segmenter's class names for the segments of one mask, to and from
core.segments.segment_labels.SegmentLabel.

A segment's ``id`` is its value in the mask: the packed 0x00RRGGBB color of a color mask, or the instance id
of a mono8 / mono16 mask, which the ingest turns into the palette color it gives that id
(monovoc_ros.ingest.instance_segments) so that labels follow the mask.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from monovoc_ros.core.segments.segment_labels import SegmentLabel
from msg_adapters.errors import AdapterError
from msg_adapters.stamps import make_header

MAX_SEGMENTS = 65536  # more than any mask can hold legibly; a bigger message is refused before conversion


def segment_array_to_labels(msg: Any) -> tuple[SegmentLabel, ...]:
    """The segments of ``msg`` as SegmentLabels, ids as packed colors (the ingest maps the ids of an
    instance-id mask to its colors). Raises AdapterError."""
    segments = msg.segments
    if len(segments) > MAX_SEGMENTS:
        raise AdapterError(f"SegmentArray: {len(segments)} segments (at most {MAX_SEGMENTS})")
    try:
        return tuple(SegmentLabel(int(s.id), str(s.class_name), float(s.score)) for s in segments)
    except ValueError as exc:
        raise AdapterError(f"SegmentArray: {exc}") from None


def segment_array(labels: Sequence[SegmentLabel], *, frame_id: str = "", stamp: Any = 0):
    """A ``monovoc_interfaces.msg.SegmentArray`` (ids as given: packed colors for color masks)."""
    from monovoc_interfaces.msg import Segment, SegmentArray

    return SegmentArray(
        header=make_header(frame_id, stamp),
        segments=[Segment(id=int(s.id), class_name=str(s.class_name), score=float(s.score)) for s in labels],
    )
