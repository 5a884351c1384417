"""The text-query service of the full node (monovoc_ros.nodes.semantic_mapper), in real processes.

* a node resumed from a saved map answers at once, edge cases included, publishes the highlight, and
  the `monovoc query` client prints its answer (or exits 2 when no node is there);
* a node fed keyframes live: no objects before, objects after, queries stay fast while it integrates,
  objects.db is written with save_map, cleared by reset and restored by load_map;
* both: the objects topic, its markers and the answers agree on every object's centroid and extent, and
  on its one label and label source (given by labels_file, restored from objects.db, or the model's guess).
"""

from __future__ import annotations

import contextlib
import json
import sqlite3
import subprocess
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

import msg_adapters as ma
from monovoc_ros.core.evidence.palette import format_object_id
from monovoc_ros.core.segments.object_labels import ObjectLabel, display
from monovoc_ros.embed import default_model_dir
from monovoc_ros.nodes.keyframe_publisher import KeyframePublisher, keyframe_messages
from monovoc_ros.nodes.qos import latched_qos
from monovoc_ros.objects.database import DB_NAME, ObjectDatabase
from monovoc_ros.ros_harness import (
    ClientNode,
    DiagnosticsMonitor,
    HarnessError,
    MessageCollector,
    NodeProcess,
    call_service,
    ros_args,
    wait_for_service,
    wait_for_subscribers,
    wait_until,
)
from tests.object_room import copy_directory, room, room_directory, room_id, room_labels, room_map
from tests.rosutil import VENV_PYTHON, ros_environment

pytestmark = pytest.mark.ros

NODE = ["-m", "monovoc_ros.nodes.semantic_mapper"]
CLI = [str(VENV_PYTHON), "-m", "monovoc_ros.cli", "query"]


def _query(client, text, top_k=0, min_score=-1.0, process=None, timeout=20.0):
    from monovoc_interfaces.srv import TextQuery

    request = TextQuery.Request(text=text, top_k=top_k, min_score=min_score)
    return call_service(client, request, timeout, process=process)


def _environment(tmp_path):
    """Loopback ROS environment; its HOME is a temporary folder, so point it at the exported models."""
    return ros_environment(tmp_path, extra={"MONOVOC_MODEL_DIR": str(default_model_dir())})


@contextlib.contextmanager
def _node_with_objects(
    env: dict, params: dict
) -> Iterator[tuple[NodeProcess, ClientNode, MessageCollector, MessageCollector, Any]]:
    """The full node started with `params` and a client of it: (node, client, objects, markers, service), the
    client collecting the objects topic and its markers, its text-query client's service up."""
    from visualization_msgs.msg import MarkerArray

    from monovoc_interfaces.msg import SemanticObjectArray
    from monovoc_interfaces.srv import TextQuery

    with NodeProcess.python([*NODE, *ros_args(params)], env, name="object_query") as node, ClientNode(env) as client:
        objects, markers = MessageCollector(), MessageCollector()
        client.node.create_subscription(SemanticObjectArray, "/monovoc/objects", objects, latched_qos())
        client.node.create_subscription(MarkerArray, "/monovoc/objects/markers", markers, latched_qos())
        service = client.node.create_client(TextQuery, "/monovoc/query")
        wait_for_service(service, 30.0, process=node)
        yield node, client, objects, markers, service


