"""QoS profiles of the semantic_mapper topics (the topic contract of docs/interfaces.md).

* Keyframe inputs (image, mask, camera_info, pose): reliable by default (a bag replayed with --fast must
  not lose messages), volatile, keep-last `input_depth`; best effort for sensor-data publishers.
* The Gaussian map and every output (semantic cloud, objects, markers): reliable + transient-local, so a node
  or viewer that starts late still gets the latest one; depth 1, the map `MAP_DEPTH`. Big clouds must be
  reliable: best effort over the default Fast DDS shared-memory segment drops most of them (ROS_WHEELS.md).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rclpy.event_handler import PublisherEventCallbacks
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy


def input_qos(depth: int, reliability: str = "reliable") -> QoSProfile:
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE if reliability == "reliable" else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.VOLATILE,
    )


def latched_qos(depth: int = 1) -> QoSProfile:
    """Reliable, transient-local, keep-last `depth`: the latest message for late joiners (outputs; the map's
    subscription: `map_qos`)."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


# Depth of the Gaussian map subscription (the node's, or its map reader's). Maps that arrive together (a bag
# replayed with --fast, a SLAM catching up, a transient-local history delivered to a late joiner) each reach the
# node, which keeps the newest of those it could not take in time and counts the others (`maps_coalesced`). One
# deep, DDS overwrote them unseen: a --fast replay of a bag with three maps delivered one, counted nowhere. The
# cost: serialized maps waiting in the reader (~56 MB each at 1M Gaussians) only while the node is behind.
MAP_DEPTH = 8


def map_qos() -> QoSProfile:
    """The Gaussian map topic's subscription: latched, MAP_DEPTH deep."""
    return latched_qos(MAP_DEPTH)


DIAGNOSTICS_QOS = QoSProfile(depth=10)


def output_events(matched: Callable[[Any], None] | None = None) -> PublisherEventCallbacks:
    """Event callbacks of an output publisher (`latched_qos`, /diagnostics): `matched` only, without rclpy's
    default handlers. Those (incompatible QoS, incompatible type: two per publisher) are waitables the executor
    enters, counts, adds to its wait set and checks on every wake-up, in Python holding the interpreter: the
    node's 27 event handlers made each of its ~80 wake-ups a second cost ~0.6 ms there, while the worker waited
    for the interpreter between its kernels. They would tell nothing here: a reliable publisher offers the most
    a reader can request (no reader's QoS is incompatible with the latched outputs; /diagnostics' readers are
    volatile), and a reader of another type is told on its own side. The inputs' subscriptions keep them: a
    sensor's best-effort publisher is the usual reason a node hears nothing."""
    return PublisherEventCallbacks(matched=matched, use_default_callbacks=False)


# Services (query, save_map, load_map, reset, publish): reliable, keep-last 1000. With rclpy's default
# (keep-last 10) requests that arrived while the callbacks were busy overwrote each other: at 100 queries/s
# during mapping 30-43% were never answered. Clients that keep many requests in flight need the same depth
# for the answers (monovoc_ros.nodes.query_load.query_client).
SERVICE_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1000,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
