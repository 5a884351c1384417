"""Crash-safe map directories: exact round trip, snapshot rotation, SIGKILL during saves."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from dataclasses import replace

import numpy as np
import pytest

from monovoc_ros.core.follow.map_updater import update_map
from monovoc_ros.core.map.ply import read_ply_vertices
from monovoc_ros.core.map_store import MapStoreError, current_snapshot, load_snapshot, save_snapshot
from monovoc_ros.core.mapping import MapperConfig, SemanticMapper
from monovoc_ros.synthetic import SceneConfig, generate_scene
from tests.evidence import assert_same_evidence


@pytest.fixture(scope="module")
def small_scene():
    return generate_scene(SceneConfig.at_resolution(160, 90, n_gaussians=15_000, n_keyframes=6))


def mapped(scene, n=3) -> SemanticMapper:
    mapper = SemanticMapper(scene.gaussians, MapperConfig(metric="ciede2000"))
    for i in range(n):
        mapper.integrate(scene.keyframe(i))
    return mapper


def test_round_trip_is_exact_and_resumes_where_it_stopped(small_scene, tmp_path):
    mapper = mapped(small_scene)
    info = save_snapshot(mapper, tmp_path)
    assert current_snapshot(tmp_path) == info.path and info.keyframes == 3
    restored = load_snapshot(tmp_path)
    assert restored.config == mapper.config
    for name in ("means", "scales", "quats", "opacities", "colors", "ids"):
        np.testing.assert_array_equal(getattr(restored.gaussians, name), getattr(mapper.gaussians, name))
    assert_same_evidence(restored.state, mapper.state)
    np.testing.assert_array_equal(restored.state.stamps_ns, mapper.state.stamps_ns)
    np.testing.assert_array_equal(restored.result().object_ids, mapper.result().object_ids)
    # Continuing after a resume equals never stopping.
    for m in (mapper, restored):
        m.integrate(small_scene.keyframe(3))
    cloud = read_ply_vertices(tmp_path / "semantic.ply")
    assert len(cloud) == len(mapper.gaussians)
    assert {"object_id", "confidence", "red"} <= set(cloud.dtype.names)


def test_rotation_keeps_two_snapshots_and_links_an_unchanged_map(small_scene, tmp_path):
    mapper = mapped(small_scene, 1)
    first = save_snapshot(mapper, tmp_path).path
    mapper.integrate(small_scene.keyframe(1))
    second = save_snapshot(mapper, tmp_path).path
    assert os.stat(second / "gaussians.npz").st_ino == os.stat(first / "gaussians.npz").st_ino
    update_map(mapper, small_scene.gaussians.subset(np.arange(100, len(small_scene.gaussians))))
    third = save_snapshot(mapper, tmp_path).path
    assert os.stat(third / "gaussians.npz").st_ino != os.stat(second / "gaussians.npz").st_ino
    assert sorted(p.name for p in tmp_path.glob("snap-*")) == [second.name, third.name]
    assert len(load_snapshot(tmp_path).gaussians) == len(small_scene.gaussians) - 100


def test_the_maps_stamp_is_kept_and_a_bad_one_refused(small_scene, tmp_path):
    """The SLAM's stamp of the map (keyframes stamped before it come from an older map: core.follow.map_frames)
    survives a resume; a meta.json whose stamp is not one is refused like any other broken snapshot."""
    mapper = SemanticMapper(replace(small_scene.gaussians, stamp_ns=123_456_789), MapperConfig())
    mapper.integrate(small_scene.keyframe(0))
    info = save_snapshot(mapper, tmp_path)
    assert load_snapshot(tmp_path).gaussians.stamp_ns == 123_456_789
    meta = json.loads((info.path / "meta.json").read_text())
    for bad in (-1, "soon", True):
        (info.path / "meta.json").write_text(json.dumps({**meta, "map_stamp_ns": bad}))
        with pytest.raises(MapStoreError, match="map_stamp_ns"):
            load_snapshot(tmp_path)
    del meta["map_stamp_ns"]  # a snapshot from before it: unknown
    (info.path / "meta.json").write_text(json.dumps(meta))
    assert load_snapshot(tmp_path).gaussians.stamp_ns == 0


def test_missing_and_corrupt_directories_raise_clear_errors(small_scene, tmp_path):
    with pytest.raises(MapStoreError, match="no saved map"):
        load_snapshot(tmp_path)
    info = save_snapshot(mapped(small_scene, 1), tmp_path)
    (info.path / "state.npz").write_bytes(b"not a zip")
    with pytest.raises(MapStoreError, match="unreadable snapshot"):
        load_snapshot(tmp_path)
    (tmp_path / "CURRENT").write_text("snap-999999\n")
    with pytest.raises(MapStoreError, match="not a complete snapshot"):
        load_snapshot(tmp_path)


def test_sigkill_during_repeated_saves_never_leaves_a_broken_map(tmp_path):
    """A writer killed at random moments: CURRENT always names a complete, loadable snapshot."""
    script = textwrap.dedent(
        f"""
        import sys
        from monovoc_ros.core.map_store import save_snapshot
        from monovoc_ros.core.mapping import SemanticMapper
        from monovoc_ros.synthetic import SceneConfig, generate_scene
        scene = generate_scene(SceneConfig.at_resolution(120, 68, n_gaussians=60_000, n_keyframes=40))
        mapper = SemanticMapper(scene.gaussians)
        for i in range(len(scene)):
            mapper.integrate(scene.keyframe(i))
            save_snapshot(mapper, {str(tmp_path)!r})
            print(i, flush=True)
        """
    )
    for delay in (0.35, 0.6, 0.9):
        proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
        assert proc.stdout.readline().strip() == "0" or (tmp_path / "CURRENT").exists()
        time.sleep(delay)  # let it get well into later saves, then kill mid-write
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        restored = load_snapshot(tmp_path)
        assert len(restored.gaussians) == 60_000
        assert len(restored.state.stamps_ns) == restored.n_keyframes >= 1
        assert np.all(np.isfinite(restored.state.total_weight))


def test_merge_command_of_two_halves_equals_the_whole(small_scene, tmp_path, capsys):
    from monovoc_ros.cli import main

    config = MapperConfig(vote_slots=8)
    whole, halves = SemanticMapper(small_scene.gaussians, config), []
    for part in ((0, 2, 4), (1, 3, 5)):
        half = SemanticMapper(small_scene.gaussians, config)
        for i in part:
            half.integrate(small_scene.keyframe(i))
            whole.integrate(small_scene.keyframe(i))
        save_snapshot(half, tmp_path / f"half{part[0]}")
        halves.append(half)
    assert main(["merge", str(tmp_path / "half0"), str(tmp_path / "half1"), "-o", str(tmp_path / "merged")]) == 0
    merged = load_snapshot(tmp_path / "merged")
    assert '"keyframes": 6' in capsys.readouterr().out and merged.n_keyframes == 6
    assert_same_evidence(merged.state, whole.state, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(merged.result().object_ids, whole.result().object_ids)
    np.testing.assert_array_equal(merged.palette_builder.ids, whole.palette_builder.ids)
    with pytest.raises(SystemExit, match="stamps are in both"):
        main(["merge", str(tmp_path / "half0"), str(tmp_path / "half0"), "-o", str(tmp_path / "twice")])
    scd = SemanticMapper(small_scene.gaussians, MapperConfig(semantic_mode="scd"))
    scd.integrate(small_scene.keyframe(5))
    with pytest.raises(ValueError, match="different semantic_mode"):
        halves[0].merged(scd)


def test_evidence_of_another_mode_or_slot_count_is_refused_on_resume(small_scene, tmp_path):
    save_snapshot(mapped(small_scene), tmp_path)
    for change in ({"semantic_mode": "scd"}, {"vote_slots": 6}, {"weight_power": 2}, {"void_policy": "include"}):
        with pytest.raises(MapStoreError, match=next(iter(change))):
            load_snapshot(tmp_path, MapperConfig(metric="ciede2000", **change))
    assert load_snapshot(tmp_path, MapperConfig(metric="ciede2000", impl="reference")).n_keyframes == 3


def test_deferred_keyframes_round_trip_whole_and_refuse_corrupt_files(tmp_path):
    from monovoc_ros.core.deferred_keyframes import load_keyframes, save_keyframes
    from monovoc_ros.core.keyframe import Keyframe
    from monovoc_ros.core.map.camera import Intrinsics
    from monovoc_ros.core.segments.segment_labels import SegmentLabel

    rng = np.random.default_rng(0)
    cam = Intrinsics(30.0, 30.0, 15.5, 11.5, 32, 24)
    pose = np.eye(4)
    pose[:3, 3] = (0.5, -1.0, 2.0)
    mask, rgb = (rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for h, w in ((24, 32), (48, 64)))
    with_all = Keyframe(3, 7_000, pose, cam, mask, rgb, (SegmentLabel(0xC81E1E, "chair", 0.75),))
    bare = Keyframe(4, 8_000, np.eye(4), cam, np.full((24, 32, 3), 9, np.uint8))
    path = tmp_path / "deferred.npz"
    save_keyframes(path, [with_all, bare])
    got = load_keyframes(path)
    assert [k.stamp_ns for k in got] == [7_000, 8_000] and [k.index for k in got] == [3, 4]
    assert np.array_equal(got[0].rgb, with_all.rgb) and got[1].rgb is None and got[1].segments is None
    assert np.array_equal(got[0].mask, with_all.mask) and np.array_equal(got[0].cam_to_world, pose)
    assert got[0].segments == with_all.segments and got[0].intrinsics == cam
    path.write_bytes(path.read_bytes()[:200])
    with pytest.raises(ValueError, match="unreadable deferred keyframes"):
        load_keyframes(path)


def test_the_map_file_is_linked_from_the_previous_snapshot_only_when_it_is_the_same_map(small_scene, tmp_path):
    mapper = mapped(small_scene)
    first = save_snapshot(mapper, tmp_path).path
    second = save_snapshot(mapper, tmp_path).path
    assert os.stat(first / "gaussians.npz").st_ino == os.stat(second / "gaussians.npz").st_ino
    # A reset map of as many Gaussians (map_version 0 again): written, not linked.
    g = small_scene.gaussians
    other = SemanticMapper(type(g)(g.means + np.float32(0.5), g.scales, g.quats, g.opacities), MapperConfig())
    assert other.map_version == mapper.map_version and len(other.gaussians) == len(g)
    third = save_snapshot(other, tmp_path).path
    assert os.stat(third / "gaussians.npz").st_ino != os.stat(second / "gaussians.npz").st_ino
    np.testing.assert_array_equal(load_snapshot(tmp_path).gaussians.means, other.gaussians.means)
