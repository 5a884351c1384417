"""Shared by the test_node_* files (no tests here): the small synthetic scene, its messages, and the
offline reference run over the very same message objects."""

from __future__ import annotations

import functools

from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.mapping import SemanticMapper
from monovoc_ros.ingest import KeyframeAssembler
from monovoc_ros.nodes.keyframe_publisher import ROLE_ORDER, keyframe_messages
from monovoc_ros.synthetic import SceneConfig, SyntheticScene, generate_scene

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
