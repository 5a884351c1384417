"""The Gaussian map topic read in a child process (monovoc_ros.nodes.map_reader): the shared-memory hand-over
bit for bit, its refusals, and the node with its reader: a reader that dies is replaced without applying the
latched map twice, and a node that dies takes its reader with it."""

from __future__ import annotations

import contextlib
import fcntl
import gc
import json
import os
import re
import signal
import socket
from dataclasses import replace
from pathlib import Path

import numpy as np
import psutil
import pytest

import msg_adapters as ma
from monovoc_ros.core.follow.map_motion import MapMotion
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.nodes import map_reader
from monovoc_ros.nodes.qos import latched_qos
from monovoc_ros.ros_harness import (
    DiagnosticsMonitor,
    NodeProcess,
    wait_for_subscribers,
    wait_until,
)
from tests.node_scene import mapper_with_client, running_mapper, small_scene
from tests.rosutil import ros_environment


def _pair() -> tuple[socket.socket, socket.socket]:
    return socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)


def _maps_open() -> int:
    """Descriptors of this process on map files (memfd "monovoc_map"): exact, whatever else the tests leak."""
    count = 0
    for fd in os.listdir("/proc/self/fd"):
        with contextlib.suppress(FileNotFoundError):  # the listing's own descriptor, closed since
            count += os.readlink(f"/proc/self/fd/{fd}").startswith("/memfd:monovoc_map")
    return count


@pytest.mark.parametrize("kind", ["full", "required arrays only", "empty"])
def test_a_map_crosses_the_socket_bit_for_bit_and_read_only(kind):
    gmap = small_scene().gaussians
    if kind == "required arrays only":
        gmap = GaussianMap(gmap.means, gmap.scales, gmap.quats, gmap.opacities)
    elif kind == "empty":  # the node refuses it (empty_gaussians) but it must get there
        gmap = gmap.subset(np.arange(0))
    ours, theirs = _pair()
    with ours, theirs:
        map_reader.send_map(ours, gmap, stamp_ns=17, frame_id="map", decode_s=0.25, superseded=3)
        got = map_reader.receive(theirs)
    assert _maps_open() == 1  # the mapping's own descriptor (Python's mmap keeps a duplicate): no other
    assert isinstance(got, map_reader.ReceivedMap)
    assert (got.stamp_ns, got.frame_id, got.decode_s, got.superseded) == (17, "map", 0.25, 3)
    assert got.gaussians.stamp_ns == 17
    for name in ("means", "scales", "quats", "opacities", "colors", "ids"):
        sent, received = getattr(gmap, name), getattr(got.gaussians, name)
        if sent is None:
            assert received is None, name
            continue
        assert received.dtype == sent.dtype and not received.flags.writeable, name
        np.testing.assert_array_equal(received, sent, err_msg=name)
    del got, received
    gc.collect()
    assert _maps_open() == 0  # the map dropped, its shared memory is gone with it


def _send_header(sock: socket.socket, header: dict, size: int = 4096, seal: bool = True) -> None:
    fd = os.memfd_create("monovoc_map", os.MFD_ALLOW_SEALING)
    os.ftruncate(fd, size)
    if seal:
        fcntl.fcntl(fd, fcntl.F_ADD_SEALS, map_reader._SEALS)
    socket.send_fds(sock, [json.dumps(header).encode()], [fd])
    os.close(fd)


