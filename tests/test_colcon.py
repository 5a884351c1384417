"""The README's "On a robot" commands, run as written: colcon build of a clean copy of the repository
with the venv's ros-jazzy wheels as the underlay, then semantic_mapper started from the install space.

The command block is read from README.md, so the README cannot drift from what CI runs. Three lines
differ on a development machine and are replaced, nothing else: `source /opt/ros/jazzy/setup.bash`
(the underlay is the venv: AMENT_PREFIX_PATH and PATH as scripts/with_env.sh sets them), the
`git clone` (a copy of the files git tracks, plus untracked files it does not ignore) and the
`pip install` line (the venv has those pins already; tests/test_packaging.py checks the line).

semantic_mapper rather than mapping_node: it is the node the README starts, it serves TextQuery from
monovoc_interfaces (so the overlay's generated interfaces are exercised) and it publishes the query
topics the RViz config shows; its embedding models load in well under a second.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
from test_packaging import RVIZ, parse_launch, rviz_topics

from monovoc_ros.embed import default_model_dir
from monovoc_ros.ros_harness import (
    ClientNode,
    NodeProcess,
    call_service,
    node_endpoints,
    wait_for_service,
    wait_until,
)
from tests.object_room import copy_directory, room_directory, room_id
from tests.rosutil import REPO, ros_environment

pytestmark = [pytest.mark.ros, pytest.mark.slow]

PACKAGES = ("monovoc_interfaces", "monovoc_ros")
BUILD_TIMEOUT_S = 900  # ~30 s alone on 2 cores (cmake + rosidl for monovoc_interfaces), more when loaded


def readme_commands() -> list[str]:
    """The commands of the README's "On a robot" block (continuation lines joined, comments dropped)."""
    text = (REPO / "README.md").read_text()
    section = text[text.index("## On a robot") :]
    block = section[section.index("```bash\n") + 8 :]
    block = block[: block.index("```")]
    return [line.split("  #")[0].strip() for line in block.replace("\\\n", " ").splitlines() if line.strip()]


@dataclass
class Workspace:
    root: Path  # ~/ws
    env: dict  # the ROS environment of the test, underlay only (nothing of the workspace sourced)
    commands: list[str]  # the README's commands after the build
    build_log: str

    def sourced(self, command: str) -> list[str]:
        """``command`` in bash, in ~/ws, with install/setup.bash sourced (as the README does)."""
        return ["bash", "-c", f"cd {self.root} && source install/setup.bash && {command}"]


