"""Fitting the face model to landmarks: recovery of known shape and pose from synthetic
landmarks, robustness, pixel alignment of the mesh, depth placement and a white furnace."""

from __future__ import annotations

import numpy as np
import pytest

from relightcli.errors import InputError
from relightcli.geometry.face_fit import face_mesh, fit_face, solve_box_qp
from relightcli.geometry.face_model import (
    FaceModel,
    rotation_angle_deg,
    rotation_matrix,
    transform,
    world_to_pixel,
)

RECT = (-0.5, 0.5, 1.2, 2.2)          # the crop's world rectangle (metres of the body)
RESOLUTION = (128, 128)
SCALE = 0.05                           # 1 cm of face = 0.05 world units = 6.4 px
TRANSLATION = np.array([0.02, 1.68, 0.0])
OUTLIERS = [3, 20, 45, 58]


@pytest.fixture(scope="module")
def model():
    return FaceModel.load()


def synthetic_face(model, seed, angles, identity_sigma=1.0, expressions=None):
    """Known coefficients and pose, and the exact landmark pixels they give."""
    rng = np.random.default_rng(seed)
    identity = rng.normal(0.0, identity_sigma, model.n_identity)
    expression = np.zeros(model.n_expression)
    for name, value in (expressions or {}).items():
        expression[model.expression_names.index(name)] = value
    rotation = rotation_matrix(*angles)
    points = transform(model.landmarks(identity, expression), SCALE, rotation, TRANSLATION)
    truth = dict(identity=identity, expression=expression, rotation=rotation,
                 vertices=transform(model.vertices(identity, expression), SCALE,
                                    rotation, TRANSLATION))
    return world_to_pixel(points, RECT, RESOLUTION), truth


def face_error_cm(model, fit, truth, axes=slice(0, 2)):
    """Mean image-plane distance (cm) between fitted and true face-region vertices."""
    diff = (fit.vertices() - truth["vertices"])[model.face_region][:, axes]
    return float(np.linalg.norm(diff, axis=1).mean() / (SCALE))


POSES = [(0, 0, 0), (25, 0, 0), (-20, 10, 5), (10, -15, -20), (35, 5, 10)]


@pytest.mark.parametrize("angles", POSES)
def test_exact_landmarks_recover_pose_within_one_degree(model, angles):
    pixels, truth = synthetic_face(model, 1, angles, expressions={"jawOpen": 0.3})
    fit = fit_face(pixels, model, RECT, RESOLUTION, landmark_sigma_px=0.1)
    assert rotation_angle_deg(fit.rotation, truth["rotation"]) < 1.0
    assert abs(fit.scale / (SCALE) - 1.0) < 0.03


@pytest.mark.parametrize("angles", POSES)
def test_exact_landmarks_recover_the_visible_face_shape(model, angles):
    pixels, truth = synthetic_face(model, 2, angles, expressions={"mouthSmile_L": 0.5})
    fit = fit_face(pixels, model, RECT, RESOLUTION, landmark_sigma_px=0.1)
    # Within 1.5 mm on average in the image plane
    assert face_error_cm(model, fit, truth) < 0.15
    assert fit.residual_px < 0.05


@pytest.mark.parametrize("name, value", [("jawOpen", 0.6), ("browInnerUp_L", 0.8),
                                         ("mouthPucker", 0.7), ("eyeBlink_R", 0.9)])
def test_exact_landmarks_recover_a_known_expression(model, name, value):
    pixels, truth = synthetic_face(model, 3, (10, 5, 0), identity_sigma=0.5,
                                   expressions={name: value})
    fit = fit_face(pixels, model, RECT, RESOLUTION, landmark_sigma_px=0.1)
    assert abs(fit.expression[model.expression_names.index(name)] - value) < 0.15


@pytest.mark.parametrize("angles", POSES[:3])
def test_dominant_identity_modes_are_recovered(model, angles):
    pixels, truth = synthetic_face(model, 4, angles)
    fit = fit_face(pixels, model, RECT, RESOLUTION, landmark_sigma_px=0.1)
    np.testing.assert_allclose(fit.identity[:3], truth["identity"][:3], atol=0.35)


