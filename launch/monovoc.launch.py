"""ros2 launch monovoc_ros monovoc.launch.py [ARG:=VALUE ...]

Starts the semantic_mapper node (or mapping_node: mapping only, no objects, no models) with both parameter files,
in a namespace, with the seven inputs remapped by launch arguments; optionally the segmenter node, whose
per-frame masks and class names then feed the mapper (a robot with only a camera and a 3DGS SLAM), replays a
bag into it (`monovoc replay`, publishing /clock) and opens RViz with rviz/monovoc.rviz.

    ros2 launch monovoc_ros monovoc.launch.py segmenter:=true image:=/camera/color/image_raw/compressed \\
        camera_info:=/camera/color/camera_info pose:=/slam/camera_pose gaussians:=/slam/gaussians

    ros2 launch monovoc_ros monovoc.launch.py image:=/camera/color/image_raw/compressed \\
        mask:=/segmentation/mask camera_info:=/camera/color/camera_info pose:=/slam/camera_pose \\
        gaussians:=/slam/gaussians map_directory:=$HOME/maps/office rviz:=true
    ros2 launch monovoc_ros monovoc.launch.py bag:=$HOME/bags/synthetic_room.mcap \\
        labels_file:=$HOME/bags/synthetic_room.labels.json use_sim_time:=true

Every argument is listed in the README ("Launch file"). tests/test_ros2_tools.py runs it with the real
`ros2 launch`; tests/test_packaging.py checks that every argument is declared and documented, and
tests/test_colcon.py that every executable and file it names is installed by colcon.
"""

import difflib
import math
import os

from launch import LaunchDescription
from launch.actions import (
    DeclareLaunchArgument,
    EmitEvent,
    ExecuteProcess,
    LogInfo,
    OpaqueFunction,
    RegisterEventHandler,
)
from launch.conditions import IfCondition, UnlessCondition
from launch.event_handlers import OnProcessExit
from launch.events import Shutdown
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution, PythonExpression
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackagePrefix, FindPackageShare

PACKAGE = "monovoc_ros"
# What launch's conditions read as a boolean: anything else would fail deep in a condition with an unreadable error.
BOOLEANS = ["true", "false", "True", "False", "TRUE", "FALSE", "1", "0"]
# Launch configurations that launch and launch_ros set themselves (an including file's PushRosNamespace, SetParameter,
# SetRemap; ExecuteProcess's settings): not arguments of this file, nor typos of them (ros_namespace ~ namespace).
LAUNCH_OWN = {"ros_namespace", "global_params", "ros_remaps", "emulate_tty", "sigterm_timeout", "sigkill_timeout"}
# `monovoc replay`'s exit code when it published nothing (monovoc_ros.commands.replay.NOT_STARTED: this file imports
# only launch packages).
REPLAY_NOT_STARTED = 3


def _stop(reason: str) -> list:
    """Says why and ends the launch."""
    return [LogInfo(msg=f"monovoc: {reason}; stopping the launch"), EmitEvent(event=Shutdown(reason=reason))]


def unusable_arguments(context) -> list:
    """Values the launch cannot run with end it with one line (its nodes may start, and are stopped at once), instead
    of a node on its defaults (launch_ros only warns about a parameter file that is not there) or a replay that exits
    on its own arguments."""
    for name in ("params_file", "query_params_file"):
        path = context.launch_configurations.get(name, "")
        if path and not os.path.isfile(path):
            return _stop(f"{name}:={path} is not a file")
    if context.launch_configurations.get("bag", ""):
        rate = context.launch_configurations.get("bag_rate", "")
        try:
            value = float(rate)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and value > 0):
            return _stop(f"bag_rate:={rate} is not a positive number")
    return []


