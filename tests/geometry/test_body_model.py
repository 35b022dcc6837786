"""The shipped body model: loading, integrity, rest pose, skinning algebra, landmarks, errors."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from relightcli.errors import MissingDependencyError, UsageError
from relightcli.geometry.body_model import (
    LANDMARK_NAMES,
    MAX_SHAPE_SIGMA,
    BodyModel,
    tree_levels,
    world_transforms,
)
from relightcli.nets.manifest import model_entry, models_dir

MODEL_PATH = models_dir() / "body_model.npz"
MIRROR = np.array([-1.0, 1.0, 1.0])


def landmark(name: str) -> int:
    return LANDMARK_NAMES.index(name)


def rotation_z(degrees: float) -> np.ndarray:
    a = np.radians(degrees)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def model():
    return BodyModel.load()


@pytest.fixture(scope="module")
def rest(model):
    return model.posed(None, model.rest_pose())


def test_file_is_small_and_matches_the_manifest_sha256(model):
    assert MODEL_PATH.stat().st_size <= 20 * 2 ** 20
    assert model.sha256 == hashlib.sha256(MODEL_PATH.read_bytes()).hexdigest()
    assert model_entry("body_model").sha256 == model.sha256


def test_manifest_entry_is_data_with_the_cc0_notice():
    spec = json.loads((models_dir() / "manifest.json").read_text())["models"]["body_model"]
    assert spec["kind"] == "data" and spec["file"] == "body_model.npz"
    assert spec["license"].startswith("CC0 1.0 Universal") and "MakeHuman" in spec["license"]


def test_license_line_names_makehuman(model):
    assert model.license.startswith("CC0 1.0 Universal") and "MakeHuman" in model.license


def test_missing_file_names_the_file_and_the_fix(tmp_path):
    missing = tmp_path / "body_model.npz"
    with pytest.raises(MissingDependencyError, match="export.body_model") as info:
        BodyModel.load(missing)
    assert info.value.path == str(missing)


def test_corrupt_file_raises_missing_dependency(tmp_path):
    broken = tmp_path / "body_model.npz"
    broken.write_bytes(b"not a zip file")
    with pytest.raises(MissingDependencyError, match="unreadable"):
        BodyModel.load(broken)


def test_shapes_are_consistent(model):
    n_vertices, n_joints, k = len(model.mean_vertices), model.n_joints, model.n_shape
    assert model.shape_basis.shape == (k, n_vertices, 3)
    assert model.joint_basis.shape == (k, n_joints, 3)
    assert model.landmark_basis.shape == (k, 33, 3)
    assert model.triangles.max() == n_vertices - 1
    np.testing.assert_allclose(model.skin_weights.sum(axis=1), 1.0, atol=1e-6)


def test_rest_pose_reproduces_the_mean_mesh_and_joints(model, rest):
    vertices, joints, landmarks = rest
    np.testing.assert_allclose(vertices, model.mean_vertices, atol=1e-6)
    np.testing.assert_allclose(joints, model.mean_joints, atol=1e-12)
    np.testing.assert_allclose(landmarks, model.mean_landmarks, atol=1e-12)


def test_mean_body_is_an_adult_standing_on_y_facing_z(model):
    height = np.ptp(model.mean_vertices[:, 1])
    assert 1.5 < height < 1.85
    nose = model.mean_landmarks[landmark("nose")]
    assert nose[2] > model.mean_joints[model.joint_names.index("head"), 2] + 0.1


def test_shape_is_linear(model):
    e0 = np.eye(model.n_shape)[0]
    difference = model.shaped(2.0 * e0) - model.shaped(e0)
    np.testing.assert_allclose(difference, model.shape_basis[0], atol=1e-12)


def test_scale_and_translation_act_after_posing(model):
    rotations = model.rest_pose()
    rotations[model.joint_names.index("upperarm01.L")] = rotation_z(30.0)
    shape = np.linspace(-1.0, 1.0, model.n_shape)
    plain = model.posed(shape, rotations)
    moved = model.posed(shape, rotations, translation=(0.1, -0.2, 3.0), scale=0.9)
    for p, q in zip(plain, moved):
        np.testing.assert_allclose(q, 0.9 * p + [0.1, -0.2, 3.0], atol=1e-12)


def test_rotating_the_left_upper_arm_keeps_arm_lengths_and_the_right_arm(model, rest):
    rotations = model.rest_pose()
    rotations[model.joint_names.index("upperarm01.L")] = rotation_z(60.0)
    _, _, landmarks = model.posed(None, rotations)
    shoulder, wrist = landmark("left_shoulder"), landmark("left_wrist")
    before = np.linalg.norm(rest[2][wrist] - rest[2][shoulder])
    after = np.linalg.norm(landmarks[wrist] - landmarks[shoulder])
    assert after == pytest.approx(before, abs=1e-9)
    assert np.linalg.norm(landmarks[wrist] - rest[2][wrist]) > 0.2
    np.testing.assert_allclose(landmarks[landmark("right_wrist")],
                               rest[2][landmark("right_wrist")], atol=1e-12)


def test_world_transforms_compose_along_a_chain():
    # Two bones on the x axis, each turned 90 degrees about z: the child's head at (1, 0, 0)
    # goes to (0, 1, 0), and a point at (2, 0, 0) on the child ends at (-1, 1, 0).
    parents = np.array([-1, 0])
    heads = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    transforms = world_transforms(tree_levels(parents), parents, heads,
                                  np.stack([rotation_z(90.0)] * 2))
    np.testing.assert_allclose(transforms[1] @ [1.0, 0.0, 0.0, 1.0], [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(transforms[1] @ [2.0, 0.0, 0.0, 1.0], [-1.0, 1.0, 0.0], atol=1e-12)


def test_tree_levels_reject_a_child_before_its_parent():
    with pytest.raises(ValueError, match="before its parent"):
        tree_levels(np.array([-1, 2, 0]))


@pytest.mark.parametrize("left", [n for n in LANDMARK_NAMES if "left" in n])
def test_left_landmarks_mirror_the_right_ones(model, left):
    right = left.replace("left", "right")
    p, q = model.mean_landmarks[landmark(left)], model.mean_landmarks[landmark(right)]
    assert p[0] > 0.01  # the person's own left is +X when facing +Z
    np.testing.assert_allclose(p, q * MIRROR, atol=0.003)


def test_nose_is_the_front_of_the_face(model):
    nose = model.mean_landmarks[landmark("nose")]
    head = model.mean_vertices[:, 1] > nose[1] - 0.05
    assert abs(nose[0]) < 1e-3
    assert nose[2] > model.mean_vertices[head, 2].max() - 0.01


def test_face_landmarks_run_from_eyes_to_mouth_to_shoulders(model):
    y = model.mean_landmarks[:, 1]
    assert y[landmark("left_eye")] > y[landmark("nose")] > y[landmark("mouth_left")]
    assert y[landmark("mouth_left")] > y[landmark("left_shoulder")] + 0.1
    x = model.mean_landmarks[:, 0]
    assert 0 < x[landmark("left_eye_inner")] < x[landmark("left_eye")] < x[
        landmark("left_eye_outer")] < x[landmark("left_ear")]


@pytest.mark.parametrize("name,bone", [("left_wrist", "wrist.L"), ("right_elbow", "lowerarm01.R"),
                                       ("left_knee", "lowerleg01.L"), ("right_hip", "upperleg01.R"),
                                       ("left_ankle", "foot.L")])
def test_limb_landmarks_sit_on_their_joints_in_a_pose(model, name, bone):
    rotations = model.rest_pose()
    rotations[model.joint_names.index("spine03")] = rotation_z(20.0)
    rotations[model.joint_names.index("upperleg01.L")] = rotation_z(-15.0)
    _, joints, landmarks = model.posed(np.full(model.n_shape, 0.5), rotations)
    np.testing.assert_allclose(landmarks[landmark(name)], joints[model.joint_names.index(bone)],
                               atol=1e-9)


def test_foot_runs_heel_ankle_toe_from_back_to_front(model):
    z = model.mean_landmarks[:, 2]
    assert z[landmark("left_heel")] < z[landmark("left_ankle")] < z[landmark("left_foot_index")]
    assert model.mean_landmarks[landmark("left_heel"), 1] < model.mean_landmarks[
        landmark("left_ankle"), 1]


@pytest.mark.parametrize("bad", [np.nan, np.inf, MAX_SHAPE_SIGMA + 0.1, -MAX_SHAPE_SIGMA - 1])
def test_a_nan_or_out_of_range_shape_raises(model, bad):
    shape = np.zeros(model.n_shape)
    shape[3] = bad
    with pytest.raises(UsageError, match="body shape"):
        model.posed(shape, model.rest_pose())


def test_a_shape_of_the_wrong_length_raises(model):
    with pytest.raises(UsageError, match=f"{model.n_shape} finite coefficients"):
        model.shaped(np.zeros(model.n_shape + 1))


def test_a_non_rotation_raises(model):
    rotations = model.rest_pose()
    rotations[5] *= 1.1
    with pytest.raises(UsageError, match="orthonormal"):
        model.posed(None, rotations)


@pytest.mark.parametrize("translation,scale", [((0.0, np.nan, 0.0), 1.0), ((0.0, 0.0), 1.0),
                                               ((0.0, 0.0, 0.0), 0.0)])
def test_a_bad_placement_raises(model, translation, scale):
    with pytest.raises(UsageError):
        model.posed(None, model.rest_pose(), translation, scale)