@pytest.mark.parametrize("seed", [5, 6, 7])
def test_one_pixel_noise_keeps_pose_within_three_degrees(model, seed):
    pixels, truth = synthetic_face(model, seed, (15, -10, 5), expressions={"jawOpen": 0.4})
    noisy = pixels + np.random.default_rng(seed).normal(0.0, 1.0, pixels.shape)
    fit = fit_face(noisy, model, RECT, RESOLUTION)
    assert rotation_angle_deg(fit.rotation, truth["rotation"]) < 3.0
    # The fitted landmarks sit closer to the truth than the noisy input does
    assert np.sqrt(np.mean(np.sum((fit.landmarks_px() - pixels) ** 2, axis=1))) < 1.0
    assert face_error_cm(model, fit, truth) < 0.35


def corrupted(pixels, seed):
    bad = pixels.copy()
    bad[OUTLIERS] += np.random.default_rng(seed).choice([-1, 1], (4, 2)) * 12.0
    return bad


@pytest.mark.parametrize("seed", [8, 9])
def test_robust_loss_ignores_four_wrong_landmarks(model, seed):
    pixels, truth = synthetic_face(model, seed, (-15, 5, 0))
    fit = fit_face(corrupted(pixels, seed), model, RECT, RESOLUTION, landmark_sigma_px=0.3)
    assert rotation_angle_deg(fit.rotation, truth["rotation"]) < 1.5
    assert not fit.inliers[OUTLIERS].any() and fit.inliers.sum() >= 60
    assert face_error_cm(model, fit, truth) < 0.2


@pytest.mark.parametrize("seed", [8, 9])
def test_without_the_robust_loss_the_outliers_pull_the_fit(model, seed):
    pixels, truth = synthetic_face(model, seed, (-15, 5, 0))
    bad = corrupted(pixels, seed)
    plain = fit_face(bad, model, RECT, RESOLUTION, landmark_sigma_px=0.3, robust=False)
    robust = fit_face(bad, model, RECT, RESOLUTION, landmark_sigma_px=0.3)
    assert face_error_cm(model, plain, truth) > 2.0 * face_error_cm(model, robust, truth)


def test_zero_weights_equal_missing_landmarks(model):
    pixels, _ = synthetic_face(model, 10, (5, 5, 5))
    bad = corrupted(pixels, 10)
    weights = np.ones(68)
    weights[OUTLIERS] = 0.0
    missing = bad.copy()
    missing[OUTLIERS] = np.nan
    a = fit_face(bad, model, RECT, RESOLUTION, weights=weights, robust=False)
    b = fit_face(missing, model, RECT, RESOLUTION, robust=False)
    np.testing.assert_allclose(a.vertices(), b.vertices(), atol=1e-9)


def test_too_few_landmarks_is_an_input_error(model):
    pixels, _ = synthetic_face(model, 11, (0, 0, 0))
    pixels[7:] = np.nan
    with pytest.raises(InputError, match="usable face landmarks"):
        fit_face(pixels, model, RECT, RESOLUTION)


def test_wrong_landmark_shape_is_an_input_error(model):
    with pytest.raises(InputError, match="shape"):
        fit_face(np.zeros((5, 2)), model, RECT, RESOLUTION)


def test_fitted_mesh_projects_onto_the_landmarks(model):
    pixels, _ = synthetic_face(model, 12, (20, -5, 10))
    fit = fit_face(pixels, model, RECT, RESOLUTION, landmark_sigma_px=0.1)
    mesh = face_mesh(fit).to_trimesh()
    projected = world_to_pixel(mesh.vertices[model.landmark_indices], RECT, RESOLUTION)
    assert np.abs(projected - pixels).max() < 0.25


