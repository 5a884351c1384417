"""The bags shipped in ``bags/`` and how to regenerate them deterministically.

``synthetic_room.mcap``: the default synthetic scene (``generate_scene(SceneConfig())``), every keyframe,
JPEG images, PNG masks. Committed, with ``synthetic_room.labels.json``: the bag's labels (``bag_labels``) as a
labels file for the node's ``labels_file`` (the launch file's ``labels_file:=``).
``replica_office0.mcap``: Replica office_0 from the plain folder in ``../shared/data/replica_office0`` beside the
repository (research-only license: generated on demand, git-ignored, never committed).
"""

from __future__ import annotations

import os
from pathlib import Path

from monovoc_ros.bags.convert import ConvertReport, sequence_to_bag

BUNDLED_DIR = Path(__file__).resolve().parents[2] / "bags"
SYNTHETIC_BAG = "synthetic_room.mcap"
REPLICA_BAG = "replica_office0.mcap"
PER_FRAME_BAG = "synthetic_room_per_frame.mcap"
SYNTHETIC_LABELS = "synthetic_room.labels.json"
DEFAULT_REPLICA_SOURCE = BUNDLED_DIR.parents[1] / "shared" / "data" / "replica_office0"


def bundled_bag(name: str = SYNTHETIC_BAG) -> Path:
    """Path of a bundled bag (it may not exist yet: ``monovoc bag make-bundled``)."""
    return BUNDLED_DIR / name


def make_synthetic_bag(out_dir: str | os.PathLike = BUNDLED_DIR, *, progress: bool = False) -> ConvertReport:
    from monovoc_ros.synthetic import SceneConfig, generate_scene

    report = sequence_to_bag(generate_scene(SceneConfig()), Path(out_dir) / SYNTHETIC_BAG, progress=progress)
    write_labels_file(report.path, Path(out_dir) / SYNTHETIC_LABELS)
    return report


def write_labels_file(bag: str | os.PathLike, path: str | os.PathLike) -> Path:
    """The labels a bag carries in its metadata, as a labels.json file: the node reads labels from a file
    only (a launched node, unlike `monovoc demo`, is not told which bag feeds it)."""
    import json

    from monovoc_ros.bags import bag_labels

    path = Path(path)
    entries = [json.dumps(entry, sort_keys=True) for entry in bag_labels(bag)]  # one object a line
    path.write_text("[\n" + ",\n".join(entries) + "\n]\n")
    return path


def per_frame_scene():
    """The scene of the per-frame bag: a small synthetic room (30k Gaussians, 20 keyframes at 308x172)
    whose every mask is renumbered at random (core.segments.segment_noise, seed 0): segment ids hold per frame; each
    mask's segments carry the class names a perfect segmenter would give (the `segments` topic)."""
    from monovoc_ros.core.evaluation.datasets import CorruptedMasks, PaletteSegments
    from monovoc_ros.synthetic import SceneConfig, generate_scene

    scene = generate_scene(SceneConfig.at_resolution(308, 172, n_gaussians=30_000, n_keyframes=20))
    return CorruptedMasks(PaletteSegments(scene), shuffled=True, seed=0)


def make_per_frame_bag(out_dir: str | os.PathLike = BUNDLED_DIR, *, progress: bool = False) -> ConvertReport:
    """``synthetic_room_per_frame.mcap``: `per_frame_scene` as a bag, for `mask_ids: per_frame`. Committed."""
    return sequence_to_bag(per_frame_scene(), Path(out_dir) / PER_FRAME_BAG, progress=progress)


def make_replica_bag(
    source: str | os.PathLike = DEFAULT_REPLICA_SOURCE,
    out_dir: str | os.PathLike = BUNDLED_DIR,
    *,
    max_keyframes: int | None = None,
    progress: bool = False,
) -> ConvertReport:
    from monovoc_ros.core.evaluation.datasets import open_sequence

    sequence = open_sequence(source, layout="plain")
    return sequence_to_bag(sequence, Path(out_dir) / REPLICA_BAG, max_keyframes=max_keyframes, progress=progress)
