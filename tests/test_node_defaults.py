"""The shipped defaults (issue 9, case 9): a `--fast` replay of the bundled bag into the node started with
config/semantic_mapper.yaml and config/object_query.yaml integrates every keyframe (26 of 60 were dropped
with the old queue_size of 32)."""

from __future__ import annotations

import pytest

from monovoc_ros.bags import bag_info
from monovoc_ros.embed import default_model_dir
from monovoc_ros.ros_harness import ClientNode, DiagnosticsMonitor, NodeProcess, wait_until
from tests.rosutil import REPO, ros_environment

pytestmark = pytest.mark.ros

BAG = REPO / "bags" / "synthetic_room.mcap"


def test_fast_replay_of_the_bundled_bag_with_the_shipped_yaml_loses_nothing(tmp_path):
    n = bag_info(BAG).topics["/monovoc/mask"].count
    env = ros_environment(tmp_path, extra={"MONOVOC_MODEL_DIR": str(default_model_dir())})
    config = ["--params-file", str(REPO / "config" / "semantic_mapper.yaml")]
    config += ["--params-file", str(REPO / "config" / "object_query.yaml")]
    node_args = ["-m", "monovoc_ros.nodes.semantic_mapper", "--ros-args", *config, "-p", "diagnostics_period_s:=0.5"]
    with NodeProcess.python(node_args, env, name="semantic_mapper") as node, ClientNode(env) as client:
        diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
        diagnostics.wait_for(lambda v: v["keyframes_processed"] == "0", 60.0, process=node)  # up and idle
        replay = ["-m", "monovoc_ros.cli", "replay", str(BAG), "--fast", "--wait-subscribers", "1"]
        with NodeProcess.python(replay, env, name="replay") as player:
            wait_until(lambda: player.returncode is not None, 120.0, "the replay to finish", process=node)
            assert player.returncode == 0, player.describe()
        done = diagnostics.wait_for(lambda v: v["keyframes_processed"] == str(n), 120.0, process=node)
        node.wait_for_output("queue 100", 10.0)  # the shipped default, as the node reports it at start
    assert done["keyframes_received"] == str(n) and done["keyframes_dropped"] == "0" and n == 60
    assert done["rejected_total"] == "0"