def test_query_service_on_a_resumed_map(tmp_path):
    from sensor_msgs.msg import PointCloud2
    from visualization_msgs.msg import MarkerArray

    from monovoc_interfaces.srv import TextQuery

    directory = copy_directory(room_directory(), tmp_path / "map")
    _, index = room_map()
    env = _environment(tmp_path)
    params = {
        "map_directory": str(directory),
        "resume": True,
        "labels_file": str(directory / "labels.json"),
        "query.top_k": 4,
        "diagnostics_period_s": 1.0,
    }
    with NodeProcess.python([*NODE, *ros_args(params)], env, name="object_query") as node, ClientNode(env) as client:
        highlight, markers = MessageCollector(), MessageCollector()
        diagnostics = DiagnosticsMonitor(client.node, "semantic mapping")
        subscribed = client.node.create_subscription(PointCloud2, "/monovoc/query/highlight", highlight, latched_qos())
        client.node.create_subscription(MarkerArray, "/monovoc/query/markers", markers, latched_qos())
        service = client.node.create_client(TextQuery, "/monovoc/query")
        wait_for_service(service, 30.0, process=node)

        sofa = _query(service, "a sofa", top_k=3, process=node)
        assert sofa.success, sofa.message
        assert [o.id for o in sofa.objects][0] == room_id("sofa") and len(sofa.objects) == 3
        assert sofa.header.frame_id == "map" and sofa.objects[0].label == "sofa"
        first = sofa.objects[0]
        assert first.description and 0 < first.score <= 1 and first.num_gaussians > 0
        lo, hi, size = first.bbox_min, first.bbox_max, first.extent
        np.testing.assert_allclose([size.x, size.y, size.z], [hi.x - lo.x, hi.y - lo.y, hi.z - lo.z])
        # The highlight holds exactly the sofa's Gaussians, the markers the three answers.
        wait_until(lambda: highlight.messages, 10.0, "a highlight cloud", process=node)
        cloud = ma.semantic_cloud_to_arrays(highlight.messages[-1])
        expected = set(int(o.id) for o in sofa.objects)
        assert set(np.unique(cloud.object_ids).tolist()) <= expected
        assert len(cloud.object_ids) == int(np.isin(index.object_ids, list(expected)).sum())
        wait_until(lambda: markers.messages, 10.0, "query markers", process=node)
        boxes = [m for m in markers.messages[-1].markers if m.ns == "monovoc/query/boxes"]
        assert sorted(m.id for m in boxes) == sorted(expected)

        # Spatial language: the head object first, and the message says how the text was read.
        book = _query(service, "the book on the table", top_k=3, process=node)
        assert book.success and book.objects[0].id == room_id("book", 0), book.message
        assert "read as 'book' on 'table'" in book.message
        # A robot pose given in the request: the closest chair from the sofa's side is the other chair.
        request = TextQuery.Request(text="the closest chair", top_k=1)
        request.viewpoint.header.frame_id = "map"
        request.viewpoint.pose.position.x, request.viewpoint.pose.position.y = 0.0, 2.0
        request.viewpoint.pose.orientation.z, request.viewpoint.pose.orientation.w = -0.7071068, 0.7071068  # facing -y
        given = call_service(service, request, 20.0, process=node)
        assert given.success and given.objects[0].id == room_id("chair", 1), given.message
        assert _query(service, "the closest chair", top_k=1, process=node).objects[0].id == room_id("chair", 0)
        request.viewpoint.header.frame_id = "odom"
        elsewhere = call_service(service, request, 20.0, process=node)
        assert not elsewhere.success and "no tf here" in elsewhere.message
        request.viewpoint.header.frame_id = "map"
        request.viewpoint.pose.position.x = 1e300  # finite, but no robot's: refused, not answered in "inf m"
        far = call_service(service, request, 20.0, process=node)
        assert not far.success and "from the map's origin" in far.message, far.message

        # Questions: the node's ask service and `monovoc ask` against it.
        from monovoc_interfaces.srv import Ask

        asker = client.node.create_client(Ask, "/monovoc/ask")
        wait_for_service(asker, 30.0, process=node)
        chairs = call_service(asker, Ask.Request(question="how many chairs are there?"), 20.0, process=node)
        assert chairs.success and chairs.count == 2 and {o.label for o in chairs.objects} == {"chair"}
        where = call_service(asker, Ask.Request(question="where is the cup"), 20.0, process=node)
        assert where.success and where.count == -1 and where.answer.startswith("the cup is on the table")
        unknown = call_service(asker, Ask.Request(question="why"), 20.0, process=node)
        assert not unknown.success and "I understand" in unknown.answer
        run = subprocess.run(
            [*CLI[:-1], "ask", "what is on the cabinet", "--json", "--timeout", "20"],
            env=env,
            capture_output=True,
            text=True,
        )
        assert run.returncode == 0, run.stderr
        assert json.loads(run.stdout)["count"] == 1 and json.loads(run.stdout)["objects"][0]["label"] == "vase"

        # Edge cases: clear answers, never a crash.
        for text in ("", "   "):
            empty = _query(service, text, process=node)
            assert not empty.success and "empty query" in empty.message and not empty.objects
        huge = _query(service, "a lamp " * 20_000, top_k=1, process=node)
        assert huge.success and "truncated" in huge.message and len(huge.objects) == 1
        assert len(_query(service, "chair", top_k=0, process=node).objects) == 4  # query.top_k
        everything = _query(service, "chair", top_k=2**32 - 1, process=node)
        assert everything.success and len(everything.objects) == len(index)
        scores = [o.score for o in everything.objects]
        assert scores == sorted(scores, reverse=True)
        strict = _query(service, "chair", min_score=2.0, process=node)
        assert strict.success and not strict.objects and "min_score" in strict.message
        nan = _query(service, "chair", min_score=float("nan"), process=node)
        assert not nan.success and "NaN" in nan.message

        # The command line client, against the same node.
        run = subprocess.run(
            [*CLI, "the sofa", "--top-k", "2", "--json", "--timeout", "20"], env=env, capture_output=True, text=True
        )
        assert run.returncode == 0, run.stderr
        answer = json.loads(run.stdout)
        assert answer["success"] and answer["objects"][0]["hex"] == f"#{room_id('sofa'):06x}"
        table = subprocess.run([*CLI, "a lamp", "--timeout", "20"], env=env, capture_output=True, text=True)
        assert table.returncode == 0 and "lamp" in table.stdout and "rank" in table.stdout
        bad = subprocess.run([*CLI, " ", "--timeout", "20"], env=env, capture_output=True, text=True)
        assert bad.returncode == 1 and "empty query" in bad.stderr

        # Nobody subscribes to the highlight: its cloud is left out (counted), and a late subscriber gets it.
        def skipped() -> int:
            return int(diagnostics.values().get("queries.highlights_skipped", -1))

        wait_until(lambda: skipped() == 0, 20.0, "diagnostics: no highlight left out while subscribed", process=node)
        client.node.destroy_subscription(subscribed)
        for _ in range(10):  # until the node's publisher has seen the subscriber go (DDS discovery)
            assert _query(service, "a vase", top_k=1, process=node).objects[0].id == room_id("vase")
            with contextlib.suppress(HarnessError):
                wait_until(lambda: skipped() >= 1, 3.0, "a highlight left out", process=node)
                break
        assert skipped() >= 1
        late = MessageCollector()
        client.node.create_subscription(PointCloud2, "/monovoc/query/highlight", late, latched_qos())

        def vase_highlighted() -> bool:
            clouds = [ma.semantic_cloud_to_arrays(m) for m in late.messages]
            return any(c.object_ids.size and set(c.object_ids.tolist()) == {room_id("vase")} for c in clouds)

        wait_until(vase_highlighted, 20.0, "the vase's highlight for the late subscriber", process=node)
        node.check_running()


