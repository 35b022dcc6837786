"""The body fit (relightcli/geometry/body_fit.py): its rotation helpers, the closed-form
initialisation, recovery of known poses and shapes from synthetic BlazePose observations of
the body model itself (observe_landmarks, plus noise), and clean fallbacks on bad inputs."""

from __future__ import annotations

import numpy as np
import pytest

from relightcli.geometry import body_fit
from relightcli.geometry.body_fit import (
    CORE_LANDMARKS,
    aim_limbs,
    axis_angle_to_matrix,
    fit_body,
    initial_pose,
    observe_landmarks,
    rotation_angle,
    rotation_between,
)
from relightcli.geometry.body_model import BodyModel

RESOLUTION = 512
# Limb directions (model frame: +X the person's left, +Y up, +Z towards the camera)
POSES = {
    "T-pose": {"upperarm01.L": (1, 0, 0), "upperarm01.R": (-1, 0, 0),
               "lowerarm01.L": (1, 0, 0), "lowerarm01.R": (-1, 0, 0)},
    "A-pose": {"upperarm01.L": (0.7, -0.7, 0), "upperarm01.R": (-0.7, -0.7, 0),
               "lowerarm01.L": (0.6, -0.8, 0.1), "lowerarm01.R": (-0.6, -0.8, 0.1)},
    "arms-up": {"upperarm01.L": (0.2, 1, 0), "upperarm01.R": (-0.2, 1, 0),
                "lowerarm01.L": (0.1, 1, 0.1), "lowerarm01.R": (-0.1, 1, 0.1)},
    "crossed-arms": {"upperarm01.L": (0.15, -0.7, 0.45), "upperarm01.R": (-0.15, -0.7, 0.45),
                     "lowerarm01.L": (-1, 0.15, 0.25), "lowerarm01.R": (1, 0.2, 0.35)},
}
LEGS = {"upperleg01.L": (0.15, -1, 0.05), "upperleg01.R": (-0.12, -1, 0.0),
        "lowerleg01.L": (0.1, -1, -0.1), "lowerleg01.R": (-0.05, -1, -0.05)}


@pytest.fixture(scope="module")
def model():
    return BodyModel.load()


def make_person(model, pose, seed, shape_sigma=0.7, noise_px=1.5, noise_m=0.02):
    """Truth (shape, rotations, translation, scale) and observations (keypoints px,
    visibility, world m) of a turned, placed person with a bent spine and random shape."""
    rng = np.random.default_rng(seed)
    shape = np.clip(rng.normal(0.0, shape_sigma, model.n_shape), -2.5, 2.5)
    rotations = model.rest_pose()
    rotations[0] = axis_angle_to_matrix(np.array([0.0, rng.uniform(-0.5, 0.5), 0.0]))
    for bone in ("spine04", "spine02", "neck01"):
        rotations[model.joint_names.index(bone)] = axis_angle_to_matrix(rng.normal(0, 0.08, 3))
    rotations = aim_limbs(model, rotations, {**POSES[pose], **LEGS}, shape)
    translation, scale = np.array([rng.uniform(-0.1, 0.1), rng.uniform(-0.1, 0.1), 0.0]), 0.95
    pixels, world = observe_landmarks(model, shape, rotations, translation, scale, RESOLUTION)
    pixels = pixels + rng.normal(0, noise_px, pixels.shape)
    world = world + rng.normal(0, noise_m, world.shape)
    return (shape, rotations, translation, scale), (pixels, np.ones(33), world)


def core_joints(model, shape, rotations):
    _, _, landmarks = model.posed(shape, rotations)
    return (landmarks - landmarks[[23, 24]].mean(axis=0))[list(CORE_LANDMARKS)]


# --- rotation helpers ------------------------------------------------------------------------

