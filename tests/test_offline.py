"""Offline mapping: `monovoc map` / `monovoc eval` on a dataset folder, and the bag-event driver."""

from __future__ import annotations

import json

import numpy as np
import pytest

from monovoc_ros.cli import main
from monovoc_ros.core.evaluation.datasets import CorruptedMasks, write_plain
from monovoc_ros.core.map_store import load_snapshot
from monovoc_ros.core.mapping import MapperConfig
from monovoc_ros.ingest import Rejection
from monovoc_ros.offline import map_events, map_sequence
from monovoc_ros.synthetic import SceneConfig, generate_scene
from tests.evidence import assert_same_evidence


@pytest.fixture(scope="module")
def scene():
    return generate_scene(SceneConfig.at_resolution(200, 112, n_gaussians=30_000, n_keyframes=8))


def test_map_and_eval_commands_on_a_plain_folder(scene, tmp_path, capsys):
    data = tmp_path / "seq"
    write_plain(scene, data)
    out = tmp_path / "map"
    assert main(["map", str(data), "-o", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["keyframes"] == 8 and summary["gaussians"] == 30_000
    assert summary["objects"] >= 15 and summary["observed_gaussians"] > 0.8 * 30_000
    mapper = load_snapshot(out)
    direct, _ = map_sequence(scene, MapperConfig())
    np.testing.assert_array_equal(mapper.result().object_ids, direct.result().object_ids)

    report_path = tmp_path / "eval.json"
    figure = tmp_path / "eval.png"
    args = ["eval", str(out), str(data), "--every", "2", "--metrics", "cmc,rgb", "-o", str(report_path)]
    assert main([*args, "--figure", str(figure)]) == 0
    report = json.loads(report_path.read_text())
    # A vote map is labelled by argmax: only the metric it was mapped with applies.
    assert "cmc" in report and "rgb" not in report
    for metric in ("cmc",):
        for protocol in ("points", "splats"):
            scores = report[metric][protocol]
            assert 0.3 < scores["miou"] <= 1 and 0 <= scores["mismatch_nonwhite"] < 0.5
            assert scores["objects"] and all("iou" in o for o in scores["objects"].values())
    assert figure.stat().st_size > 10_000
    assert "cmc" in capsys.readouterr().out


def test_map_objects_writes_a_database_that_answers_queries(scene, tmp_path, capsys):
    from monovoc_ros.embed import default_model_dir
    from monovoc_ros.objects.database import ObjectDatabase

    data = tmp_path / "seq"
    write_plain(scene, data)
    out = tmp_path / "map"
    assert main(["map", str(data), "-o", str(out), "--quiet", "--objects", "--crop-mode", "hard"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    db = ObjectDatabase(summary["objects_db"], create=False)
    records = db.records()
    assert len(records) >= 10 and all(r.label for r in records)  # named from the folder's labels.json
    assert db.gaussian_index().object_ids.size == 30_000
    assert default_model_dir().exists()
    capsys.readouterr()
    assert main(["query", "--map", str(out), "a sofa", "--top-k", "3", "--json"]) == 0
    answer = json.loads(capsys.readouterr().out)
    assert answer["success"] and len(answer["objects"]) == 3


def test_synthetic_frames_carry_ground_truth_and_score_both_protocols():
    from monovoc_ros.commands.eval import score, sequence_frames

    scene = generate_scene(SceneConfig.at_resolution(160, 90, n_gaussians=20_000, n_keyframes=4))
    name, frames, names, truth = sequence_frames(scene)
    assert len(frames) == 4 and truth.shape == (20_000,) and len(names) == len(scene.objects)
    np.testing.assert_array_equal(frames[1][2], scene.clean_mask(1))
    mapper, _ = map_sequence(scene, MapperConfig())
    for protocol in ("points", "splats"):
        ideal, _ = score(scene.gaussians, truth, frames, protocol, 0.05)
        shuffled, _ = score(scene.gaussians, np.random.default_rng(0).permutation(truth), frames, protocol, 0.05)
        ours, rendered = score(scene.gaussians, mapper.result().object_ids, frames, protocol, 0.05)
        assert len(rendered) == 4 and rendered[0].shape == (90, 160)
        assert ideal["miou"] > 3 * shuffled["miou"]
        assert ours["miou"] > 3 * shuffled["miou"]


def test_bag_event_driver_waits_for_the_map_and_applies_updates(scene):
    keyframes = [scene.keyframe(i) for i in range(len(scene))]
    full, _ = map_sequence(scene, MapperConfig())
    # Keyframes before the map wait for it; a rejection is counted; order of evidence does not matter.
    events = [keyframes[0], Rejection("bad_pose", "pose", 1, "nan"), scene.gaussians, *keyframes[1:]]
    mapper, stats = map_events(events, MapperConfig())
    assert stats.keyframes_processed == len(keyframes) and stats.rejected == {"bad_pose": 1}
    assert_same_evidence(mapper.state, full.state, rtol=1e-12, atol=1e-12)
    # A duplicate keyframe is refused and counted, as in the live node.
    mapper, stats = map_events([scene.gaussians, keyframes[0], keyframes[0]], MapperConfig())
    assert stats.keyframes_processed == 1 and stats.rejected == {"duplicate_stamp": 1}
    # A map update halfway (some Gaussians pruned) keeps the evidence of the survivors (ids).
    keep = np.arange(len(scene.gaussians)) % 10 != 0
    pruned = scene.gaussians.subset(keep)
    mapper, stats = map_events([scene.gaussians, *keyframes[:4], pruned, *keyframes[4:]], MapperConfig())
    assert stats.map_updates == 1 and len(mapper.gaussians) == keep.sum()
    first, _ = map_events([scene.gaussians, *keyframes[:4]], MapperConfig())
    expect = first.state.total_weight[keep]
    second, _ = map_events([pruned, *keyframes[4:]], MapperConfig())
    np.testing.assert_allclose(mapper.state.total_weight, expect + second.state.total_weight, rtol=1e-12)
    with pytest.raises(ValueError, match="no Gaussian map"):
        map_events(keyframes[:1], MapperConfig())


def test_map_per_frame_on_shuffled_masks_and_eval_matches_instances(scene, tmp_path, capsys):
    data = tmp_path / "seq"
    write_plain(scene, data)
    out = tmp_path / "map"
    args = ["map", str(data), "-o", str(out), "--quiet", "--mask-ids", "per-frame", "--mask-noise", "shuffled"]
    assert main(args) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["config"]["mask_ids"] == "per_frame" and summary["objects"] >= 15
    mapper = load_snapshot(out)
    assert mapper.associator is not None and len(mapper.associator.issued) >= summary["objects"]
    # Deterministic, and the snapshot carries the association (issued ids, pair statistics).
    direct, _ = map_sequence(CorruptedMasks(scene, shuffled=True), MapperConfig(mask_ids="per_frame"))
    assert direct.associator.to_json() == mapper.associator.to_json()
    np.testing.assert_array_equal(mapper.result().object_ids, direct.result().object_ids)
    report_path = tmp_path / "eval.json"
    assert main(["eval", str(out), str(data), "--every", "2", "--protocols", "splats", "-o", str(report_path)]) == 0
    splats = json.loads(report_path.read_text())["cmc"]["splats"]
    assert splats["miou"] > 0.6 and splats["matched_objects"] >= 15
    assert abs(splats["map_objects"] - splats["reference_objects"]) <= 0.2 * splats["reference_objects"]
    assert "per-frame ids, splats: matched mIoU" in capsys.readouterr().out
    global_out = tmp_path / "global"
    assert main(["map", str(data), "-o", str(global_out), "--quiet"]) == 0
    assert (
        main(["eval", str(global_out), str(data), "--every", "2", "--protocols", "splats", "-o", str(report_path)]) == 0
    )
    assert splats["miou"] >= json.loads(report_path.read_text())["cmc"]["splats"]["miou"] - 0.03


def test_segment_labels_from_a_folder_and_from_labels_reach_the_snapshot(scene, tmp_path):
    from monovoc_ros.core.evaluation.datasets import open_sequence
    from monovoc_ros.core.segments.segment_labels import SegmentLabel, write_segments

    data = tmp_path / "seq"
    write_plain(scene, data)
    first = sorted((data / "masks").iterdir())[0]
    (data / "segments").mkdir()
    write_segments(data / "segments" / f"{first.stem}.json", (SegmentLabel(0x123456, "lamp", 0.7),))
    seq = open_sequence(str(data))
    assert seq.keyframe(0).segments == (SegmentLabel(0x123456, "lamp", 0.7),) and seq.keyframe(1).segments is None
    (data / "segments" / f"{first.stem}.json").write_text('[{"class_name": "lamp"}]')
    with pytest.raises(ValueError, match="color"):
        seq.keyframe(0)
    (data / "segments" / f"{first.stem}.json").unlink()
    out = tmp_path / "map"
    args = ["map", str(data), "-o", str(out), "--quiet", "--mask-ids", "per-frame", "--mask-noise", "shuffled"]
    assert main([*args, "--segments-from-labels"]) == 0
    labels = load_snapshot(out).object_labels()
    names = {e["class_name"] for e in scene.labels()}
    assert len(labels) >= 15 and set(labels.values()) <= names


def test_per_frame_map_with_segment_labels_answers_queries_through_instance_matching(scene, tmp_path, capsys):
    from monovoc_ros.objects.database import ObjectDatabase

    data = tmp_path / "seq"
    write_plain(scene, data)
    out = tmp_path / "map"
    args = ["map", str(data), "-o", str(out), "--quiet", "--objects", "--crop-mode", "hard"]
    assert main([*args, "--mask-ids", "per-frame", "--mask-noise", "shuffled", "--segments-from-labels"]) == 0
    records = ObjectDatabase(out, create=False).records()
    names = {e["class_name"] for e in scene.labels()}
    # Every object is named by the segmenter's leading class, not by a palette it does not have.
    assert len(records) >= 10 and all(r.label in names and r.label_source == "segments" for r in records)
    queries = tmp_path / "queries.json"
    sofa = next(e for e in scene.labels() if e["class_name"] == "sofa")
    sofa_id = "#" + "".join(f"{v:02x}" for v in sofa["color"])
    queries.write_text(json.dumps([
        {"text": "a sofa", "expected": ["sofa"], "kind": "class"},
        {"text": "the sofa", "expected": [sofa_id], "kind": "id"},
    ]))  # fmt: skip
    report_path = tmp_path / "retrieval.json"
    common = ["eval-retrieval", str(queries), "--map", str(out), "--modes", "hard", "--out", str(report_path)]
    assert main([*common, "--description", "on", "--label-nouns", "on", "--reference", str(data)]) == 0
    variant = json.loads(report_path.read_text())["variants"][0]
    assert variant["unanswerable"] == [] and variant["label_nouns"]
    # the palette id of the reference sofa now names the map object matched to it
    assert variant["per_query"][1]["expected"] == variant["per_query"][0]["expected"]
    assert variant["all"]["top3"] == 1.0
    capsys.readouterr()