def _xyz(v) -> np.ndarray:
    return np.array([v.x, v.y, v.z])


def _disagreements(objects, markers, answer) -> list[str]:
    """Where an answered object's centroid or extent differs between the query answer, the latest
    `objects` message and its `objects/markers` boxes (empty: they agree)."""
    published = {o.id: o for o in objects.objects}
    boxes = {m.id: m for m in markers.markers if m.ns == "monovoc/boxes"}
    problems = []
    for a in answer.objects:
        o, box = published.get(a.id), boxes.get(a.id)
        if o is None or box is None:
            problems.append(f"#{a.id:06x}: on the objects topic {o is not None}, a marker box {box is not None}")
            continue
        size = np.maximum(_xyz(a.extent), 0.01)  # markers clamp sizes to 1 cm
        pairs = [
            ("centroid (topic)", _xyz(o.centroid), _xyz(a.centroid)),
            ("extent (topic)", _xyz(o.extent), _xyz(a.extent)),
            ("box min (topic)", _xyz(o.bbox_min), _xyz(a.bbox_min)),
            ("centroid (marker)", _xyz(box.pose.position), _xyz(a.centroid)),
            ("extent (marker)", _xyz(box.scale), size),
        ]
        for what, got, want in pairs:
            if not np.allclose(got, want, atol=1e-6):
                problems.append(f"#{a.id:06x} {what}: {got.round(3).tolist()} != answer {want.round(3).tolist()}")
        if o.num_gaussians != a.num_gaussians:
            problems.append(f"#{a.id:06x} num_gaussians: topic {o.num_gaussians}, answer {a.num_gaussians}")
    return problems


