"""Per-frame mask ids: the one-pass label rendering against its float64 twin, the association rules,
exact object merges in the vote state, segment noise, instance matching and the mapper end to end."""

from __future__ import annotations

import numpy as np
import pytest

from monovoc_ros.core.evaluation.datasets import CorruptedMasks
from monovoc_ros.core.evaluation.evaluation import render_splat_labels
from monovoc_ros.core.evaluation.instance_eval import UNMATCHED_ID, match_instances, renamed, score_matched
from monovoc_ros.core.evidence.palette import UNOBSERVED_ID, VOID_ID, PaletteBuilder, pack_rgb, unpack_rgb
from monovoc_ros.core.evidence.votes import VoteState
from monovoc_ros.core.mapping import MapperConfig, SemanticMapper
from monovoc_ros.core.segments.association import (
    AssociationConfig,
    Associator,
    SegmentNames,
    compact_index_reference,
    display_color,
    overlap_counts,
    overlap_counts_reference,
    rendered_object_index,
)
from monovoc_ros.core.segments.label_render import render_label_weights
from monovoc_ros.core.segments.segment_noise import NoiseRates, parse_mask_noise, segment_noise, shuffle_ids
from tests.test_raster import SCENES, random_scene


@pytest.mark.parametrize("seed,kind", SCENES)
def test_label_render_matches_reference(seed, kind):
    gmap, k, pose, _ = random_scene(seed, kind=kind)
    labels = np.random.default_rng(seed).integers(-1, 5, len(gmap))
    got = render_label_weights(gmap, labels, k, pose)
    ref = render_label_weights(gmap, labels, k, pose, impl="reference")
    assert np.abs(got.weights - ref.weights).max() <= 1e-4
    assert (got.labels == ref.labels).mean() >= 0.999  # float32 against float64: near-ties only
    assert (ref.labels >= 0).any() and (ref.labels < 0).any()


def test_label_render_leads_as_render_splat_labels():
    gmap, k, pose, _ = random_scene(1)
    labels = np.random.default_rng(1).integers(-1, 7, len(gmap))
    ids = np.array([0x102030 + 17 * i for i in range(7)], np.uint32)
    lead = render_label_weights(gmap, labels, k, pose).labels
    mine = np.where(lead >= 0, ids[np.maximum(lead, 0)], VOID_ID)
    gaussian_ids = np.where(labels >= 0, ids[np.maximum(labels, 0)], UNOBSERVED_ID).astype(np.uint32)
    splat = render_splat_labels(gmap, gaussian_ids, k, pose)
    assert (mine == splat).mean() >= 0.995


@pytest.mark.parametrize("seed", range(3))
def test_compact_index_matches_reference(seed):
    from monovoc_ros.core.segments.label_render_kernels import compact_index

    rng = np.random.default_rng(seed)
    table = np.unique(rng.integers(0, 0xFFFFFE, 40)).astype(np.uint32)
    ids = rng.choice(np.concatenate([table, [UNOBSERVED_ID, 7, 0xFFFFFD]]).astype(np.uint32), 5000)
    out = np.empty(len(ids), np.int32)
    missing = compact_index(ids, table, np.uint32(UNOBSERVED_ID), out)
    np.testing.assert_array_equal(out, compact_index_reference(ids, table))
    assert missing == int(np.sum(out == -2)) and missing > 0
    # Every id issued: the table is the answer; one id not issued: the ids are collected instead.
    issued_only = ids[(out >= 0) | (out == -1)]
    compact, rendered = rendered_object_index(issued_only, table.tolist())
    np.testing.assert_array_equal(rendered, table)
    np.testing.assert_array_equal(compact, compact_index_reference(issued_only, table))
    # Issued ids no Gaussian holds (merged away) are left out of the table.
    compact, rendered = rendered_object_index(issued_only, [*table.tolist(), 0xFFFFFE])
    np.testing.assert_array_equal(rendered, table)
    np.testing.assert_array_equal(compact, compact_index_reference(issued_only, table))
    compact, rendered = rendered_object_index(ids, table.tolist())
    known = ids != UNOBSERVED_ID
    np.testing.assert_array_equal(rendered[compact[known]], ids[known])
    assert np.all(compact[~known] == -1)


def test_overlap_counts_match_reference():
    rng = np.random.default_rng(0)
    seg, ren = rng.integers(-1, 5, (30, 40)), rng.integers(-1, 7, (30, 40))
    assert np.array_equal(overlap_counts(seg, 5, ren, 7), overlap_counts_reference(seg, 5, ren, 7))