def test_refusals_end_of_stream_and_malformed_messages():
    """What the node's end refuses however the header lies (our child never sends these): each one clear
    ValueError, its descriptor closed."""
    base = {"kind": "map", "stamp_ns": 1, "frame_id": "", "decode_s": 0, "superseded": 0, "size": 64}
    means = {"name": "means", "dtype": "<f4", "shape": [4, 3], "offset": 0}
    lies = [
        ({**base, "size": 8192}, "shared file of 4096 bytes, header says 8192"),
        ({**base, "arrays": [{**means, "dtype": "|O"}]}, "not expected"),  # object arrays from raw memory
        ({**base, "arrays": [{**means, "dtype": "<f8"}]}, "not expected"),
        ({**base, "arrays": [{**means, "name": "semantics"}]}, "not expected"),
        ({**base, "arrays": [means, means]}, "not expected"),
        ({**base, "arrays": [{**means, "shape": [-1, 3]}]}, "outside"),
        ({**base, "arrays": [{**means, "shape": [2**70, 3]}]}, "outside"),
        ({**base, "arrays": [{**means, "offset": 60}]}, "outside"),
        ({**base, "arrays": [{**means, "offset": -4}]}, "outside"),
        ([1, 2], "malformed message"),
    ]
    ours, theirs = _pair()
    with ours, theirs:
        refusal = map_reader.Refusal("Gaussian map ignored: no x field", bad_input=True)
        map_reader.send_refusal(ours, refusal)
        assert map_reader.receive(theirs) == refusal
        # A hostile message's error may quote anything: its refusal still fits one socket message.
        huge = map_reader.Refusal("Gaussian map ignored: " + "\U0001f600" * 300_000, bad_input=True)
        map_reader.send_refusal(ours, huge)
        received = map_reader.receive(theirs)
        cut = len(huge.message) - map_reader.MAX_REFUSAL_CHARS
        assert received.message == f"{huge.message[: map_reader.MAX_REFUSAL_CHARS]}... ({cut} characters more)"
        ours.send(json.dumps({"kind": "map", "stamp_ns": 1}).encode())  # a map without its descriptor
        with pytest.raises(ValueError, match="unexpected message 'map' with 0 descriptors") as error:
            map_reader.receive(theirs)
        assert not error.value.map_lost  # no descriptor came: no map was lost, no credit is due
        for header, error in lies:
            _send_header(ours, header)
            with pytest.raises(ValueError, match=re.escape(error)) as refused:
                map_reader.receive(theirs)
            assert refused.value.map_lost  # a descriptor came with it: it may have been a map
            del refused  # its traceback holds the frame that mapped the file
            assert _maps_open() == 0, header
        _send_header(ours, base, seal=False)  # a file that could still shrink under the node's arrays
        with pytest.raises(ValueError, match="not sealed"):
            map_reader.receive(theirs)
        ours.send(b"{not json")
        with pytest.raises(ValueError, match="malformed message") as error:
            map_reader.receive(theirs)
        assert not error.value.map_lost
        ours.shutdown(socket.SHUT_RDWR)
        assert map_reader.receive(theirs) is None
    assert _maps_open() == 0


def _motion() -> MapMotion:
    rng = np.random.default_rng(3)
    angle = 0.01
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    return MapMotion(rotation, rng.normal(size=3), rng.normal(size=3), 1.5, rng.normal(0, 0.01, (5, 4, 2, 3)),
                     rms=0.004, inliers=0.97, converged=True, by="registration")  # fmt: skip


def test_a_motion_crosses_the_socket_bit_for_bit():
    motion = _motion()
    ours, theirs = _pair()
    with ours, theirs:
        map_reader.send_motion(ours, 7, motion, 0.125)
        got = map_reader.receive(theirs)
        map_reader.send_motion(ours, 8, None, 0.5)  # not estimated: the node's plan estimates it
        assert map_reader.receive(theirs) == map_reader.ReceivedMotion(8, None, 0.5)
    assert isinstance(got, map_reader.ReceivedMotion) and (got.seq, got.seconds) == (7, 0.125)
    for name in ("rotation", "translation", "origin", "offsets"):
        np.testing.assert_array_equal(getattr(got.motion, name), getattr(motion, name), err_msg=name)
    assert (got.motion.spacing, got.motion.rms, got.motion.inliers, got.motion.converged, got.motion.by) == (
        1.5, 0.004, 0.97, True, "registration")  # fmt: skip
    assert _maps_open() == 0  # copied out: its file is closed at once


def test_a_malformed_motion_is_refused():
    ours, theirs = _pair()
    motion = _motion()
    bad = [
        (replace(motion, offsets=np.zeros((2, 2, 3))), "not expected"),
        (replace(motion, rotation=np.full((3, 3), np.nan)), "not finite"),
        (replace(motion, by="magic"), "a motion by 'magic'"),
        (replace(motion, spacing=0.0), "field spacing of 0.0"),
    ]
    with ours, theirs:
        for sent, error in bad:
            map_reader.send_motion(ours, 1, sent, 0.0)
            with pytest.raises(ValueError, match=re.escape(error)):
                map_reader.receive(theirs)
        header = {"kind": "motion", "seq": 1, "seconds": 0, "size": 64, "arrays": [], "spacing": 1, "rms": 0,
                  "inliers": 1, "converged": True, "by": "ids"}  # fmt: skip
        _send_header(ours, header)
        with pytest.raises(map_reader.MalformedMessage, match="a motion of arrays") as error:
            map_reader.receive(theirs)
        # Told from a map: the node gives no credit for it and does not count it as a map message.
        assert error.value.kind == "motion"
    assert _maps_open() == 0