def copy_repository(target: Path) -> None:
    """The repository as a fresh clone has it (tracked + untracked-not-ignored files; no .venv, build, out)."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=REPO,
        capture_output=True,
        check=True,
    ).stdout.split(b"\0")
    for name in filter(None, (n.decode() for n in listed)):
        source = REPO / name
        if source.is_symlink() or not source.is_file():  # e.g. a .venv symlink, a deleted file
            continue
        (target / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(source, target / name)


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Workspace:
    tmp = tmp_path_factory.mktemp("colcon")
    env = ros_environment(tmp, extra={"MONOVOC_MODEL_DIR": str(default_model_dir())})
    env.pop("PYTHONPATH")  # the node must import the installed package, not the working tree
    home = Path(env["HOME"])
    commands = readme_commands()
    assert commands[0] == "source /opt/ros/jazzy/setup.bash"  # replaced by the underlay environment
    assert commands[1] == "mkdir -p ~/ws/src && git clone <this repository> ~/ws/src/monovoc_ros"
    assert commands[2].startswith("pip install ")  # the venv has these (tests/test_packaging.py)
    assert commands[4] == "source install/setup.bash"  # Workspace.sourced() does it for every later command
    copy_repository(home / "ws" / "src" / "monovoc_ros")
    build = commands[3]
    assert build == "cd ~/ws && colcon build --base-paths src src/monovoc_ros/monovoc_interfaces"
    start = time.monotonic()
    log = tmp / "colcon_build.log"
    with open(log, "wb") as out:
        result = subprocess.run(
            ["bash", "-c", build], cwd=home, env=env, stdout=out, stderr=subprocess.STDOUT, timeout=BUILD_TIMEOUT_S
        )
    seconds = time.monotonic() - start
    assert result.returncode == 0, f"colcon build failed:\n{log.read_text()[-6000:]}"
    print(f"colcon build: {seconds:.1f} s")
    return Workspace(home / "ws", env, commands[5:], log.read_text())


def test_colcon_builds_both_packages_into_the_install_layout(workspace: Workspace) -> None:
    ws = workspace.root
    for package in PACKAGES:
        assert f"Finished <<< {package}" in workspace.build_log, workspace.build_log
        assert (ws / "install" / package / "share" / package / "package.xml").is_file()
    share = ws / "install" / "monovoc_ros" / "share" / "monovoc_ros"
    for name in ("config/semantic_mapper.yaml", "config/object_query.yaml", "config/queries/synthetic_room.json",
                 "config/queries/replica_office0.json", "config/fastdds_large_clouds.xml", "launch/monovoc.launch.py",
                 "rviz/monovoc.rviz"):  # fmt: skip
        assert (share / name).read_bytes() == (REPO / name).read_bytes(), name
    lib = ws / "install" / "monovoc_ros" / "lib" / "monovoc_ros"
    assert sorted(p.name for p in lib.iterdir()) == ["mapping_node", "monovoc", "segmenter", "semantic_mapper"]
    assert all(os.access(p, os.X_OK) for p in lib.iterdir())
    assert (
        ws / "install" / "monovoc_ros" / "share" / "ament_index" / "resource_index" / "packages" / "monovoc_ros"
    ).is_file()
    # Sourcing the install space puts its packages first: the working tree is not on the path.
    probe = "python3 -c 'import monovoc_ros as a, monovoc_interfaces as b; print(a.__file__, b.__file__)'"
    paths = subprocess.run(workspace.sourced(probe), env=workspace.env, capture_output=True, text=True, timeout=60)
    assert paths.returncode == 0, paths.stderr
    ours, interfaces = paths.stdout.split()
    assert ours.startswith(str(ws / "install" / "monovoc_ros" / "lib")), ours
    assert interfaces.startswith(str(ws / "install" / "monovoc_interfaces" / "lib")), interfaces


def test_every_executable_and_file_the_launch_file_names_is_installed(workspace: Workspace) -> None:
    install = workspace.root / "install"
    launch = parse_launch(install / "monovoc_ros" / "share" / "monovoc_ros" / "launch" / "monovoc.launch.py")
    for package, relative in launch.share_files:
        assert (install / package / "share" / package / relative).is_file(), relative
    for package, relative in launch.prefix_files:
        path = install / package / relative
        assert path.is_file() and os.access(path, os.X_OK), relative
    ours = {e for p, e in launch.executables if p == "monovoc_ros"}
    assert ours == {"semantic_mapper", "mapping_node", "segmenter"}
    for executable in ours:  # what `ros2 run monovoc_ros <executable>` / launch_ros's Node start
        assert os.access(install / "monovoc_ros" / "lib" / "monovoc_ros" / executable, os.X_OK), executable


def test_the_installed_node_answers_a_query_and_publishes_what_rviz_shows(workspace: Workspace) -> None:
    from monovoc_interfaces.srv import TextQuery

    export, warm, node_line, query_line = workspace.commands
    env = workspace.env
    assert export == "python3 -m monovoc_ros.embed.export"
    done = subprocess.run(workspace.sourced(export), env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    # The kernels compile into the install space's own cache (next to its modules), not the working tree's.
    assert warm == "install/monovoc_ros/lib/monovoc_ros/monovoc warm-up"
    done = subprocess.run(workspace.sourced(warm), env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0 and '"seconds"' in done.stdout, done.stdout + done.stderr
    installed = workspace.root / "install" / "monovoc_ros" / "lib"
    assert any(installed.rglob("numba_kernels.accumulate_tiles-*.nbi")), "no kernel cache in the install space"
    # The README's map directory ($HOME/maps/office) holds a saved map here, so the node resumes it.
    assert "-p map_directory:=$HOME/maps/office -p resume:=true" in node_line and node_line.endswith(" &")
    copy_directory(room_directory(), Path(env["HOME"]) / "maps" / "office")
    node_command = node_line.removesuffix("&").strip()
    assert node_command.startswith("install/monovoc_ros/lib/monovoc_ros/semantic_mapper --ros-args ")
    with NodeProcess(workspace.sourced("exec " + node_command), env, name="installed_semantic_mapper") as node:
        with ClientNode(env) as client:
            service = client.node.create_client(TextQuery, "/monovoc/query")
            wait_for_service(service, 60.0, process=node)
            answer = call_service(service, TextQuery.Request(text="a sofa", top_k=3), 30.0, process=node)
            assert answer.success, answer.message
            assert len(answer.objects) == 3 and answer.objects[0].id == room_id("sofa")
            assert answer.objects[0].num_gaussians > 0

            # The README's client line, from the install space too.
            assert query_line.startswith("install/monovoc_ros/lib/monovoc_ros/monovoc query ")
            printed = subprocess.run(
                workspace.sourced(query_line), env=env, capture_output=True, text=True, timeout=120
            )
            assert printed.returncode == 0, printed.stdout + printed.stderr
            first = next(line for line in printed.stdout.splitlines() if line.strip().startswith("1  "))
            assert "sofa" in first, printed.stdout

            # Every topic of rviz/monovoc.rviz is published by this node, with the display's type.
            wanted = rviz_topics()
            assert RVIZ.is_file() and wanted

            def published() -> dict[str, list[str]]:
                return node_endpoints(client.node, "publishers", "semantic_mapper", "/monovoc")

            wait_until(lambda: set(wanted) <= set(published()), 30.0, f"publishers of {sorted(wanted)}", process=node)
            types = published()
            for topic, type_name in wanted.items():
                assert types[topic] == [type_name], topic
        assert node.stop() == 0, node.describe()
