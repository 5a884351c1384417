"""How components run beside the mapping node: what the node offers them (`MappingHost`) and what they offer
back (`Component`: start and stop).

The full node (monovoc_ros.nodes.semantic_mapper) composes the mapping node with the object database and
query service the way rclpy's executor examples compose nodes: its ``main`` creates both and wires them
through these two interfaces; a component never touches the mapping node itself.

Life cycle (monovoc_ros.nodes.mapping_node.run): every component's ``start`` runs before the mapping
worker starts (so its listeners see the first result, and a resumed component state is in place before
it), its ``stop`` after the worker stopped (so the final snapshot, and what its save listeners write
with it, comes first).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Protocol

from monovoc_ros.core.map_store import SnapshotInfo
from monovoc_ros.core.mapping import SemanticMapper
from monovoc_ros.core.session import KeyframeListener, LoadCheck
from monovoc_ros.nodes.outputs import LabelProvider
from monovoc_ros.nodes.worker import ResultListener

SaveListener = Callable[[str, SnapshotInfo, SemanticMapper], None]


class Component(Protocol):
    def start(self) -> None:
        """Registers listeners and starts the component's threads (before the mapping worker starts)."""
        ...

    def stop(self) -> None:
        """Ends the component's threads (after the mapping worker stopped)."""
        ...


@dataclass(frozen=True)
class MappingHost:
    """What the mapping node offers the components composed with it. Listeners run on the worker thread,
    in order with keyframes, map updates and services (monovoc_ros.nodes.worker)."""

    logger: Any  # the mapping node's logger: one log for the node and its components
    clock: Any  # the mapping node's clock (ROS time, /clock with use_sim_time): stamps of what components publish
    # create_publisher(type, topic, qos): a publisher of the mapping node (`ros2 node info` lists it there)
    create_publisher: Callable[..., Any]
    # create_service(type, name, handler, qos): a service of the mapping node, in a callback group of its own
    create_service: Callable[..., Any]
    # create_action_server(type, name, execute, goal, cancel) and create_action_client(type, name): actions of
    # the mapping node, in one reentrant callback group (an execute callback waits for other callbacks)
    create_action_server: Callable[..., Any]
    create_action_client: Callable[..., Any]
    # Read-only settings of the mapping node.
    frame_id: str
    marker_up: tuple[float, float, float]
    labels: Mapping[int, str]  # labels_file: object id -> class name
    map_directory: str
    resume: bool
    # The mapper: before the worker starts, the resumed one (or None); afterwards read it on the worker thread.
    mapper: Callable[[], SemanticMapper | None]
    busy: Callable[[], bool]  # keyframes wait or the worker is on a task (components defer heavy work)
    add_keyframe_listener: Callable[[KeyframeListener], None]  # fn(keyframe, mapper) after each keyframe
    add_result_listener: Callable[[ResultListener], None]  # fn(mapper, result) before each publication
    add_reset_listener: Callable[[Callable[[], None]], None]  # fn() after a reset
    add_save_listener: Callable[[SaveListener], None]  # see MapWorker.add_save_listener
    add_load_check: Callable[[LoadCheck], None]  # see MapWorker.add_load_check
    add_diagnostics_source: Callable[[Callable[[], dict[str, Any]]], None]  # fn() -> pairs for /diagnostics
    # Object labels (core.segments.object_labels): set_label_provider(fn), fn() -> {object id: ObjectLabel}, gives the
    # objects topic and its markers the labels a component knows (after labels_file and segment labels; one
    # provider; fn runs on the worker thread, so it returns a ready mapping). republish_objects() asks for
    # the last objects and markers again with the current labels (queued on the worker thread; when a
    # component's labels changed; requests queued meanwhile are coalesced).
    set_label_provider: Callable[[LabelProvider], None]
    republish_objects: Callable[[], None]
