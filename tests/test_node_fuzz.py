"""A seeded, bounded fuzz corpus against the live node (issue 9): >= 500 malformed messages across every
input topic (image, mask, camera_info, pose, gaussians), among them the cases of the issue (bombs, lying
cloud headers, empty clouds, far-future stamps, implausible cameras, 16-bit masks). Every one is counted
under its reason, the node keeps running, the state after the corpus equals the state before, and the
final map equals an offline run over the good keyframes alone."""

from __future__ import annotations

import copy
import time

import cv2
import numpy as np
import pytest

import msg_adapters as ma
from monovoc_ros.core.map.camera import Intrinsics
from monovoc_ros.core.map_store import load_snapshot
from monovoc_ros.nodes.keyframe_publisher import keyframe_messages
from monovoc_ros.ros_harness import (
    call_service,
)
from tests.evidence import assert_same_evidence
from tests.node_scene import N_KEYFRAMES, assemble, offline_mapper, running_mapper, small_scene
from tests.test_node_bombs import jpeg_bomb, png_bomb

pytestmark = pytest.mark.ros

S = 1_000_000_000
SEED = 9
PER_TOPIC = 120  # 4 keyframe topics x 120 + the clouds >= 500
FAR = (2**31 - 1) * S


def _stamp(msg, ns: int) -> None:
    msg.header.stamp = ma.ns_to_time(ns)


def _image_mutations(rng, good, role: str, cam: Intrinsics):
    """(mutate(msg), reason) for a CompressedImage of `role`; every one is rejected on its own."""
    bad = f"bad_{role}"
    h, w = (cam.height, cam.width) if role == "image" else good[role].shape[:2]

    def data(payload):
        return lambda m: setattr(m, "data", payload)

    def garbage(m):
        m.data = rng.integers(0, 256, int(rng.integers(0, 4000)), dtype=np.uint8).tobytes()

    def truncated(m):
        m.data = bytes(m.data)[: int(rng.integers(0, max(1, len(m.data) - 1)))]

    def flipped_header(m):
        raw = bytearray(m.data)
        for pos in rng.integers(0, min(len(raw), 30), size=3):
            raw[pos] ^= 0xFF
        m.data = bytes(raw)
        raw[0] = 0  # the magic is always broken: a header we cannot trust
        m.data = bytes(raw)

    def resized(m):
        scale = float(rng.choice([0.5, 2.0, 3.0]))
        size = (max(1, int(w * scale)), max(1, int(h * scale * (1.3 if role == "mask" else 1.0))))
        payload = cv2.resize(good[role], size, interpolation=cv2.INTER_NEAREST)
        m.data = ma.numpy_to_compressed_image(payload, "png").data
        m.format = "png"

    deep = (good["mask"].astype(np.uint16) * 257)[:, :, ::-1]
    deep_png = cv2.imencode(".png", deep)[1].tobytes()
    cases = [
        (lambda m: setattr(m, "format", str(rng.choice(["tiff", "bmp", "rgb8", "", "16UC1; compressedDepth png"]))),
         bad),
        (data(b""), bad),
        (garbage, bad),
        (truncated, bad),
        (flipped_header, bad),
        (lambda m: (data(png_bomb(30000, 30000))(m), setattr(m, "format", "png")), "size_mismatch"),
        (lambda m: (data(jpeg_bomb(int(rng.integers(20000, 40000)), 30000))(m), setattr(m, "format", "jpeg")),
         "size_mismatch"),
        (resized, "size_mismatch"),
    ]  # fmt: skip
    if role == "mask":
        white = ma.numpy_to_compressed_image(np.full_like(good["mask"], 255), "png").data
        cases += [(data(deep_png), bad), (data(white), "void_mask")]
    return cases


def _camera_mutations(rng, cam: Intrinsics):
    def k_entry(index, value):
        def mutate(m):
            k = list(m.k)
            k[index] = value
            m.k = k

        return mutate

    def field(name, value):
        return lambda m: setattr(m, name, value)

    def roi(m):
        m.roi.width, m.roi.height, m.roi.x_offset = int(cam.width), int(cam.height), int(rng.integers(1, 50))

    return [
        (k_entry(0, float(rng.choice([np.nan, np.inf, -1.0, 0.0, 1e-30, 1e9]))), "bad_camera_info"),
        (k_entry(4, float(rng.choice([np.nan, -np.inf, 1e-30, 1e12]))), "bad_camera_info"),
        (k_entry(1, 0.5), "bad_camera_info"),  # skew
        (k_entry(8, 2.0), "bad_camera_info"),
        (field("width", int(rng.choice([0, 16385, 2**32 - 1]))), "bad_camera_info"),
        (field("height", int(rng.choice([0, 20000, 2**32 - 1]))), "bad_camera_info"),
        (field("k", [0.0] * 9), "bad_camera_info"),
        (field("k", [1.0] * int(rng.integers(0, 9))), "bad_camera_info"),
        (field("d", [float(rng.uniform(-0.5, 0.5))] + [0.0] * 4), "bad_camera_info"),
        (roi, "bad_camera_info"),
    ]


