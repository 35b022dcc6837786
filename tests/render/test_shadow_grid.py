"""Shadows traced on a coarse pixel grid (stages.shading.traced with step > 1, `--shadows half`): the
visibility found on every step-th pixel, applied to every pixel's own unoccluded shading."""

from __future__ import annotations

import numpy as np
import pytest
from render_testing import floor_under_a_square, one_hot_map, quad

from relightcli.io.envmap import uv_to_direction
from relightcli.render.camera import pixel_centres, render_pixel_geometry
from relightcli.render.environment import EnvironmentLight
from relightcli.render.scene import Scene
from relightcli.stages.shading import traced, upsample


@pytest.mark.parametrize("step", [2, 3])
def test_a_subsampled_grid_keeps_its_pixels_centres(step):
    scene = Scene(*quad(-1.0, 1.0, -1.0, 1.0, 0.0))
    rect, (width, height) = (-1.2, 0.9, -0.7, 1.1), (9, 7)
    full = render_pixel_geometry(scene, rect, (width, height))
    coarse = full.subsampled(step)
    rows, cols = coarse.mask.shape
    assert (rows, cols) == (-(-height // step), -(-width // step))
    np.testing.assert_allclose(pixel_centres(coarse.rect, (cols, rows)),
                               pixel_centres(rect, (width, height))[::step, ::step], atol=1e-12)
    np.testing.assert_array_equal(coarse.position, full.position[::step, ::step])
    np.testing.assert_array_equal(coarse.normal, full.normal[::step, ::step])
    assert full.subsampled(1) is full


def test_upsampling_keeps_the_coarse_pixels_and_interpolates_between_them():
    coarse = np.random.default_rng(0).random((3, 4, 2)).astype(np.float32)
    fine = upsample(coarse, (6, 8), 2)
    assert fine.shape == (6, 8, 2)
    np.testing.assert_array_equal(fine[::2, ::2], coarse)
    np.testing.assert_allclose(fine[1, 2], (coarse[0, 1] + coarse[1, 1]) / 2, rtol=1e-6)
    np.testing.assert_allclose(fine[3, 3], coarse[1:3, 1:3].mean(axis=(0, 1)), rtol=1e-6)
    # beyond the last coarse row and column the values are held, not extrapolated
    np.testing.assert_array_equal(fine[5], fine[4])
    np.testing.assert_array_equal(fine[:, 7], fine[:, 6])



def test_upsampling_a_window_is_that_window_of_the_whole():
    coarse = np.random.default_rng(1).random((9, 7, 3)).astype(np.float32)
    whole = upsample(coarse, (36, 28), 4)
    box = (slice(5, 31), slice(3, 11))
    np.testing.assert_array_equal(upsample(coarse, (36, 28), 4, box), whole[box])

def _render(scene, hits, env, step, spp=64):
    light = EnvironmentLight(env)
    values, result = traced(scene, hits, light, spp, None, 3, 1, hits.mask, step)
    return values[..., :3], values[..., 3:], light


@pytest.mark.parametrize("sky", [0.0, 1e-6])
def test_a_cast_shadow_on_the_coarse_grid_matches_every_pixels_rays(sky):
    # A hard sun low in +X+Z, alone or a million times brighter than a uniform sky
    height, row, col = 128, 40, 224
    env = one_hot_map(height, row, col, 50.0) + np.float32(sky * 50.0)
    scene, hits = floor_under_a_square()
    full, full_err, light = _render(scene, hits, env, 1)
    half, half_err, _ = _render(scene, hits, env, 2)
    assert np.isfinite(half).all() and np.isfinite(half_err).all() and (half >= 0).all()
    # Where the shadow ray lands on the square: distance to the square's edge, in pixels
    d = uv_to_direction((col + 0.5) / (2 * height), (row + 0.5) / height)
    p = scene.to_world(hits.position.reshape(-1, 3)).reshape(96, 96, 3)
    floor = hits.mask & (np.abs(p[..., 2]) < 1e-4)
    edge = (np.max(np.abs(p[..., :2] + (1.0 / d[2]) * d[:2]), axis=-1) - 0.5) / (8.0 / 96)
    umbra, lit = floor & (edge < -3), floor & (edge > 3)
    assert umbra.sum() > 30 and lit.sum() > 1000
    if sky == 0.0:
        assert np.all(half[umbra] == 0.0) and np.all(full[umbra] == 0.0)
    # the same within the Monte Carlo error and the irradiance table's interpolation
    scale = np.abs(full[lit]).mean()
    assert np.all(np.abs(half[lit] - full[lit]) <= 5 * np.hypot(full_err[lit], half_err[lit]) + 2e-3 * scale)
    # the unoccluded shading at each pixel's own normal carries the coarse grid's visibility
    unoccluded = light.irradiance(hits.normal[lit])
    np.testing.assert_allclose(half[lit], unoccluded, rtol=0.05)


def test_a_convex_ball_on_the_coarse_grid_is_its_exact_unoccluded_shading():
    import trimesh

    ball = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    scene = Scene.from_trimesh(ball, smooth_normals=False)  # facets: no ray grazes its own surface
    hits = render_pixel_geometry(scene, (-1.1, 1.1, -1.1, 1.1), (64, 64))
    env = np.random.default_rng(1).random((32, 64, 3)).astype(np.float32) ** 4 * 10.0
    full, full_err, light = _render(scene, hits, env, 1, spp=16)
    half, half_err, _ = _render(scene, hits, env, 2, spp=16)
    # Nothing blocks a convex surface: the visibility is 1, the shading the irradiance table's
    # at each pixel's own normal
    facing = hits.mask & (hits.normal[..., 2] > 0.2)
    assert facing.sum() > 2500 and np.all(full_err[facing] == 0.0)
    np.testing.assert_allclose(half[facing], light.irradiance(hits.normal[facing]), rtol=1e-5)
    np.testing.assert_allclose(half[facing], full[facing], rtol=1e-5)
    assert np.all(half_err[facing] == 0.0)


def test_a_black_environment_on_the_coarse_grid_shades_black():
    scene, hits = floor_under_a_square(32)
    half, half_err, _ = _render(scene, hits, np.zeros((16, 32, 3), np.float32), 2, spp=4)
    assert np.all(half == 0.0) and np.all(half_err == 0.0)
