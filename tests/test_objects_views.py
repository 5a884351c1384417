"""Object views: top-k by prevalence over a keyframe stream, bounded memory, versions, exact crops."""

import numpy as np
import pytest

from monovoc_ros.core.evidence.palette import pack_rgb
from monovoc_ros.embed.crops import crop_object, resize_mask
from monovoc_ros.objects.views import ObjectViews, ViewConfig
from tests.object_room import make_keyframe

RED, GREEN, BLUE, WHITE = (200, 30, 30), (30, 200, 30), (30, 30, 200), (255, 255, 255)
RED_ID, GREEN_ID, BLUE_ID = (int(pack_rgb(np.array(c, np.uint8))) for c in (RED, GREEN, BLUE))


def square_mask(h: int, w: int, squares: dict[tuple, tuple[int, int, int]]) -> np.ndarray:
    """White mask with one filled square (y, x, size) per color."""
    mask = np.full((h, w, 3), 255, np.uint8)
    for color, (y, x, size) in squares.items():
        mask[y : y + size, x : x + size] = color
    return mask


def random_rgb(h: int, w: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


def test_keeps_the_top_k_views_by_prevalence_and_bumps_versions_only_on_change():
    views = ObjectViews(ViewConfig(views_per_object=3, min_pixels=4))
    sizes = [10, 17, 7, 20, 14, 5, 16]  # red square side per keyframe: prevalence = side^2
    versions = []
    for i, side in enumerate(sizes):
        mask = square_mask(40, 60, {RED: (5, 5, side), GREEN: (25, 40, 6)})
        changed = views.observe(make_keyframe(i, mask, random_rgb(40, 60, i)), [RED_ID, GREEN_ID])
        versions.append(views.version(RED_ID))
        assert (RED_ID in changed) == (versions[-1] != (versions[-2] if i else 0))
    kept = views.views(RED_ID)
    assert [v.prevalence for v in kept] == [400, 289, 256]  # sides 20, 17, 16, best first
    assert [v.keyframe_index for v in kept] == [3, 1, 6]
    # 10 (v1), 17 (v2), 7 (v3: a slot was free), 20 (v4: replaces 7), 14 (v5: replaces 10), 5 (no change),
    # 16 (v6: replaces 14)
    assert versions == [1, 2, 3, 4, 5, 5, 6]
    assert views.observations(RED_ID) == len(sizes)
    # Green has the same prevalence every time: the first three views stay, later equal ones do not enter.
    assert [v.keyframe_index for v in views.views(GREEN_ID)] == [0, 1, 2]
    assert views.version(GREEN_ID) == 3


def test_memory_is_bounded_by_objects_times_k():
    config = ViewConfig(views_per_object=2, max_side=64)
    views = ObjectViews(config)
    for i in range(40):
        side = 10 + (i * 7) % 30
        mask = square_mask(120, 160, {RED: (2, 2, side), GREEN: (60, 80, 50), BLUE: (80, 5, 30)})
        views.observe(make_keyframe(i, mask, random_rgb(240, 320, i)))
    held = views.all_views()
    assert len(held) == 3 * 2
    assert all(max(v.rgb.shape[:2]) <= config.max_side for v in held)
    assert views.nbytes() <= 3 * 2 * (64 * 64 * 4)
    assert views.keyframes == 40


def test_stored_views_recrop_exactly_like_the_full_keyframe():
    # RGB at twice the mask's resolution plus an odd-shaped object touching the image border.
    h, w = 48, 64
    mask = square_mask(h, w, {GREEN: (20, 30, 12), BLUE: (30, 2, 9)})
    mask[0:6, 50:64] = RED  # at the top-right border: context gets clipped by the image
    mask[10:14, 58:64] = RED
    rgb = random_rgb(2 * h, 2 * w, 7)
    views = ObjectViews(ViewConfig(context=0.15, min_pixels=4))
    views.observe(make_keyframe(0, mask, rgb))
    for oid, color in ((RED_ID, RED), (GREEN_ID, GREEN), (BLUE_ID, BLUE)):
        (view,) = views.views(oid)
        full_mask = resize_mask(np.all(mask == color, axis=2), 2 * h, 2 * w)
        assert view.prevalence == int(np.all(mask == color, axis=2).sum())  # counted in mask pixels
        for mode in ("soft", "hard"):
            for context in (0.0, 0.1, 0.15):
                expected = crop_object(rgb, full_mask, mode, context=context)
                got = crop_object(view.rgb, view.mask, mode, context=context)
                np.testing.assert_array_equal(got, expected, err_msg=f"{oid:06x} {mode} {context}")
        np.testing.assert_array_equal(view.pixels(), rgb[full_mask])


def test_palette_filters_colors_and_void_is_never_an_object():
    mask = square_mask(30, 30, {RED: (0, 0, 10), GREEN: (15, 15, 10)})
    views = ObjectViews(ViewConfig(min_pixels=4))
    assert views.observe(make_keyframe(0, mask, random_rgb(30, 30, 0)), [RED_ID]) == [RED_ID]
    assert views.object_ids() == [RED_ID]
    views.observe(make_keyframe(1, mask, random_rgb(30, 30, 1)))  # None: every non-void color
    assert views.object_ids() == [GREEN_ID, RED_ID]
    assert 0xFFFFFF not in views.versions()


def test_keyframes_without_rgb_count_observations_only_and_tiny_objects_are_skipped():
    views = ObjectViews(ViewConfig(min_pixels=20))
    mask = square_mask(30, 30, {RED: (0, 0, 10), GREEN: (20, 20, 4)})  # green: 16 px < 20
    assert views.observe(make_keyframe(0, mask, None)) == []
    assert views.observations(RED_ID) == 1 and views.views(RED_ID) == []
    assert views.observe(make_keyframe(1, mask, random_rgb(30, 30, 1))) == [RED_ID]
    assert views.observations(GREEN_ID) == 0


def test_the_same_stamp_twice_adds_no_second_view():
    views = ObjectViews(ViewConfig(min_pixels=4))
    mask = square_mask(20, 20, {RED: (0, 0, 8)})
    keyframe = make_keyframe(0, mask, random_rgb(20, 20, 0))
    views.observe(keyframe)
    assert views.observe(keyframe) == []
    assert len(views.views(RED_ID)) == 1


def test_large_views_are_downscaled_with_their_mask():
    views = ObjectViews(ViewConfig(max_side=32, context=0.0, min_pixels=4))
    mask = square_mask(100, 100, {RED: (10, 10, 80)})
    views.observe(make_keyframe(0, mask, random_rgb(100, 100, 0)))
    (view,) = views.views(RED_ID)
    assert view.rgb.shape == (32, 32, 3) and view.mask.shape == (32, 32) and view.mask.all()


def test_restore_and_clear():
    views = ObjectViews(ViewConfig(views_per_object=2, min_pixels=4))
    for i in range(3):
        views.observe(make_keyframe(i, square_mask(20, 20, {RED: (0, 0, 5 + i)}), random_rgb(20, 20, i)))
    saved = views.all_views()
    version = views.version(RED_ID)
    other = ObjectViews(ViewConfig(views_per_object=2))
    other.restore(saved, {RED_ID: 3})
    assert [v.prevalence for v in other.views(RED_ID)] == [49, 36] and other.observations(RED_ID) == 3
    views.clear()
    assert views.object_ids() == [] and views.version(RED_ID) > version


@pytest.mark.parametrize("bad", [{"views_per_object": 0}, {"context": -0.1}, {"min_pixels": 0}, {"max_side": 4}])
def test_bad_view_config(bad):
    with pytest.raises(ValueError):
        ViewConfig(**bad)


@pytest.mark.parametrize("seed", range(3))
def test_view_kernels_match_their_plain_twins(seed):
    from monovoc_ros.core.evidence.palette import pack_rgb
    from monovoc_ros.objects import views_kernels as vk
    from monovoc_ros.objects.views import boxes_reference, label_image_reference

    rng = np.random.default_rng(seed)
    colors = rng.integers(0, 256, (6, 3), dtype=np.uint8)
    mask = colors[rng.integers(0, 6, (37, 53))]
    mask[rng.random((37, 53)) < 0.2] = 255  # void and colors outside the palette
    ids = np.unique(pack_rgb(colors[:4])).astype(np.uint32)
    labels = np.empty(mask.shape[:2], np.int32)
    vk.label_image(mask, ids, labels)
    np.testing.assert_array_equal(labels, label_image_reference(mask, ids))
    counts, boxes = vk.label_boxes(labels, ids.size + 1)  # one label without pixels
    wanted = np.arange(labels.max() + 1)
    ref_boxes, ref_visible = boxes_reference(labels, wanted)
    np.testing.assert_array_equal(counts[wanted] > 0, ref_visible)
    np.testing.assert_array_equal(boxes[wanted][ref_visible], ref_boxes[ref_visible])
    np.testing.assert_array_equal(counts[: ids.size], np.bincount(labels[labels >= 0], minlength=ids.size))
    assert counts[-1] == 0
