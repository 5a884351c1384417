"""semantic_mapper parameters: the YAML file, validation, and start-up with files, remaps and bad values."""

from __future__ import annotations

import json
import subprocess

import pytest
import yaml

from monovoc_ros.nodes.params import DEFAULTS, PARAMETERS, NodeParams, ParameterError, load_labels
from monovoc_ros.ros_harness import ClientNode, NodeProcess, call_service, ros_args, wait_for_service
from tests.node_scene import NODE
from tests.rosutil import REPO, VENV_PYTHON, ros_environment

CONFIG = REPO / "config" / "semantic_mapper.yaml"


def test_config_file_lists_every_parameter_with_its_default():
    params = yaml.safe_load(CONFIG.read_text())["/**"]["ros__parameters"]
    assert list(params) == [p.name for p in PARAMETERS]
    assert params == DEFAULTS
    for p in PARAMETERS:  # same YAML types as the declared defaults (ROS parameters are typed)
        assert type(params[p.name]) is type(p.default), p.name


def test_defaults_are_valid():
    p = NodeParams.from_values(DEFAULTS)
    assert p.mapper.impl == "numba" and p.mapper.metric == "cmc" and p.mapper.device is None
    assert p.ingest.pose_type == "pose" and p.queue_size == 100 and p.labels == {}


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
        ("marker_up", [0.0, 0.0, 0.0]),
        ("frame_id", ""),
        ("map_ply", "/nonexistent/map.ply"),
        ("labels_file", "/nonexistent/labels.json"),
        ("resume", True),  # without map_directory
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


def test_object_query_config_lists_every_parameter_with_its_default():
    from monovoc_ros.nodes.object_query import PARAMETERS as OBJECT_PARAMETERS

    nested = yaml.safe_load((REPO / "config" / "object_query.yaml").read_text())["/**"]["ros__parameters"]
    flat = {f"{group}.{key}": value for group, values in nested.items() for key, value in values.items()}
    assert list(flat) == [name for name, _, _ in OBJECT_PARAMETERS]
    for name, default, _ in OBJECT_PARAMETERS:
        assert flat[name] == default and type(flat[name]) is type(default), name


def test_readme_documents_every_parameter_with_its_default():
    from monovoc_ros.nodes.object_query import PARAMETERS as OBJECT_PARAMETERS

    readme = (REPO / "README.md").read_text()
    specs = [(p.name, p.default) for p in PARAMETERS] + [(name, default) for name, default, _ in OBJECT_PARAMETERS]
    for name, default in specs:
        text = str(default).lower() if isinstance(default, bool) else json.dumps(default)
        assert f"| `{name}` | `{text}` |" in readme, name
