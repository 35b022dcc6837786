"""Synthetic albedo: skin tone range, texture value ranges, bilinear lookup."""

import numpy as np
import pytest

from export.factory import albedo


def test_skin_palette_spans_light_to_dark():
    lum = albedo.luminance(albedo.skin_palette())
    assert lum.max() / lum.min() > 5.0
    assert np.all(np.diff(lum[2:]) < 0)  # darkening along the scale (first swatches are close)


@pytest.mark.parametrize("t", [0.0, 0.33, 0.5, 0.9, 1.0])
def test_skin_tone_is_a_valid_albedo(t):
    tone = albedo.skin_tone(t)
    assert tone.dtype == np.float32 and np.all((tone > 0) & (tone < 1))


def test_skin_tone_ends_are_the_palette_ends():
    palette = albedo.skin_palette()
    np.testing.assert_allclose(albedo.skin_tone(0.0), palette[0])
    np.testing.assert_allclose(albedo.skin_tone(1.0), palette[-1])


@pytest.mark.parametrize("pattern", albedo.PATTERNS)
def test_cloth_texture_in_unit_range(pattern):
    tex, name = albedo.cloth_texture(np.random.default_rng(1), 64, pattern)
    assert name == pattern and tex.shape == (64, 64, 3) and tex.dtype == np.float32
    assert tex.min() >= 0.0 and tex.max() <= 1.0


@pytest.mark.parametrize("pattern", ["stripes", "checks", "noise"])
def test_patterned_cloth_is_not_flat(pattern):
    tex, _ = albedo.cloth_texture(np.random.default_rng(2), 128, pattern)
    assert albedo.luminance(tex).std() > 1e-3


def test_unknown_pattern_raises():
    with pytest.raises(ValueError, match="unknown cloth pattern"):
        albedo.cloth_texture(np.random.default_rng(0), 8, "tartan")


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_hair_texture_in_unit_range(seed):
    rng = np.random.default_rng(seed)
    _, colour = albedo.sample_hair_colour(rng, 0.9)
    tex = albedo.hair_texture(rng, 32, colour)
    assert tex.min() >= 0.0 and tex.max() <= 1.0


@pytest.mark.parametrize("t", [0.0, 1.0])
def test_skin_texture_in_unit_range_and_near_its_tone(t):
    tone = albedo.skin_tone(t)
    tex = albedo.skin_texture(np.random.default_rng(0), 32, tone)
    assert tex.min() >= 0.0 and tex.max() <= 1.0
    np.testing.assert_allclose(tex.reshape(-1, 3).mean(axis=0), tone, rtol=0.1)


def test_sample_texture_bilinear_on_a_gradient():
    # 2x4 texture whose red channel is the column index: u maps linearly between texel centres.
    tex = np.zeros((2, 4, 3), dtype=np.float32)
    tex[..., 0] = np.arange(4)
    tex[0, :, 1] = 1.0  # top row green: v = 1 is the top
    uv = np.array([[0.125, 0.75], [0.5, 0.25], [0.875, 0.5]], dtype=np.float32)
    got = albedo.sample_texture(tex, uv)
    np.testing.assert_allclose(got[:, 0], [0.0, 1.5, 3.0], atol=1e-6)
    np.testing.assert_allclose(got[:, 1], [1.0, 0.0, 0.5], atol=1e-6)
