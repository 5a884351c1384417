"""Offline processing of a bag without any ROS graph: maps, keyframes and rejections in log-time order.

Keyframe messages go through the same ``KeyframeAssembler`` as in the live node, so offline results
equal those of a replay into the node. A map message that does not convert is yielded as a
``Rejection`` with reason ``bad_gaussians`` (role ``gaussians``); the stream goes on.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping

import msg_adapters as ma
from monovoc_ros.bags.reader import BagMessage, bag_info, iter_messages
from monovoc_ros.bags.schemas import normalize_type_name
from monovoc_ros.contract import (
    BAD_MESSAGE,
    DEFAULT_NAMESPACE,
    KEYFRAME_POSES_ROLE,
    MAP_ROLE,
    SEGMENTS_ROLE,
    topic_names,
)
from monovoc_ros.core.follow.keyframe_log import KeyframePoses
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.ingest import IngestConfig, KeyframeAssembler, Rejection

BAD_GAUSSIANS = "bad_gaussians"  # as the live node counts an unreadable map
BagEvent = GaussianMap | Keyframe | KeyframePoses | Rejection
_OWN_ROLES = (MAP_ROLE, KEYFRAME_POSES_ROLE)  # not keyframe inputs: converted here, not by the assembler


def bag_events(
    path: str | os.PathLike,
    ingest_config: IngestConfig | None = None,
    namespace: str = DEFAULT_NAMESPACE,
    *,
    topics: Mapping[str, str] | None = None,
    assembler: KeyframeAssembler | None = None,
) -> Iterator[BagEvent]:
    """Yields, in log-time order, each Gaussian map message as a ``GaussianMap`` and the ``Keyframe``s and
    ``Rejection``s of a ``KeyframeAssembler`` fed with the decoded keyframe messages.

    ``topics``: role -> topic overrides (roles image, mask, camera_info, pose, segments, gaussians), for bags
    recorded with other names. ``assembler``: pass one to read its counters afterwards. Without
    ``ingest_config``, a bag with a segments topic is read with ``use_segments`` (every mask waits for its
    SegmentArray); an explicit config is taken as given.
    """
    names = topic_names(namespace)
    if topics:
        unknown = set(topics) - set(names)
        if unknown:
            raise ValueError(f"unknown role(s) {sorted(unknown)}; roles are {sorted(names)}")
        names.update(topics)
    if assembler is None:
        config = ingest_config
        if config is None:  # read what the bag holds: its segments as a node with use_segments: true
            config = IngestConfig(use_segments=names[SEGMENTS_ROLE] in bag_info(path).topics)
        assembler = KeyframeAssembler(config)
    role_of = {topic: role for role, topic in names.items() if role in _OWN_ROLES or role in assembler.roles}
    for message in iter_messages(path, topics=list(role_of)):
        role = role_of[message.topic]
        if role == MAP_ROLE:
            yield _map_event(message)
            continue
        try:
            decoded = message.decode()
        except Exception as exc:  # a CDR payload that does not match its schema (truncated, corrupt)
            yield from _undecodable(assembler, role, message.log_time_ns, exc)
            continue
        if role == KEYFRAME_POSES_ROLE:
            try:
                yield ma.path_to_keyframe_poses(decoded, assembler.config.frame_convention)
            except ValueError as exc:
                yield Rejection(BAD_MESSAGE[role], role, _stamp_or_none(decoded), str(exc))
            continue
        keyframes, rejections = assembler.push(role, decoded)
        yield from rejections
        yield from keyframes


def _map_event(message: BagMessage) -> GaussianMap | Rejection:
    """A map message as the live node reads the topic's bytes (msg_adapters.gaussian_map_from_cdr, whose points are a
    view of the message until they are copied: mcap_ros2's decoder copied a 1M map's 57 MB first)."""
    try:
        type_name = normalize_type_name(message.type_name)
    except ValueError:
        type_name = message.type_name
    if message.encoding != "cdr" or type_name != ma.POINT_CLOUD_TYPE:
        what = f"{message.type_name or 'a message without a schema'} in {message.encoding!r}"
        return Rejection(BAD_GAUSSIANS, MAP_ROLE, message.log_time_ns, f"{what}, not a CDR PointCloud2")
    try:
        return ma.gaussian_map_from_cdr(message.data)[0]
    except ValueError as exc:
        return Rejection(BAD_GAUSSIANS, MAP_ROLE, message.log_time_ns, str(exc))


def _stamp_or_none(msg) -> int | None:
    try:
        return ma.header_stamp_ns(msg)
    except ValueError:
        return None


def _undecodable(assembler: KeyframeAssembler, role: str, log_time_ns: int, exc: Exception) -> Iterator[Rejection]:
    detail = f"undecodable CDR ({type(exc).__name__}: {exc})"
    if role == KEYFRAME_POSES_ROLE:
        yield Rejection(BAD_MESSAGE[role], role, log_time_ns, detail)
        return
    # Counted like any other bad message of that role, as the live node would (its rmw drops it).
    reason = BAD_MESSAGE[role]
    assembler.rejected[reason] += 1
    yield Rejection(reason, role, log_time_ns, detail)