def test_axis_angle_gives_the_rotation_of_the_right_angle_about_the_axis():
    vector = np.array([0.3, -0.4, 1.2])
    rotation = axis_angle_to_matrix(vector)
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(rotation @ vector, vector, atol=1e-12)  # the axis stays
    assert rotation_angle(rotation) == pytest.approx(np.linalg.norm(vector), abs=1e-9)
    # A quarter turn about +Z takes +X to +Y
    np.testing.assert_allclose(axis_angle_to_matrix(np.array([0, 0, np.pi / 2])) @ [1, 0, 0],
                               [0, 1, 0], atol=1e-12)


@pytest.mark.parametrize("b", [(0.0, 1.0, 0.0), (-1.0, 0.0, 0.0), (1.0, 1e-12, 0.0)],
                         ids=["perpendicular", "opposite", "same"])
def test_rotation_between_takes_one_direction_onto_the_other(b):
    a, b = np.array([1.0, 0.0, 0.0]), np.array(b)
    rotation = rotation_between(a, b)
    np.testing.assert_allclose(rotation @ a, b / np.linalg.norm(b), atol=1e-9)
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)


# --- initialisation --------------------------------------------------------------------------

@pytest.mark.parametrize("pose", POSES)
def test_initial_pose_points_every_limb_along_its_world_segment(model, pose):
    _, (_, _, world) = make_person(model, pose, seed=1, noise_m=0.0)
    _, _, landmarks = model.posed(None, initial_pose(model, world))
    target = body_fit.blazepose_world_to_model(world)
    index = {n: i for i, n in enumerate(body_fit.LANDMARK_NAMES)}

    def direction(points, heads, tips):
        d = points[[index[n] for n in tips]].mean(0) - points[[index[n] for n in heads]].mean(0)
        return d / np.linalg.norm(d)

    for _, heads, tips in body_fit.LIMB_SEGMENTS:
        cosine = direction(landmarks, heads, tips) @ direction(target, heads, tips)
        assert cosine > 0.999, (heads, tips)


# --- recovery --------------------------------------------------------------------------------

@pytest.mark.parametrize("pose", POSES)
def test_fit_recovers_every_limb_of_a_known_pose(model, pose):
    truth, (keypoints, visibility, world) = make_person(model, pose, seed=2)
    fit = fit_body(model, keypoints, visibility, world, resolution=RESOLUTION)
    assert fit.converged, fit.reason
    errors = np.linalg.norm(core_joints(model, fit.shape, fit.rotations)
                            - core_joints(model, truth[0], truth[1]), axis=1)
    initial = np.linalg.norm(core_joints(model, None, initial_pose(model, world))
                             - core_joints(model, truth[0], truth[1]), axis=1)
    assert errors.mean() < 0.025 and errors.max() < 0.05, errors  # metres
    assert errors.mean() < 0.6 * initial.mean()  # the optimisation beats the closed form
    assert fit.residual_px < 2.5


def test_fit_recovers_a_known_shape_and_placement_from_clean_observations(model):
    truth, (keypoints, visibility, world) = make_person(model, "A-pose", seed=3, shape_sigma=1.0,
                                                        noise_px=0.0, noise_m=0.0)
    fit = fit_body(model, keypoints, visibility, world, resolution=RESOLUTION)
    rest_error = np.linalg.norm(model.rest_landmarks(fit.shape) - model.rest_landmarks(truth[0]),
                                axis=1)[list(CORE_LANDMARKS)]
    mean_error = np.linalg.norm(model.rest_landmarks(None) - model.rest_landmarks(truth[0]),
                                axis=1)[list(CORE_LANDMARKS)]
    assert rest_error.mean() < 0.3 * mean_error.mean(), (rest_error.mean(), mean_error.mean())
    assert fit.scale == pytest.approx(truth[3], rel=0.02)
    # Placement: the hips land where they were (the model origin alone is not identifiable)
    _, _, fitted = model.posed(fit.shape, fit.rotations, fit.translation, fit.scale)
    _, _, true = model.posed(truth[0], truth[1], truth[2], truth[3])
    np.testing.assert_allclose(fitted[[23, 24], :2].mean(0), true[[23, 24], :2].mean(0), atol=0.004)
    assert fit.residual_px < 0.5


