"""QoS as rosbag2 stores it (channel metadata ``offered_qos_profiles``) and the profiles replay/record use.

rosbag2 (Jazzy, metadata version 9) writes, per channel, a YAML list of the publishers' offered
profiles with lower-case enum names. We write the same for converted and recorded bags, so replay
(ours or ``ros2 bag play``) knows which topics were latched: the Gaussian map is transient-local, so
a node started after the replay still receives it.
"""

from __future__ import annotations

from dataclasses import dataclass

import yaml

OFFERED_QOS_KEY = "offered_qos_profiles"
_INFINITE = {"sec": 9223372036, "nsec": 854775807}  # rmw's "infinite" duration, as rosbag2 writes it


@dataclass(frozen=True)
class OfferedQos:
    reliable: bool = True
    transient_local: bool = False
    depth: int = 10


def qos_items(profiles: list[OfferedQos]) -> list[dict]:
    """The profiles as rosbag2 Jazzy writes them (a list of dicts with lower-case enum names)."""
    return [
        {
            "history": "keep_last",
            "depth": int(p.depth),
            "reliability": "reliable" if p.reliable else "best_effort",
            "durability": "transient_local" if p.transient_local else "volatile",
            "deadline": dict(_INFINITE),
            "lifespan": dict(_INFINITE),
            "liveliness": "automatic",
            "liveliness_lease_duration": dict(_INFINITE),
            "avoid_ros_namespace_conventions": False,
        }
        for p in profiles
    ]


def qos_yaml(profiles: list[OfferedQos]) -> str:
    """rosbag2-compatible YAML for ``offered_qos_profiles`` (MCAP channel metadata)."""
    return yaml.safe_dump(qos_items(profiles), sort_keys=False)


def _enum(value: object, names: dict[int, str]) -> str:
    # rosbag2 before Jazzy wrote the rmw enum integers; Jazzy writes names.
    if isinstance(value, int):
        return names.get(value, "unknown")
    return str(value).lower()


def parse_qos_yaml(text: str) -> list[OfferedQos]:
    """The profiles of an ``offered_qos_profiles`` string (empty or unreadable: [])."""
    try:
        items = yaml.safe_load(text) if text else []
    except yaml.YAMLError:
        return []
    out = []
    for item in items or []:
        if not isinstance(item, dict):
            continue
        reliability = _enum(item.get("reliability", "reliable"), {1: "reliable", 2: "best_effort"})
        durability = _enum(item.get("durability", "volatile"), {1: "transient_local", 2: "volatile"})
        depth = item.get("depth", 10)
        out.append(OfferedQos(reliability != "best_effort", durability == "transient_local", int(depth or 10)))
    return out


def offered_from_endpoint(qos_profile) -> OfferedQos:
    """The OfferedQos of an rclpy ``QoSProfile`` (e.g. from ``get_publishers_info_by_topic``)."""
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    return OfferedQos(
        reliable=qos_profile.reliability == ReliabilityPolicy.RELIABLE,
        transient_local=qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL,
        depth=max(int(qos_profile.depth), 1),
    )


def rclpy_profile(*, reliable: bool = True, transient_local: bool = False, depth: int = 10):
    """An rclpy ``QoSProfile``, KEEP_LAST ``depth``."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=max(int(depth), 1),
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if transient_local else DurabilityPolicy.VOLATILE,
    )
