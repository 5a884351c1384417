"""semantic_mapper parameters: one specification each, the YAML files and the docs table made of it,
validation, the descriptors a running node shows, and start-up with files, remaps and bad values."""

from __future__ import annotations

import json
import math
import re
import subprocess

import pytest
import yaml

from monovoc_ros.core.mapping import MapperConfig
from monovoc_ros.ingest import POSE_TYPES, IngestConfig
from monovoc_ros.nodes.object_query_params import PARAMETERS as OBJECT_PARAMETERS
from monovoc_ros.nodes.param_spec import Param, ParameterError, validate
from monovoc_ros.nodes.params import DEFAULTS, PARAMETERS, TRANSPORTS, NodeParams, load_labels
from monovoc_ros.ros_harness import SEMANTIC_MAPPER as OBJECT_NODE_MODULE
from monovoc_ros.ros_harness import ClientNode, NodeProcess, call_service, ros_args, wait_for_service
from tests.node_scene import NODE
from tests.rosutil import REPO, VENV_PYTHON, ros_environment

CONFIG = REPO / "config" / "semantic_mapper.yaml"
OBJECT_CONFIG = REPO / "config" / "object_query.yaml"
WITH_OBJECTS = ["-m", OBJECT_NODE_MODULE]


def _yaml_comments(path) -> dict[str, str]:
    """Parameter name (dotted for nested keys) -> the comment after its value in a parameter file."""
    out, group = {}, ""
    for line in path.read_text().splitlines():
        match = re.match(r"^( +)([\w.]+):(.*?)(?:  # (.*))?$", line)
        if not match or match.group(2) == "ros__parameters":
            continue
        indent, key, value, comment = match.groups()
        if not value.strip():  # a group of dotted names (query:, objects:)
            group = key
            continue
        out[f"{group}.{key}" if len(indent) > 4 else key] = comment
    return out


def test_config_file_lists_every_parameter_with_its_default_and_meaning():
    params = yaml.safe_load(CONFIG.read_text())["/**"]["ros__parameters"]
    assert list(params) == [p.name for p in PARAMETERS]
    assert params == DEFAULTS
    for p in PARAMETERS:  # same YAML types as the declared defaults (ROS parameters are typed)
        assert type(params[p.name]) is type(p.default), p.name
    assert _yaml_comments(CONFIG) == {p.name: p.description for p in PARAMETERS}


def test_defaults_are_the_core_defaults():
    p = NodeParams.from_values(DEFAULTS)
    assert p.mapper == MapperConfig() and p.ingest == IngestConfig()
    assert p.queue_size == 100 and p.labels == {}


def test_every_specification_is_valid_at_its_default_and_states_its_range():
    for p in PARAMETERS + OBJECT_PARAMETERS:
        assert p.check(p.default) == p.default, p.name
        if p.choices or p.low is not None or p.high is not None or p.above is not None:
            assert p.constraints().startswith("must be "), p.name


def test_ranges_and_choices_are_checked_with_the_name():
    spec = (
        Param("rate", 1.0, "", above=0),
        Param("share", 0.5, "", low=0, high=1),
        Param("count", 3, "", low=1),
        Param("mode", "a", "", choices=("a", "b")),
    )
    assert validate(spec, {"rate": 2, "count": 1}) == {"rate": 2.0, "share": 0.5, "count": 1, "mode": "a"}
    for name, value, message in [
        ("rate", 0.0, "must be > 0"),
        ("rate", math.inf, "must be finite"),
        ("share", 1.5, r"must be in \[0, 1\]"),
        ("count", 0, "must be >= 1"),
        ("count", 2.0, "must be an integer"),
        ("count", True, "must be an integer"),
        ("mode", "c", r"must be one of \['a', 'b'\]"),
    ]:
        with pytest.raises(ParameterError, match=f"^{name}: {message}, got "):
            validate(spec, {name: value})


