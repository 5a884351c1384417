"""The real ROS 2 command line (upstream ros2cli / launch wheels from ../shared/ros2_tools, installed into the
venv by scripts/install.sh, with the development install registered in the venv's ament index) against the
nodes, with the README's commands as a user types them:

* `ros2 launch ... bag:=...` integrates all 60 keyframes of the bundled bag, twice; Ctrl-C sent to the
  launch's whole process group (as a terminal does) stops everything with the final snapshot written;
* `ros2 node list` names every node once; `ros2 param get` answers 5 of 5, `ros2 param describe` shows the
  range; `ros2 service call /monovoc/query ...` and `ros2 topic echo --once /monovoc/objects` answer;
* `ros2 run monovoc_ros semantic_mapper` and a plain `monovoc replay --fast` started as soon as the query
  service appears: 60 of 60.
"""

from __future__ import annotations

import shlex
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from monovoc_ros.bags import bag_info
from monovoc_ros.core.map_store import load_deferred, load_snapshot
from monovoc_ros.embed import default_model_dir
from monovoc_ros.ros_harness import ClientNode, DiagnosticsMonitor, NodeProcess, wait_for_service, wait_until
from tests.rosutil import REPO, ros_environment

pytestmark = [pytest.mark.ros, pytest.mark.slow]

BAG = REPO / "bags" / "synthetic_room.mcap"
KEYFRAMES = bag_info(BAG).topics["/monovoc/mask"].count


def readme_live_launch() -> str:
    """The first command of the README's "Launch file and RViz" block: the node on a robot's topics."""
    text = (REPO / "README.md").read_text()
    section = text[text.index("### Launch file and RViz") :]
    block = section[section.index("```bash\n") + 8 :]
    return block[: block.index("```")].replace("\\\n", " ").splitlines()[0].strip()


def readme_session() -> list[str]:
    """The commands of the README's "With the ROS 2 command line" block."""
    text = (REPO / "README.md").read_text()
    section = text[text.index("### With the ROS 2 command line") :]
    block = section[section.index("```bash\n") + 8 :]
    return [line.strip() for line in block[: block.index("```")].splitlines() if line.strip()]


@pytest.fixture()
def env(tmp_path) -> Iterator[dict]:
    if shutil.which("ros2") is None:
        pytest.fail("no `ros2` on PATH: scripts/install.sh installs it from ../shared/ros2_tools")
    env = ros_environment(tmp_path, extra={"MONOVOC_MODEL_DIR": str(default_model_dir())})
    yield env
    # `ros2 param` and `ros2 node` start a daemon for the test's domain, which outlived the test run.
    ros2("ros2 daemon stop", env)


def ros2(command: str, env: dict, timeout: float = 60.0) -> subprocess.CompletedProcess:
    """One README line in bash ($HOME expands to the test's home)."""
    return subprocess.run(["bash", "-c", command], env=env, cwd=REPO, capture_output=True, text=True, timeout=timeout)


def answered(command: str, env: dict, expected: str, timeout: float = 60.0) -> str:
    """Runs `command` until its output holds `expected` (the daemon's first answers may predate discovery)."""
    out: list[str] = []

    def done() -> bool:
        result = ros2(command, env)
        out[:] = [result.stdout + result.stderr]
        return result.returncode == 0 and expected in result.stdout

    wait_until(done, timeout, f"`{command}` to print {expected!r}", interval=0.5)
    return out[0]


def launch(line: str, env: dict, name: str) -> NodeProcess:
    assert line.startswith("ros2 launch monovoc_ros monovoc.launch.py ")
    return NodeProcess(["bash", "-c", "exec " + line.removesuffix("&").strip()], env, name=name, cwd=REPO,
                       process_group=True)  # fmt: skip


def snapshot_keyframes(env: dict, line: str) -> int:
    map_dir = shlex.split(line.split("map_directory:=")[1])[0].replace("$HOME", env["HOME"])
    return load_snapshot(Path(map_dir)).n_keyframes


def integrate_the_bag(process: NodeProcess, client: ClientNode) -> None:
    diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
    process.wait_for_output('"unmatched": []', 120.0)  # the replay's summary: every keyframe topic matched
    diagnostics.wait_for(lambda v: v["keyframes_processed"] == str(KEYFRAMES), 120.0, process=process)