def generate_launch_description() -> LaunchDescription:
    share = FindPackageShare(PACKAGE)
    arguments = [
        DeclareLaunchArgument(
            "executable",
            default_value="semantic_mapper",
            choices=["semantic_mapper", "mapping_node"],
            description="semantic_mapper (mapping + object database + query service) or mapping_node (mapping only)",
        ),
        DeclareLaunchArgument("namespace", default_value="monovoc", description="namespace of topics and services"),
        DeclareLaunchArgument(
            "params_file",
            default_value=PathJoinSubstitution([share, "config", "semantic_mapper.yaml"]),
            description="parameters of the mapping node",
        ),
        DeclareLaunchArgument(
            "query_params_file",
            default_value=PathJoinSubstitution([share, "config", "object_query.yaml"]),
            description="parameters of the object database and query service (ignored by mapping_node)",
        ),
        DeclareLaunchArgument("image", default_value="image", description="input topic: RGB keyframes"),
        DeclareLaunchArgument("mask", default_value="mask", description="input topic: palette masks"),
        DeclareLaunchArgument("camera_info", default_value="camera_info", description="input topic: CameraInfo"),
        DeclareLaunchArgument("pose", default_value="pose", description="input topic: camera-to-map pose"),
        DeclareLaunchArgument(
            "segments", default_value="segments", description="input topic: segment class names (use_segments)"
        ),
        DeclareLaunchArgument("gaussians", default_value="gaussians", description="input topic: Gaussian map"),
        DeclareLaunchArgument(
            "keyframe_poses", default_value="keyframe_poses", description="input topic: corrected keyframe poses (Path)"
        ),
        DeclareLaunchArgument("map_directory", default_value="", description="snapshot directory ('' = none)"),
        DeclareLaunchArgument(
            "labels_file",
            default_value="",
            description="labels.json naming objects by mask color ('' = none: segment names or the model's guess)",
        ),
        DeclareLaunchArgument(
            "use_segments",
            default_value="false",
            choices=BOOLEANS,
            description="subscribe to `segments` (a segmenter's class names)",
        ),
        DeclareLaunchArgument(
            "segmenter",
            default_value="false",
            choices=BOOLEANS,
            description="start the segmenter node on `image` and map its masks (mask_ids per_frame, use_segments)",
        ),
        DeclareLaunchArgument(
            "segmenter_model",
            default_value="yolov5s-seg",
            description="the segmenter's model: yolov5s-seg, yolov7-seg or a YOLO-seg .onnx file",
        ),
        DeclareLaunchArgument(
            "use_sim_time", default_value="false", choices=BOOLEANS, description="stamp by /clock (bag replay)"
        ),
        DeclareLaunchArgument("bag", default_value="", description="MCAP bag to replay into the node ('' = none)"),
        DeclareLaunchArgument("bag_rate", default_value="1.0", description="replay speed, multiple of the recorded"),
        DeclareLaunchArgument(
            "rviz", default_value="false", choices=BOOLEANS, description="open RViz with rviz/monovoc.rviz"
        ),
        DeclareLaunchArgument(
            "navigation_mode",
            default_value="none",
            choices=["none", "goal_topic", "nav2"],
            description="go_to: nav2 drives through Nav2's navigate_to_pose, goal_topic publishes the pose, none only "
            "answers (overrides navigation.mode in query_params_file)",
        ),
    ]
    use_sim_time = LaunchConfiguration("use_sim_time")
    bag = LaunchConfiguration("bag")
    with_segmenter = LaunchConfiguration("segmenter")
    typed = {
        "use_sim_time": ParameterValue(use_sim_time, value_type=bool),
        "map_directory": ParameterValue(LaunchConfiguration("map_directory"), value_type=str),
        "labels_file": ParameterValue(LaunchConfiguration("labels_file"), value_type=str),
        "use_segments": ParameterValue(LaunchConfiguration("use_segments"), value_type=bool),
        "navigation.mode": ParameterValue(LaunchConfiguration("navigation_mode"), value_type=str),
    }
    # With the segmenter the mapper reads its mono16 per-frame masks and their class names.
    from_segmenter = {
        "mask_transport": "raw",
        "mask_ids": "per_frame",
        "use_segments": True,
        "min_support": 0.5,
        "min_object_score": 0.5,
    }

    def mapping_node(extra: dict, condition) -> Node:
        return Node(
            package=PACKAGE,
            executable=LaunchConfiguration("executable"),
            name="semantic_mapper",
            namespace=LaunchConfiguration("namespace"),
            output="screen",
            # Typed: launch would read map_directory:='' as YAML (null) and "false" is a bool.
            parameters=[
                LaunchConfiguration("params_file"),
                LaunchConfiguration("query_params_file"),
                {**typed, **extra},
            ],
            remappings=[
                ("image", LaunchConfiguration("image")),
                ("mask", LaunchConfiguration("mask")),
                ("camera_info", LaunchConfiguration("camera_info")),
                ("pose", LaunchConfiguration("pose")),
                ("segments", LaunchConfiguration("segments")),
                ("gaussians", LaunchConfiguration("gaussians")),
                ("keyframe_poses", LaunchConfiguration("keyframe_poses")),
            ],
            condition=condition,
        )

    mappers = [
        mapping_node({}, UnlessCondition(with_segmenter)),
        mapping_node(from_segmenter, IfCondition(with_segmenter)),
    ]
    segmenter = Node(
        package=PACKAGE,
        executable="segmenter",
        name="segmenter",
        namespace=LaunchConfiguration("namespace"),
        output="screen",
        parameters=[{"model": ParameterValue(LaunchConfiguration("segmenter_model"), value_type=str)}],
        remappings=[
            ("image", LaunchConfiguration("image")),
            ("mask", LaunchConfiguration("mask")),
            ("segments", LaunchConfiguration("segments")),
        ],
        condition=IfCondition(with_segmenter),
    )
    # `monovoc replay` is an argparse command, not a node taking --ros-args: run it as a plain process.
    # It publishes the bag's own topics (/monovoc/image, ...), which are the node's inputs with the
    # default namespace and remappings.
    replay = ExecuteProcess(
        cmd=[
            PathJoinSubstitution([FindPackagePrefix(PACKAGE), "lib", PACKAGE, "monovoc"]),
            "replay",
            bag,
            "--rate",
            LaunchConfiguration("bag_rate"),
            "--clock",
            # A node whose kernel cache is empty compiles them before it subscribes (~20-40 s on 2 cores).
            "--wait-timeout",
            "300",
        ],
        output="screen",
        condition=IfCondition(PythonExpression(["'", bag, "' != ''"])),
    )

    def replay_ended(event, context) -> list:
        """A replay that published nothing (`monovoc replay` exit code 3: no such bag, not a bag, no subscriber in
        time) ends the launch: a mapper waiting for a bag that never comes looks like a working one. A replay that
        fails later is said, the node (and what it mapped) kept."""
        if event.returncode in (0, 130) or event.returncode < 0 or context.is_shutdown:  # done, or stopped
            return []
        if event.returncode != REPLAY_NOT_STARTED:
            ended = f"monovoc: the bag replay ended with exit code {event.returncode} (see its error above)"
            return [LogInfo(msg=ended)]
        return _stop("the bag replay failed (its error is above): nothing was replayed")

    def segmenter_ended(event, context) -> list:
        """A segmenter that stopped by itself (no such model, a model it cannot run) ends the launch: without it no
        mask comes, and a mapper waiting for masks looks like a working one."""
        if event.returncode in (0, 130) or event.returncode < 0 or context.is_shutdown:  # stopped with the launch
            return []
        return _stop(f"the segmenter ended with exit code {event.returncode} (its error is above): no masks will come")

    rviz = Node(
        package="rviz2",
        executable="rviz2",
        arguments=["-d", PathJoinSubstitution([share, "rviz", "monovoc.rviz"])],
        parameters=[{"use_sim_time": ParameterValue(use_sim_time, value_type=bool)}],
        condition=IfCondition(LaunchConfiguration("rviz")),
    )
    on_replay_exit = RegisterEventHandler(OnProcessExit(target_action=replay, on_exit=replay_ended))
    on_segmenter_exit = RegisterEventHandler(OnProcessExit(target_action=segmenter, on_exit=segmenter_ended))
    declared = {a.name for a in arguments}

    def misspelt_arguments(context) -> list:
        """`ros2 launch` takes any NAME:=VALUE: a misspelt argument (segmentr:=true) would be ignored without a word.
        Only names close to one of this file's are said: the context also holds launch's own settings and the
        arguments of a launch file that includes this one."""
        said = []
        for name in sorted(set(context.launch_configurations) - declared - LAUNCH_OWN):
            if name.startswith("anon"):  # launch's AnonName substitutions
                continue
            close = difflib.get_close_matches(name, declared, n=1, cutoff=0.75)
            if close:
                said.append(LogInfo(msg=f"monovoc: WARNING: {name} is not an argument of monovoc.launch.py, "
                                        f"ignored (did you mean {close[0]}? see docs/parameters.md)"))  # fmt: skip
        return said

    checks = [
        OpaqueFunction(function=misspelt_arguments),
        OpaqueFunction(function=unusable_arguments),
        on_replay_exit,
        on_segmenter_exit,
    ]
    return LaunchDescription([*arguments, *checks, *mappers, segmenter, replay, rviz])
