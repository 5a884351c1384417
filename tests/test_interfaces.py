"""monovoc_interfaces: the generated types import, match their sources, and work over loopback."""

from __future__ import annotations

import math
import textwrap
import time
from pathlib import Path

import pytest
from rclpy.serialization import deserialize_message, serialize_message

from monovoc_interfaces.msg import SemanticObject, SemanticObjectArray
from monovoc_interfaces.srv import LoadMap, Reset, SaveMap, TextQuery
from monovoc_ros.ros_harness import ClientNode, NodeProcess, call_service, wait_for_service
from tests.rosutil import REPO, VENV, ros_environment

SOURCE = REPO / "monovoc_interfaces"
SERVICE = "/monovoc_test/text_query"

# A tiny TextQuery server: five fixed objects with descending scores; top_k 0 means 3; an empty
# text fails. Prints "ready" once the service exists; exits 0 on SIGINT.
SERVER = textwrap.dedent(
    """
    import sys

    import rclpy
    from geometry_msgs.msg import Point, Vector3
    from rclpy.executors import ExternalShutdownException
    from std_msgs.msg import ColorRGBA

    from monovoc_interfaces.msg import SemanticObject
    from monovoc_interfaces.srv import TextQuery

    IDS = [0xFF0000, 0x00FF00, 0x0000FF, 0x808000, 0x008080]
    SCORES = [0.9, 0.7, 0.5, 0.3, 0.1]


    def handle(request, response):
        response.header.frame_id = "map"
        response.header.stamp.sec = 42
        if not request.text:
            response.success = False
            response.message = "empty text"
            return response
        k = request.top_k or 3
        kept = [i for i in range(len(IDS)) if SCORES[i] >= request.min_score][:k]
        for i in kept:
            oid = IDS[i]
            response.objects.append(
                SemanticObject(
                    id=oid,
                    label=f"{request.text} {i}",
                    score=SCORES[i],
                    color=ColorRGBA(r=(oid >> 16) / 255.0, g=((oid >> 8) & 255) / 255.0, b=(oid & 255) / 255.0, a=1.0),
                    centroid=Point(x=float(i), y=2.0 * i, z=3.0 * i),
                    extent=Vector3(x=0.5, y=0.25, z=1.0),
                    num_gaussians=100 * (i + 1),
                    num_observations=i + 1,
                )
            )
        response.success = True
        response.message = f"{len(kept)} objects"
        return response


    def main():
        rclpy.init(args=sys.argv)
        node = rclpy.create_node("text_query_test_server")
        node.create_service(TextQuery, sys.argv[1], handle)
        print("ready", flush=True)
        try:
            rclpy.spin(node)
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        finally:
            node.destroy_node()
            rclpy.try_shutdown()


    main()
    """
)


DEFINITIONS = sorted(
    p.relative_to(SOURCE).as_posix()
    for p in [*SOURCE.glob("msg/*.msg"), *SOURCE.glob("srv/*.srv"), *SOURCE.glob("action/*.action")]
)


def test_every_definition_is_built() -> None:
    assert len(DEFINITIONS) == 11, DEFINITIONS
    cmake = (SOURCE / "CMakeLists.txt").read_text()
    assert all(f'"{d}"' in cmake for d in DEFINITIONS), "CMakeLists.txt does not list every definition"


@pytest.mark.parametrize("relpath", DEFINITIONS)
def test_installed_definitions_match_sources(relpath: str) -> None:
    installed = VENV / "share" / "monovoc_interfaces" / relpath
    assert installed.exists(), f"{installed} missing: run scripts/install.sh"
    assert installed.read_text() == (SOURCE / relpath).read_text(), f"{relpath} changed: run scripts/install.sh"


def test_semantic_object_fields_defaults_and_serialization() -> None:
    assert SemanticObject.VOID_ID == 0xFFFFFF
    assert TextQuery.Request().min_score == -1.0  # default keeps every score
    obj = SemanticObject(id=0x12AB34, label="chair", description="a red chair", score=0.75, num_gaussians=7)
    obj.centroid.x, obj.extent.z, obj.bbox_min.y, obj.bbox_max.y = 1.5, 0.8, -1.0, 2.0
    obj.color.r, obj.color.a = 0.5, 1.0  # float32 fields: exactly representable values
    array = SemanticObjectArray(objects=[obj, SemanticObject(id=1)])
    array.header.frame_id = "map"
    back = deserialize_message(serialize_message(array), SemanticObjectArray)
    assert back == array
    assert back.objects[0].label == "chair" and back.objects[0].id == 0x12AB34
    assert math.isclose(back.objects[0].score, 0.75)


