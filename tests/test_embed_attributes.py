"""Color naming, size words, descriptions and embedding combination."""

import numpy as np
import pytest

from monovoc_ros.core.evidence.color import srgb_to_lab
from monovoc_ros.embed.attributes import (
    ALWAYS_BLACK_BELOW_L,
    BASIC_COLORS,
    DARK_HUE_MIN_CHROMA,
    clean_class_name,
    color_names,
    color_names_reference,
    combine,
    describe,
    dominant_color_name,
    masked_pixels,
    size_word,
)

# Reference colors (CSS/X11 names) and the basic term a person would use for each.
KNOWN_COLORS = {
    "red": [(255, 0, 0), (139, 0, 0), (220, 20, 60), (178, 34, 34)],
    "orange": [(255, 165, 0), (255, 140, 0), (255, 127, 80)],
    "yellow": [(255, 255, 0), (255, 215, 0), (240, 230, 140)],
    "green": [(0, 128, 0), (0, 255, 0), (34, 139, 34), (144, 238, 144), (128, 128, 0)],
    "blue": [(0, 0, 255), (0, 0, 128), (65, 105, 225), (135, 206, 235), (0, 128, 128)],
    "purple": [(128, 0, 128), (75, 0, 130), (186, 85, 211), (238, 130, 238)],
    "pink": [(255, 192, 203), (255, 105, 180), (255, 20, 147)],
    "brown": [(139, 69, 19), (160, 82, 45), (101, 67, 33), (210, 180, 140)],
    "black": [(0, 0, 0), (20, 20, 20), (10, 10, 30)],
    "white": [(255, 255, 255), (245, 245, 245), (250, 240, 230)],
    "gray": [(128, 128, 128), (169, 169, 169), (100, 100, 100), (112, 128, 144)],
}


@pytest.mark.parametrize("name", sorted(KNOWN_COLORS))
def test_known_colors_get_their_basic_name(name):
    pixels = np.array(KNOWN_COLORS[name], dtype=np.uint8)
    assert color_names(pixels) == [name] * len(pixels)


def test_color_names_equal_their_plain_twin():
    """The numba CIEDE2000 search, for the hued pixels only and once per distinct color, names every pixel as
    colour-science's full distance matrix does."""
    rng = np.random.default_rng(5)
    pixels = np.concatenate([
        rng.integers(0, 256, (20000, 3)),
        rng.integers(0, 40, (2000, 3)),  # dark: the achromatic and always-black rules
        rng.integers(100, 140, (2000, 3)),  # grayish: achromatic and near it
        np.array([c for cs in KNOWN_COLORS.values() for c in cs]),
    ]).astype(np.uint8)  # fmt: skip
    pixels = np.concatenate([pixels, pixels[rng.integers(0, len(pixels), 5000)]])  # colors repeated, in any order
    assert color_names(pixels) == color_names_reference(pixels)
    assert color_names(np.zeros((0, 3), np.uint8)) == color_names_reference(np.zeros((0, 3), np.uint8)) == []


def test_dominant_color_votes_over_pixels_rather_than_averaging():
    # 60% red and 40% green: the mean (a muddy olive) is neither; the vote says red.
    pixels = np.array([(220, 20, 30)] * 60 + [(20, 160, 40)] * 40, dtype=np.uint8)
    assert dominant_color_name(pixels) == "red"
    assert dominant_color_name(pixels[::-1]) == "red"
    assert dominant_color_name(np.full((50_000, 3), (30, 60, 200), dtype=np.uint8)) == "blue"


def test_dominant_color_of_masked_object_in_image():
    rgb = np.full((10, 10, 3), 240, dtype=np.uint8)  # white background
    rgb[2:6, 2:6] = (255, 220, 0)
    mask = np.zeros((5, 5), dtype=bool)
    mask[1:3, 1:3] = True  # same object at half resolution
    assert masked_pixels(rgb, mask).shape == (16, 3)
    assert dominant_color_name(masked_pixels(rgb, mask)) == "yellow"


