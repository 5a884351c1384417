"""Palette: packing, counting, the blend filter (kernel vs reference), persistence, real masks."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from monovoc_ros.core.evidence.palette import (
    UNOBSERVED_ID,
    VOID_ID,
    VOID_RGB,
    Palette,
    PaletteBuilder,
    color_counts,
    format_object_id,
    labels_from_entries,
    pack_rgb,
    parse_object_id,
    read_label_entries,
    read_labels,
    region_counts_reference,
    unpack_rgb,
)
from monovoc_ros.core.evidence.palette_kernels import region_counts

WALL, TABLE, CHAIR, CUP, CABLE = (0, 170, 255), (221, 255, 0), (255, 0, 153), (68, 170, 85), (255, 119, 0)
REAL = {int(pack_rgb(np.array(c, np.uint8))) for c in (WALL, TABLE, CHAIR, CUP, CABLE)}


def scene_mask(h: int = 300, w: int = 400) -> np.ndarray:
    """A clean label image: wall, a table, a round chair, a small cup, a void region."""
    mask = np.empty((h, w, 3), np.uint8)
    mask[:] = WALL
    mask[180:, :] = TABLE
    cv2.circle(mask, (120, 120), 50, CHAIR, -1)
    mask[200:208, 300:308] = CUP  # 8x8 px: small, but a region
    mask[:40, 330:] = VOID_RGB
    return mask


def test_pack_unpack():
    rgb = np.array([[1, 2, 3], [255, 255, 255], [0, 0, 0]], np.uint8)
    ids = pack_rgb(rgb)
    assert ids.dtype == np.uint32
    assert ids.tolist() == [0x010203, VOID_ID, 0]
    np.testing.assert_array_equal(unpack_rgb(ids), rgb)
    all_colors = np.random.default_rng(0).integers(0, 256, (50, 40, 3), dtype=np.uint8)
    np.testing.assert_array_equal(unpack_rgb(pack_rgb(all_colors)), all_colors)
    assert UNOBSERVED_ID > VOID_ID
    with pytest.raises(ValueError, match="UNOBSERVED_ID"):
        unpack_rgb(np.array([UNOBSERVED_ID], np.uint32))
    with pytest.raises(ValueError, match="uint8"):
        pack_rgb(np.zeros((2, 3), np.float32))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        pack_rgb(np.zeros((2, 4), np.uint8))


def test_counts_presence_and_labels_on_a_clean_mask():
    mask = scene_mask()
    builder = PaletteBuilder()
    builder.update(mask)
    second = mask.copy()
    second[200:208, 300:308] = TABLE  # the cup is not in the second view
    builder.update(second)
    palette = builder.build()
    ids, counts = color_counts(mask)
    expected = dict(zip(ids.tolist(), counts.tolist(), strict=True))
    assert set(palette.ids.tolist()) == REAL - {int(pack_rgb(np.array(CABLE, np.uint8)))}
    assert palette.void_pixels == 2 * expected[VOID_ID]
    assert palette.n_masks == 2 and len(palette.rejected_ids) == 0
    cup = palette.index_of(np.array([pack_rgb(np.array(CUP, np.uint8))]))[0]
    assert palette.pixel_counts[cup] == 64 and palette.mask_counts[cup] == 1
    table = palette.index_of(np.array([pack_rgb(np.array(TABLE, np.uint8))]))[0]
    assert palette.pixel_counts[table] == 2 * expected[int(palette.ids[table])] + 64
    assert palette.mask_counts.tolist() == [1 if i == cup else 2 for i in range(len(palette))]
    # Ids ascend and colors match ids, whatever the discovery order.
    assert np.all(np.diff(palette.ids.astype(np.int64)) > 0)
    np.testing.assert_array_equal(pack_rgb(palette.colors), palette.ids)

    labels = palette.labels(mask)
    assert labels.dtype == np.int32 and labels.shape == mask.shape[:2]
    assert (labels[:40, 330:] == -1).all()  # void
    assert (labels[200:208, 300:308] == cup).all()
    np.testing.assert_array_equal(palette.colors[labels[labels >= 0]], mask[labels >= 0])
    unknown = mask.copy()
    unknown[0, 0] = (1, 2, 3)
    assert palette.labels(unknown)[0, 0] == -1


def anti_aliased(mask: np.ndarray, scale: float) -> np.ndarray:
    h, w = mask.shape[:2]
    return cv2.resize(mask, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_LINEAR)


@pytest.mark.parametrize("scale", [0.75, 1.5, 2.3])
def test_blended_edge_colors_are_filtered_and_reported(scale):
    mask = anti_aliased(scene_mask(), scale)
    ids, counts = color_counts(mask)
    spurious = {i: c for i, c in zip(ids.tolist(), counts.tolist(), strict=True) if i not in REAL and i != VOID_ID}
    cup_pixels = int(counts[ids == pack_rgb(np.array(CUP, np.uint8))][0])
    assert len(spurious) > 20
    # A pixel-count threshold could not do it: some blends are larger than the smallest real object.
    views = [mask, np.ascontiguousarray(mask[:, ::-1]), np.ascontiguousarray(mask[::-1])]
    builder = PaletteBuilder()
    for view in views:
        builder.update(view)
    assert max(spurious.values()) * len(views) > cup_pixels

    palette = builder.build()
    assert set(palette.ids.tolist()) == REAL - {int(pack_rgb(np.array(CABLE, np.uint8)))}
    assert set(palette.rejected_ids.tolist()) == set(spurious)
    assert palette.rejected_pixels.sum() == len(views) * sum(spurious.values())
    assert palette.pixel_counts.sum() + palette.rejected_pixels.sum() + palette.void_pixels == mask.size // 3 * 3


def test_thin_real_structure_is_kept_but_a_thin_blend_is_not():
    mask = scene_mask()
    mask[60:260, 250] = CABLE  # a 1-px-wide real object across wall and table: no 3x3 interior anywhere
    palette = PaletteBuilder()
    palette.update(mask)
    assert int(pack_rgb(np.array(CABLE, np.uint8))) in palette.build().ids
    strict = palette.build(thin_min_pixels=1000)
    assert int(pack_rgb(np.array(CABLE, np.uint8))) in strict.rejected_ids
    assert strict.rejected_pixels.tolist() == [200]

    # The same line drawn in the color halfway between its neighbours is a blend, however long.
    halfway = (np.array(WALL, np.int64) + np.array(CHAIR, np.int64)) // 2
    blend = np.empty((300, 400, 3), np.uint8)
    blend[:, :250], blend[:, 250], blend[:, 251:] = WALL, halfway, CHAIR
    builder = PaletteBuilder()
    builder.update(blend)
    result = builder.build()
    assert int(pack_rgb(halfway.astype(np.uint8))) in result.rejected_ids
    assert int(pack_rgb(halfway.astype(np.uint8))) not in result.ids


def test_min_pixels():
    builder = PaletteBuilder()
    builder.update(scene_mask())
    palette = builder.build(min_pixels=65)
    assert int(pack_rgb(np.array(CUP, np.uint8))) in palette.rejected_ids
    assert len(palette) == 3


@pytest.mark.parametrize("kind", ["clean", "linear", "noise"])
def test_update_kernel_matches_reference(kind):
    rng = np.random.default_rng(1)
    if kind == "clean":
        mask = scene_mask()
    elif kind == "linear":
        mask = anti_aliased(scene_mask(), 1.7)
    else:  # few colors in random blocks plus their exact midpoints: blends by construction and by chance
        base = rng.integers(0, 256, (4, 3))
        colors = np.concatenate([base, (base[:, None] + base[None]).reshape(-1, 3) // 2]).astype(np.uint8)
        mask = colors[rng.integers(0, len(colors), (90, 70))]
        mask = np.repeat(np.repeat(mask, 3, axis=0), 2, axis=1)
    packed = pack_rgb(mask)
    ids = np.unique(packed)
    ref_ids, ref_interior, ref_blend = region_counts_reference(mask)
    interior, blend = region_counts(mask, packed, ids)
    np.testing.assert_array_equal(ref_ids, ids)
    np.testing.assert_array_equal(interior, ref_interior)
    np.testing.assert_array_equal(blend, ref_blend)
    if kind != "clean":
        assert blend.sum() > 0
    assert interior.sum() > 0


def test_builders_merge_and_round_trip(tmp_path):
    masks = [scene_mask(), anti_aliased(scene_mask(), 0.8), scene_mask()[::-1].copy()]
    whole = PaletteBuilder()
    for m in masks:
        whole.update(m)
    first, second = PaletteBuilder(), PaletteBuilder()
    first.update(masks[0])
    second.update(masks[1])
    second.update(masks[2])
    merged = first.merged(second)
    for key, value in whole.to_arrays().items():
        np.testing.assert_array_equal(merged.to_arrays()[key], value, err_msg=key)
    assert len(first.to_arrays()["palette_ids"]) < len(merged.to_arrays()["palette_ids"])  # inputs untouched

    np.savez(tmp_path / "palette.npz", **whole.to_arrays())
    with np.load(tmp_path / "palette.npz") as data:
        restored = PaletteBuilder.from_arrays(dict(data))
    a, b = whole.build(), restored.build()
    for name in ("ids", "colors", "pixel_counts", "mask_counts", "rejected_ids", "rejected_pixels"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert (a.void_pixels, a.n_masks) == (b.void_pixels, b.n_masks) == (a.void_pixels, 3)
    restored.update(masks[0])  # a restored builder keeps counting
    assert restored.build().n_masks == 4

    arrays = whole.to_arrays()
    del arrays["palette_interior"]
    with pytest.raises(ValueError, match="palette_interior"):
        PaletteBuilder.from_arrays(arrays)
    arrays = whole.to_arrays()
    arrays["palette_pixels"] = arrays["palette_pixels"][:-1]
    with pytest.raises(ValueError, match="palette_pixels"):
        PaletteBuilder.from_arrays(arrays)


def test_empty_builder_and_bad_input():
    palette = PaletteBuilder().build()
    assert len(palette) == 0 and palette.colors.shape == (0, 3)
    assert (palette.labels(scene_mask()) == -1).all()
    with pytest.raises(ValueError, match="mask"):
        PaletteBuilder().update(np.zeros((10, 10), np.uint8))
    with pytest.raises(ValueError, match="mask"):
        PaletteBuilder().update(np.zeros((10, 10, 3), np.float32))
    with pytest.raises(ValueError, match="void"):
        Palette(np.array([VOID_RGB], np.uint8), np.array([VOID_ID]), np.zeros(1), np.zeros(1))


def test_from_colors():
    palette = Palette.from_colors(np.array([CHAIR, WALL, VOID_RGB, CHAIR], np.uint8))
    assert palette.ids.tolist() == sorted([int(pack_rgb(np.array(c, np.uint8))) for c in (CHAIR, WALL)])
    np.testing.assert_array_equal(palette.index_of(np.array([palette.ids[1], VOID_ID, UNOBSERVED_ID])), [1, -1, -1])


def test_replica_palette_keeps_every_labeled_object(replica_office0):
    """Office_0's masks have no blends: every labeled color is kept (including a 1-2 px wall sliver);
    resampled with bilinear interpolation, the thousands of blends are all rejected."""
    labels = json.loads((replica_office0 / "labels.json").read_text())
    real = {int(pack_rgb(np.array(entry["color"], np.uint8))) for entry in labels}
    masks = [cv2.imread(str(p))[:, :, ::-1].copy() for p in sorted((replica_office0 / "masks").glob("*.png"))]
    clean, resampled = PaletteBuilder(), PaletteBuilder()
    for i, mask in enumerate(masks):
        clean.update(mask)
        if i % 3 == 0:
            resampled.update(cv2.resize(mask, (616, 344), interpolation=cv2.INTER_LINEAR))
    palette = clean.build()
    assert set(palette.ids.tolist()) == real
    assert len(palette.rejected_ids) == 0 and palette.n_masks == len(masks) == 81

    blended = resampled.build()
    assert len(blended.rejected_ids) > 1000
    assert set(blended.ids.tolist()) <= real
    assert len(blended) >= len(real) - 2  # only objects the resampling erased entirely may go


def test_object_ids_are_written_and_read_as_people_write_them():
    assert format_object_id(0xFF7700) == "#ff7700"
    for text in ("#ff7700", "0xff7700", "FF7700", " #ff7700 ", 16742144, "16742144"):
        assert parse_object_id(text) == 0xFF7700, text
    for bad in ("#ff77", "red", True, 0x1000000, -1):
        with pytest.raises(ValueError):
            parse_object_id(bad)


def test_labels_name_every_color_of_a_labels_file(tmp_path):
    entries = [{"color": [1, 2, 3], "class_name": " chair ", "instance_id": 4}, {"color": [255, 0, 0]}]
    assert labels_from_entries(entries) == {0x010203: "chair", 0xFF0000: ""}
    path = tmp_path / "labels.json"
    path.write_text(json.dumps(entries))
    assert read_label_entries(path) == entries and read_labels(path) == {0x010203: "chair", 0xFF0000: ""}
    for bad in ([1, 2], [1, 2, 256], [1.0, 2, 3], "abc"):
        with pytest.raises(ValueError, match="labels entry 0"):
            labels_from_entries([{"color": bad}])
    path.write_text("{}")
    with pytest.raises(ValueError, match="expected a JSON list"):
        read_labels(path)
