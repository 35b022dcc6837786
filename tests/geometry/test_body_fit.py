"""The body fit (relightcli/geometry/body_fit.py): its rotation helpers, the closed-form
initialisation, recovery of known poses and shapes from synthetic BlazePose observations of
the body model itself (observe_landmarks, plus noise), the silhouette term against masks
rasterised from the true body, and clean fallbacks on bad inputs."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from relightcli.geometry import body_fit
from relightcli.geometry.body_fit import (
    CORE_LANDMARKS,
    aim_limbs,
    axis_angle_to_matrix,
    body_silhouette,
    fit_body,
    initial_pose,
    mask_contour,
    observe_landmarks,
    rotation_angle,
    rotation_between,
    silhouette_cover_residuals,
    silhouette_inside_residuals,
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
    # Thighs towards the camera, shins down, hands on the knees
    "sitting": {"upperarm01.L": (0.25, -0.8, 0.5), "upperarm01.R": (-0.25, -0.8, 0.5),
                "lowerarm01.L": (0.0, -0.3, 1), "lowerarm01.R": (0.0, -0.3, 1),
                "upperleg01.L": (0.15, -0.1, 1), "upperleg01.R": (-0.15, -0.1, 1),
                "lowerleg01.L": (0.05, -1, 0.1), "lowerleg01.R": (-0.05, -1, 0.1)},
}
LEGS = {"upperleg01.L": (0.15, -1, 0.05), "upperleg01.R": (-0.12, -1, 0.0),
        "lowerleg01.L": (0.1, -1, -0.1), "lowerleg01.R": (-0.05, -1, -0.05)}


@pytest.fixture(scope="module")
def model():
    return BodyModel.load()


def make_person(model, pose, seed, shape_sigma=0.7, noise_px=1.5, noise_m=0.02, turn=0.0):
    """Truth (shape, rotations, translation, scale) and observations (keypoints px,
    visibility, world m) of a turned, placed person with a bent spine and random shape
    (`turn` radians more about the vertical: pi for a person seen from behind)."""
    rng = np.random.default_rng(seed)
    shape = np.clip(rng.normal(0.0, shape_sigma, model.n_shape), -2.5, 2.5)
    rotations = model.rest_pose()
    rotations[0] = axis_angle_to_matrix(np.array([0.0, turn + rng.uniform(-0.5, 0.5), 0.0]))
    for bone in ("spine04", "spine02", "neck01"):
        rotations[model.joint_names.index(bone)] = axis_angle_to_matrix(rng.normal(0, 0.08, 3))
    rotations = aim_limbs(model, rotations, {**LEGS, **POSES[pose]}, shape)
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
    assert fit.residual_px < 2.5 and fit.faces_camera


@pytest.mark.parametrize("pose", ["T-pose", "crossed-arms"])
def test_fit_recovers_a_person_seen_from_behind(model, pose):
    truth, (keypoints, visibility, world) = make_person(model, pose, seed=7, turn=np.pi)
    fit = fit_body(model, keypoints, visibility, world, resolution=RESOLUTION)
    assert fit.converged, fit.reason
    errors = np.linalg.norm(core_joints(model, fit.shape, fit.rotations)
                            - core_joints(model, truth[0], truth[1]), axis=1)
    assert errors.mean() < 0.025 and errors.max() < 0.05, errors  # metres
    # The fitted torso faces away from the camera, as the true one does
    _, _, landmarks = model.posed(fit.shape, fit.rotations)
    assert body_fit._torso_frame(landmarks)[2, 2] < -0.5 and not fit.faces_camera
    assert fit.residual_px < 2.5


def test_a_side_view_is_not_taken_for_a_left_right_contradiction(model):
    truth, (keypoints, visibility, world) = make_person(model, "A-pose", seed=8, turn=np.pi / 2)
    fit = fit_body(model, keypoints, visibility, world, resolution=RESOLUTION)
    assert "opposite sides" not in fit.reason


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


# --- the silhouette --------------------------------------------------------------------------

def test_inside_residual_is_the_distance_beyond_the_mask_edge():
    outside = np.tile(np.maximum(np.arange(16.0) - 7.0, 0.0), (16, 1))  # mask: columns 0-7
    pixels = np.array([[[3.0, 5.0], [7.25, 5.0], [10.5, 5.5], [18.0, 5.0]]])
    np.testing.assert_allclose(silhouette_inside_residuals(pixels, outside),
                               [[0.0, 0.0, 3.0, 7.5]])  # beyond the crop: the border's


def test_cover_residual_is_the_robust_distance_to_the_nearest_body_point():
    body = np.array([[[0.0, 0.0], [1.0, 0.0]], [[0.0, 0.1], [1.0, 0.0]]])  # 2 parameter sets
    contour = np.array([[0.0, 0.3], [5.0, 0.0]])
    residual = silhouette_cover_residuals(body, contour, pixels_per_unit=10.0, loss_scale=3.0)
    distance = np.array([[3.0, 40.0], [2.0, 40.0]])  # the first set's nearest points, px
    np.testing.assert_allclose(residual, distance * 3.0 / np.sqrt(distance ** 2 + 9.0))
    assert residual.max() < 3.0


def test_mask_contour_leaves_out_the_crop_border_and_other_people():
    mask = np.zeros((32, 32), bool)
    mask[10:32, 4:12] = True   # this person, cut by the bottom edge
    mask[5:9, 25:30] = True    # someone else
    points = mask_contour(mask, 1000, keep=np.array([0.0, 0.0, 16.0, 31.0]))
    assert len(points) > 0
    assert points[:, 1].max() < 31 and points[:, 0].max() < 12
    assert mask[points[:, 1].astype(int), points[:, 0].astype(int)].all()


def wrong_world(model, truth, seed, sigma=0.2, noise_m=0.03):
    """BlazePose-like world landmarks of the true person with each limb turned by a random
    rotation (sigma rad per axis) and noise: a world estimate that is off in depth and angle."""
    rng = np.random.default_rng(seed + 100)
    rotations = truth[1].copy()
    for bone in ("upperarm01.L", "upperarm01.R", "lowerarm01.L", "lowerarm01.R", "spine02",
                 "upperleg01.L", "upperleg01.R", "lowerleg01.L", "lowerleg01.R"):
        b = model.joint_names.index(bone)
        rotations[b] = rotations[b] @ axis_angle_to_matrix(rng.normal(0, sigma, 3))
    _, world = observe_landmarks(model, truth[0], rotations, truth[2], truth[3], RESOLUTION)
    return world + rng.normal(0, noise_m, world.shape)


def iou(a, b):
    return (a & b).sum() / (a | b).sum()


@pytest.fixture(scope="module")
def silhouette_cases(model):
    """Per person (4 poses, 2 seeds): the true mask, the mask dilated by 10 px (clothes), and
    fits without a silhouette, with the true one and with the dilated one, from 4 px keypoints
    and a wrong-ish world. Rows: (2D joint cm, 3D joint cm, IoU with the true mask, fitted
    body area / true area)."""
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (21, 21))
    rows = {"none": [], "mask": [], "dilated": []}
    for pose in POSES:
        for seed in (0, 1):
            truth, (keypoints, visibility, _) = make_person(model, pose, seed, noise_px=4.0)
            world = wrong_world(model, truth, seed)
            vertices, _, _ = model.posed(truth[0], truth[1], truth[2], truth[3])
            mask = body_silhouette(model, vertices, RESOLUTION)
            dilated = cv2.dilate(mask.astype(np.uint8), disc).astype(np.float32)
            for key, silhouette in (("none", None), ("mask", mask.astype(np.float32)),
                                    ("dilated", dilated)):
                fit = fit_body(model, keypoints, visibility, world, silhouette,
                               resolution=RESOLUTION)
                assert fit.silhouette_used == (silhouette is not None)
                error = (core_joints(model, fit.shape, fit.rotations)
                         - core_joints(model, truth[0], truth[1]))
                body = body_silhouette(model, fit.vertices, RESOLUTION)
                rows[key].append((100 * np.linalg.norm(error[:, :2], axis=1).mean(),
                                  100 * np.linalg.norm(error, axis=1).mean(),
                                  iou(body, mask), body.sum() / mask.sum()))
    return {key: np.array(value) for key, value in rows.items()}


def test_silhouette_reduces_the_joint_error_and_raises_the_iou(silhouette_cases):
    none, mask = silhouette_cases["none"], silhouette_cases["mask"]
    # The mask sees the image plane only: the depth error of the wrong world stays
    assert mask[:, 0].mean() < 0.98 * none[:, 0].mean()   # 2D joint error, cm
    assert mask[:, 1].mean() < none[:, 1].mean() + 0.05   # 3D joint error, cm
    assert mask[:, 2].mean() > none[:, 2].mean() + 0.04   # IoU with the true silhouette
    assert (mask[:, 2] >= none[:, 2] - 0.01).all()


def test_a_dilated_silhouette_does_not_inflate_the_body(silhouette_cases):
    none, dilated = silhouette_cases["none"], silhouette_cases["dilated"]
    # 10 px of clothes around a ~240 px tall body would add about a third of its area
    assert dilated[:, 3].max() < 1.2 and dilated[:, 3].mean() < none[:, 3].mean() + 0.05
    assert dilated[:, 2].mean() > none[:, 2].mean() - 0.03


@pytest.mark.parametrize("kind", ["NaN", "empty", "full"])
def test_unusable_silhouettes_fall_back_to_no_silhouette_term(model, kind):
    _, (keypoints, visibility, world) = make_person(model, "A-pose", seed=2)
    silhouette = {"NaN": np.full((RESOLUTION, RESOLUTION), np.nan),
                  "empty": np.zeros((RESOLUTION, RESOLUTION)),
                  "full": np.ones((RESOLUTION, RESOLUTION))}[kind]
    fit = fit_body(model, keypoints, visibility, world, silhouette)
    plain = fit_body(model, keypoints, visibility, world, resolution=RESOLUTION)
    assert fit.converged and not fit.silhouette_used
    np.testing.assert_allclose(fit.vertices, plain.vertices)


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
    elif kind == "sides disagree":  # the world turned half a turn, the keypoints not
        world = world * np.array([-1.0, 1.0, -1.0])
    return keypoints, visibility, world


@pytest.mark.parametrize("kind, words", [
    ("no world", "world"), ("world NaN", "world"), ("world collapsed", "collapsed"),
    ("keypoints NaN", "main joints"), ("keypoints collapsed", "collapse"),
    ("cut by the frame", "main joints"), ("sides disagree", "opposite sides")])
def test_bad_inputs_fall_back_with_a_reason_and_finite_numbers(model, kind, words):
    _, observed = make_person(model, "A-pose", seed=5)
    fit = fit_body(model, *_degrade(kind, *observed), resolution=RESOLUTION)
    assert not fit.converged
    assert words in fit.reason
    assert np.isfinite(fit.vertices).all() and np.isfinite(fit.translation).all()
    assert np.isfinite(fit.scale) and fit.scale > 0


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


# --- the turn's sign -------------------------------------------------------------------------

def turned_person(model, yaw, seed=11):
    """A person in the A-pose turned `yaw` radians about the vertical (torso_yaw's sense)."""
    truth, (keypoints, visibility, world) = make_person(model, "A-pose", seed, noise_px=0.5, noise_m=0.0)
    world = body_fit.turn_world(world, yaw)
    shape, rotations, _, _ = truth
    rotations = rotations.copy()
    _, _, landmarks = model.posed(shape, rotations)
    turn = axis_angle_to_matrix(np.array([0.0, yaw - body_fit.torso_yaw(landmarks), 0.0]))
    rotations[0] = turn @ rotations[0]
    keypoints, _ = observe_landmarks(model, shape, rotations, np.zeros(3), 0.95, RESOLUTION)
    return keypoints, visibility, world


def image_landmarks(world):
    """BlazePose's image landmarks (x, y, z in one pixel unit, z toward the camera negative) of
    world landmarks, 300 px a metre."""
    return np.asarray(world) * 300.0 + np.array([256.0, 256.0, 0.0])


def test_depth_side_says_which_side_is_farther_in_torso_lengths():
    _, (_, _, world) = make_person(BodyModel.load(), "A-pose", seed=3, noise_m=0.0)
    for yaw in (0.4, -0.4):
        side = body_fit.depth_side(image_landmarks(body_fit.turn_world(world, yaw)))
        assert np.sign(side) == np.sign(yaw) and 0.1 < abs(side) < 2.0
    # in torso lengths: the same at any pixel scale
    turned = image_landmarks(body_fit.turn_world(world, 0.4))
    assert body_fit.depth_side(turned * 3.0) == pytest.approx(body_fit.depth_side(turned))
    turned[11, 2] = np.nan
    assert np.isnan(body_fit.depth_side(turned))


def test_turn_world_turns_the_torso_about_the_hips_and_keeps_the_bones(model):
    _, (_, _, world) = make_person(model, "T-pose", seed=4, noise_m=0.0)
    turned = body_fit.turn_world(world, 0.6)
    assert body_fit.torso_yaw(body_fit.blazepose_world_to_model(turned)) == pytest.approx(0.6, abs=1e-9)
    np.testing.assert_allclose(turned[[23, 24]].mean(axis=0), world[[23, 24]].mean(axis=0), atol=1e-12)
    distances = lambda points: np.linalg.norm(points[:, None] - points[None], axis=-1)  # noqa: E731
    np.testing.assert_allclose(distances(turned), distances(world), atol=1e-12)


def test_a_firm_depth_witness_refits_the_turn_the_world_landmarks_mirrored(model):
    yaw = 0.45  # 26 degrees; BlazePose's world landmarks say -26
    keypoints, visibility, world = turned_person(model, yaw)
    wrong = body_fit.turn_world(world, -yaw)

    def fitted_yaw(fit):
        _, _, landmarks = model.posed(fit.shape, fit.rotations)
        return body_fit.torso_yaw(landmarks)

    plain = fit_body(model, keypoints, visibility, wrong, resolution=RESOLUTION)
    assert plain.converged and fitted_yaw(plain) < 0 and not plain.turn_mirrored
    refit = fit_body(model, keypoints, visibility, wrong, resolution=RESOLUTION, turn_witness=1.0)
    assert refit.converged and refit.turn_mirrored
    assert fitted_yaw(refit) == pytest.approx(yaw, abs=np.radians(6))
    assert refit.residual_px <= plain.residual_px + 0.5
    # a witness that agrees with the fit, or a faint one, changes nothing
    for side in (-1.0, 0.3, float("nan")):
        same = fit_body(model, keypoints, visibility, wrong, resolution=RESOLUTION, turn_witness=side)
        assert not same.turn_mirrored
        np.testing.assert_array_equal(same.vertices, plain.vertices)
