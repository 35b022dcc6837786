"""Crop / paste-back alignment, relit = albedo * shading, backgrounds, preview."""

from __future__ import annotations

import tracemalloc

import cv2
import numpy as np
import pytest

from relightcli.compose import (
    snap_mask,
    CropBox,
    composite,
    sharpened,
    composite_crop,
    crop_square,
    display_exposure,
    parse_colour,
    paste_back,
    person_crop_box,
    OUTLINE_NET_SHARE,
    anchor_albedo,
    preview_sheet,
    shading_the_photo_shows,
    ratio_albedo,
    relight,
    replace_in_box,
)
from relightcli.errors import InputError
from relightcli.io.images import BAND_ROWS, LUMINANCE


def ramp(height, width):
    """Value = the pixel-centre x coordinate in full-frame pixels."""
    x = np.arange(width, dtype=np.float32) + 0.5
    return np.broadcast_to(x, (height, width)).copy()


def test_crop_box_is_square_and_holds_the_person_with_margin():
    mask = np.zeros((300, 200), np.float32)
    mask[50:250, 80:120] = 1.0  # 200 tall, 40 wide
    box = person_crop_box(mask, 128, margin=0.1)
    assert box.size == 240
    assert box.y0 == 30 and box.y0 + box.size == 270  # centred vertically
    assert box.x0 + box.size / 2 == pytest.approx(100, abs=0.5)


def test_crop_box_of_empty_mask_is_input_error():
    with pytest.raises(InputError, match="empty"):
        person_crop_box(np.zeros((10, 10), np.float32), 64, path="p.png")


def test_crop_at_same_size_is_exact():
    image = np.random.default_rng(0).random((50, 60, 3)).astype(np.float32)
    box = CropBox(5, 3, 40, 40)
    np.testing.assert_array_equal(crop_square(image, box), image[3:43, 5:45])


def test_crop_downscale_keeps_pixel_centres():
    # Shrinking by 2: crop pixel j covers full pixels x0 + 2j, x0 + 2j + 1; the ramp's average is
    # the centre of that footprint: x0 + (j + 0.5) * 2.
    image = ramp(80, 80)
    box = CropBox(10, 10, 64, 32)
    crop = crop_square(image, box)
    expected = 10 + (np.arange(32) + 0.5) * 2
    np.testing.assert_allclose(crop[5], expected, atol=1e-4)


def test_paste_back_inverts_crop_on_smooth_content():
    image = ramp(100, 90)[..., None].repeat(3, axis=2)
    box = CropBox(7, 11, 60, 30)
    back = paste_back(crop_square(image, box), box, 100, 90)
    inner = (slice(11 + 2, 71 - 2), slice(7 + 2, 67 - 2))  # away from the box edge
    np.testing.assert_allclose(back[inner], image[inner], atol=1e-3)
    assert back[0:11].max() == 0 and back[:, 0:7].max() == 0  # nothing outside the box


def test_box_reaching_outside_the_photo_pads_with_zero():
    image = np.ones((20, 20), np.float32)
    box = CropBox(-10, -10, 20, 20)
    crop = crop_square(image, box)
    assert crop[:10, :10].max() == 0 and crop[10:, 10:].min() == 1
    back = paste_back(crop, box, 20, 20)
    assert back.shape == (20, 20)
    np.testing.assert_array_equal(back[:10, :10], 1.0)


