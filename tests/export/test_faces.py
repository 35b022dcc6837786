"""The synthetic face renders (export/factory/faces.py): the sampled distribution and ground
truth aligned with the renderer's pixels."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from export.factory import faces, lighting
from relightcli.geometry.face_model import FaceModel, world_to_pixel
from relightcli.render import Scene


@pytest.fixture(scope="module")
def model():
    return FaceModel.load()


@pytest.fixture(scope="module")
def hdris():
    if not (lighting.hdri_dir() / "index.csv").is_file():
        pytest.skip(f"HDRIs not found in {lighting.hdri_dir()}")
    return lighting.hdri_splits()


def test_sampled_shapes_and_poses_stay_in_their_ranges(model, hdris):
    for index in range(30):
        spec = faces.sample_spec(np.random.default_rng([0, 0, index]), model, hdris["train"])
        assert all(abs(a) <= limit for a, limit in zip(spec.angles_deg, faces.POSE_LIMITS_DEG))
        assert np.abs(spec.identity).max() <= faces.IDENTITY_CLIP
        expression = np.asarray(spec.expression)
        assert expression.min() >= 0 and expression.max() <= 1 and np.count_nonzero(expression) <= 4
        assert spec.light.kind == "sky" or spec.light.name in hdris["train"]


def test_same_seed_same_spec(model, hdris):
    a = faces.sample_spec(np.random.default_rng([1, 2, 3]), model, hdris["val"])
    b = faces.sample_spec(np.random.default_rng([1, 2, 3]), model, hdris["val"])
    assert a == b


def test_landmarks_follow_the_pixel_convention_of_the_renderer(model, hdris):
    # Frontal face: the nose-tip landmark's pixel sees the nose tip (the front-most point)
    spec = faces.sample_spec(np.random.default_rng(5), model, hdris["train"])
    spec = dataclasses.replace(spec, angles_deg=(0.0, 0.0, 0.0), expression=(0.0,) * model.n_expression)
    sample = faces.render_face(model, spec)
    vertices, landmarks = faces.posed_face(model, spec)
    rect = tuple(float(v) for v in sample["rect"])
    np.testing.assert_allclose(sample["landmarks"], world_to_pixel(landmarks, rect, (128, 128)), atol=1e-4)
    geometry, _, _ = faces.trace_surface(Scene(vertices, model.triangles), rect, 128)
    col, row = np.rint(sample["landmarks"][30]).astype(int)
    depth = geometry.position[..., 2] + Scene(vertices, model.triangles).centre[2]
    pixel = (rect[1] - rect[0]) / 128
    assert geometry.mask[row, col] and abs(depth[row, col] - landmarks[30, 2]) < pixel
    assert depth[row, col] >= depth[geometry.mask].max() - 2 * pixel