def blocks(h: int = 40, w: int = 60) -> np.ndarray:
    """Six 20x20 object blocks (2 rows x 3 columns), index 0..5."""
    return (np.arange(h)[:, None] // 20) * 3 + np.arange(w)[None, :] // 20


def test_display_colors_are_distinct_and_never_reserved():
    colors = [display_color(k) for k in range(2000)]
    assert len(set(colors)) >= 1990  # 24-bit rounding may repeat a few; new_object skips those
    a = Associator()
    issued = [a.new_object() for _ in range(500)]
    assert len(set(issued)) == 500 and all(0 <= c <= 0xFFFFFF for c in issued)
    assert not {VOID_ID, 0, 0x808080} & set(issued)


def test_first_keyframe_seeds_objects_then_segments_match_by_overlap():
    a = Associator()
    seg = blocks()
    first = a.associate(seg, 6, np.full(seg.shape, -1, np.int32), np.zeros(0, np.uint32))
    assert first.new == 6 and first.matched == 0 and len(set(first.segment_objects.tolist())) == 6
    # Next frame: the map renders those objects; the segmenter numbered the same segments differently.
    rendered_ids = first.segment_objects
    perm = np.array([3, 0, 5, 1, 4, 2])
    second = a.associate(perm[seg], 6, seg.astype(np.int32), rendered_ids)
    assert second.matched == 6 and second.new == 0
    assert np.array_equal(second.segment_objects[perm], rendered_ids)


def test_unseen_objects_are_never_matched_by_absence():
    a = Associator()
    seg = blocks()
    ids = a.associate(seg, 6, np.full(seg.shape, -1, np.int32), np.zeros(0, np.uint32)).segment_objects
    # The map renders only objects 0 and 1 (the rest occluded / out of view); the frame shows two
    # segments: one where object 0 renders, one in a region the map has not seen.
    rendered = np.where(seg <= 1, seg, -1).astype(np.int32)
    frame = np.full(seg.shape, -1)
    frame[seg == 0] = 0
    frame[seg == 5] = 1
    out = a.associate(frame, 2, rendered, ids)
    assert out.segment_objects[0] == ids[0]
    assert out.segment_objects[1] not in ids.tolist() and out.new == 1


def test_split_piece_joins_its_object_and_small_segments_add_nothing():
    a = Associator(AssociationConfig(new_object_fraction=0.05))
    seg = blocks()
    ids = a.associate(seg, 6, np.full(seg.shape, -1, np.int32), np.zeros(0, np.uint32)).segment_objects
    frame = seg.copy()
    frame[(seg == 2) & (np.arange(60)[None, :] >= 50)] = 6  # object 2 cut in two
    frame[0:3, 0:3] = 7  # a 9-pixel segment in a new region... inside object 0: a piece? too small to be one
    out = a.associate(frame, 8, seg.astype(np.int32), ids)
    assert out.segment_objects[6] == ids[2] and out.parts == 1
    assert out.segment_objects[7] == UNOBSERVED_ID and out.skipped == 1
    assert np.array_equal(out.segment_objects[:6], ids)


def test_objects_covered_together_are_merged_only_when_repeatedly():
    cfg = AssociationConfig(merge_min_keyframes=3)
    a = Associator(cfg)
    seg = blocks()
    ids = a.associate(seg, 6, np.full(seg.shape, -1, np.int32), np.zeros(0, np.uint32)).segment_objects
    together = np.where(seg == 1, 0, seg)  # one segment covers objects 0 and 1
    together = np.unique(together, return_inverse=True)[1].reshape(seg.shape)
    for _ in range(2):
        out = a.associate(together, 5, seg.astype(np.int32), ids)
        assert out.merges == []
    out = a.associate(together, 5, seg.astype(np.int32), ids)
    assert out.merges == [(int(ids[0]), int(ids[1]))]  # the older object stays
    assert a.resolve(int(ids[1])) == ids[0]
    # A pair seen apart more often than together is not merged.
    b = Associator(cfg)
    ids = b.associate(seg, 6, np.full(seg.shape, -1, np.int32), np.zeros(0, np.uint32)).segment_objects
    for _ in range(4):
        b.associate(seg, 6, seg.astype(np.int32), ids)
    for _ in range(3):
        assert b.associate(together, 5, seg.astype(np.int32), ids).merges == []


def test_only_confident_segments_cover_objects_together():
    """A detector's unsure mask bleeding over a partly hidden neighbour is no evidence that two objects are one:
    stage 5 counts a segment covering two objects only from merge_min_score on."""
    seg = blocks()
    together = np.unique(np.where(seg == 1, 0, seg), return_inverse=True)[1].reshape(seg.shape)
    for score, merged in ((0.3, False), (0.5, True)):
        a = Associator(AssociationConfig(merge_min_keyframes=3, merge_min_score=0.5))
        ids = a.associate(seg, 6, np.full(seg.shape, -1, np.int32), np.zeros(0, np.uint32)).segment_objects
        names = SegmentNames(("chair",) * 5, {}, (score,) + (0.9,) * 4)
        merges = [a.associate(together, 5, seg.astype(np.int32), ids, names=names).merges for _ in range(3)]
        assert merges[-1] == ([(int(ids[0]), int(ids[1]))] if merged else []), score
    # Unnamed segments (no scores) count as before.
    assert SegmentNames((None,) * 3, {}).confident(AssociationConfig()).tolist() == [True] * 3


def test_a_named_segment_never_takes_an_object_named_otherwise():
    """office_0 under fusion noise: a fused segment once voted the desk organizer's Gaussians into the tissue
    box; seen again, the organizer's segment took the tissue box's id and the tissue box was born anew."""
    a = Associator()
    seg = blocks()
    ids = a.associate(seg, 6, np.full(seg.shape, -1, np.int32), np.zeros(0, np.uint32)).segment_objects
    tissue, organizer = int(ids[0]), int(ids[1])
    # The map renders the tissue box over its quarter of block 0 and over 3/4 of block 1 (the organizer).
    rendered = np.full(seg.shape, -1, np.int32)
    rendered[0:10, 0:10] = 0
    rendered[seg == 1] = 0
    rendered[10:20, 30:40] = 1
    frame = np.full(seg.shape, -1)
    frame[0:10, 0:10] = 0  # the tissue box
    frame[seg == 1] = 1  # the organizer
    two = np.array([tissue, organizer], np.uint32)
    unnamed = Associator.from_json(a.to_json()).associate(frame, 2, rendered, two)
    assert unnamed.segment_objects[1] == tissue  # by overlap alone the organizer's segment is the tissue box
    names = SegmentNames(
        ("tissue-paper", "desk-organizer"), {tissue: {"tissue-paper": 3.0}, organizer: {"desk-organizer": 2.0}}
    )
    named = a.associate(frame, 2, rendered, two, names=names)
    assert named.segment_objects.tolist() == [tissue, organizer] and named.matched == 2
    assert set(named.split[1].tolist()) == {tissue, organizer}  # stage 6 still reads the rendering as it is
    # An object named by less than name_min_score is not named yet: overlap decides.
    young = SegmentNames(names.segments, {tissue: {"tissue-paper": 1.0}, organizer: {"desk-organizer": 1.0}})
    assert (
        Associator.from_json(a.to_json()).associate(frame, 2, rendered, two, names=young).segment_objects[1] == tissue
    )
    # A name among the object's minor ones (>= name_share of its names) does not conflict.
    mixed = SegmentNames(names.segments, {tissue: {"tissue-paper": 3.0, "desk-organizer": 1.0}, organizer: {}})
    assert mixed.conflicts(two, a.config).tolist() == [[False, False], [False, False]]
    assert names.conflicts(two, a.config).tolist() == [[False, True], [True, False]]


def test_a_named_fused_segment_is_still_split_and_the_runner_up_still_continues():
    seg = blocks()
    a = Associator()
    ids = a.associate(seg, 6, np.full(seg.shape, -1, np.int32), np.zeros(0, np.uint32)).segment_objects
    chair, table = int(ids[0]), int(ids[1])
    names = SegmentNames(("chair",) + (None,) * 4, {chair: {"chair": 3.0}, table: {"table": 3.0}})
    fused = np.unique(np.where(seg == 1, 0, seg), return_inverse=True)[1].reshape(seg.shape)  # "chair" over both
    out = a.associate(fused, 5, seg.astype(np.int32), ids, names=names)
    assert 0 in out.split and set(out.split[0].tolist()) == {chair, table}
    # Every object the map renders under a named segment is named otherwise: the runner-up rendering (where an
    # object of that name is being born) still decides, and conflicting runner-ups are skipped.
    b = Associator()
    ids = b.associate(seg, 6, np.full(seg.shape, -1, np.int32), np.zeros(0, np.uint32)).segment_objects
    tissue, organizer = int(ids[0]), int(ids[1])
    names = SegmentNames(("desk-organizer",), {tissue: {"tissue-paper": 3.0}, organizer: {"desk-organizer": 1.0}})
    frame = np.where(seg == 1, 0, -1)
    rendered = np.where(seg == 1, 0, -1).astype(np.int32)  # the organizer's block renders as the tissue box
    two = np.array([tissue, organizer], np.uint32)
    calls = []

    def runner_up():
        calls.append(1)
        return np.where(seg == 1, 1, -1).astype(np.int32), two

    out = b.associate(frame, 1, rendered, two, runner_up, names=names)
    assert calls and out.continued == 1 and out.segment_objects.tolist() == [organizer]
    conflicting = SegmentNames(("desk-organizer",), {tissue: {"tissue-paper": 3.0}, organizer: {"lamp": 3.0}})
    out = b.associate(frame, 1, rendered, two, runner_up, names=conflicting)
    assert out.new == 1 and out.segment_objects[0] not in (tissue, organizer)


def test_objects_named_differently_are_never_merged():
    seg = blocks()
    together = np.unique(np.where(seg == 1, 0, seg), return_inverse=True)[1].reshape(seg.shape)
    for first, second, merged in (("chair", "chair", True), ("chair", "table", False)):
        a = Associator(AssociationConfig(merge_min_keyframes=3))
        ids = a.associate(seg, 6, np.full(seg.shape, -1, np.int32), np.zeros(0, np.uint32)).segment_objects
        objects = {int(ids[0]): {first: 5.0}, int(ids[1]): {second: 5.0}}
        names = SegmentNames((None,) * 5, objects)  # an unnamed segment covers both
        merges = [a.associate(together, 5, seg.astype(np.int32), ids, names=names).merges for _ in range(3)]
        assert (merges[-1] == [(int(ids[0]), int(ids[1]))]) is merged, (first, second, merges)


def test_associator_round_trips_through_json():
    a = Associator()
    seg = blocks()
    ids = a.associate(seg, 6, np.full(seg.shape, -1, np.int32), np.zeros(0, np.uint32)).segment_objects
    a.associate(np.where(seg == 1, 0, seg), 6, seg.astype(np.int32), ids)
    b = Associator.from_json(a.to_json())
    assert b.issued == a.issued and b.together == a.together and b.apart == a.apart
    assert b.new_object() == a.new_object()


def test_vote_state_merge_objects_adds_votes_exactly():
    rng = np.random.default_rng(0)
    n, objs = 200, np.array([10, 20, 30], np.uint32)
    a = VoteState.zeros(n, slots=4)
    b = VoteState.zeros(n, slots=4)  # the same votes with object 20 named 10 from the start
    for stamp in range(5):
        rows = rng.choice(n, 120, replace=False)
        objects = objs[rng.integers(0, 3, (120, 2))]
        votes = rng.random((120, 2))
        other = rng.random(120) * 0.1
        a.add(rows, objects, votes, other, stamp)
        b.add(rows, np.where(objects == 20, 10, objects), votes, other, stamp)
    changed = a.merge_objects(10, 20)
    assert changed.size > 0 and not (a.objects == 20).any()
    assert np.array_equal(a.objects, b.objects)
    np.testing.assert_allclose(a.votes, b.votes, rtol=1e-12)
    np.testing.assert_allclose(a.other, b.other, rtol=1e-12)
    with pytest.raises(ValueError):
        a.merge_objects(10, 10)


def test_palette_builder_merge_ids_moves_counts():
    mask = np.zeros((8, 8, 3), np.uint8)
    mask[:, 4:] = (0, 0, 200)
    builder = PaletteBuilder()
    builder.update(mask)
    builder.merge_ids(0x0000C8, 0x000000)
    assert builder.ids.tolist() == [0x0000C8] and builder.counts["pixels"].tolist() == [64]


def test_shuffle_and_segment_noise():
    rng = np.random.default_rng(0)
    seg = blocks()
    mask = unpack_rgb(np.where(seg == 5, VOID_ID, 0x101010 * (seg + 1)).astype(np.uint32))
    shuffled = shuffle_ids(mask, rng)
    a, b = pack_rgb(mask), pack_rgb(shuffled)
    assert ((a == VOID_ID) == (b == VOID_ID)).all()
    pairs = set(zip(a.ravel().tolist(), b.ravel().tolist(), strict=True))
    assert len(pairs) == 6 and len({p for p, _ in pairs}) == 6 and len({q for _, q in pairs}) == 6
    assert not (set(np.unique(a).tolist()) - {VOID_ID}) & set(np.unique(b).tolist())
    merged, counts = segment_noise(mask, NoiseRates(merge=1.0), np.random.default_rng(1))
    assert counts["merged"] >= 1 and len(np.unique(pack_rgb(merged))) == 6 - counts["merged"]
    split, counts = segment_noise(mask, NoiseRates(split=1.0), np.random.default_rng(2))
    assert counts["split"] == 5 and len(np.unique(pack_rgb(split))) == 11
    dropped, counts = segment_noise(mask, NoiseRates(drop=1.0, small_fraction=0.2), np.random.default_rng(3))
    assert counts["dropped"] == 5 and (pack_rgb(dropped) == VOID_ID).all()
    assert parse_mask_noise("shuffled,merge=0.1,split=0.05") == (True, NoiseRates(merge=0.1, split=0.05))
    with pytest.raises(ValueError):
        parse_mask_noise("merge")


@pytest.mark.parametrize("cut", ["line", "voronoi"])
def test_segments_fall_into_two_to_pieces_parts_inside_themselves(cut):
    seg = (np.arange(80)[:, None] // 40) * 3 + np.arange(120)[None, :] // 40  # six 40x40 blocks
    mask = unpack_rgb((0x101010 * (seg + 1)).astype(np.uint32))
    out, counts = segment_noise(mask, NoiseRates(split=1.0, pieces=4, cut=cut), np.random.default_rng(4))
    packed = pack_rgb(out)
    assert counts["split"] == 6
    per_block = [np.unique(packed[seg == b]).size for b in range(6)]
    assert all(2 <= k <= 4 for k in per_block) and max(per_block) > 2, per_block
    # Parts never cross blocks: every new color lies inside one block.
    for color in np.unique(packed).tolist():
        assert np.unique(seg[packed == color]).size == 1


def test_boundary_jitter_and_granularity():
    seg = (np.arange(96)[:, None] // 48) * 2 + np.arange(128)[None, :] // 64
    mask = unpack_rgb((0x202020 * (seg + 1)).astype(np.uint32))
    out, _ = segment_noise(mask, NoiseRates(jitter=3), np.random.default_rng(5))
    a, b = pack_rgb(mask), pack_rgb(out)
    assert set(np.unique(b).tolist()) == set(np.unique(a).tolist())  # the same segments
    moved = a != b
    assert 0 < moved.mean() < 0.1  # boundaries wander, by a few pixels only
    near = np.zeros_like(moved)
    near[:, 61:67] = near[45:51, :] = True  # within 3 pixels of a boundary
    assert not (moved & ~near).any()
    kinds = [segment_noise(mask, NoiseRates(merge=0.2, split=0.2, granularity=0.4), np.random.default_rng(k))[1]
             for k in range(40)]  # fmt: skip
    coarse = [c for c in kinds if c["coarse"]]
    fine = [c for c in kinds if c["fine"]]
    assert coarse and fine and all(c["split"] == 0 for c in coarse) and all(c["merged"] == 0 for c in fine)
    assert parse_mask_noise("merge=0.1,split=0.1,pieces=4,cut=voronoi,jitter=2,granularity=0.2") == (
        False, NoiseRates(merge=0.1, split=0.1, pieces=4, cut="voronoi", jitter=2, granularity=0.2)
    )  # fmt: skip
    for bad in ("cut=sam", "pieces=1", "jitter=x", "granularity=0.7"):
        with pytest.raises(ValueError):
            parse_mask_noise(bad)


def test_instance_matching_counts_merges_and_splits():
    seg = blocks()
    ref = (0x010101 * (seg + 1)).astype(np.uint32)
    perm = (0x200000 + 7 * (seg[::-1, ::-1] + 1)).astype(np.uint32)[::-1, ::-1]  # same partition, new ids
    result, match = score_matched([perm], [ref])
    assert result["miou"] == 1.0 and match.merges == 0 and match.splits == 0 and match.objects == 6
    merged = np.where(ref == 0x020202, 0x010101, ref).astype(np.uint32)  # instances 1 and 2 as one object
    m = match_instances([merged], [ref])
    assert m.merges == 1 and m.splits == 0 and m.objects == 5 and m.reference_objects == 6
    split = ref.copy()
    split[(seg == 3) & (np.arange(60)[None, :] < 10)] = 0xABCDEF  # instance 4 as two objects
    m = match_instances([split], [ref])
    assert m.splits == 1 and m.merges == 0 and m.objects == 7
    assert (renamed(split, m.mapping) == UNMATCHED_ID).sum() == 200


def test_per_frame_config_rules():
    with pytest.raises(ValueError, match="per_frame"):
        MapperConfig(mask_ids="per_frame", semantic_mode="scd")
    with pytest.raises(ValueError, match="mask_ids"):
        MapperConfig(mask_ids="frame")
    with pytest.raises(ValueError, match="association_scale"):
        MapperConfig(mask_ids="per_frame", association_scale=5)
    with pytest.raises(ValueError, match="object_colors"):
        MapperConfig(mask_ids="per_frame", object_colors=(0x102030,))
    gmap, _, _, _ = random_scene(0)
    mapper = SemanticMapper(gmap, MapperConfig(mask_ids="per_frame", association_scale=1))
    assert mapper.associator.config.render_scale == 1


@pytest.fixture(scope="module")
def small_room():
    from monovoc_ros.synthetic import SceneConfig, generate_scene

    return generate_scene(SceneConfig(n_gaussians=12_000, n_keyframes=12, width=308, height=172, fx=154.0,
                                      fy=151.8, cx=153.9, cy=85.9))  # fmt: skip


def test_mapper_per_frame_on_shuffled_masks_matches_global_ids(small_room):
    seq = small_room
    shuffled = CorruptedMasks(seq, shuffled=True, seed=5)
    a = SemanticMapper(seq.load_gaussians(), MapperConfig())
    b = SemanticMapper(seq.load_gaussians(), MapperConfig(mask_ids="per_frame"))
    reports = []
    for i in range(len(seq)):
        a.integrate(seq.keyframe(i))
        reports.append(b.integrate(shuffled.keyframe(i)))
    assert reports[0].association.new > 5 and reports[0].association.matched == 0
    assert sum(r.association.matched for r in reports[1:]) > 5 * (len(seq) - 1)
    ra, rb = a.result(), b.result()
    both = ra.observed & rb.observed
    # The two labelings are the same partition up to renaming: each global object maps to one id.
    pairs, counts = np.unique(np.stack([ra.object_ids[both], rb.object_ids[both]]), axis=1, return_counts=True)
    best = {}
    for (ga, _), c in zip(pairs.T.tolist(), counts.tolist(), strict=True):
        best[ga] = max(best.get(ga, 0), c)
    assert sum(best.values()) >= 0.97 * both.sum()
    assert set(np.unique(rb.object_ids[rb.observed]).tolist()) <= set(b.associator.issued)
    frames = [(kf.intrinsics, kf.cam_to_world, kf.mask) for kf in (seq.keyframe(i) for i in range(0, len(seq), 3))]
    preds = [render_splat_labels(b.gaussians, rb.object_ids, k, p) for k, p, _ in frames]
    global_preds = [render_splat_labels(a.gaussians, ra.object_ids, k, p) for k, p, _ in frames]
    refs = [pack_rgb(m) for _, _, m in frames]
    matched, _ = score_matched(preds, refs)
    same, _ = score_matched(global_preds, refs)
    assert matched["miou"] >= same["miou"] - 0.03
    with pytest.raises(ValueError, match="per-frame"):
        a.merged(b)


def test_objects_named_by_unsure_segments_alone_are_no_objects(small_room):
    """min_object_score: an object whose names add up to less is a fragment (its Gaussians unlabelled); one
    confident detection keeps an object, and objects never named stay."""
    from dataclasses import replace

    from monovoc_ros.core.evaluation.datasets import PaletteSegments
    from monovoc_ros.core.segments.segment_labels import SegmentLabel

    named = PaletteSegments(small_room)
    unsure, unnamed = sorted(named.names)[:2]

    def keyframe(i):
        kf = named.keyframe(i)
        segments = [SegmentLabel(s.id, s.class_name, 0.02 if s.id == unsure else s.score) for s in kf.segments]
        return replace(kf, segments=tuple(s for s in segments if s.id != unnamed))

    results = {}
    for score in (0.0, 0.5):
        mapper = SemanticMapper(small_room.load_gaussians(), MapperConfig(min_object_score=score))
        for i in range(len(small_room)):
            mapper.integrate(keyframe(i))
        results[score] = mapper.result().object_ids
    before, after = results[0.0], results[0.5]
    assert (before == unsure).sum() > 100 and not (after == unsure).any()
    assert (after == unnamed).sum() == (before == unnamed).sum() > 100
    kept = (before != unsure) & (before != UNOBSERVED_ID)
    np.testing.assert_array_equal(after[kept], before[kept])
    with pytest.raises(ValueError, match="min_object_score"):
        MapperConfig(min_object_score=-1.0)
    with pytest.raises(ValueError, match="semantic_mode 'vote'"):
        MapperConfig(semantic_mode="scd", min_object_score=0.5)


def test_label_histogram_leads_merges_and_round_trips():
    from monovoc_ros.core.segments.segment_labels import LabelHistogram, SegmentLabel

    h = LabelHistogram()
    h.add_keyframe((SegmentLabel(1, "chair", 0.9), SegmentLabel(2, "table", 0.5), SegmentLabel(9, "x")), {1: 10, 2: 20})
    h.add(10, "sofa", 0.6)
    h.add(10, "sofa", 0.6)
    h.add(20, "table", 0.2)
    assert h.leading() == {10: "sofa", 20: "table"}
    h.merge_objects(20, 10)
    assert h.leading() == {20: "sofa"} and h.scores[20]["chair"] == pytest.approx(0.9)
    assert LabelHistogram.from_json(h.to_json()).scores == h.scores
    other = LabelHistogram()
    other.add(20, "chair", 2.0)
    assert h.merged(other).leading() == {20: "chair"} and h.leading() == {20: "sofa"}
    with pytest.raises(ValueError):
        SegmentLabel(VOID_ID, "wall")


def test_segment_labels_follow_shuffled_segments():
    from monovoc_ros.core.segments.segment_labels import palette_segments, relabel_segments

    seg = blocks()
    mask = unpack_rgb((0x101010 * (seg + 1)).astype(np.uint32))
    names = {0x101010 * (i + 1): f"class{i}" for i in range(6)}
    segments = palette_segments(mask, names)
    shuffled = shuffle_ids(mask, np.random.default_rng(0))
    moved = relabel_segments(segments, pack_rgb(mask), pack_rgb(shuffled))
    new_of = {
        int(pack_rgb(mask)[y, x]): int(pack_rgb(shuffled)[y, x])
        for y, x in ((0, 0), (0, 25), (0, 45), (25, 0), (25, 25), (25, 45))
    }
    assert {s.id: s.class_name for s in moved} == {new_of[k]: v for k, v in names.items()}


def test_mapper_gathers_segment_labels_per_object(small_room):
    from monovoc_ros.core.evaluation.datasets import PaletteSegments

    seq = CorruptedMasks(PaletteSegments(small_room), shuffled=True, seed=2)
    mapper = SemanticMapper(seq.load_gaussians(), MapperConfig(mask_ids="per_frame"))
    for i in range(len(seq)):
        mapper.integrate(seq.keyframe(i))
    labels = mapper.object_labels()
    names = {i: o.class_name for i, o in enumerate(small_room.objects)}
    ids = mapper.result().object_ids
    right = total = 0
    for oid in np.unique(ids[ids != UNOBSERVED_ID]).tolist():
        truth = small_room.gaussian_object[ids == oid]
        truth = truth[truth >= 0]
        if truth.size >= 50:
            total += 1
            right += labels.get(oid) == names[int(np.bincount(truth).argmax())]
    assert total >= 15 and right >= 0.9 * total


def test_a_fused_segment_is_split_along_the_rendered_labels():
    a = Associator()
    seg = blocks()
    ids = a.associate(seg, 6, np.full(seg.shape, -1, np.int32), np.zeros(0, np.uint32)).segment_objects
    fused = np.where(seg == 1, 0, seg)  # the segmenter fused touching objects 0 and 1
    fused = np.unique(fused, return_inverse=True)[1].reshape(seg.shape)
    report = a.associate(fused, 5, seg.astype(np.int32), ids)
    assert list(report.split) == [0] and set(report.split[0].tolist()) == {int(ids[0]), int(ids[1])}
    weights = np.ones(seg.shape, np.float32)
    weights[0:5, 20:25] = 0.3  # the map is unsure there: no evidence
    packed = pack_rgb(a.relabel_mask(fused, report, ids, seg.astype(np.int32), weights))
    expected = ids[seg].astype(np.uint32)
    expected[0:5, 20:25] = VOID_ID
    np.testing.assert_array_equal(packed, expected)  # each object keeps its own pixels
    # A sliver of a neighbour rendered across the border is no fusion: segment 0 stays whole.
    rendered = seg.copy()
    rendered[0:2, 18:20] = 1
    sliver = a.associate(seg, 6, rendered.astype(np.int32), ids)
    assert sliver.split == {}


def test_a_segment_inside_a_larger_object_continues_the_object_born_there():
    a = Associator(AssociationConfig(new_object_fraction=0.002))
    seg = blocks()
    ids = a.associate(seg, 6, np.full(seg.shape, -1, np.int32), np.zeros(0, np.uint32)).segment_objects
    frame = seg.copy()
    frame[2:6, 2:6] = 6  # a small object the map still renders as part of object 0
    none = np.full(seg.shape, -1, np.int32)
    born = a.associate(frame, 7, seg.astype(np.int32), ids, lambda: (none, np.zeros(0, np.uint32)))
    assert born.new == 1
    newborn = born.segment_objects[6]
    # Next keyframe: its Gaussians still lead with object 0, the newborn is their runner-up.
    runner = np.where(frame == 6, 0, -1).astype(np.int32)
    calls = []

    def runner_up():
        calls.append(1)
        return runner, np.array([newborn], np.uint32)

    again = a.associate(frame, 7, seg.astype(np.int32), ids, runner_up)
    assert again.segment_objects[6] == newborn and again.continued == 1 and again.new == 0
    assert len(calls) == 1
    # Without a segment that needs it, the runner-up rendering is never made.
    a.associate(seg, 6, seg.astype(np.int32), ids, runner_up)
    assert len(calls) == 1


def test_a_fused_segments_class_name_names_neither_object(small_room):
    from dataclasses import replace

    from monovoc_ros.core.segments.association import associate_keyframe
    from monovoc_ros.core.segments.segment_labels import SegmentLabel, palette_segments
    from monovoc_ros.core.segments.segment_noise import _adjacent_pairs

    mapper = SemanticMapper(small_room.load_gaussians(), MapperConfig(mask_ids="per_frame"))
    for i in range(6):
        mapper.integrate(small_room.keyframe(i))
    kf = small_room.keyframe(6)
    packed = pack_rgb(kf.mask)
    colors, labels = np.unique(packed, return_inverse=True)
    labels = labels.reshape(packed.shape)
    sizes = np.bincount(labels.ravel())
    pairs = [(a, b) for a, b in _adjacent_pairs(labels).tolist() if VOID_ID not in (colors[a], colors[b])]
    a, b = max(pairs, key=lambda p: min(sizes[p[0]], sizes[p[1]]))  # the two largest touching objects
    fused = np.where(packed == colors[b], colors[a], packed).astype(np.uint32)
    others = {int(c): f"name{k}" for k, c in enumerate(colors) if c not in (VOID_ID, colors[b])}
    others[int(colors[a])] = "fusedname"
    fused_kf = replace(kf, mask=unpack_rgb(fused), segments=palette_segments(unpack_rgb(fused), others))
    ids, _ = mapper._vote_labels()
    relabeled, report = associate_keyframe(mapper.associator, mapper.gaussians, ids, fused_kf,
                                           runner_up_ids=mapper.state.runner_up)  # fmt: skip
    assert len(report.split) == 1
    assert "fusedname" not in {s.class_name for s in relabeled.segments}
    assert all(isinstance(s, SegmentLabel) for s in relabeled.segments) and relabeled.segments
    out = pack_rgb(relabeled.mask)
    # The fused segment's pixels went to both objects, each mostly its own, as the map renders them.
    leading = []
    for color in (colors[a], colors[b]):
        got = out[(packed == color) & (out != VOID_ID)]
        values, counts = np.unique(got, return_counts=True)
        assert counts.max() >= 0.8 * got.size, (values, counts)
        leading.append(int(values[np.argmax(counts)]))
    assert leading[0] != leading[1]


def test_rebuilt_objects_take_the_ids_of_the_objects_they_replace():
    """core.segments.object_match and Associator.adopt_ids: a rebuilt labelling matched to the old one by its
    Gaussians, one to one; unmatched objects get ids the old associator never issued; everything renames."""
    from monovoc_ros.core.segments.object_match import match_objects
    from monovoc_ros.core.segments.segment_labels import LabelHistogram

    old_a, new_a = Associator(), Associator()
    o1, o2, o3 = (old_a.new_object() for _ in range(3))
    n1, n2, n3, n4 = (new_a.new_object() for _ in range(4))  # the rebuild issued the same colors otherwise
    u = UNOBSERVED_ID
    old = np.array([o1] * 10 + [o2] * 6 + [o3] * 4 + [u] * 3, np.uint32)
    # n2 is old o1 (its larger part), n1 old o2, n4 a piece of o1 too small to keep it, n3 where nothing was.
    new = np.array([n2] * 8 + [n4] * 2 + [n1] * 6 + [u] * 4 + [n3] * 3, np.uint32)
    matches = match_objects(old, new)
    assert matches == {n2: o1, n1: o2}
    mapping = new_a.adopt_ids(old_a, matches)
    assert mapping[n2] == o1 and mapping[n1] == o2
    assert mapping[n3] not in old_a.issued and mapping[n4] not in old_a.issued  # fresh: o3's id is dead
    assert len(set(mapping.values())) == 4 and set(old_a.issued) <= set(new_a.issued)
    assert new_a.new_object() not in set(old_a.issued) | set(mapping.values())
    back = Associator.from_json(new_a.to_json())
    assert back.issued == new_a.issued
    # The votes, palette counts and segment labels follow the ids.
    state = VoteState.zeros(3, 2)
    state.add(np.arange(3), np.array([[n1, n2], [n2, 0], [n3, n4]], np.uint32), np.array([[2.0, 1.0], [1.0, 0.0],
              [3.0, 1.0]]), np.zeros(3), 1)  # fmt: skip
    state.rename_objects(mapping)
    np.testing.assert_array_equal(state.objects[:, 0], [o2, o1, mapping[n3]])
    with pytest.raises(ValueError, match="stays"):  # row 0 would hold one object in two slots
        state.rename_objects({o2: mapping[n3]})
    builder = PaletteBuilder()
    builder.update(unpack_rgb(np.array([n1] * 5 + [n2] * 7, np.uint32)).reshape(3, 4, 3))
    builder.rename_ids(mapping)
    assert dict(zip(builder.ids.tolist(), builder.counts["pixels"].tolist(), strict=True)) == {o1: 7, o2: 5}
    labels = LabelHistogram()
    labels.add(n1, "chair", 1.0)
    labels.rename_objects(mapping)
    assert labels.leading() == {o2: "chair"}