def test_paste_back_in_bands_leaves_no_seams():
    # A frame several bands tall, content that changes along the rows: any band misplaced
    # by a row or warped with the wrong offset shows up against the ramp.
    height = 3 * BAND_ROWS + 17
    image = (np.arange(height, dtype=np.float32)[:, None] + 0.5).repeat(40, axis=1)
    box = CropBox(-5, 3, height, height // 2)  # reaches past the left and bottom edges
    back = paste_back(crop_square(image, box), box, height, 40)
    inner = (slice(3 + 4, height - 4), slice(4, 36))  # away from the box and photo edges
    np.testing.assert_allclose(back[inner], image[inner], atol=1e-3)
    assert back[:3].max() == 0  # nothing above the box


@pytest.mark.parametrize("rows", [slice(0, 5), slice(BAND_ROWS - 3, BAND_ROWS + 40), slice(290, None)])
def test_paste_back_rows_are_those_rows_of_the_frame(rows):
    crop = np.random.default_rng(1).random((32, 32, 3)).astype(np.float32)
    box = CropBox(10, 20, 250, 32)  # rows 20..270 of 300
    full = paste_back(crop, box, 300, 280)
    # atol: OpenCV's warp rounds a few ulps differently when a band starts on another row
    np.testing.assert_allclose(paste_back(crop, box, 300, 280, rows), full[rows], atol=1e-5)


def tall_scene(height=2 * BAND_ROWS + 50, width=60):
    """A relit crop, its box, a soft mask, a photo and an environment view, several bands tall."""
    rng = np.random.default_rng(2)
    mask = np.zeros((height, width), np.float32)
    mask[40:height - 40, 20:40] = 1.0
    mask[30:40, 20:40] = 0.3
    box = person_crop_box(mask, 32)
    crop = rng.random((32, 32, 3)).astype(np.float32)
    photo, env_view = rng.random((2, height, width, 3)).astype(np.float32)
    return crop, box, mask, photo, env_view


@pytest.mark.parametrize("background", ["keep", "env", "transparent", "#336699"])
def test_composite_crop_is_composite_of_the_pasted_crop(background):
    crop, box, mask, photo, env_view = tall_scene()
    height, width = mask.shape
    rgb, alpha = composite_crop(crop, box, mask, background, photo=photo, env_view=env_view, scale=1.7)
    expected, expected_alpha = composite(paste_back(crop, box, height, width) * np.float32(1.7), mask, background,
                                         photo=photo, env_view=env_view * np.float32(1.7))
    np.testing.assert_allclose(rgb, expected, atol=1e-5)
    assert (alpha is None) == (expected_alpha is None)
    if alpha is not None:
        np.testing.assert_array_equal(alpha, expected_alpha)


def test_composite_crop_may_write_over_its_background():
    crop, box, mask, photo, env_view = tall_scene()
    expected, _ = composite_crop(crop, box, mask, "env", env_view=env_view, scale=0.5)
    rgb, _ = composite_crop(crop, box, mask, "env", env_view=env_view, scale=0.5, out=env_view)
    assert rgb is env_view
    np.testing.assert_array_equal(rgb, expected)


def test_composite_crop_of_a_large_frame_makes_no_frame_sized_temporaries():
    # Issue "End to end": a 24 MP photo must relight in 1.5 GB, where one float32 RGB frame is
    # 288 MB. Whole-frame compositing (paste, scale, alpha, sums) took ~5 frames of temporaries.
    crop, box, mask, photo, _ = tall_scene(height=16 * BAND_ROWS, width=512)
    frame_bytes = photo.nbytes
    tracemalloc.start()
    try:
        composite_crop(crop, box, mask, "keep", photo=photo, scale=2.0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 2 * frame_bytes  # the result (one frame) and band-sized temporaries


def test_relit_is_albedo_times_shading():
    albedo = np.full((2, 2, 3), 0.5, np.float32)
    shading = np.array([0.0, 1.0, 40.0], np.float32) * np.ones((2, 2, 3), np.float32)
    np.testing.assert_array_equal(relight(albedo, shading)[0, 0], [0.0, 0.5, 20.0])


def test_composite_keep_uses_alpha():
    relit = np.full((1, 3, 3), 2.0, np.float32)
    photo = np.full((1, 3, 3), 0.25, np.float32)
    mask = np.array([[0.0, 0.5, 1.0]], np.float32)
    rgb, alpha = composite(relit, mask, "keep", photo=photo)
    assert alpha is None
    np.testing.assert_allclose(rgb[0, :, 0], [0.25, 1.125, 2.0])


def test_a_matte_sharpens_the_mask_before_compositing():
    relit = np.full((1, 5, 3), 2.0, np.float32)
    photo = np.full((1, 5, 3), 0.25, np.float32)
    mask = np.array([[0.1, 0.2, 0.5, 0.8, 0.95]], np.float32)
    np.testing.assert_allclose(sharpened(mask, (0.2, 0.8))[0], [0.0, 0.0, 0.5, 1.0, 1.0], atol=1e-6)
    rgb, _ = composite(relit, mask, "keep", photo=photo, matte=(0.2, 0.8))
    np.testing.assert_allclose(rgb[0, :, 0], [0.25, 0.25, 1.125, 2.0, 2.0], atol=1e-6)
    plain, _ = composite(relit, mask, "keep", photo=photo)  # without a matte: the mask as alpha
    np.testing.assert_allclose(plain[0, :, 0], 2.0 * mask[0] + 0.25 * (1.0 - mask[0]), atol=1e-6)
    _, alpha = composite(relit, mask, "transparent", matte=(0.2, 0.8))
    np.testing.assert_allclose(alpha[0], [0.0, 0.0, 0.5, 1.0, 1.0], atol=1e-6)


def test_composite_crop_gives_the_sharpened_alpha_when_transparent():
    crop = np.full((4, 4, 3), 0.5, np.float32)
    box = CropBox(0, 0, 4, 4)
    mask = np.full((4, 4), 0.65, np.float32)
    _, alpha = composite_crop(crop, box, mask, "transparent", matte=(0.2, 0.8))
    np.testing.assert_allclose(alpha, 0.75, atol=1e-6)
    _, alpha = composite_crop(crop, box, mask, "transparent")
    np.testing.assert_allclose(alpha, 0.65, atol=1e-6)


def test_composite_transparent_gives_straight_alpha():
    relit = np.full((1, 2, 3), 0.7, np.float32)
    mask = np.array([[0.0, 0.4]], np.float32)
    rgb, alpha = composite(relit, mask, "transparent")
    np.testing.assert_array_equal(alpha, mask)
    np.testing.assert_allclose(rgb[0, 1], 0.7)  # straight, not premultiplied


@pytest.mark.parametrize("text, linear", [("#fff", 1.0), ("#000000", 0.0), ("#808080", 0.21586)])
def test_parse_colour(text, linear):
    np.testing.assert_allclose(parse_colour(text), linear, atol=1e-4)


def test_display_exposure_maps_p95_to_target():
    relit = np.linspace(0, 100, 1000, dtype=np.float32)[:, None, None].repeat(3, axis=2)
    mask = np.ones((1000, 1), np.float32)
    factor = display_exposure(relit, mask, 0.8)
    assert factor * np.percentile(relit[:, 0, 0], 95) == pytest.approx(0.8, rel=1e-4)
    assert display_exposure(np.zeros_like(relit), mask, 0.8) == 1.0


def test_preview_sheet_shape():
    tiles = [("input", np.zeros((100, 50, 3))), ("ao", np.ones((40, 40)))]
    sheet = preview_sheet(tiles, height=64)
    assert sheet.shape == (64 + 24, 32 + 4 + 64, 3)
    assert 0.0 <= sheet.min() and sheet.max() <= 1.0


def test_preview_sheet_enlarges_a_small_tile_smoothly():
    # the 16 x 32 input light shown at 256 rows: bilinear, not 16 rows of blocks
    light = np.zeros((16, 32, 3), np.float32)
    light[8:, :, :] = 1.0
    sheet = preview_sheet([("input light", light)], height=256)
    column = sheet[24:, 100, 0]
    assert len(np.unique(np.round(column, 4))) > 8  # a ramp across the step, not two values
    assert np.all(np.diff(column) >= -1e-6)


def test_ratio_albedo_inverts_relight_where_the_shading_is_bright():
    rng = np.random.default_rng(0)
    albedo = rng.uniform(0.05, 0.95, (16, 16, 3)).astype(np.float32)
    shading = rng.uniform(0.5, 3.0, (16, 16, 3)).astype(np.float32)
    fallback = np.full_like(albedo, 0.3)
    got = ratio_albedo(relight(albedo, shading), shading, fallback, np.ones((16, 16)))
    np.testing.assert_allclose(got, albedo, rtol=1e-5)


def test_ratio_albedo_falls_back_where_the_shading_is_dark_and_stays_finite():
    shading = np.ones((8, 8, 3), np.float32)
    shading[:, :2] = 0.0  # facing away from every light
    shading[:, 2] = 1e-6  # almost
    shading[:, 7] = 1e6  # a sun a million times brighter
    image = np.full((8, 8, 3), 0.4, np.float32)
    fallback = np.full_like(image, 0.7)
    got = ratio_albedo(image, shading, fallback, np.ones((8, 8)))
    assert np.isfinite(got).all() and got.min() >= 0.0 and got.max() <= 1.0
    np.testing.assert_allclose(got[:, :3], 0.7)  # below RATIO_DARK x the median: the net's albedo
    np.testing.assert_allclose(got[:, 3:7], 0.4)
    np.testing.assert_allclose(got[:, 7], 0.4e-6, rtol=1e-4)
    # Black shading everywhere (no light estimated): the net's albedo, not a division by zero
    np.testing.assert_array_equal(ratio_albedo(image, np.zeros_like(image), fallback, np.ones((8, 8))), fallback)
    # Saturated photo under dim light: above 1 until the level is set, then clipped to a
    # physical albedo
    bright = ratio_albedo(np.full_like(image, 0.9), np.full_like(image, 0.5), fallback, np.ones((8, 8)))
    np.testing.assert_allclose(bright, 1.8, rtol=1e-6)
    assert anchor_albedo(bright, bright, np.ones((8, 8)), ring=0).max() == 1.0


def test_anchor_albedo_takes_the_level_from_the_net_and_the_detail_and_colour_from_the_ratio():
    rng = np.random.default_rng(1)
    albedo = rng.uniform(0.05, 0.6, (24, 24, 3)).astype(np.float32) * np.array([0.3, 1.0, 0.2], np.float32)
    ratio = albedo * np.float32(0.5)  # the light's intensity was off
    mask = np.zeros((24, 24), np.float32)
    mask[4:20, 4:20] = 1.0
    level = albedo[4:20, 4:20].mean()
    net = np.full(albedo.shape, level, np.float32)  # grey, flat, at the right level
    got = anchor_albedo(ratio, net, mask, ring=0)
    np.testing.assert_allclose(got, albedo, rtol=1e-5)  # the green stays green
    # The outline ring (1 px) is the mean of the net's and the nearest pixel's inside it; the
    # core keeps the ratio's detail, at the net's level inside the ring
    got = anchor_albedo(ratio, net, mask, ring=1)
    albedo = albedo * (level / albedo[5:19, 5:19].mean())
    share = OUTLINE_NET_SHARE
    np.testing.assert_allclose(got[4, 5:19], share * net[4, 5:19] + (1 - share) * albedo[5, 5:19], rtol=1e-5)
    np.testing.assert_allclose(got[19, 5:19], share * net[19, 5:19] + (1 - share) * albedo[18, 5:19], rtol=1e-5)
    np.testing.assert_allclose(got[4, 4], share * net[4, 4] + (1 - share) * albedo[5, 5], rtol=1e-5)
    np.testing.assert_allclose(got[5:19, 5:19], albedo[5:19, 5:19], rtol=1e-5)
    # A person no wider than the ring: all outline, the net's there
    thin = np.zeros((24, 24), np.float32)
    thin[4:20, 10:12] = 1.0
    got = anchor_albedo(ratio, net, thin, ring=1)
    np.testing.assert_allclose(got[4:20, 10:12], net[4:20, 10:12])


def test_anchor_albedo_stays_physical_and_finite_on_extreme_inputs():
    mask = np.ones((8, 8), np.float32)
    net = np.full((8, 8, 3), 0.9, np.float32)
    dim = np.full((8, 8, 3), 1e-3, np.float32)
    dim[0, 0] = 0.5  # one bright texel: scaled x900, must clip
    got = anchor_albedo(dim, net, mask, ring=0)
    assert np.isfinite(got).all() and got.min() >= 0.0 and got.max() == 1.0
    # A black ratio (nothing to scale): left black, not divided by zero
    np.testing.assert_array_equal(anchor_albedo(np.zeros_like(net), net, mask, ring=0), 0.0)
    # No person: unchanged
    np.testing.assert_array_equal(anchor_albedo(dim, net, np.zeros((8, 8)), ring=1), dim)


def disc_scene(side=512, radius=160.0):
    """A red disc (the person) on a green, noisy background, and the disc's true mask."""
    y, x = np.mgrid[:side, :side] + 0.5
    truth = ((x - side / 2) ** 2 + (y - side / 2) ** 2 <= radius**2).astype(np.float32)
    rng = np.random.default_rng(0)
    crop = np.where(truth[..., None] > 0, [0.6, 0.05, 0.05], [0.05, 0.4, 0.1]).astype(np.float32)
    crop = np.clip(crop + rng.normal(0, 0.02, crop.shape), 0, 1).astype(np.float32)
    return crop, truth


def iou(a, b):
    return np.logical_and(a > 0.5, b > 0.5).sum() / np.logical_or(a > 0.5, b > 0.5).sum()


def test_snap_mask_pulls_a_blurred_mask_to_the_photos_edge_and_keeps_it_soft():
    crop, truth = disc_scene(radius=60.0)
    # What a 256-px segmentation enlarged to a 512 crop looks like: blurred, 2 px off
    soft = cv2.GaussianBlur(np.roll(truth, 2, axis=1), (0, 0), 3.0)
    got = snap_mask(crop, soft)
    assert got.dtype == np.float32 and got.shape == truth.shape and 0.0 <= got.min() and got.max() <= 1.0
    edge = np.abs(cv2.Laplacian(truth, cv2.CV_32F)) > 0
    assert np.abs(got - truth)[edge].mean() < np.abs(soft - truth)[edge].mean()
    assert iou(got, truth) > iou(soft, truth)


def test_snap_mask_survives_nan_and_infinite_pixels():
    crop, truth = disc_scene()
    crop[10:20, 10:20] = np.nan
    crop[250:252, 250:252] = np.inf
    got = snap_mask(crop, truth)
    assert np.isfinite(got).all() and iou(got, truth) > 0.99


def test_replace_in_box_changes_only_the_box_even_where_it_leaves_the_photo():
    full = np.full((40, 50), 0.25, np.float32)
    box = CropBox(x0=-10, y0=20, size=30, resolution=15)  # its left third and bottom lie outside
    replace_in_box(full, np.ones((15, 15), np.float32), box)
    np.testing.assert_array_equal(full[20:40, 0:20], 1.0)
    np.testing.assert_array_equal(full[:20], 0.25)
    np.testing.assert_array_equal(full[:, 20:], 0.25)


def _textured_photo(side=512, seed=0):
    """A smooth gradient times a fine random texture (finer than a 128-px crop's pixels), and a
    disc mask (the person)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[:side, :side] / side
    smooth = (0.2 + 0.5 * x)[..., None] * np.array([0.9, 0.7, 0.5], np.float32)
    texture = rng.uniform(0.5, 1.5, (side, side, 1))
    mask = (((x - 0.5) ** 2 + (y - 0.5) ** 2) < 0.16).astype(np.float32)
    return (smooth * texture).astype(np.float32), mask


def test_the_photos_own_detail_comes_back_where_the_crop_was_coarser():
    from relightcli.compose import LUMINANCE, CropBox, PhotoDetail, composite_crop, crop_square

    photo, mask = _textured_photo()
    box = CropBox(0, 0, 512, 128)  # 4 photo pixels per crop pixel
    crop = crop_square(photo, box)
    relit = crop * np.float32(0.5)  # a relight that halves the light everywhere
    sharp, _ = composite_crop(relit, box, mask, "#000000", detail=PhotoDetail(photo, crop, box, mask))
    blurred, _ = composite_crop(relit, box, mask, "#000000")
    inside = np.zeros_like(mask, bool)
    inside[200:312, 200:312] = True  # well inside the disc
    lum = lambda image: image[inside] @ LUMINANCE  # noqa: E731
    want = 0.5 * lum(photo)
    assert np.corrcoef(lum(sharp), want)[0, 1] > 0.97  # the texture, pixel for pixel
    assert np.corrcoef(lum(blurred), want)[0, 1] < 0.5  # what the enlarged crop alone gave
    np.testing.assert_allclose(lum(sharp).mean(), want.mean(), rtol=0.02)  # the level kept
    # outside the person nothing changes
    outside = mask < 0.5
    np.testing.assert_array_equal(sharp[outside], blurred[outside])


def test_a_crop_finer_than_the_photo_loses_no_detail_either():
    """Enlarged into the crop and shrunk back, the photo comes back blurred: its detail is put
    back the same way."""
    from relightcli.compose import LUMINANCE, CropBox, PhotoDetail, composite_crop, crop_square

    photo, mask = _textured_photo(128)
    box = CropBox(0, 0, 128, 200)  # 0.64 photo pixels per crop pixel
    crop = crop_square(photo, box)
    sharp, _ = composite_crop(crop * np.float32(0.5), box, mask, "#000000", detail=PhotoDetail(photo, crop, box, mask))
    blurred, _ = composite_crop(crop * np.float32(0.5), box, mask, "#000000")
    inside = np.zeros_like(mask, bool)
    inside[50:78, 50:78] = True
    lum = lambda image: image[inside] @ LUMINANCE  # noqa: E731
    assert np.corrcoef(lum(blurred), lum(photo))[0, 1] < 0.95
    assert np.corrcoef(lum(sharp), lum(photo))[0, 1] > 0.999


def test_the_photos_colour_detail_comes_back_too():
    """Fine colour texture (paint, lips, eyes) comes back channel by channel: the relit person
    keeps the photo's colour edges instead of the crop's blurred colour."""
    from relightcli.compose import CropBox, PhotoDetail, composite_crop, crop_square

    photo, mask = _textured_photo()
    photo = photo * np.random.default_rng(1).uniform(0.5, 1.5, photo.shape).astype(np.float32)
    box = CropBox(0, 0, 512, 128)
    crop = crop_square(photo, box)
    relit = crop * np.array([0.5, 0.6, 0.8], np.float32)  # a relight that changes the colour too
    sharp, _ = composite_crop(relit, box, mask, "#000000", detail=PhotoDetail(photo, crop, box, mask))
    inside = np.zeros_like(mask, bool)
    inside[200:312, 200:312] = True
    ratio = np.log(sharp[inside]) - np.log(photo[inside])  # per channel: smooth, the relight's
    colour = ratio - ratio.mean(axis=-1, keepdims=True)
    np.testing.assert_allclose(np.exp(ratio.mean(axis=0)), [0.5, 0.6, 0.8], rtol=0.03)
    assert colour.std(axis=0).max() < 0.03


def test_the_photos_detail_is_left_out_where_the_crop_has_its_pixels_and_bounded_elsewhere():
    from relightcli.compose import DETAIL_RANGE, CropBox, PhotoDetail, crop_square

    photo, mask = _textured_photo(128)
    same = CropBox(0, 0, 128, 128)
    assert PhotoDetail(photo, crop_square(photo, same), same, mask).factor(slice(0, 128)) is None
    # a black photo with one bright pixel: finite, within the range, 1 outside the person
    photo = np.zeros_like(photo)
    photo[64, 64] = 50.0
    coarse = CropBox(0, 0, 128, 32)
    factor = PhotoDetail(photo, crop_square(photo, coarse), coarse, mask).factor(slice(0, 128))
    assert np.isfinite(factor).all() and factor.max() <= DETAIL_RANGE and factor.min() >= 0.0
    assert (factor[64, 64] == DETAIL_RANGE).all()
    assert (factor[mask < 0.5] == 1.0).all()


def test_a_black_pixel_of_the_photo_stays_black_in_the_relit_person():
    """The detail puts back the photo times the crop's relight ratio: a pixel the photo has at 0
    (a nostril, a pupil, clipped shadows) is 0 in the relit too, never lifted into a bright spot."""
    from relightcli.compose import CropBox, PhotoDetail, composite_crop, crop_square

    photo, mask = _textured_photo()
    photo[250:254, 250:254] = 0.0  # a few black pixels, finer than a crop pixel
    photo[300, 300, 0] = 0.0  # one channel of one pixel
    box = CropBox(0, 0, 512, 128)
    crop = crop_square(photo, box)
    relit, _ = composite_crop(crop * np.float32(2.0), box, mask, "#000000", detail=PhotoDetail(photo, crop, box, mask))
    assert (relit[250:254, 250:254] == 0.0).all() and relit[300, 300, 0] == 0.0
    assert (relit[300, 300, 1:] > 0.0).all()


def _face_relit(input_shading, photo, mask, net_albedo):
    """The relit crop under a uniform new light (shading 1), the albedo as stage_delight
    composes it."""
    return anchor_albedo(ratio_albedo(photo, input_shading, net_albedo, mask), net_albedo, mask)


def test_a_dip_of_the_input_shading_the_photo_does_not_show_makes_no_bright_spot():
    """The solved light's shading dips where the mesh occludes itself but the photo's face is
    evenly lit: divided by it, the albedo would be a bright spot in the relit face."""
    size = 96
    mask = np.zeros((size, size), np.float32)
    mask[8:88, 8:88] = 1.0
    photo = np.full((size, size, 3), 0.3, np.float32) * mask[..., None]
    net_albedo = np.full((size, size, 3), 0.3, np.float32)
    shading = np.ones((size, size, 3), np.float32)
    shading[44:52, 44:52] = 0.08  # tiny: 8% of the face's shading
    inside = mask > 0.5

    def spot(relit):
        ratio = (relit @ LUMINANCE)[inside] / (photo @ LUMINANCE)[inside]
        return ratio.max() / np.median(ratio)

    assert spot(_face_relit(shading, photo, mask, net_albedo)) > 1.65  # the spot, undivided
    bounded = shading_the_photo_shows(shading, photo, mask, sigma=8.0)
    assert spot(_face_relit(bounded, photo, mask, net_albedo)) < 1.1
    # A shadow the photo shows stays in the shading (the albedo is not darkened by it)
    photo[44:52, 44:52] *= 0.08
    np.testing.assert_allclose(shading_the_photo_shows(shading, photo, mask, sigma=8.0)[44:52, 44:52], 0.08, rtol=0.05)


def _fill_over_the_whole_image(values, covered, wanted):
    """fill_uncovered's definition: the nearest covered pixel by a transform of the whole image."""
    from scipy.ndimage import distance_transform_edt

    holes = wanted & ~covered
    _, (rows, cols) = distance_transform_edt(~covered, return_indices=True)
    filled = values.copy()
    filled[holes] = values[rows[holes], cols[holes]]
    return filled


@pytest.mark.parametrize("seed", range(4))
def test_fill_uncovered_within_its_box_is_the_whole_images_fill(seed):
    """The transform runs over the box around the covered pixels and the holes only: the same
    nearest pixels, ties included (a symmetric cover leaves many equidistant ones)."""
    from relightcli.compose import fill_uncovered

    rng = np.random.default_rng(seed)
    covered = np.zeros((60, 50), bool)
    if seed == 0:  # two covered pixels mirrored about the holes' column: every hole is a tie
        covered[30, 10] = covered[30, 40] = True
    else:
        covered[15:45, 12:30] = rng.random((30, 18)) < 0.6
    wanted = np.zeros_like(covered)
    wanted[10:50, 8:38] = True
    values = rng.random((60, 50, 2)).astype(np.float32)
    np.testing.assert_array_equal(fill_uncovered(values, covered, wanted),
                                  _fill_over_the_whole_image(values, covered, wanted))


def test_fill_smooth_fills_a_wide_hole_from_both_sides_without_wedges():
    """A hole 40 px wide across a ramp (the mesh missing between two people): the smooth fill
    follows the ramp (pull-push is not exact on it: within 10% of its range, under half the
    nearest copy's mean error) where the nearest pixel's copy alone leaves two flat halves; covered
    pixels, pixels not wanted and a NaN texel's neighbours stay put."""
    from relightcli.compose import fill_smooth, fill_uncovered

    rows, cols = np.mgrid[:64, :96]
    values = np.stack([cols / 95.0, 1.0 - rows / 63.0], axis=-1).astype(np.float32)
    covered = np.ones((64, 96), bool)
    covered[8:56, 28:68] = False
    wanted = np.ones_like(covered)
    wanted[8:12, 28:68] = False  # a strip of the hole nobody asked for
    values[0, 0] = np.nan  # a covered NaN texel: it does not spread
    smooth = fill_smooth(values, covered, wanted)
    nearest = fill_uncovered(values, covered, wanted)
    filled = wanted & ~covered
    truth = np.stack([cols / 95.0, 1.0 - rows / 63.0], axis=-1)
    assert np.isfinite(smooth[filled]).all()
    assert np.abs(smooth - truth)[filled].max() < 0.1
    assert np.abs(smooth - truth)[filled].mean() < 0.5 * np.abs(nearest - truth)[filled].mean()
    # across the hole's middle row the fill rises with the ramp (flat only in the rim that
    # copies its nearest pixel): no flat wedge
    assert (np.diff(smooth[32, 28:68, 0]) >= 0).all() and (np.diff(smooth[32, 34:62, 0]) > 0).all()
    assert not (np.diff(nearest[32, 34:62, 0]) > 0).all()
    untouched = ~filled
    np.testing.assert_array_equal(np.isnan(smooth[untouched]), np.isnan(values[untouched]))
    np.testing.assert_array_equal(smooth[untouched][1:], values[untouched][1:])


def test_fill_smooth_on_degenerate_covers():
    from relightcli.compose import fill_smooth

    values = np.arange(12, dtype=np.float32).reshape(2, 2, 3)
    nothing = np.zeros((2, 2), bool)
    np.testing.assert_array_equal(fill_smooth(values, nothing, ~nothing), values)  # nothing covered
    one = np.zeros((2, 2), bool)
    one[1, 1] = True
    np.testing.assert_allclose(fill_smooth(values, one, ~one), np.broadcast_to(values[1, 1], (2, 2, 3)))
    single = np.ones((1, 1, 3), np.float32)
    assert fill_smooth(single, np.ones((1, 1), bool), np.ones((1, 1), bool)) is single
    # values near float32's largest (a sun's shading in odd units) and tiny ones: finite, in range
    for size in (3e38, 1e-38):
        huge = np.full((16, 16, 3), size, np.float32)
        covered = np.ones((16, 16), bool)
        covered[4:12, 4:12] = False
        filled = fill_smooth(huge, covered, np.ones_like(covered))
        assert np.isfinite(filled).all() and np.allclose(filled, size, rtol=1e-5, atol=0)


def test_bounding_box():
    from relightcli.compose import bounding_box

    mask = np.zeros((8, 9), bool)
    assert bounding_box(mask) == (slice(0, 0), slice(0, 0))
    mask[2, 7] = mask[5, 3] = True
    assert bounding_box(mask) == (slice(2, 6), slice(3, 8))