def test_fitted_mesh_is_aligned_with_the_keypoints_in_the_crop(model):
    _, (keypoints, visibility, world) = make_person(model, "T-pose", seed=4)
    fit = fit_body(model, keypoints, visibility, world, resolution=RESOLUTION)
    vertices, _, landmarks = model.posed(fit.shape, fit.rotations, fit.translation, fit.scale)
    np.testing.assert_allclose(vertices, fit.vertices)
    pixels = body_fit.world_to_pixel(landmarks, body_fit.CROP_RECT, (RESOLUTION, RESOLUTION))
    assert np.median(np.linalg.norm(pixels - keypoints, axis=1)) < 3.0
    # Hips at depth 0 and the body inside the crop square
    assert abs(landmarks[[23, 24], 2].mean()) < 1e-9
    assert np.abs(vertices[:, :2]).max() < 1.2


# --- fallbacks -------------------------------------------------------------------------------

def _degrade(kind, keypoints, visibility, world):
    keypoints, visibility = keypoints.copy(), visibility.copy()
    world = None if world is None else world.copy()
    if kind == "no world":
        world = None
    elif kind == "world NaN":
        world[11] = np.nan
    elif kind == "world collapsed":
        world[:] = world[0]
    elif kind == "keypoints NaN":
        keypoints[:] = np.nan
    elif kind == "keypoints collapsed":
        keypoints[:] = keypoints[0]
    elif kind == "cut by the frame":
        visibility[23:] = 0.0
    elif kind == "back view":
        world = world * np.array([-1.0, 1.0, -1.0])  # turned half a turn about the vertical
    return keypoints, visibility, world


@pytest.mark.parametrize("kind, words", [
    ("no world", "world"), ("world NaN", "world"), ("world collapsed", "collapsed"),
    ("keypoints NaN", "main joints"), ("keypoints collapsed", "collapse"),
    ("cut by the frame", "main joints"), ("back view", "back view")])
def test_bad_inputs_fall_back_with_a_reason_and_finite_numbers(model, kind, words):
    _, observed = make_person(model, "A-pose", seed=5)
    fit = fit_body(model, *_degrade(kind, *observed), resolution=RESOLUTION)
    assert not fit.converged
    assert words in fit.reason
    assert np.isfinite(fit.vertices).all() and np.isfinite(fit.translation).all()
    assert np.isfinite(fit.scale) and fit.scale > 0


def test_a_sitting_person_falls_back(model):
    rotations = aim_limbs(model, model.rest_pose(), {"upperleg01.L": (0.1, 0, 1),
                                                     "upperleg01.R": (-0.1, 0, 1),
                                                     "lowerleg01.L": (0, -1, 0),
                                                     "lowerleg01.R": (0, -1, 0)})
    pixels, world = observe_landmarks(model, None, rotations, np.zeros(3), 0.9, RESOLUTION)
    fit = fit_body(model, pixels, np.ones(33), world, resolution=RESOLUTION)
    assert not fit.converged and "sitting" in fit.reason


def test_keypoints_far_from_any_body_do_not_converge(model):
    _, (keypoints, visibility, world) = make_person(model, "T-pose", seed=6)
    scrambled = np.random.default_rng(0).permutation(keypoints)
    fit = fit_body(model, scrambled, visibility, world, resolution=RESOLUTION)
    assert not fit.converged and "did not converge" in fit.reason
    assert np.isfinite(fit.vertices).all()


def test_the_crop_size_must_be_known(model):
    _, (keypoints, visibility, world) = make_person(model, "T-pose", seed=6)
    with pytest.raises(ValueError, match="resolution"):
        fit_body(model, keypoints, visibility, world)
