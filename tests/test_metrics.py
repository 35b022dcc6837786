"""Metrics: closed forms for MSE/PSNR, scikit-image as an independent SSIM reference."""

from __future__ import annotations

import numpy as np
import pytest

from relightcli.metrics import SSIM_RADIUS, mse, psnr, ssim


def noisy_pair(shape, seed=0, noise=0.1):
    """Random image in [0, 1] and a noisy, clipped copy, both float64."""
    rng = np.random.default_rng(seed)
    clean = rng.random(shape)
    return clean, np.clip(clean + noise * rng.standard_normal(shape), 0.0, 1.0)


# --- MSE and PSNR -------------------------------------------------------------------------

def test_mse_of_constant_offset_is_its_square():
    a = np.zeros((5, 7, 3))
    assert mse(a, a + 0.25) == pytest.approx(0.0625, rel=1e-12)


def test_mse_ignores_differences_outside_the_mask():
    a = np.zeros((6, 6, 3))
    b = a.copy()
    b[:, 3:] = 1.0
    mask = np.zeros((6, 6), dtype=bool)
    mask[:, :3] = True
    assert mse(a, b, mask) == 0.0
    assert mse(a, b, ~mask) == 1.0


def test_mse_float_mask_is_thresholded_at_half():
    a = np.zeros((2, 2))
    b = np.array([[1.0, 0.0], [0.0, 0.0]])
    assert mse(a, b, np.array([[0.9, 0.1], [0.6, 0.4]])) == pytest.approx(0.5)


def test_mse_with_empty_mask_is_a_clear_error():
    a = np.zeros((4, 4, 3))
    with pytest.raises(ValueError, match="empty mask"):
        mse(a, a, np.zeros((4, 4), dtype=bool))


@pytest.mark.parametrize("shapes", [((4, 4, 3), (4, 4)), ((4, 5), (5, 4)), ((4,), (4,))])
def test_shape_mismatch_is_refused(shapes):
    with pytest.raises(ValueError):
        mse(np.zeros(shapes[0]), np.zeros(shapes[1]))


@pytest.mark.parametrize("offset, data_range, expected", [(0.1, 1.0, 20.0), (0.01, 1.0, 40.0),
                                                          (1.0, 255.0, 48.130803608679)])
def test_psnr_closed_form(offset, data_range, expected):
    a = np.full((8, 8, 3), 0.3)
    assert psnr(a, a + offset, data_range=data_range) == pytest.approx(expected, rel=1e-9)


def test_psnr_of_identical_images_is_infinite():
    a = np.random.default_rng(3).random((8, 8, 3))
    assert psnr(a, a) == float("inf")


def test_psnr_matches_scikit_image():
    metrics = pytest.importorskip("skimage.metrics")
    a, b = noisy_pair((20, 30, 3), seed=4)
    expected = metrics.peak_signal_noise_ratio(a, b, data_range=1.0)
    assert psnr(a, b) == pytest.approx(expected, rel=1e-12)


# --- SSIM ---------------------------------------------------------------------------------

@pytest.mark.parametrize("shape, seed", [((32, 48, 3), 0), ((11, 11, 3), 1), ((40, 23), 2),
                                         ((25, 30, 1), 3)])
def test_ssim_matches_scikit_image(shape, seed):
    metrics = pytest.importorskip("skimage.metrics")
    a, b = noisy_pair(shape, seed=seed)
    channel_axis = -1 if len(shape) == 3 else None
    expected = metrics.structural_similarity(
        a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0,
        channel_axis=channel_axis)
    assert ssim(a, b) == pytest.approx(expected, abs=1e-6)


def test_ssim_data_range_matches_scaled_images():
    a, b = noisy_pair((24, 24, 3), seed=5)
    assert ssim(255.0 * a, 255.0 * b, data_range=255.0) == pytest.approx(ssim(a, b), abs=1e-9)


def test_ssim_of_identical_images_is_one():
    a = np.random.default_rng(6).random((20, 20, 3))
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-12)


def test_ssim_full_mask_equals_no_mask():
    a, b = noisy_pair((24, 30, 3), seed=7)
    assert ssim(a, b, np.ones((24, 30), dtype=bool)) == ssim(a, b)


def test_ssim_is_one_on_a_mask_far_from_differences():
    # left half identical, right half noise; pixels further than the window radius from the
    # noisy half see identical windows, so their SSIM is exactly 1
    a, b = noisy_pair((40, 60, 3), seed=8)
    b[:, :30] = a[:, :30]
    mask = np.zeros((40, 60), dtype=bool)
    mask[:, : 30 - SSIM_RADIUS] = True
    assert ssim(a, b, mask) == pytest.approx(1.0, abs=1e-12)
    assert ssim(a, b, ~mask) < 0.99


def test_masked_ssim_is_the_mean_of_scikit_image_map_over_the_mask():
    metrics = pytest.importorskip("skimage.metrics")
    a, b = noisy_pair((30, 36, 3), seed=10)
    mask = np.random.default_rng(11).random((30, 36)) < 0.3
    _, full_map = metrics.structural_similarity(
        a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0,
        channel_axis=-1, full=True)
    inside = mask.copy()
    inside[:SSIM_RADIUS] = inside[-SSIM_RADIUS:] = False
    inside[:, :SSIM_RADIUS] = inside[:, -SSIM_RADIUS:] = False
    assert ssim(a, b, mask) == pytest.approx(full_map[inside].mean(), abs=1e-6)


def test_ssim_is_symmetric():
    a, b = noisy_pair((16, 16, 3), seed=9)
    assert ssim(a, b) == pytest.approx(ssim(b, a), abs=1e-14)


def test_ssim_refuses_images_smaller_than_the_window():
    with pytest.raises(ValueError, match="11x11"):
        ssim(np.zeros((10, 40, 3)), np.zeros((10, 40, 3)))


def test_ssim_refuses_mask_only_on_the_border():
    mask = np.zeros((20, 20), dtype=bool)
    mask[0, :] = True
    with pytest.raises(ValueError, match="border"):
        ssim(np.zeros((20, 20)), np.zeros((20, 20)), mask)