def test_descriptors_carry_ranges_and_constraints():
    by_name = {p.name: p.descriptor() for p in PARAMETERS + OBJECT_PARAMETERS}
    slots = by_name["vote_slots"]
    assert (slots.integer_range[0].from_value, slots.integer_range[0].to_value) == (1, 16) and slots.read_only
    power = by_name["weight_power"]  # integer choices: their span
    assert (power.integer_range[0].from_value, power.integer_range[0].to_value) == (1, 4)
    margin = by_name["min_snap_margin"]
    assert (margin.floating_point_range[0].from_value, margin.floating_point_range[0].to_value) == (0.0, 1.0)
    assert margin.dynamic_typing  # float parameters take integers
    rate = by_name["publish_rate_hz"]
    assert rate.floating_point_range[0].from_value == 0.0 and rate.floating_point_range[0].to_value == math.inf
    assert by_name["impl"].additional_constraints == "must be one of ['numba', 'torch', 'reference']"
    assert not by_name["impl"].integer_range and not by_name["impl"].floating_point_range
    assert by_name["diagnostics_period_s"].additional_constraints == "must be > 0"
    assert by_name["objects.description_weight"].floating_point_range[0].to_value == 1.0
    assert Param("n", 2, "", above=0).descriptor().integer_range[0].from_value == 1  # > 0 for integers


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("impl", "cuda"),
        ("metric", "lab"),
        ("void_policy", "maybe"),
        ("pose_type", "tf"),
        ("frame_convention", "enu"),
        ("image_transport", "theora"),
        ("mask_transport", "jpeg"),
        ("input_reliability", "sometimes"),
        ("queue_size", 0),
        ("input_depth", 0),
        ("sync_tolerance_s", -0.1),
        ("sync_max_pending", 0),
        ("publish_rate_hz", -1.0),
        ("publish_rate_hz", float("nan")),
        ("save_period_s", "often"),
        ("diagnostics_period_s", 0.0),
        ("interpreter_hold_trace_ms", 5.0),  # under MIN_HOLD_TRACE_MS: the watch's own wakes would trace
        ("interpreter_hold_trace_ms", -1.0),
        ("marker_up", [0.0, 0.0, 0.0]),
        ("frame_id", ""),
        ("map_ply", "/nonexistent/map.ply"),
        ("labels_file", "/nonexistent/labels.json"),
        ("resume", True),  # without map_directory
        ("vote_slots", 17),
        ("weight_power", 5),
        ("min_snap_margin", 1.5),
        ("map_update_max_shrink", -0.1),
        ("use_image", "yes"),
        ("queue_size", 2.5),
    ],
)
def test_invalid_values_name_the_parameter(name, value):
    with pytest.raises(ParameterError, match=f"^{name}: "):
        NodeParams.from_values({**DEFAULTS, name: value})


def test_integers_are_accepted_for_floats():
    assert NodeParams.from_values({"publish_rate_hz": 2, "save_period_s": 0}).publish_rate_hz == 2.0


def test_labels_file(tmp_path):
    path = tmp_path / "labels.json"
    path.write_text(json.dumps([{"color": [1, 2, 3], "class_name": "chair"}, {"color": [255, 0, 0]}]))
    assert load_labels(str(path)) == {0x010203: "chair", 0xFF0000: ""}
    path.write_text(json.dumps([{"color": [1, 2]}]))
    with pytest.raises(ParameterError, match="labels_file"):
        load_labels(str(path))


@pytest.mark.ros
def test_invalid_parameter_stops_the_node_with_a_clear_message(tmp_path):
    env = ros_environment(tmp_path)
    args = [str(VENV_PYTHON), *NODE, *ros_args({"metric": "lab", "queue_size": 4})]
    proc = subprocess.run(args, env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert "semantic_mapper: invalid parameter metric: must be one of" in proc.stderr


@pytest.mark.ros
def test_ros_arguments_rcl_cannot_parse_stop_the_node_with_one_line(tmp_path):
    """A parameter file that is no YAML, a remapping rule that is none: rclpy's RCLError was a traceback."""
    env = ros_environment(tmp_path)
    garbage = tmp_path / "garbage.yaml"
    garbage.write_text("not: [valid yaml\n")
    for module, name, ros, problem in (
        (NODE, "semantic_mapper", ["--params-file", str(garbage)], "Couldn't parse params file"),
        (NODE, "semantic_mapper", ["-r", "bad remap"], "Couldn't parse remap rule"),
        (["-m", "monovoc_ros.nodes.segmenter"], "segmenter", ["-r", "bad remap"], "Couldn't parse remap rule"),
    ):
        proc = subprocess.run([str(VENV_PYTHON), *module, "--ros-args", *ros], env=env, capture_output=True,
                              text=True, timeout=60)  # fmt: skip
        assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
        line = next(x for x in proc.stderr.splitlines() if x.startswith(f"{name}: cannot start: "))
        assert f"failed to initialize rcl: {problem}" in line and ", at " not in line, line


@pytest.mark.ros
def test_params_file_loads_under_a_remapped_name_and_namespace(tmp_path):
    from rcl_interfaces.srv import GetParameters
    from std_srvs.srv import Trigger

    params = yaml.safe_load(CONFIG.read_text())
    params["/**"]["ros__parameters"].update(queue_size=7, metric="ciede2000", marker_up=[0.0, -1.0, 0.0])
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(params))
    env = ros_environment(tmp_path)
    args = [*NODE, "--ros-args", "--params-file", str(path), "-r", "__node:=mapper2", "-r", "__ns:=/robot1"]
    with NodeProcess.python(args, env, name="semantic_mapper") as node, ClientNode(env) as client:
        get = client.node.create_client(GetParameters, "/robot1/mapper2/get_parameters")
        wait_for_service(get, timeout=20.0, process=node)
        response = call_service(get, GetParameters.Request(names=["queue_size", "metric", "marker_up"]), process=node)
        values = response.values
        assert values[0].integer_value == 7 and values[1].string_value == "ciede2000"
        assert list(values[2].double_array_value) == [0.0, -1.0, 0.0]
        # Topics and services are relative: they follow the namespace.
        publish = client.node.create_client(Trigger, "/robot1/publish")
        wait_for_service(publish, process=node)
        assert call_service(publish, Trigger.Request(), process=node).success
        assert node.stop() == 0  # SIGINT: clean exit


