"""The adaptive Wiener filter on the integrator's own error estimate (render.denoise) and its
use on the traced visibility (stages.shading.traced)."""

from __future__ import annotations

import numpy as np
import pytest
from render_testing import floor_under_a_square

from relightcli.stages import shading
from relightcli.render.denoise import adaptive_wiener
from relightcli.render.environment import EnvironmentLight


def _shadow_edge(sigma, seed=0, size=64):
    """A visibility field with a hard edge (0.2 left, 0.9 right), Gaussian noise of `sigma`
    and that sigma as every pixel's standard error."""
    truth = np.full((size, size, 3), 0.2, np.float32)
    truth[:, size // 2:] = 0.9
    noise = np.random.default_rng(seed).normal(0.0, sigma, truth.shape).astype(np.float32)
    return truth, truth + noise, np.full(truth.shape, sigma, np.float32)


def test_the_noise_the_integrator_measured_is_taken_out_and_a_shadow_edge_kept():
    truth, noisy, error = _shadow_edge(0.08)
    mask = np.ones(truth.shape[:2], bool)
    out = adaptive_wiener(noisy, error, mask)
    rmse = lambda image: float(np.sqrt(np.mean((image - truth) ** 2)))  # noqa: E731
    assert rmse(out) < 0.6 * rmse(noisy)
    # the columns on either side of the edge keep their level (a box blur would give 0.43 / 0.67)
    assert abs(out[:, 31].mean() - 0.2) < 0.05 and abs(out[:, 32].mean() - 0.9) < 0.05


def test_values_without_error_are_kept():
    _, noisy, error = _shadow_edge(0.08)
    mask = np.ones(noisy.shape[:2], bool)
    np.testing.assert_allclose(adaptive_wiener(noisy, np.zeros_like(error), mask), noisy, atol=1e-6)


def test_pixels_off_the_mask_are_neither_changed_nor_used():
    _, noisy, error = _shadow_edge(0.08)
    mask = np.ones(noisy.shape[:2], bool)
    mask[:, :8] = False
    poisoned = noisy.copy()
    poisoned[:, :8] = np.nan
    error = error.copy()
    error[:, :8] = 1e30
    out = adaptive_wiener(poisoned, error, mask)
    assert np.isnan(out[:, :8]).all()
    clean = adaptive_wiener(noisy, np.where(mask[..., None], error, 0.0), mask)
    np.testing.assert_allclose(out[:, 8:], clean[:, 8:], rtol=1e-6)


@pytest.mark.parametrize("scale", [1e-20, 1e20])
def test_the_filter_does_not_depend_on_the_values_scale(scale):
    _, noisy, error = _shadow_edge(0.08)
    mask = np.ones(noisy.shape[:2], bool)
    out = adaptive_wiener(noisy * np.float32(scale), error * np.float32(scale), mask)
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out / np.float32(scale), adaptive_wiener(noisy, error, mask), rtol=1e-4, atol=1e-6)


def _floor_shading(env, spp, radius, monkeypatch, step=1, seed=3):
    monkeypatch.setattr(shading, "SHADING_FILTER_RADIUS", radius)
    scene, hits = floor_under_a_square(96)
    values, _ = shading.traced(scene, hits, EnvironmentLight(env), spp, None, seed, 1, hits.mask, step)
    return values, hits.mask


@pytest.mark.parametrize("step", [1, 2])
def test_a_map_of_many_small_lights_is_shaded_closer_to_the_truth(monkeypatch, step):
    # Bright texels scattered over a dim map: each shadow ray sees a different subset, so the
    # square's penumbra on the floor is noisy at a few samples per pixel
    rng = np.random.default_rng(5)
    env = np.full((32, 64, 3), 0.05, np.float32)
    env[rng.integers(0, 16, 40), rng.integers(0, 64, 40)] = 40.0
    reference, mask = _floor_shading(env, 1024, 0, monkeypatch, step, seed=11)
    raw, _ = _floor_shading(env, 8, 0, monkeypatch, step)
    filtered, _ = _floor_shading(env, 8, 1, monkeypatch, step)
    error = lambda v: float(np.sqrt(np.mean((v[mask, :3] - reference[mask, :3]) ** 2)))  # noqa: E731
    assert error(filtered) < 0.75 * error(raw)
    # the error reported is the Monte Carlo estimate before filtering
    np.testing.assert_array_equal(filtered[..., 3:], raw[..., 3:])