def _label_disagreements(objects, markers, answer) -> list[str]:
    """Where an object's label or label source differs between the latest `objects` message, the text of
    its `objects/markers` label and the query answer (empty: they agree). Every object on the topic has
    a marker showing its label (a guess marked "couch?", no label: its hex id)."""
    texts = {m.id: m.text for m in markers.markers if m.ns == "monovoc/labels"}
    published = {o.id: o for o in objects.objects}
    problems = []
    for o in objects.objects:
        shown = display(ObjectLabel.stored(o.label, o.label_source)) or format_object_id(o.id)
        if texts.get(o.id) != shown:
            problems.append(f"#{o.id:06x}: marker text {texts.get(o.id)!r}, topic {o.label!r} ({o.label_source!r})")
    for a in answer.objects:
        o = published.get(a.id)
        if o is None or (o.label, o.label_source) != (a.label, a.label_source):
            topic = None if o is None else (o.label, o.label_source)
            problems.append(f"#{a.id:06x}: topic {topic}, answer {(a.label, a.label_source)}")
    return problems


@pytest.mark.parametrize("labels", ["restored", "guessed"])
def test_objects_topic_markers_and_query_answers_agree_on_every_object(tmp_path, labels):
    """One object geometry (core.object_geometry): a resumed map's objects topic and its markers (computed by the
    mapping worker from the resumed result) and the answers (restored from objects.db) agree everywhere.
    One label (core.segments.object_labels) too, without a labels_file: "restored", the names objects.db was
    written with; "guessed", a database without names (written before label sources had names), whose
    objects the component names by the model's guess after the first result was published."""
    directory = copy_directory(room_directory(), tmp_path / "map")
    _, index = room_map()
    if labels == "guessed":
        with sqlite3.connect(directory / DB_NAME) as db:
            db.execute("UPDATE objects SET label = '', label_source = 'imagenet'")
    env = _environment(tmp_path)
    params = {"map_directory": str(directory), "resume": True, "diagnostics_period_s": 5.0}
    with _node_with_objects(env, params) as (node, client, objects, markers, service):
        answer = _query(service, "anything", top_k=1000, process=node)
        assert answer.success and len(answer.objects) == len(index) >= 20, answer.message
        objects.wait_for(1, 20.0, process=node)
        markers.wait_for(1, 20.0, process=node)
        assert _disagreements(objects.messages[-1], markers.messages[-1], answer) == []

        def labels_agree() -> bool:
            nonlocal answer
            answer = _query(service, "anything", top_k=1000, process=node)
            latest = objects.messages[-1], markers.messages[-1]
            return all(a.label for a in answer.objects) and not _label_disagreements(*latest, answer)

        wait_until(labels_agree, 30.0, "one label on the topic, markers and answers", process=node, interval=0.2)
        sources = {a.label_source for a in answer.objects}
        if labels == "restored":
            assert sources == {"given"}
            assert {a.id: a.label for a in answer.objects} == {r.id: r.label for r in index.records()}
        else:
            assert sources == {"guess"}
            texts = {m.id: m.text for m in markers.messages[-1].markers if m.ns == "monovoc/labels"}
            assert all(texts[a.id] == f"{a.label}?" for a in answer.objects)
        # The geometry is the main cluster's: the vase (0.12 m across, 0.25 m tall) is no longer metres wide.
        vase = next(o for o in objects.messages[-1].objects if o.id == room_id("vase"))
        assert _xyz(vase.extent).max() < 0.5