def _pose_mutations(rng):
    def position(value):
        return lambda m: setattr(m.pose.position, str(rng.choice(["x", "y", "z"])), value)

    def orientation(**q):
        def mutate(m):
            for k, v in q.items():
                setattr(m.pose.orientation, k, v)

        return mutate

    return [
        (position(float(rng.choice([np.nan, np.inf, -np.inf]))), "bad_pose"),
        (orientation(w=float(rng.uniform(2, 100))), "bad_pose"),
        (orientation(w=0.0, x=0.0, y=0.0, z=0.0), "bad_pose"),
        (orientation(x=float("nan")), "bad_pose"),
    ]


def _stamp_mutations(rng, role: str, integrated: list[int]):
    """Stamps only: the content is good."""
    return [
        (lambda m: _stamp(m, FAR - int(rng.integers(0, 10**12))), "stamp_future"),
        (lambda m: _stamp(m, int(integrated[-1])), "duplicate_stamp"),  # the watermark itself
        (lambda m: _stamp(m, int(rng.choice(integrated[:-1]))), "stamp_out_of_order"),  # older keyframes
        (lambda m: _stamp(m, int(integrated[0]) - int(rng.integers(1, S))), "stamp_out_of_order"),
        (lambda m: setattr(m.header.stamp, "nanosec", int(rng.integers(10**9, 2**32))), f"bad_{role}"),
    ]


