"""Data adapters: flips, crops, translation-invariant depth, stand-in shadings, face crops."""

import numpy as np
import pytest

from export.train import data
from export.train.fake_data import fake_sample
from relightcli.io.envmap import texel_directions


@pytest.fixture
def sample():
    return fake_sample(np.random.default_rng(3), size=32)


def test_flip_twice_is_the_identity(sample):
    twice = data.flip_horizontal(data.flip_horizontal(sample))
    for key, value in sample.items():
        np.testing.assert_array_equal(twice[key], value, err_msg=key)


def test_flip_negates_the_normals_x(sample):
    flipped = data.flip_horizontal(sample)
    np.testing.assert_array_equal(flipped["normal"][:, ::-1, 0], -sample["normal"][..., 0])
    np.testing.assert_array_equal(flipped["normal"][:, ::-1, 1:], sample["normal"][..., 1:])


def test_flip_mirrors_the_light_about_the_yz_plane(sample):
    # a single lit texel must move to the texel whose direction has the opposite x
    light = np.zeros((16, 32, 3), dtype=np.float32)
    light[5, 27] = 1.0
    flipped = data.flip_horizontal({**sample, "light_a": light})["light_a"]
    row, col = np.argwhere(flipped[..., 0] > 0)[0]
    dirs = texel_directions(16, 32)
    np.testing.assert_allclose(dirs[row, col], dirs[5, 27] * np.array([-1, 1, 1]), atol=1e-12)


def test_flip_mirrors_the_face_box(sample):
    x0, y0, x1, y1 = sample["face_box"]
    flipped = data.flip_horizontal(sample)["face_box"]
    np.testing.assert_array_equal(flipped, [32 - x1, y0, 32 - x0, y1])


def test_crop_narrows_the_rect_to_the_window(sample):
    cropped = data.crop_sample(sample, top=4, left=8, size=16)
    px = (sample["rect"][1] - sample["rect"][0]) / 32
    np.testing.assert_allclose(cropped["rect"], [-1.2 + 8 * px, -1.2 + 24 * px, 1.2 - 20 * px, 1.2 - 4 * px], atol=1e-6)
    assert cropped["input"].shape == (16, 16, 3)
    assert cropped["light_a"].shape == (16, 32, 3)


def test_crop_that_cuts_the_face_drops_the_face_box(sample):
    cropped = data.crop_sample(sample, top=16, left=0, size=16)
    assert not data.has_face(cropped)


def test_crop_larger_than_the_sample_is_refused(sample):
    with pytest.raises(ValueError, match="larger than"):
        data.augment(sample, np.random.default_rng(0), flip=False, crop=64)


def test_relative_depth_is_translation_invariant(sample):
    shifted = dict(sample)
    inside = sample["mask"] > 0.5
    shifted["front_depth"] = np.where(inside, sample["front_depth"] + 7.0, 0).astype(np.float32)
    shifted["back_depth"] = np.where(inside, sample["back_depth"] + 7.0, 0).astype(np.float32)
    for a, b in zip(data.relative_depths(sample), data.relative_depths(shifted)):
        np.testing.assert_allclose(a, b, atol=1e-5)


def test_relative_depth_is_scale_invariant(sample):
    # the same person in a crop twice as large in world units: depths in crop units are equal
    scaled = {**sample, "rect": sample["rect"] * 2, "front_depth": sample["front_depth"] * 2,
              "back_depth": sample["back_depth"] * 2}
    for a, b in zip(data.relative_depths(sample), data.relative_depths(scaled)):
        np.testing.assert_allclose(a, b, atol=1e-6)


def test_relative_front_depth_has_zero_mean_on_the_person(sample):
    front, _ = data.relative_depths(sample)
    assert abs(front[sample["mask"] > 0.5].mean()) < 1e-6


def test_standin_coarse_shading_is_zero_off_the_person(sample):
    coarse = data.standin_coarse_shading(sample["shading_b"], sample["ao"], sample["mask"],
                                         np.random.default_rng(0), {"blur_sigma": 2, "noise": 0.1, "ao_power": 1})
    assert np.all(coarse[sample["mask"] <= 0.5] == 0) and np.all(coarse >= 0)


def test_standin_coarse_shading_is_the_truth_with_no_degradation(sample):
    coarse = data.standin_coarse_shading(sample["shading_b"], sample["ao"], sample["mask"],
                                         np.random.default_rng(0), {"blur_sigma": 0, "noise": 0, "ao_power": 0})
    np.testing.assert_allclose(coarse, sample["shading_b"] * (sample["mask"] > 0.5)[..., None], atol=1e-6)


def test_crop_resample_of_the_whole_frame_is_the_identity(sample):
    out = data.crop_resample(sample["albedo"], 16.0, 16.0, 32.0, 32)
    np.testing.assert_allclose(out, sample["albedo"], atol=1e-6)


def test_validation_rng_is_fixed_per_sample():
    a = data.sample_rng(0, "val", "x").random(3)
    b = data.sample_rng(0, "val", "x").random(3)
    c = data.sample_rng(0, "val", "y").random(3)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
