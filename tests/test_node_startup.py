"""The node's start-up on a robot's timeline (issue 24): a Ctrl-C while it starts ends the start at once
with the map directory untouched, and keyframes a stopping node deferred to its snapshot are integrated
first when it resumes."""

from __future__ import annotations

import os
import signal
import subprocess
import time

import numpy as np
import pytest

from monovoc_ros.core.map_store import load_deferred, load_snapshot, save_snapshot
from monovoc_ros.core.mapping import SemanticMapper
from monovoc_ros.ros_harness import ClientNode, DiagnosticsMonitor, NodeProcess, ros_args, wait_until
from tests.node_scene import NODE, assemble, scene_messages, small_scene
from tests.rosutil import ros_environment

pytestmark = pytest.mark.ros


def tree(directory) -> dict[str, tuple[int, int]]:
    """Every file under `directory` with its size and modification time (ns)."""
    out = {}
    for root, _, files in os.walk(directory):
        for name in files:
            st = os.stat(os.path.join(root, name))
            out[os.path.relpath(os.path.join(root, name), directory)] = (st.st_size, st.st_mtime_ns)
    return out


def warm_up_children() -> list[str]:
    found = subprocess.run(["pgrep", "-f", "monovoc_ros.cli warm-up"], capture_output=True, text=True)
    return found.stdout.split()


def test_sigint_while_the_kernels_compile_ends_the_start_at_once_and_writes_nothing(tmp_path):
    scene = small_scene()
    keyframes = assemble(scene_messages())
    mapper = SemanticMapper(scene.gaussians)
    for keyframe in keyframes[:3]:
        mapper.integrate(keyframe)
    map_dir = tmp_path / "map"
    save_snapshot(mapper, map_dir, deferred=keyframes[3:5])
    before = tree(map_dir)
    cold = tmp_path / "numba_cache"  # an empty cache: a fresh install compiles its kernels at start
    cold.mkdir()
    env = ros_environment(tmp_path, extra={"NUMBA_CACHE_DIR": str(cold)})
    params = {"map_directory": str(map_dir), "resume": True, "save_period_s": 0.0}
    with NodeProcess.python([*NODE, *ros_args(params)], env, name="semantic_mapper") as node:
        wait_until(lambda: bool(warm_up_children()), 60.0, "the warm-up child to start", process=node)
        start = time.monotonic()
        os.kill(node.pid, signal.SIGINT)
        wait_until(lambda: not node.running(), 10.0, "the node to exit")
        seconds = time.monotonic() - start
        assert node.returncode == 0, node.describe()
    assert seconds < 5.0, seconds  # well inside ros2 launch's SIGTERM grace
    assert "stop requested during start-up (the kernels were compiling): exiting, nothing written" in node.output()
    assert "Traceback" not in node.output()
    assert tree(map_dir) == before  # the snapshot and its deferred keyframes untouched
    wait_until(lambda: not warm_up_children(), 10.0, "the warm-up child to be gone")


def test_keyframes_deferred_by_the_last_run_are_integrated_first_on_resume(tmp_path):
    scene, messages = small_scene(), scene_messages()
    keyframes = assemble(messages)
    mapper = SemanticMapper(scene.gaussians)
    for keyframe in keyframes[:2]:
        mapper.integrate(keyframe)
    map_dir = tmp_path / "map"
    save_snapshot(mapper, map_dir, deferred=keyframes[2:6])  # what a stop with no time left writes
    env = ros_environment(tmp_path)
    params = {"map_directory": str(map_dir), "resume": True, "save_period_s": 0.0, "diagnostics_period_s": 0.2}
    with (
        NodeProcess.python([*NODE, *ros_args(params)], env, name="semantic_mapper") as node,
        ClientNode(env) as client,
    ):
        diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
        diagnostics.wait_for(lambda v: v["keyframes_processed"] == "4" and v["queue_length"] == "0", 30.0, process=node)
        assert node.stop() == 0, node.describe()
    saved = load_snapshot(map_dir)
    assert saved.n_keyframes == 6 and load_deferred(map_dir) == []
    reference = SemanticMapper(scene.gaussians)
    for keyframe in keyframes[:6]:
        reference.integrate(keyframe)
    assert np.array_equal(saved.result().object_ids, reference.result().object_ids)


def test_a_stop_while_the_node_still_imports_is_one_line(tmp_path, monkeypatch, capsys):
    """The console scripts (nodes/entry.py) import the node when run: a SIGINT landing in an import (a launch that
    stops at once because its bag cannot be replayed) ends it as a stop during start-up does, without a traceback."""
    from monovoc_ros.nodes import entry

    (tmp_path / "interrupted_node.py").write_text("raise KeyboardInterrupt\n")  # the signal, inside the import
    monkeypatch.syspath_prepend(str(tmp_path))
    assert entry._run("interrupted_node") == 0
    assert (
        capsys.readouterr().err
        == "interrupted_node: stop requested during start-up (importing): exiting, nothing written\n"
    )
    (tmp_path / "finished_node.py").write_text("def main():\n    return 3\n")
    assert entry._run("finished_node") == 3  # otherwise the node's main, its exit code passed on