def test_ray_cast_mesh_is_pixel_aligned_at_the_nose_tip(model):
    from relightcli.render.camera import render_pixel_geometry
    from relightcli.render.scene import Scene

    pixels, _ = synthetic_face(model, 13, (0, 0, 0))
    fit = fit_face(pixels, model, RECT, RESOLUTION, landmark_sigma_px=0.1)
    mesh = face_mesh(fit).to_trimesh()
    scene = Scene.from_trimesh(mesh)
    geometry = render_pixel_geometry(scene, RECT, RESOLUTION)
    col, row = np.rint(pixels[30]).astype(int)
    nose = mesh.vertices[model.landmark_indices[30]]
    assert geometry.mask[row, col]
    # The hit at the nose-tip pixel is the front of the nose, within half a pixel's depth
    hit_z = scene.to_world(geometry.position[row, col])[2]
    assert abs(hit_z - nose[2]) < 0.5 * (RECT[1] - RECT[0]) / 128


def test_depth_map_places_the_face_on_the_surface(model):
    pixels, _ = synthetic_face(model, 14, (10, 0, 0))
    fit = fit_face(pixels, model, RECT, RESOLUTION, landmark_sigma_px=0.1)
    depth = np.full((128, 128), 0.25, np.float32)
    lm = fit.landmarks_px()
    rows, cols = np.rint(lm[17:, 1]).astype(int), np.rint(lm[17:, 0]).astype(int)
    z = transform(model.landmarks(fit.identity, fit.expression), fit.scale, fit.rotation,
                  fit.translation)[17:, 2]
    depth[rows, cols] = 0.25 + z        # the surface the landmarks lie on, shifted by 0.25
    placed = fit_face(pixels, model, RECT, RESOLUTION, landmark_sigma_px=0.1, depth=depth)
    assert placed.translation[2] == pytest.approx(0.25, abs=1e-6)


def test_box_qp_matches_brute_force_on_a_small_problem():
    rng = np.random.default_rng(15)
    a = rng.normal(size=(6, 3))
    hessian, gradient = a.T @ a + 0.1 * np.eye(3), rng.normal(size=3) * 3
    lower, upper = np.array([-np.inf, -0.2, 0.0]), np.array([np.inf, 0.3, 0.5])
    x = solve_box_qp(hessian, gradient, lower, upper)
    grid = np.stack(np.meshgrid(np.linspace(-0.2, 0.3, 201), np.linspace(0, 0.5, 201)), -1)
    grid = grid.reshape(-1, 2)
    # For each grid (x1, x2), the unbounded x0 minimises exactly
    x0 = (gradient[0] - grid @ hessian[0, 1:]) / hessian[0, 0]
    pts = np.column_stack([x0, grid])
    values = 0.5 * np.einsum("ni,ij,nj->n", pts, hessian, pts) - pts @ gradient
    value = 0.5 * x @ hessian @ x - gradient @ x
    assert value <= values.min() + 1e-9
    assert np.all(x >= lower - 1e-12) and np.all(x <= upper + 1e-12)


def test_white_furnace_on_the_forehead(model):
    from relightcli.render.camera import render_pixel_geometry
    from relightcli.render.environment import EnvironmentLight
    from relightcli.render.integrator import shade_environment
    from relightcli.render.scene import Scene

    pixels, _ = synthetic_face(model, 16, (0, 0, 0))
    fit = fit_face(pixels, model, RECT, RESOLUTION, landmark_sigma_px=0.1)
    scene = Scene.from_trimesh(face_mesh(fit).to_trimesh())
    geometry = render_pixel_geometry(scene, RECT, RESOLUTION)
    # Forehead: above the brows, between the outer brow ends, facing the camera
    lm = fit.landmarks_px()
    rows, cols = np.mgrid[0:128, 0:128]
    brow_row = lm[17:27, 1].min()
    region = (geometry.mask & (rows < brow_row - 2) & (rows > brow_row - 8)
              & (cols > lm[19, 0]) & (cols < lm[24, 0]) & (geometry.normal[..., 2] > 0.9))
    assert region.sum() >= 10
    radiance = np.array([0.5, 1.0, 2.0], np.float32)
    light = EnvironmentLight(np.broadcast_to(radiance, (8, 16, 3)).copy())
    result = shade_environment(scene, geometry, light, spp=64)
    shading = result.mean[region]
    np.testing.assert_allclose(shading, np.broadcast_to(radiance, shading.shape), rtol=0.02)