def test_each_map_gets_the_motion_its_child_sends_after_it():
    """MotionHandover: a map's GivenMotion is from the map the same child handed over before; the motion message
    completes it; a map without its motion (a newer one came first, or the child ended) completes it with None."""
    handover = map_reader.MotionHandover()
    maps = [small_scene().gaussians.subset(np.arange(i + 1)) for i in range(5)]

    def received(seq: int) -> map_reader.ReceivedMap:
        return map_reader.ReceivedMap(maps[seq - 1], seq, "map", 0.0, seq=seq)

    assert handover.handed_over(received(1)).motion is None  # a child's first map: nothing before it
    second = handover.handed_over(received(2)).motion
    assert second.base is maps[0] and second.config == map_reader.READER_MOTION and not second.motion.done()
    handover.arrived(map_reader.ReceivedMotion(1, _motion(), 0.1))  # not the awaited map's: ignored
    assert not second.motion.done()
    motion = _motion()
    handover.arrived(map_reader.ReceivedMotion(2, motion, 0.2))
    assert second.motion.result(0) is motion and handover.seconds == 0.2
    third = handover.handed_over(received(3)).motion
    fourth = handover.handed_over(received(4)).motion  # before the third's motion came
    assert third.motion.result(0) is None and fourth.base is maps[2] and not fourth.motion.done()
    handover.reset()  # the child ended
    assert fourth.motion.result(0) is None
    assert handover.handed_over(received(1)).motion is None  # a new child's first map
    # A map the node could not read (seq 2) is no base: the child's motion of 3 is from it, not from 1.
    assert handover.handed_over(received(3)).motion is None
    assert handover.handed_over(received(4)).motion.base is maps[2]


def test_the_reader_keeps_only_the_newest_map_the_node_has_not_asked_for():
    newest = map_reader.NewestMap()
    for i in range(5):  # a node starting up, or busy
        newest.put(i)
    assert newest.take(timeout=0.0) is None  # not asked for
    newest.credit()
    assert newest.take(timeout=0.0) == (4, 4)  # the newest, and how many it replaced
    assert newest.take(timeout=0.0) is None  # nothing new
    newest.put(5)
    assert newest.take(timeout=0.0) is None  # that credit was spent
    newest.credit(2)
    assert newest.take(timeout=0.0) == (5, 0)
    newest.put(6)
    assert newest.take(timeout=0.0) == (6, 0)  # the second credit


def _reader_of(node: NodeProcess) -> psutil.Process:
    """The node's map reader process (the one child running monovoc_ros.nodes.map_reader)."""
    found: list[psutil.Process] = []

    def one() -> bool:
        try:
            found[:] = [c for c in psutil.Process(node.pid).children() if "monovoc_ros.nodes.map_reader" in c.cmdline()]
        except psutil.NoSuchProcess:  # a child that exited between the two calls: look again
            return False
        return len(found) == 1

    wait_until(one, 30.0, "the node's map reader process", process=node)
    return found[0]


