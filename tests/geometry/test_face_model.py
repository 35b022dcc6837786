"""The shipped face model file: loading, integrity, linearity, landmarks, camera helpers."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
import trimesh

from export.face_model import MIRROR_PAIRS
from relightcli.errors import MissingDependencyError
from relightcli.geometry.face_model import (
    FaceModel,
    pixel_to_world,
    rotation_matrix,
    world_to_pixel,
)
from relightcli.nets.manifest import models_dir
from relightcli.render.camera import pixel_centres

MODEL_PATH = models_dir() / "face_model.npz"
ICT_DIR = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "ict_facekit"


@pytest.fixture(scope="module")
def model():
    return FaceModel.load()


def test_file_is_small_and_sha256_matches_its_bytes(model):
    assert MODEL_PATH.stat().st_size <= 10 * 2 ** 20
    assert model.sha256 == hashlib.sha256(MODEL_PATH.read_bytes()).hexdigest()


def test_sha256_is_stable_across_loads(model):
    assert FaceModel.load(MODEL_PATH).sha256 == model.sha256


def test_license_line_is_recorded(model):
    assert model.license == ("MIT License, Copyright (c) 2020 USC Institute for Creative "
                             "Technologies")


def test_missing_file_names_the_file_and_the_fix(tmp_path):
    missing = tmp_path / "face_model.npz"
    with pytest.raises(MissingDependencyError, match="export.face_model") as info:
        FaceModel.load(missing)
    assert info.value.path == str(missing)


def test_corrupt_file_raises_missing_dependency(tmp_path):
    broken = tmp_path / "face_model.npz"
    broken.write_bytes(b"not a zip file")
    with pytest.raises(MissingDependencyError, match="unreadable"):
        FaceModel.load(broken)


def test_shapes_are_consistent(model):
    v = model.neutral.shape[0]
    assert model.identity_basis.shape == (40, v, 3)
    assert model.expression_basis.shape == (model.n_expression, v, 3)
    assert model.n_expression == len(model.expression_names) == 55
    assert model.triangles.max() == v - 1 and model.landmark_indices.shape == (68,)


@pytest.mark.parametrize("mode", [0, 7, 39, 40, 70, 94])
def test_vertices_are_linear_in_each_coefficient(model, mode):
    c = np.zeros(model.n_identity + model.n_expression)
    c[mode] = 0.7
    got = model.vertices(c[:40], c[40:]) - model.neutral
    basis = model.identity_basis[mode] if mode < 40 else model.expression_basis[mode - 40]
    np.testing.assert_allclose(got, 0.7 * basis, atol=1e-5)


def test_landmarks_are_the_landmark_vertices(model):
    rng = np.random.default_rng(1)
    identity, expression = rng.normal(size=40), rng.uniform(size=model.n_expression)
    np.testing.assert_allclose(model.landmarks(identity, expression),
                               model.vertices(identity, expression)[model.landmark_indices],
                               atol=1e-4)


@pytest.mark.parametrize("pair", MIRROR_PAIRS)
def test_landmark_pairs_mirror_across_the_midline(model, pair):
    p = model.landmark_neutral
    left, right = pair
    assert p[left, 0] < 0 < p[right, 0]
    np.testing.assert_allclose(p[left] * [-1, 1, 1], p[right], atol=0.05)


def test_only_the_neck_is_open_and_normals_face_outward(model):
    mesh = trimesh.Trimesh(model.neutral, model.triangles, process=False)
    assert mesh.is_winding_consistent
    edges, counts = np.unique(mesh.edges_sorted, axis=0, return_counts=True)
    boundary = np.unique(edges[counts == 1])
    # Every boundary vertex is on the neck's cut, well below the chin
    assert model.neutral[boundary, 1].max() < model.landmark_neutral[8, 1] - 3.0
    nose_tip = model.landmark_indices[30]
    assert mesh.vertex_normals[nose_tip, 2] > 0.95


def test_pixel_world_round_trip_follows_design_pixel_centres():
    rect, resolution = (-0.3, 0.5, 1.0, 1.6), (40, 30)
    centres = pixel_centres(rect, resolution).reshape(-1, 2)
    rows, cols = np.divmod(np.arange(30 * 40), 40)
    pixels = np.stack([cols, rows], axis=1).astype(float)
    np.testing.assert_allclose(pixel_to_world(pixels, rect, resolution), centres, atol=1e-12)
    np.testing.assert_allclose(world_to_pixel(centres, rect, resolution), pixels, atol=1e-9)


@pytest.mark.parametrize("angles, axis, expected", [
    ((30, 0, 0), 2, [0.5, 0.0, 0.8660254]),      # yaw: the face turns toward +X
    ((0, 30, 0), 2, [0.0, -0.5, 0.8660254]),     # pitch: the face looks down
    ((0, 0, 30), 0, [0.8660254, 0.5, 0.0]),      # roll: counter-clockwise in the image
])
def test_rotation_angle_conventions(angles, axis, expected):
    np.testing.assert_allclose(rotation_matrix(*angles)[:, axis], expected, atol=1e-7)


@pytest.mark.slow
def test_export_reproduces_the_shipped_file(tmp_path):
    if not ICT_DIR.is_dir():
        pytest.skip("ICT FaceKit data not found at ../shared/data/ict_facekit")
    from export.face_model import build_arrays, read_ict, write_npz

    data, landmarks = read_ict(ICT_DIR)
    digest = write_npz(tmp_path / "face_model.npz", build_arrays(data, landmarks, 40))
    assert digest == hashlib.sha256(MODEL_PATH.read_bytes()).hexdigest()