def test_object_query_config_lists_every_parameter_with_its_default_and_meaning():
    nested = yaml.safe_load(OBJECT_CONFIG.read_text())["/**"]["ros__parameters"]
    flat = {f"{group}.{key}": value for group, values in nested.items() for key, value in values.items()}
    assert list(flat) == [p.name for p in OBJECT_PARAMETERS]
    for p in OBJECT_PARAMETERS:
        assert flat[p.name] == p.default and type(flat[p.name]) is type(p.default), p.name
    assert _yaml_comments(OBJECT_CONFIG) == {p.name: p.description for p in OBJECT_PARAMETERS}


def test_docs_document_every_parameter_with_its_default_and_meaning():
    text = (REPO / "docs" / "parameters.md").read_text()
    rows = [line for line in text.splitlines() if re.match(r"^\| `[\w.]+` \| `", line)]
    expected = []
    for p in PARAMETERS + OBJECT_PARAMETERS:
        default = str(p.default).lower() if isinstance(p.default, bool) else json.dumps(p.default)
        expected.append(f"| `{p.name}` | `{default}` | {p.description} |")
    assert [row for row in rows if row in expected] == expected


@pytest.mark.ros
def test_invalid_object_parameter_stops_the_node_with_a_clear_message(tmp_path):
    env = ros_environment(tmp_path)
    args = [str(VENV_PYTHON), *WITH_OBJECTS, *ros_args({"objects.up_axis": "up"})]
    proc = subprocess.run(args, env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert "semantic_mapper: invalid parameter objects.up_axis: must be one of ['+x'" in proc.stderr


@pytest.mark.ros
def test_out_of_range_value_is_refused_at_declaration(tmp_path):
    env = ros_environment(tmp_path)
    args = [str(VENV_PYTHON), *NODE, *ros_args({"min_snap_margin": 1.5})]
    proc = subprocess.run(args, env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert "semantic_mapper: invalid parameter min_snap_margin: must be in [0, 1]" in proc.stderr


@pytest.mark.ros
def test_running_node_describes_its_parameters_with_their_ranges(tmp_path):
    from rcl_interfaces.srv import DescribeParameters

    env = ros_environment(tmp_path)
    with NodeProcess.python(WITH_OBJECTS, env, name="semantic_mapper") as node, ClientNode(env) as client:
        describe = client.node.create_client(DescribeParameters, "/monovoc/semantic_mapper/describe_parameters")
        wait_for_service(describe, timeout=20.0, process=node)
        specs = {p.name: p for p in PARAMETERS + OBJECT_PARAMETERS}
        request = DescribeParameters.Request(names=list(specs))
        described = {d.name: d for d in call_service(describe, request, process=node).descriptors}
        assert set(described) == set(specs)
        for name, spec in specs.items():
            d, expected = described[name], spec.descriptor()
            assert d.description == spec.description and d.read_only, name
            assert d.additional_constraints == spec.constraints(), name
            assert [(r.from_value, r.to_value) for r in d.integer_range] == [
                (r.from_value, r.to_value) for r in expected.integer_range
            ], name
            assert [(r.from_value, r.to_value) for r in d.floating_point_range] == [
                (r.from_value, r.to_value) for r in expected.floating_point_range
            ], name
        assert (
            described["vote_slots"].integer_range[0].from_value,
            described["vote_slots"].integer_range[0].to_value,
        ) == (1, 16)
        weight = described["objects.description_weight"].floating_point_range[0]
        assert (weight.from_value, weight.to_value) == (0.0, 1.0)
        assert node.stop() == 0


def test_contract_names_a_message_class_for_every_input_setting():
    from monovoc_ros.contract import MAP_TYPE, keyframe_types, message_class

    images = {"raw": "Image", "compressed": "CompressedImage"}
    poses = {"pose": "PoseStamped", "odometry": "Odometry", "transform": "TransformStamped"}
    for transport in TRANSPORTS:
        for pose_type in POSE_TYPES:
            names = keyframe_types(transport, transport, pose_type)
            types = {role: message_class(name).__name__ for role, name in names.items()}
            assert types == {"image": images[transport], "mask": images[transport], "camera_info": "CameraInfo",
                             "pose": poses[pose_type]}  # fmt: skip
    assert message_class(MAP_TYPE).__name__ == "PointCloud2"
