"""Padding to the model's multiple, cropping back, and layout conversion."""

from __future__ import annotations

import numpy as np
import pytest

from relightcli.nets.geometry import AONet
from relightcli.nets.layout import Padding, crop_padding, hwc_to_nchw, nchw_to_hwc, pad_to_multiple, padding_for
from relightcli.nets.refine import BodyRefineNet, shading_scale


@pytest.mark.parametrize("shape", [(1, 1), (1, 5, 3), (2, 3, 3), (37, 50, 3), (64, 32), (33, 17, 1)])
@pytest.mark.parametrize("mode", ["reflect", "edge", "zero"])
def test_pad_crop_round_trip(shape, mode):
    image = np.random.default_rng(0).random(shape, dtype=np.float32)
    padded, pad = pad_to_multiple(image, 16, mode)
    assert padded.shape[0] % 16 == 0 and padded.shape[1] % 16 == 0
    np.testing.assert_array_equal(crop_padding(padded, pad), image)


def test_padding_is_split_evenly():
    assert padding_for(37, 50, 16) == Padding(5, 6, 7, 7)


def test_reflect_pad_mirrors_without_repeating_edge():
    padded, _ = pad_to_multiple(np.arange(3, dtype=np.float32)[None, :].repeat(4, 0), 4, "reflect")
    np.testing.assert_array_equal(padded[0], [0, 1, 2, 1])


def test_zero_pad_is_background():
    padded, pad = pad_to_multiple(np.ones((3, 3, 3), np.float32), 8, "zero")
    assert padded.sum() == 27 and padded[0, 0, 0] == 0


def test_nchw_round_trip():
    image = np.random.default_rng(1).random((5, 7, 3), dtype=np.float32)
    tensor = hwc_to_nchw(image)
    assert tensor.shape == (1, 3, 5, 7) and tensor.flags.c_contiguous
    np.testing.assert_array_equal(nchw_to_hwc(tensor), image)


@pytest.mark.parametrize("shape", [(37, 50), (16, 16), (5, 90)])
def test_family_class_pads_runs_and_crops(ao_model_dir, shape):
    image = np.random.default_rng(2).random(shape + (3,), dtype=np.float32)
    ao = AONet(models_dir=ao_model_dir, threads=1).predict(image)
    assert ao.shape == shape and ao.dtype == np.float32
    np.testing.assert_allclose(ao, image.mean(axis=2), atol=1e-6)


def test_body_refine_identity_round_trips_hdr_shading(body_model_dir):
    rng = np.random.default_rng(3)
    shading = (rng.random((40, 30, 3), dtype=np.float32) * 1e4).astype(np.float32)
    mask = np.zeros((40, 30), np.float32)
    mask[5:35, 5:25] = 1
    out = BodyRefineNet(models_dir=body_model_dir, threads=1).predict(shading, np.ones((40, 30), np.float32), mask)
    np.testing.assert_allclose(out, shading, rtol=1e-6)


def test_shading_scale_of_constant_map():
    assert shading_scale(np.full((4, 4, 3), 2.0, np.float32)) == pytest.approx(2.0 / 0.8)


def test_shading_scale_uses_the_mask():
    shading = np.zeros((4, 4, 3), np.float32)
    shading[:2] = 8.0
    mask = np.zeros((4, 4), np.float32)
    mask[:2] = 1
    assert shading_scale(shading, mask) == pytest.approx(10.0)


@pytest.mark.parametrize("mask_value", [0.0, 1.0])
def test_shading_scale_of_black_or_empty_is_one(mask_value):
    assert shading_scale(np.zeros((4, 4, 3), np.float32), np.full((4, 4), mask_value, np.float32)) == 1.0
