"""Object crops: bounding box with context, hard/soft masking, mask resolution, bad input."""

import numpy as np
import pytest

from monovoc_ros.embed.crops import GREY, crop_object, mask_bbox, resize_mask


def _scene():
    rgb = np.zeros((20, 30, 3), dtype=np.uint8)
    rgb[..., 0] = np.arange(30, dtype=np.uint8)[None, :] * 8  # red ramp along x
    rgb[..., 1] = np.arange(20, dtype=np.uint8)[:, None] * 12  # green ramp along y
    rgb[..., 2] = 200
    mask = np.zeros((20, 30), dtype=bool)
    mask[5:15, 10:20] = True  # 10 x 10 object
    mask[5, 10] = False  # a notch, so "outside the mask" also happens inside the box
    return rgb, mask


def test_hard_crop_is_exact_box_with_grey_outside():
    rgb, mask = _scene()
    crop = crop_object(rgb, mask, "hard", context=0.0)
    assert crop.shape == (10, 10, 3) and crop.dtype == np.uint8
    np.testing.assert_array_equal(crop[1:, 1:], rgb[6:15, 11:20])
    np.testing.assert_array_equal(crop[0, 0], [GREY, GREY, GREY])
    np.testing.assert_array_equal(crop[0, 1], rgb[5, 11])


def test_context_grows_box_by_fraction_of_its_size():
    rgb, mask = _scene()
    crop = crop_object(rgb, mask, "hard", context=0.2)  # 2 px on each side of the 10 px box
    assert crop.shape == (14, 14, 3)
    np.testing.assert_array_equal(crop[2:12, 3:12], rgb[5:15, 11:20])
    assert np.all(crop[:2] == GREY) and np.all(crop[:, :2] == GREY)


def test_context_is_clipped_at_the_image_border():
    rgb, _ = _scene()
    mask = np.zeros((20, 30), dtype=bool)
    mask[0:4, 26:30] = True
    crop = crop_object(rgb, mask, "soft", context=0.5)
    assert crop.shape == (6, 6, 3)  # grows 2 px down and left only


def test_soft_crop_dims_outside_pixels_toward_grey():
    rgb, mask = _scene()
    crop = crop_object(rgb, mask, "soft", context=0.2, dim=0.25)
    box = rgb[3:17, 8:22].astype(np.float64)
    expected = np.rint(box * 0.75 + GREY * 0.25).astype(np.uint8)
    inside = mask[3:17, 8:22]
    expected[inside] = rgb[3:17, 8:22][inside]
    np.testing.assert_array_equal(crop, expected)
    # The object's own pixels are untouched, the context is not grey.
    np.testing.assert_array_equal(crop[2:12, 3:12], rgb[5:15, 11:20])
    assert not np.all(crop[0] == GREY)


def test_soft_dim_extremes_match_plain_and_hard_crops():
    rgb, mask = _scene()
    plain = crop_object(rgb, mask, "soft", context=0.2, dim=0.0)
    np.testing.assert_array_equal(plain, rgb[3:17, 8:22])
    np.testing.assert_array_equal(
        crop_object(rgb, mask, "soft", context=0.2, dim=1.0), crop_object(rgb, mask, "hard", context=0.2)
    )


def test_mask_at_other_resolution_is_resized_nearest():
    rgb, mask = _scene()
    half = mask[::2, ::2]  # (10, 15): a mask rendered at half resolution
    up = resize_mask(half, 20, 30)
    assert up.dtype == bool and up.shape == (20, 30)
    np.testing.assert_array_equal(up, np.repeat(np.repeat(half, 2, axis=0), 2, axis=1))
    crop = crop_object(rgb, half, "hard", context=0.0)
    y0, x0, y1, x1 = mask_bbox(up)
    assert crop.shape == (y1 - y0, x1 - x0, 3)
    np.testing.assert_array_equal(crop[up[y0:y1, x0:x1]], rgb[y0:y1, x0:x1][up[y0:y1, x0:x1]])


@pytest.mark.parametrize(
    ("rgb", "mask", "kwargs", "message"),
    [
        (np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4), bool), {}, "empty"),
        (np.zeros((4, 4), np.uint8), np.ones((4, 4), bool), {}, "uint8"),
        (np.zeros((4, 4, 3), np.float32), np.ones((4, 4), bool), {}, "uint8"),
        (np.zeros((4, 4, 3), np.uint8), np.ones((4, 4, 1), bool), {}, "2-D"),
        (np.zeros((4, 4, 3), np.uint8), np.ones((4, 4), bool), {"mode": "blur"}, "mode"),
        (np.zeros((4, 4, 3), np.uint8), np.ones((4, 4), bool), {"dim": 1.5}, "dim"),
        (np.zeros((4, 4, 3), np.uint8), np.ones((4, 4), bool), {"context": -0.1}, "context"),
    ],
)
def test_bad_input_raises_clear_error(rgb, mask, kwargs, message):
    with pytest.raises(ValueError, match=message):
        crop_object(rgb, mask, **kwargs)