def test_client_without_a_node_exits_2(tmp_path):
    env = _environment(tmp_path)
    run = subprocess.run([*CLI, "a chair", "--timeout", "1"], env=env, capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and "/monovoc/query is not available" in run.stderr


def test_live_node_indexes_keyframes_and_saves_objects(tmp_path):
    from sensor_msgs.msg import PointCloud2

    from monovoc_interfaces.srv import LoadMap, Reset, SaveMap

    scene = room()
    directory = tmp_path / "map"
    labels_file = tmp_path / "labels.json"
    labels_file.write_text(json.dumps(scene.labels()))
    env = _environment(tmp_path)
    params = {
        "map_directory": str(directory),
        "save_period_s": 0.0,
        "publish_rate_hz": 2.0,
        "labels_file": str(labels_file),
        "diagnostics_period_s": 5.0,
    }
    with _node_with_objects(env, params) as (node, client, objects, markers, service):
        before = _query(service, "a sofa", process=node)
        assert not before.success and "no objects" in before.message

        publisher = KeyframePublisher(client.node)
        for pub in publisher.all_publishers():
            wait_for_subscribers(pub, timeout=20.0, process=node)
        publisher.publish_map(scene.gaussians)
        latencies = []
        for i in range(len(scene)):
            publisher.publish_messages(keyframe_messages(scene.keyframe(i)))
            start = time.perf_counter()
            _query(service, "a sofa", process=node)  # while the worker integrates and the index embeds
            latencies.append(time.perf_counter() - start)

        def sofa_found() -> bool:
            answer = _query(service, "a sofa", top_k=1, process=node)
            return answer.success and answer.objects[0].id == room_id("sofa")

        wait_until(sofa_found, 60.0, "the sofa to be indexed", process=node, interval=0.2)

        def all_embedded() -> bool:
            return len(_query(service, "anything", top_k=1000, process=node).objects) >= 20

        wait_until(all_embedded, 60.0, "most objects to be embedded", process=node, interval=0.2)

        # The objects topic, its markers and the answers report one geometry and one label (labels_file's), once
        # the index has the last result.
        answer = None

        def agree() -> bool:
            nonlocal answer
            answer = _query(service, "anything", top_k=1000, process=node)
            latest = objects.messages[-1], markers.messages[-1]
            return answer.success and not _disagreements(*latest, answer) and not _label_disagreements(*latest, answer)

        wait_until(agree, 30.0, "the objects topic, markers and answers to agree", process=node, interval=0.2)
        assert {(a.label, a.label_source) for a in answer.objects} <= {(n, "given") for n in room_labels().values()}
        median, worst = 1e3 * np.median(latencies), 1e3 * max(latencies)
        print(f"query latency while mapping: median {median:.1f} ms, max {worst:.1f} ms")
        assert np.median(latencies) < 0.5 and max(latencies) < 5.0

        # Nothing subscribed to the semantic cloud: the publications left it out. A viewer that subscribes now
        # gets the current cloud (its matched event asks the worker for a publication), not the empty one of the
        # node's start that the transient-local history held.
        diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
        diagnostics.wait_for(lambda v: int(v.get("clouds_skipped", "0")) > 0, 30.0, process=node)
        clouds = MessageCollector()
        client.node.create_subscription(PointCloud2, "/monovoc/semantic_cloud", clouds, latched_qos())
        wait_until(lambda: any(c.width > 1000 for c in clouds.messages), 30.0, "the current cloud", process=node)
        assert max(c.width for c in clouds.messages) <= len(scene.gaussians)

        save = client.node.create_client(SaveMap, "/monovoc/save_map")
        wait_for_service(save, process=node)
        saved = call_service(save, SaveMap.Request(), 60.0, process=node)
        assert saved.success, saved.message
        db = ObjectDatabase(directory / DB_NAME, create=False)
        assert len(db.records()) >= 20 and db.gaussian_index().object_ids.size == len(scene.gaussians)

        reset = client.node.create_client(Reset, "/monovoc/reset")
        wait_for_service(reset, process=node)
        assert call_service(reset, Reset.Request(keep_gaussians=True), 30.0, process=node).success
        assert not _query(service, "a sofa", process=node).success  # objects forgotten with the evidence

        load = client.node.create_client(LoadMap, "/monovoc/load_map")
        wait_for_service(load, process=node)
        assert call_service(load, LoadMap.Request(), 60.0, process=node).success
        wait_until(sofa_found, 20.0, "the objects restored with the map", process=node, interval=0.2)

        # objects.db is written beside the worker: a write that fails is logged and counted, the snapshot and
        # the node go on.
        broken = tmp_path / "broken"
        (broken / DB_NAME).mkdir(parents=True)
        saved = call_service(save, SaveMap.Request(directory=str(broken)), 60.0, process=node)
        assert saved.success, saved.message
        diagnostics.wait_for(lambda v: v.get("objects.save_errors") == "1", 30.0, process=node)
        node.wait_for_output("could not save objects to", 10.0)
        # Waited on, as after the load above: one fresh-clone CI run answered the query right after the failed
        # write without the sofa at the top (not reproduced in reruns; cause not found). Never found fails as before.
        wait_until(sofa_found, 20.0, "the objects still answered after a failed objects.db write", process=node,
                   interval=0.2)  # fmt: skip
        node.check_running()