@pytest.mark.ros
def test_a_reader_that_dies_is_replaced_and_the_latched_map_is_not_applied_twice(tmp_path):
    """On a remapped map topic: the reader subscribes to the name the node resolves."""
    from sensor_msgs.msg import PointCloud2

    scene = small_scene()
    env = ros_environment(tmp_path)
    params = {"publish_rate_hz": 0.0, "diagnostics_period_s": 0.2}
    with mapper_with_client(env, params, remaps={"gaussians": "/slam/map"}, name="mapping_node") as (node, client):
        diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
        maps = client.node.create_publisher(PointCloud2, "/slam/map", latched_qos())

        def publish_map(gmap: GaussianMap, stamp_ns: int) -> None:
            maps.publish(ma.gaussian_map_to_cloud(gmap, stamp=stamp_ns))

        wait_for_subscribers(maps, timeout=30.0, process=node)
        publish_map(scene.gaussians, stamp_ns=1)
        diagnostics.wait_for(lambda v: v["maps_decoded"] == "1" and v["gaussians"] == str(len(scene.gaussians)),
                             30.0, process=node)  # fmt: skip
        first = _reader_of(node)
        # A terminal's Ctrl-C, or a SIGTERM to the process group, reaches the reader too: only the node stops it.
        first.send_signal(signal.SIGINT)
        first.send_signal(signal.SIGTERM)
        fewer = scene.gaussians.subset(np.arange(len(scene.gaussians) - 100))
        publish_map(fewer, stamp_ns=2)
        values = diagnostics.wait_for(lambda v: v["gaussians"] == str(len(fewer)), 30.0, process=node)
        assert values["maps_decoded"] == "2" and values["map_reader_restarts"] == "0" and first.is_running()

        first.kill()
        first.wait(10.0)
        # A new reader starts after a back-off and loads its modules and kernels, then discovers the publisher: on
        # two cores shared with another test session that took longer than 30 s once (twenty-fourth session).
        diagnostics.wait_for(lambda v: v["map_reader_restarts"] == "1", 90.0, process=node)
        second = _reader_of(node)
        assert second.pid != first.pid
        # It receives the latched map again: the map in use, which the session skips as any map sent twice (the
        # count of subscribers may still hold the dead reader's, so wait for that map, not for a match).
        diagnostics.wait_for(lambda v: v["maps_decoded"] == "3" and v["maps_unchanged"] == "1", 90.0, process=node)
        smaller = scene.gaussians.subset(np.arange(len(scene.gaussians) - 500))
        publish_map(smaller, stamp_ns=3)
        values = diagnostics.wait_for(lambda v: v["gaussians"] == str(len(smaller)), 30.0, process=node)
        assert values["maps_decoded"] == "4" and values["map_reader_restarts"] == "1"
        assert values["map_updates"] == "2" and values["maps_unchanged"] == "1"  # the redelivered map not applied
        assert "the map reader exited" in node.output()

        segments = _own_fastdds_segments(second.pid)
        assert segments, "the reader's participant holds no Fast DDS shared-memory segment"
        node.proc.kill()  # the node dies without a word: its reader must not outlive it
        node.proc.wait()
        wait_until(lambda: _gone(second), 10.0, "the reader to exit after its node")
        # ... nor leave its participant's shared-memory files in /dev/shm (an os._exit alone did, at every stop).
        assert [p.name for p in segments if p.exists() or p.with_name(p.name + "_el").exists()] == []


@pytest.mark.ros
def test_a_reader_that_stops_answering_is_replaced(tmp_path):
    """A reader stopped (SIGSTOP) or hung sends no heartbeat: after SILENT_S the node kills it, counts and logs it,
    and a new one takes the latched map the stopped one never handed over."""
    scene = small_scene()
    with running_mapper(tmp_path, {"publish_rate_hz": 0.0, "diagnostics_period_s": 0.2}) as mapper:
        node, diagnostics, publisher = mapper.node, mapper.diagnostics, mapper.publisher
        publisher.publish_map(scene.gaussians, stamp_ns=1)
        diagnostics.wait_for(lambda v: v["maps_decoded"] == "1", 30.0, process=node)
        stopped = _reader_of(node)
        stopped.suspend()
        fewer = scene.gaussians.subset(np.arange(len(scene.gaussians) - 100))
        publisher.publish_map(fewer, stamp_ns=2)
        wait = map_reader.SILENT_S + 30.0
        values = diagnostics.wait_for(lambda v: v["gaussians"] == str(len(fewer)), wait, process=node)
        assert values["map_reader_restarts"] == "1" and values["maps_decoded"] == "2"
        assert f"the map reader was silent for {map_reader.SILENT_S:g} s" in node.output()
        assert _reader_of(node).pid != stopped.pid
        wait_until(lambda: _gone(stopped), 10.0, "the stopped reader to be killed")


def _own_fastdds_segments(pid: int) -> list[Path]:
    """The Fast DDS shared-memory segments the participant of process `pid` created: /dev/shm/fastrtps_<id>, whose
    lock file <id>_el the process holds (/proc/locks); the shared port files are left out."""
    held = set()
    for line in Path("/proc/locks").read_text().splitlines():
        fields = line.split()
        if str(pid) in fields:
            held.add(fields[fields.index(str(pid)) + 1].rsplit(":", 1)[-1])
    return [
        lock.with_name(lock.name[: -len("_el")])
        for lock in Path("/dev/shm").glob("fastrtps_*_el")
        if not lock.name.startswith("fastrtps_port") and str(lock.stat().st_ino) in held
    ]


def _gone(process: psutil.Process) -> bool:
    try:
        return not process.is_running() or process.status() == psutil.STATUS_ZOMBIE  # a zombie: exited, not reaped
    except psutil.NoSuchProcess:
        return True