def test_launch_with_a_bag_and_the_ros2_command_line(env):
    launch_line, node_list, param_get, param_describe, service_call, topic_echo, node_info = readme_session()
    # As on a robot where it already runs: the first `ros2` command would start the daemon and answer
    # without it, and the next one would ask a daemon that has not discovered the graph yet.
    assert ros2("ros2 daemon start", env).returncode == 0
    try:
        with launch(launch_line, env, "ros2_launch_1") as process, ClientNode(env) as client:
            integrate_the_bag(process, client)
            nodes = answered(node_list, env, "/monovoc/semantic_mapper")  # the daemon knows the graph
            listed = [line for line in nodes.splitlines() if line.startswith("/")]
            assert [n for n in listed if n.startswith("/monovoc/")] == ["/monovoc/semantic_mapper"], nodes
            assert "share an exact name" not in nodes
            info = answered(node_info, env, "/monovoc/query: monovoc_interfaces/srv/TextQuery")
            assert "/monovoc/save_map: monovoc_interfaces/srv/SaveMap" in info, info
            for _ in range(5):
                got = ros2(param_get, env)
                assert got.returncode == 0 and got.stdout.strip() == "Integer value is: 4", got.stdout + got.stderr
            described = answered(param_describe, env, "Min value: 1")
            assert "Max value: 16" in described, described
            answer = answered(service_call, env, "success=True", timeout=120.0)
            first = answer[answer.index("monovoc_interfaces.msg.SemanticObject(") :]
            assert "label='sofa', label_source='given'" in first[: first.index("description=")], answer
            echoed = answered(topic_echo, env, "objects:")
            assert echoed.count("num_gaussians:") >= 5, echoed
            assert process.stop() == 0, process.describe()  # SIGINT to the process group
        assert "Traceback" not in process.output()
        assert snapshot_keyframes(env, launch_line) == KEYFRAMES, process.describe()
        # A second run on the same map directory: the launch again integrates the whole bag.
        shutil.rmtree(Path(env["HOME"]) / "maps")
        with launch(launch_line, env, "ros2_launch_2") as process, ClientNode(env) as client:
            integrate_the_bag(process, client)
            assert process.stop() == 0, process.describe()
        assert snapshot_keyframes(env, launch_line) == KEYFRAMES, process.describe()
    finally:
        ros2("ros2 daemon stop", env)


def test_ctrl_c_two_seconds_after_the_replay_keeps_every_keyframe_on_a_cold_start(env, tmp_path):
    """Issue 24: a fresh install (numba's cache empty) launched on the bag, and a terminal's Ctrl-C 2 s after
    the replay ended. The node compiled its kernels before it subscribed (the replay waited for it), and its
    shutdown integrated or deferred what was queued: the final snapshot holds every keyframe."""
    cold = tmp_path / "numba_cache"
    cold.mkdir()
    env = {**env, "NUMBA_CACHE_DIR": str(cold)}
    launch_line = readme_session()[0]
    with launch(launch_line, env, "ros2_launch_cold") as process, ClientNode(env) as client:
        diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
        process.wait_for_output('"unmatched": []', 300.0)  # the replay's summary: it has ended
        compiled = diagnostics.wait_for(lambda v: float(v["kernel_compile_ms"]) > 0, 30.0, process=process)
        time.sleep(2.0)
        assert process.stop(timeout=9.0) == 0, process.describe()  # SIGINT to the group; SIGTERM comes at 5 s
    output = process.output()
    assert "Traceback" not in output and "SIGTERM" not in output and "still busy" not in output, output[-4000:]
    map_dir = Path(shlex.split(launch_line.split("map_directory:=")[1])[0].replace("$HOME", env["HOME"]))
    saved, deferred = load_snapshot(map_dir), load_deferred(map_dir)
    assert saved.n_keyframes + len(deferred) == KEYFRAMES, (saved.n_keyframes, len(deferred), compiled)


