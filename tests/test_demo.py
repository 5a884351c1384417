"""`monovoc demo` end to end: a bag replayed into the live node (a separate process), against `monovoc map --bag`.

The demo starts the semantic_mapper with its query service, replays the bag with the player of `monovoc
replay`, and scores the semantic cloud it received. The same bag mapped offline (no ROS graph) must give
the very same labels: same messages, same assembler, same mapper.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from monovoc_ros.bags import sequence_to_bag
from monovoc_ros.cli import main
from monovoc_ros.commands.eval import bag_frames, score
from monovoc_ros.core.map_store import load_snapshot
from monovoc_ros.embed import default_model_dir
from tests.node_scene import N_KEYFRAMES, small_scene
from tests.rosutil import VENV_PYTHON, ros_environment

pytestmark = pytest.mark.ros


def test_demo_replays_a_bag_into_the_live_node_and_matches_offline_mapping(tmp_path):
    bag = tmp_path / "room.mcap"
    sequence_to_bag(small_scene(), bag)
    out = tmp_path / "demo"
    env = ros_environment(tmp_path, extra={"MONOVOC_MODEL_DIR": str(default_model_dir())})
    command = [str(VENV_PYTHON), "-m", "monovoc_ros.cli", "demo", "--bag", str(bag), "-o", str(out)]
    command += ["--query", "a sofa", "--query", "a lamp", "--timeout", "120"]
    run = subprocess.run(command, env=env, capture_output=True, text=True, timeout=400)
    log = (out / "semantic_mapper.log").read_text() if (out / "semantic_mapper.log").exists() else ""
    assert run.returncode == 0, f"{run.stdout}\n{run.stderr}\n{log[-3000:]}"
    summary = json.loads((out / "demo.json").read_text())

    # Every keyframe sent was integrated; nothing dropped.
    assert summary["keyframes_sent"] == N_KEYFRAMES == summary["keyframes_processed"]
    assert summary["keyframes_dropped"] == 0
    assert summary["objects"] > 10 and summary["objects_embedded"] > 10
    for name in ("semantic_ply", "object_database", "figure"):
        assert Path(summary[name]).is_file(), name
    sofa, lamp = summary["queries"]
    assert sofa["success"] and lamp["success"] and len(sofa["objects"]) == 3
    assert "sofa" in [o["label"] for o in sofa["objects"]]
    assert "query: 'a sofa'" in run.stdout and "score" in run.stdout

    # The same bag mapped offline (`monovoc map --bag`): identical labels, and the live cloud scores what the
    # offline map does.
    assert main(["map", "--bag", str(bag), "-o", str(tmp_path / "offline"), "--quiet"]) == 0
    assert json.loads((tmp_path / "offline" / "summary.json").read_text())["keyframes"] == N_KEYFRAMES
    mapper = load_snapshot(tmp_path / "offline")
    expected = mapper.result()
    saved = load_snapshot(summary["map_directory"])
    np.testing.assert_array_equal(saved.result().object_ids, expected.object_ids)
    np.testing.assert_array_equal(saved.state.stamps_ns, mapper.state.stamps_ns)
    reference, _ = score(mapper.gaussians, expected.object_ids, bag_frames(bag, every=3), "points", 0.05)
    assert summary["miou_points"] >= reference["miou"] - 0.01, (summary["miou_points"], reference["miou"])
    splats, _ = score(mapper.gaussians, expected.object_ids, bag_frames(bag, every=3), "splats", 0.05)
    assert summary["miou_splats"] == round(splats["miou"], 4) and summary["miou_splats"] > 0.5