def _cloud_corpus(rng, gaussians, count: int):
    """(cloud, reason): every one is refused."""
    n = len(gaussians)
    out = []
    for k in range(count):
        msg = ma.gaussian_map_to_cloud(gaussians)
        kind = k % 8
        if kind == 0:
            msg = ma.gaussian_map_to_cloud(gaussians.subset(np.zeros(0, np.int64)))
            out.append((msg, "empty_gaussians"))
            continue
        if kind == 1:
            msg.fields[int(rng.integers(0, len(msg.fields)))].count = int(rng.choice([0, 2, 7]))
        elif kind == 2:
            msg.row_step = int(rng.choice([2**32 - 1, msg.row_step + 4, msg.row_step // 2]))
        elif kind == 3:
            gone = str(rng.choice(["x", "opacity", "rot_w", "scale_1"]))
            msg.fields = [f for f in msg.fields if f.name != gone]
        elif kind == 4:
            data = np.frombuffer(bytes(msg.data), np.float32).copy()
            data[int(rng.integers(0, data.size))] = float(rng.choice([np.nan, np.inf]))
            msg.data = data.tobytes()
        elif kind == 5:
            msg.data = bytes(msg.data)[: int(rng.integers(0, len(msg.data)))]
        elif kind == 6:
            msg.fields[int(rng.integers(0, len(msg.fields)))].datatype = int(rng.choice([0, 9, 200]))
        else:
            keep = np.sort(rng.choice(n, int(rng.integers(1, n // 3)), replace=False))
            out.append((ma.gaussian_map_to_cloud(gaussians.subset(keep)), "map_shrink"))
            continue
        out.append((msg, "bad_gaussians"))
    return out


def test_seeded_fuzz_corpus_changes_nothing(tmp_path):
    from monovoc_interfaces.srv import SaveMap

    rng = np.random.default_rng(SEED)
    scene = small_scene()
    cam = scene.keyframe(0).intrinsics
    good = [keyframe_messages(scene.keyframe(i), stamp_ns=(i + 1) * S) for i in range(len(scene))]
    keyframes = assemble(good)
    integrated = [kf.stamp_ns for kf in keyframes[:4]]
    arrays = {"mask": scene.keyframe(4).mask, "image": scene.keyframe(4).rgb}
    corpus, expected = [], {}
    for role in ("image", "mask", "camera_info", "pose"):
        kinds = _stamp_mutations(rng, role, integrated)
        kinds += _image_mutations(rng, arrays, role, cam) if role in ("image", "mask") else []
        kinds += _camera_mutations(rng, cam) if role == "camera_info" else []
        kinds += _pose_mutations(rng) if role == "pose" else []
        for k in range(PER_TOPIC):
            mutate, reason = kinds[int(rng.integers(0, len(kinds)))]
            # Between good keyframes 4 and 5 (4 s and 5 s): far from both, so never matched with them.
            msg = copy.deepcopy(good[4][role])
            _stamp(msg, 4 * S + (k + 1) * (S // (PER_TOPIC + 2)))
            mutate(msg)
            corpus.append((role, msg, reason))
            expected[reason] = expected.get(reason, 0) + 1
    clouds = _cloud_corpus(rng, scene.gaussians, 40)
    n_keyframe_corpus = len(corpus)
    assert n_keyframe_corpus + len(clouds) >= 500
    order = rng.permutation(len(corpus))  # topics interleaved at random; each topic keeps its own order
    by_topic: dict[str, list] = {}
    for role, msg, _ in corpus:
        by_topic.setdefault(role, []).append(msg)
    sequence = []
    cursors = dict.fromkeys(by_topic, 0)
    for i in order:
        role = corpus[i][0]
        sequence.append((role, by_topic[role][cursors[role]]))
        cursors[role] += 1

    reference = offline_mapper(scene.gaussians, keyframes)
    params = {"publish_rate_hz": 0.0, "diagnostics_period_s": 0.2, "input_depth": 1000}
    with running_mapper(tmp_path, params) as mapper:
        node, diagnostics, publisher, save = mapper.node, mapper.diagnostics, mapper.publisher, mapper.save
        publisher.publish_map(scene.gaussians)
        for msgs in good[:4]:
            publisher.publish_messages(msgs)
        diagnostics.wait_for(lambda v: v["keyframes_processed"] == "4" and v["queue_length"] == "0", 30.0, process=node)
        assert call_service(save, SaveMap.Request(directory=str(tmp_path / "before")), process=node).success

        start = time.monotonic()
        for role, msg in sequence:
            publisher.publishers[role].publish(msg)
        keyframe_reasons = {r for r in expected}
        diagnostics.wait_for(
            lambda v: sum(int(v[f"rejected.{r}"]) for r in keyframe_reasons) == n_keyframe_corpus, 60.0, process=node
        )
        counts: dict[str, int] = {}
        for cloud, reason in clouds:  # one at a time: the latched map topic keeps only the newest
            counts[reason] = counts.get(reason, 0) + 1
            publisher.gaussians.publish(cloud)
            diagnostics.wait_for(lambda v, r=reason, n=counts[reason]: v[f"rejected.{r}"] == str(n), 10.0, process=node)
        seconds = time.monotonic() - start
        after = diagnostics.wait_for(lambda v: v["keyframes_processed"] == "4", 5.0, process=node)
        assert call_service(save, SaveMap.Request(directory=str(tmp_path / "after")), process=node).success

        for msgs in good[4:]:
            publisher.publish_messages(msgs)
        done = diagnostics.wait_for(lambda v: v["keyframes_processed"] == str(N_KEYFRAMES), 60.0, process=node)
        assert call_service(save, SaveMap.Request(directory=str(tmp_path / "final")), process=node).success
        node.check_running()
    print(f"fuzz: {n_keyframe_corpus} keyframe-topic messages + {len(clouds)} clouds rejected in {seconds:.1f} s")

    for reason, n in counts.items():
        expected[reason] = expected.get(reason, 0) + n
    got = {k.split(".", 1)[1]: int(v) for k, v in done.items() if k.startswith("rejected.") and v != "0"}
    assert got == expected
    assert after["map_updates"] == "0" and after["gaussians"] == str(len(scene.gaussians))
    before, after_map = load_snapshot(tmp_path / "before"), load_snapshot(tmp_path / "after")
    assert_same_evidence(after_map.state, before.state)
    np.testing.assert_array_equal(after_map.state.stamps_ns, before.state.stamps_ns)
    np.testing.assert_array_equal(after_map.gaussians.means, before.gaussians.means)
    final = load_snapshot(tmp_path / "final")
    np.testing.assert_array_equal(final.state.stamps_ns, [kf.stamp_ns for kf in keyframes])
    assert_same_evidence(final.state, reference.state, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(final.result().object_ids, reference.result().object_ids)