@pytest.mark.parametrize(
    "pixels", [np.zeros((0, 3), np.uint8), np.zeros((4, 3), np.float32), np.zeros((4, 4), np.uint8)]
)
def test_color_bad_input(pixels):
    with pytest.raises(ValueError):
        dominant_color_name(pixels)


def test_descriptions():
    assert describe("chair", color="red", extent=(0.5, 0.45, 0.9)) == "a red chair, 0.9 m tall"
    assert (
        describe("box", color="brown", extent=(0.2, 0.15, 0.1), height_above_floor=0.8)
        == "a small brown box, 0.2 m wide, 0.8 m above the floor"
    )
    assert describe("orange", color="orange", extent=(0.08, 0.07, 0.07)) == "a tiny orange orange, 0.08 m wide"
    assert describe("sofa", extent=(2.1, 0.9, 0.8), height_above_floor=0.05) == "a large sofa, 2.1 m wide"
    assert describe("apple") == "an apple"
    # Camera-style frame (y up axis) and a wall-mounted object.
    assert describe("clock", color="white", extent=(0.3, 0.3, 0.05), height_above_floor=1.85, up_axis=1) == (
        "a small white clock, 0.3 m tall, 1.9 m above the floor"
    )


def test_size_words_and_nouns():
    assert [size_word((s, s / 2, s / 3)) for s in (0.05, 0.2, 0.9, 2.0)] == ["tiny", "small", "", "large"]
    assert clean_class_name("kite (bird of prey)") == "kite"
    assert clean_class_name("cardboard box / carton") == "cardboard box"
    assert clean_class_name("red wolf or maned wolf") == "red wolf"
    assert clean_class_name("folding chair") == "folding chair"


@pytest.mark.parametrize(
    "kwargs",
    [{"color": "teal"}, {"extent": (1.0, 2.0)}, {"extent": (1.0, -2.0, 1.0)}, {"extent": (1, 1, 1), "up_axis": 3}],
)
def test_describe_bad_input(kwargs):
    with pytest.raises(ValueError):
        describe("chair", **kwargs)
    with pytest.raises(ValueError):
        describe("  ")


def test_combine_is_unit_and_weighted():
    rng = np.random.default_rng(1)
    image, text = rng.normal(size=(5, 16)) * 3.0, rng.normal(size=(5, 16)) * 0.1
    mixed = combine(image, text, 0.3)
    assert mixed.dtype == np.float32 and mixed.shape == (5, 16)
    np.testing.assert_allclose(np.linalg.norm(mixed, axis=1), 1.0, atol=1e-6)
    # Inputs are renormalised first, so the weight alone sets each part's share.
    unit = lambda x: x / np.linalg.norm(x, axis=-1, keepdims=True)  # noqa: E731
    np.testing.assert_allclose(mixed, unit(0.7 * unit(image) + 0.3 * unit(text)), atol=1e-6)
    np.testing.assert_allclose(combine(image, text, 0.0), unit(image), atol=1e-6)
    np.testing.assert_allclose(combine(image[0], text[0], 1.0), unit(text[0]), atol=1e-6)
    with pytest.raises(ValueError):
        combine(image, text[:, :8])
    with pytest.raises(ValueError):
        combine(image, text, 1.5)


def test_basic_color_table_is_complete():
    assert set(BASIC_COLORS) == set(KNOWN_COLORS)


def test_very_dark_pixels_keep_a_clear_hue():
    # Pixels of office_0's (dimly exposed) blue recycling bin and black trash bin: both below L* 12, the
    # first with chroma ~20, the second ~4; only the second is black.
    navy_bin, black_bin = (19, 22, 48), (22, 17, 23)
    lab = srgb_to_lab(np.array([navy_bin, black_bin]))
    assert lab[:, 0].max() < ALWAYS_BLACK_BELOW_L
    assert np.hypot(lab[0, 1], lab[0, 2]) > DARK_HUE_MIN_CHROMA > np.hypot(lab[1, 1], lab[1, 2])
    assert color_names(np.array([navy_bin, black_bin], np.uint8)) == ["blue", "black"]
    assert color_names(np.array([(3, 3, 3), (10, 4, 6)], np.uint8)) == ["black", "black"]  # noise in near-black