@pytest.mark.parametrize(
    ("srv", "request_fields", "response_fields"),
    [
        (TextQuery, {"text": "sofa", "top_k": 4, "min_score": 0.25}, {"success": True, "message": "ok"}),
        (SaveMap, {"directory": "/tmp/map"}, {"success": True, "message": "saved", "directory": "/tmp/map"}),
        (LoadMap, {"directory": ""}, {"success": False, "message": "no map", "num_gaussians": 3, "num_objects": 2}),
        (Reset, {"keep_gaussians": True}, {"success": True, "message": "reset"}),
    ],
)
def test_service_types_round_trip(srv, request_fields: dict, response_fields: dict) -> None:
    request, response = srv.Request(**request_fields), srv.Response(**response_fields)
    assert deserialize_message(serialize_message(request), srv.Request) == request
    assert deserialize_message(serialize_message(response), srv.Response) == response
    for name, value in request_fields.items():
        assert getattr(request, name) == pytest.approx(value)


@pytest.mark.ros
def test_text_query_between_two_processes(tmp_path: Path) -> None:
    env = ros_environment(tmp_path)
    script = tmp_path / "text_query_server.py"
    script.write_text(SERVER)
    with NodeProcess.python([script, SERVICE], env, name="text_query_server") as server, ClientNode(env) as client:
        cli = client.node.create_client(TextQuery, SERVICE)
        server.wait_for_output("ready", timeout=15.0)
        wait_for_service(cli, timeout=10.0, process=server)

        response = call_service(cli, TextQuery.Request(text="chair", top_k=2), timeout=5.0, process=server)
        assert response.success, response.message
        assert response.header.frame_id == "map" and response.header.stamp.sec == 42
        assert [o.id for o in response.objects] == [0xFF0000, 0x00FF00]
        assert [o.label for o in response.objects] == ["chair 0", "chair 1"]
        scores = [o.score for o in response.objects]
        assert scores == sorted(scores, reverse=True) and scores[0] == pytest.approx(0.9)
        second = response.objects[1]
        assert (second.centroid.x, second.centroid.y, second.centroid.z) == (1.0, 2.0, 3.0)
        assert (second.extent.x, second.extent.y, second.extent.z) == (0.5, 0.25, 1.0)
        assert second.color.g == pytest.approx(1.0) and second.color.r == 0.0
        assert (second.num_gaussians, second.num_observations) == (200, 2)

        default_k = call_service(cli, TextQuery.Request(text="desk"), timeout=5.0, process=server)
        assert len(default_k.objects) == 3
        filtered = call_service(cli, TextQuery.Request(text="desk", top_k=5, min_score=0.4), timeout=5.0)
        assert [o.score for o in filtered.objects] == pytest.approx([0.9, 0.7, 0.5])
        failed = call_service(cli, TextQuery.Request(text=""), timeout=5.0, process=server)
        assert not failed.success and failed.message == "empty text" and not failed.objects

        start = time.perf_counter()
        for _ in range(20):
            call_service(cli, TextQuery.Request(text="lamp", top_k=5), timeout=5.0, process=server)
        per_call_ms = (time.perf_counter() - start) / 20 * 1e3
        assert per_call_ms < 200, f"service round trip {per_call_ms:.1f} ms"

        code = server.stop()
        assert code == 0, f"server did not shut down cleanly on SIGINT\n{server.describe()}"
        assert "Traceback" not in server.output(), server.describe()


def test_segment_array_round_trips_through_cdr() -> None:
    from rclpy.serialization import deserialize_message, serialize_message

    import msg_adapters as ma
    from monovoc_interfaces.msg import SegmentArray
    from monovoc_ros.core.segments.segment_labels import SegmentLabel

    labels = (SegmentLabel(0x00AA11, "chair", 0.75), SegmentLabel(3, "lamp", 1.0))
    msg = ma.segment_array(labels, frame_id="camera_optical_frame", stamp=5_000_000_123)
    back = deserialize_message(serialize_message(msg), SegmentArray)
    assert ma.header_stamp_ns(back) == 5_000_000_123
    assert ma.segment_array_to_labels(back) == labels
    back.segments[1].score = 2.0
    with pytest.raises(ma.AdapterError, match="score"):
        ma.segment_array_to_labels(back)
