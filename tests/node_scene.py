"""Shared by the test_node_* files (no tests here): the small synthetic scene, its messages, and the
offline reference run over the very same message objects."""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.mapping import SemanticMapper
from monovoc_ros.ingest import KeyframeAssembler
from monovoc_ros.nodes.keyframe_publisher import ROLE_ORDER, KeyframePublisher, keyframe_messages
from monovoc_ros.synthetic import SceneConfig, SyntheticScene, generate_scene

if TYPE_CHECKING:
    from monovoc_ros.ros_harness import ClientNode, NodeProcess

NODE = ["-m", "monovoc_ros.nodes.mapping_node"]
N_KEYFRAMES = 16


@functools.lru_cache(maxsize=1)
def small_scene() -> SyntheticScene:
    """30k Gaussians, 16 keyframes at 308x172: generated once per test session (shared by the files)."""
    return generate_scene(SceneConfig.at_resolution(308, 172, n_gaussians=30_000, n_keyframes=N_KEYFRAMES))


@functools.lru_cache(maxsize=1)
def scene_messages() -> tuple[dict, ...]:
    """role -> message per keyframe of `small_scene` (jpeg image, png mask, camera_info, pose)."""
    scene = small_scene()
    return tuple(keyframe_messages(scene.keyframe(i)) for i in range(len(scene)))


def assemble(messages, order=ROLE_ORDER) -> list[Keyframe]:
    """The keyframes an offline KeyframeAssembler makes of these messages (what the node must make)."""
    asm = KeyframeAssembler()
    keyframes = []
    for msgs in messages:
        for role in order:
            if role in msgs:
                keyframes += asm.push(role, msgs[role])[0]
    return keyframes


def offline_mapper(gaussians, keyframes) -> SemanticMapper:
    mapper = SemanticMapper(gaussians)
    for keyframe in keyframes:
        mapper.integrate(keyframe)
    return mapper


class RecordingLog:
    """A logger (info / warning / error) that keeps its lines, for the worker and session tests."""

    def __init__(self):
        self.lines = []

    def info(self, msg):
        self.lines.append(("info", msg))

    def warning(self, msg):
        self.lines.append(("warning", msg))

    def error(self, msg):
        self.lines.append(("error", msg))


@contextlib.contextmanager
def mapper_with_client(
    env: dict,
    params: dict,
    node_env: dict | None = None,
    *,
    remaps: dict[str, str] | None = None,
    name: str = "semantic_mapper",
) -> Iterator[tuple[NodeProcess, ClientNode]]:
    """The mapping node started with `params` (and topic `remaps`) in the ROS environment `env` (plus `node_env`,
    the node's only), its process called `name`, and a client node in `env`: (node, client), both stopped on exit."""
    from monovoc_ros.ros_harness import ClientNode, NodeProcess, ros_args

    with (
        NodeProcess.python([*NODE, *ros_args(params, remaps)], {**env, **(node_env or {})}, name=name) as node,
        ClientNode(env) as client,
    ):
        yield node, client


@dataclass(frozen=True)
class RunningMapper:
    node: Any  # the mapping node's NodeProcess
    diagnostics: Any  # DiagnosticsMonitor of its /diagnostics
    publisher: Any  # KeyframePublisher of its inputs (and its map)
    save: Any  # client of /monovoc/save_map (None when not asked for)
    env: dict  # the test's ROS environment (the client's; the node's less `node_env`)


@contextlib.contextmanager
def running_mapper(
    tmp_path: Path, params: dict, node_env: dict | None = None, *, save_map: bool = True
) -> Iterator[RunningMapper]:
    """The mapping node started with `params` in a test's own ROS environment (plus `node_env`, the node's
    only), and a client ready to talk to it: every input publisher matched and, with `save_map`, the save_map
    service up (without it no save_map client is made)."""
    from monovoc_interfaces.srv import SaveMap
    from monovoc_ros.ros_harness import DiagnosticsMonitor, wait_for_service, wait_for_subscribers
    from tests.rosutil import ros_environment

    env = ros_environment(tmp_path)
    with mapper_with_client(env, params, node_env) as (node, client):
        diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
        publisher = KeyframePublisher(client.node)
        save = client.node.create_client(SaveMap, "/monovoc/save_map") if save_map else None
        for pub in publisher.all_publishers():
            wait_for_subscribers(pub, timeout=20.0, process=node)
        if save is not None:
            wait_for_service(save, process=node)
        yield RunningMapper(node, diagnostics, publisher, save, env)