def test_ros2_run_then_a_plain_fast_replay_loses_nothing(env):
    from monovoc_interfaces.srv import TextQuery

    config = "--params-file config/semantic_mapper.yaml --params-file config/object_query.yaml"
    run = f"exec ros2 run monovoc_ros semantic_mapper --ros-args {config} -p diagnostics_period_s:=0.5"
    with NodeProcess(["bash", "-c", run], env, name="ros2_run", cwd=REPO, process_group=True) as node:
        with ClientNode(env) as client:
            diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
            wait_for_service(client.node.create_client(TextQuery, "/monovoc/query"), 120.0, process=node)
            replay = ros2("monovoc replay bags/synthetic_room.mcap --fast", env, timeout=180.0)
            assert replay.returncode == 0, replay.stdout + replay.stderr
            done = diagnostics.wait_for(lambda v: v["keyframes_processed"] == str(KEYFRAMES), 120.0, process=node)
            assert done["keyframes_received"] == str(KEYFRAMES) and done["keyframes_dropped"] == "0"
        assert node.stop() == 0, node.describe()


def test_launch_on_a_robots_topics(env):
    """The README's launch on a camera's and a SLAM's topics: the bag replayed onto them arrives whole."""
    line = readme_live_launch()
    remaps = {
        role: line.split(f" {role}:=")[1].split()[0] for role in ("image", "mask", "camera_info", "pose", "gaussians")
    }
    assert remaps["image"] == "/camera/color/image_raw/compressed" and "map_directory:=$HOME/maps/office" in line
    replay = "monovoc replay bags/synthetic_room.mcap --fast --remap " + " ".join(
        f"/monovoc/{role}:={topic}" for role, topic in remaps.items()
    )
    with launch(line, env, "ros2_launch_live") as process, ClientNode(env) as client:
        diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
        played = ros2(replay, env, timeout=180.0)  # waits for the launched node's subscriptions
        assert played.returncode == 0, played.stdout + played.stderr
        # The launch argument sets the query component's parameter (navigation_mode:=goal_topic in the line).
        answered("ros2 param get /monovoc/semantic_mapper navigation.mode", env, "goal_topic")
        diagnostics.wait_for(lambda v: v["keyframes_processed"] == str(KEYFRAMES), 120.0, process=process)
        assert process.stop() == 0, process.describe()
    assert snapshot_keyframes(env, line) == KEYFRAMES, process.describe()


def test_a_bag_that_cannot_be_replayed_ends_the_launch_with_the_reason_and_a_typo_is_said(env, tmp_path):
    """A typo in bag:= must not leave a mapper waiting for keyframes that never come, looking like a working one."""
    line = f"ros2 launch monovoc_ros monovoc.launch.py bag:={tmp_path / 'no_such.mcap'} map_directry:=/tmp/typo"
    with launch(line, env, "ros2_launch_no_bag") as process:
        # `ros2 launch` returns once every process it started has ended: the mapper was stopped too.
        wait_until(lambda: not process.running(), 120.0, "the launch to end by itself")
        out = process.output()
        assert "no such bag file" in out and "the bag replay failed" in out, process.describe()
        assert "map_directry is not an argument of monovoc.launch.py, ignored (did you mean map_directory?" in out


@pytest.mark.parametrize(
    ("arguments", "reason"),
    [
        ("bag:=bags/synthetic_room.mcap bag_rate:=abc", "bag_rate:=abc is not a positive number"),
        ("params_file:={tmp}/no_such.yaml", "no_such.yaml is not a file"),
        ("segmenter:=true segmenter_model:={tmp}/no_such.onnx", "the segmenter ended with exit code"),
    ],
)
def test_arguments_the_launch_cannot_run_with_end_it_with_the_reason(env, tmp_path, arguments, reason):
    """A bad replay rate, a parameter file that is not there (launch_ros only warns and the node ran on its
    defaults), a segmenter that cannot start: each ended nothing, and a mapper waited for inputs that never came."""
    line = f"ros2 launch monovoc_ros monovoc.launch.py map_directory:={tmp_path / 'map'} " + arguments.format(
        tmp=tmp_path
    )
    with launch(line, env, "ros2_launch_unusable") as process:
        wait_until(lambda: not process.running(), 120.0, "the launch to end by itself")
        out = process.output()
        assert reason in out and "stopping the launch" in out, process.describe()
