"""ROS 2 MCAP bags: writing, reading, conversion from sequences, offline events, replay and record.

ROS-graph free: ``writer``, ``reader``, ``convert``, ``events`` (rclpy is only used to serialize
message objects). ``replayer`` (``replay``) and ``recorder`` (``record``) talk to live topics.
The topic contract is ``monovoc_ros.contract``.
"""

from monovoc_ros.bags.convert import ConvertReport, sequence_to_bag
from monovoc_ros.bags.events import BAD_GAUSSIANS, bag_events
from monovoc_ros.bags.reader import BagError, BagInfo, BagMessage, TopicInfo, bag_info, bag_metadata, iter_messages
from monovoc_ros.bags.writer import BagWriter
from monovoc_ros.contract import (
    CAMERA_FRAME,
    DEFAULT_NAMESPACE,
    LABELS_METADATA,
    MAP_FRAME,
    SOURCE_METADATA,
    topic_names,
)


def bag_labels(path) -> list[dict]:
    """The palette labels stored in a bag (``monovoc_labels``; [] when absent)."""
    return bag_metadata(path, LABELS_METADATA) or []


def __getattr__(name: str):
    # replay / record need rclpy with a ROS environment: imported on first use only.
    if name == "replay":
        from monovoc_ros.bags.replayer import replay

        return replay
    if name == "record":
        from monovoc_ros.bags.recorder import record

        return record
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "BAD_GAUSSIANS",
    "CAMERA_FRAME",
    "DEFAULT_NAMESPACE",
    "LABELS_METADATA",
    "MAP_FRAME",
    "SOURCE_METADATA",
    "BagError",
    "BagInfo",
    "BagMessage",
    "BagWriter",
    "ConvertReport",
    "TopicInfo",
    "bag_events",
    "bag_info",
    "bag_labels",
    "bag_metadata",
    "iter_messages",
    "record",
    "replay",
    "sequence_to_bag",
    "topic_names",
]