@pytest.mark.ros
@pytest.mark.parametrize("reader_process", [True, False])
def test_a_burst_of_maps_loses_none_silently(tmp_path, reader_process):
    """Maps sent back to back (a bag replayed with --fast, a SLAM catching up) each reach the node: decoded, or
    replaced by a newer one in the map reader and counted (`maps_received`); the newest is the map in use. With a
    map subscription one deep, maps that came while the reader decoded the one before were overwritten unseen."""
    from sensor_msgs.msg import PointCloud2

    from monovoc_ros.bags.qos import rclpy_profile

    scene = small_scene()
    env = ros_environment(tmp_path)
    params = {"publish_rate_hz": 0.0, "diagnostics_period_s": 0.2, "map_reader_process": reader_process}
    burst = 6
    with mapper_with_client(env, params, name="mapping_node") as (node, client):
        diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
        # As the replayer's: transient-local, the whole burst in its history.
        maps = client.node.create_publisher(
            PointCloud2, "/monovoc/gaussians", rclpy_profile(transient_local=True, depth=burst)
        )
        wait_for_subscribers(maps, timeout=30.0, process=node)
        sizes = [len(scene.gaussians) - 100 * i for i in range(burst)]
        messages = [
            ma.gaussian_map_to_cloud(scene.gaussians.subset(np.arange(n)), stamp=i + 1) for i, n in enumerate(sizes)
        ]
        for message in messages:  # back to back, as a replay sends them
            maps.publish(message)
        values = diagnostics.wait_for(lambda v: v["maps_received"] == str(burst), 30.0, process=node)
        values = diagnostics.wait_for(lambda v: v["gaussians"] == str(sizes[-1]), 30.0, process=node)
    # Every map is the first, an update, or one replaced by a newer map before it was applied (counted).
    assert 1 + int(values["map_updates"]) + int(values["maps_coalesced"]) == burst, values


@pytest.mark.ros
@pytest.mark.parametrize("reader_process", [True, False])
def test_map_bytes_that_are_no_point_cloud_are_refused_and_counted(tmp_path, reader_process):
    """The map topic is taken serialized (msg_adapters.point_cloud_from_cdr) in the reader and in the node alike: bytes
    a broken publisher sent are refused as bad input and counted, and the next map is taken."""
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import PointCloud2, PointField

    scene = small_scene()
    env = ros_environment(tmp_path)
    params = {"publish_rate_hz": 0.0, "diagnostics_period_s": 0.2, "map_reader_process": reader_process}
    smaller = scene.gaussians.subset(np.arange(len(scene.gaussians) - 100))

    def with_fields(names: list[str], drop: str = "") -> bytes:
        msg = ma.gaussian_map_to_cloud(scene.gaussians)
        msg.fields = [f for f in msg.fields if f.name != drop]
        msg.fields += [PointField(name=name, offset=0, datatype=PointField.UINT8, count=1) for name in names]
        return serialize_message(msg)

    garbage = [
        serialize_message(ma.gaussian_map_to_cloud(scene.gaussians))[:5000],  # cut in its point data
        b"\x00\x01\x00\x00" + bytes(range(256)),  # a CDR header and noise
        b"\x07",  # no CDR header
        # Errors that would quote 300 kB: their refusals crossed no socket (lost unlogged, or counted as the node's).
        with_fields(["n" * 300_000]),
        with_fields([f"f{k}" for k in range(20_000)], drop="x"),
    ]
    with mapper_with_client(env, params, name="mapping_node") as (node, client):
        diagnostics = DiagnosticsMonitor(client.node, "semantic_mapper")
        maps = client.node.create_publisher(PointCloud2, "/monovoc/gaussians", latched_qos())
        wait_for_subscribers(maps, timeout=30.0, process=node)
        maps.publish(ma.gaussian_map_to_cloud(scene.gaussians, stamp=1))
        diagnostics.wait_for(lambda v: v["gaussians"] == str(len(scene.gaussians)), 30.0, process=node)
        for count, data in enumerate(garbage, 1):  # one at a time: the latched topic keeps the newest only
            maps.publish(data)
            diagnostics.wait_for(lambda v, n=count: v["rejected.bad_gaussians"] == str(n), 20.0, process=node)
        maps.publish(ma.gaussian_map_to_cloud(smaller, stamp=2))
        values = diagnostics.wait_for(lambda v: v["gaussians"] == str(len(smaller)), 30.0, process=node)
        node.check_running()
    assert values["rejected.bad_gaussians"] == str(len(garbage)) and values["worker_errors"] == "0", values
    assert values["ingest_errors"] == "0", values
