"""Training losses on known inputs: zero for identical inputs, closed forms, the light weights."""

import math

import numpy as np
import pytest
import torch

from export.train import losses
from relightcli.io.envmap import texel_solid_angles

torch.set_num_threads(1)


def images(seed=0, shape=(2, 3, 32, 32)):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(shape, generator=g)


def person_mask(shape=(2, 1, 32, 32)):
    m = torch.zeros(shape)
    m[..., 8:24, 10:22] = 1
    return m


def test_masked_l1_identical_is_zero():
    x = images()
    assert losses.masked_l1(x, x.clone(), person_mask()).item() == 0.0


def test_masked_l1_ignores_pixels_outside_the_mask():
    x, m = images(), person_mask()
    y = x + 10 * (1 - m)  # differs only off the person
    assert losses.masked_l1(x, y, m).item() == 0.0


def test_masked_l1_closed_form_constant_offset():
    x = images()
    assert losses.masked_l1(x, x + 0.25, person_mask()).item() == pytest.approx(0.25, abs=1e-6)


def test_angular_loss_identical_normals_is_zero():
    n = torch.nn.functional.normalize(images() - 0.5, dim=1)
    assert losses.angular_loss(n, n.clone(), person_mask()).item() == pytest.approx(0.0, abs=1e-6)


def test_angular_loss_opposite_normals_is_two():
    n = torch.nn.functional.normalize(images() - 0.5, dim=1)
    assert losses.angular_loss(n, -n, person_mask()).item() == pytest.approx(2.0, abs=1e-5)


def test_gradient_l1_ignores_a_constant_offset():
    x = images()
    assert losses.gradient_l1(x, x + 0.3).item() == pytest.approx(0.0, abs=1e-6)


def test_ms_ssim_identical_is_one():
    x = images()
    assert losses.ms_ssim(x, x.clone(), person_mask()).item() == pytest.approx(1.0, abs=1e-6)


def test_ms_ssim_drops_with_noise():
    ramp = torch.linspace(0.2, 0.8, 32)
    x = (ramp[None, :] * ramp[:, None]).expand(1, 3, 32, 32)
    noisy = x + 0.4 * (images(shape=(1, 3, 32, 32)) - 0.5)
    assert losses.ms_ssim(x, noisy).item() < 0.8


def test_ms_ssim_scale_count_adapts_to_size():
    assert [losses.ms_ssim_scales(s, s) for s in (8, 32, 128, 512)] == [1, 3, 5, 5]


def test_perceptual_identical_is_zero():
    x = images()
    assert losses.perceptual(x, x.clone(), person_mask()).item() == pytest.approx(0.0, abs=1e-6)


def test_perceptual_is_positive_for_different_images():
    assert losses.perceptual(images(0), images(1)).item() > 0.1


def test_perceptual_has_finite_gradients_for_anticorrelated_images():
    x = images().requires_grad_(True)
    losses.perceptual(x, 1 - x.detach()).backward()
    assert torch.isfinite(x.grad).all()


def test_light_weights_sum_to_one():
    assert losses.light_weights(16, 32).sum().item() == pytest.approx(1.0, abs=1e-6)


def test_light_weights_are_the_texel_solid_angles():
    w = texel_solid_angles(16, 32)
    np.testing.assert_allclose(losses.light_weights(16, 32).numpy(), w / (4 * math.pi), rtol=1e-6)


def test_light_loss_identical_is_zero():
    light = 100 * images(shape=(2, 3, 16, 32))
    assert losses.light_loss(light, light.clone()).item() == 0.0


def test_light_loss_closed_form_for_constant_maps():
    # constant maps: sum_texels w (log(1+c) - log(1+d))^2 = (log(1+c) - log(1+d))^2, as sum w = 1
    pred, target = torch.full((1, 3, 16, 32), 3.0), torch.full((1, 3, 16, 32), 0.5)
    expected = (math.log(4.0) - math.log(1.5)) ** 2
    assert losses.light_loss(pred, target).item() == pytest.approx(expected, rel=1e-5)


def test_light_loss_weighs_a_polar_texel_less_than_an_equatorial_one():
    target = torch.zeros(1, 3, 16, 32)
    polar, equator = target.clone(), target.clone()
    polar[..., 0, 5] = 10.0
    equator[..., 8, 5] = 10.0
    assert losses.light_loss(polar, target) < losses.light_loss(equator, target) / 5


def test_fft_l1_identical_is_zero():
    x = images()
    assert losses.fft_l1(x, x.clone()).item() == 0.0


def test_fft_l1_of_a_constant_offset_is_in_the_dc_term_only():
    # rfft2 of a constant c on H x W is H*W*c at DC and 0 elsewhere: mean over H x (W/2+1) bins, /2
    x = images(shape=(1, 1, 8, 8))
    expected = 64 * 0.5 / (8 * 5) / 2
    assert losses.fft_l1(x + 0.5, x).item() == pytest.approx(expected, rel=1e-4)


def test_lsgan_loss_values():
    scores = [torch.full((1, 1, 4, 4), 0.5), torch.full((1, 1, 2, 2), 1.0)]
    assert losses.lsgan_loss(scores, real=True).item() == pytest.approx((0.25 + 0.0) / 2)
    assert losses.lsgan_loss(scores, real=False).item() == pytest.approx((0.25 + 1.0) / 2)


def test_pyramid_matches_average_pooling():
    x = images(shape=(1, 3, 32, 32))
    levels = losses.pyramid(x, 5)
    assert [t.shape[-1] for t in levels] == [32, 16, 8, 4, 2]
    assert levels[1][0, 0, 0, 0].item() == pytest.approx(x[0, 0, :2, :2].mean().item(), abs=1e-6)
