"""Reconstruction against rendered ground truth: the MakeHuman body and an arm in front of a
torso (maps from our own embreex ray casts, tests/geometry/geometry_truth.py)."""

from __future__ import annotations

import numpy as np
import scipy.spatial
import trimesh

from geometry_truth import render_maps
from relightcli.geometry.mesh import reconstruct_mesh
from relightcli.geometry.normal_integration import integrate_normals
from relightcli.geometry.smoothing import smooth_mesh


def _pixel(maps):
    return (maps.rect[1] - maps.rect[0]) / maps.mask.shape[1]


def _chamfer(a, b, samples=20_000):
    """Symmetric mean closest-point distance between surface samples."""
    pa, _ = trimesh.sample.sample_surface(a, samples, seed=0)
    pb, _ = trimesh.sample.sample_surface(b, samples, seed=1)
    return 0.5 * (scipy.spatial.cKDTree(pb).query(pa)[0].mean()
                  + scipy.spatial.cKDTree(pa).query(pb)[0].mean())


def _body_mesh(maps, smooth):
    mesh = reconstruct_mesh(maps.mask, maps.front_depth, maps.back_depth, maps.rect).to_trimesh()
    return smooth_mesh(mesh) if smooth else mesh


def test_body_depth_error_on_mask(body_maps):
    # Re-rendered front depth over every pixel both cover, rim included: measured 0.003 px
    mesh = _body_mesh(body_maps, smooth=False)
    again = render_maps(mesh, body_maps.rect, *body_maps.mask.shape)
    both = again.mask & body_maps.mask
    error = np.abs(again.front_depth - body_maps.front_depth)[both].mean()
    assert error < 0.02 * _pixel(body_maps)


def test_body_chamfer_distance(body_maps, body_mesh):
    # The pixel-centre surface stops half a pixel inside the silhouette: measured 0.54 px
    assert _chamfer(_body_mesh(body_maps, smooth=False), body_mesh) < 0.75 * _pixel(body_maps)


def test_smoothed_body_chamfer_distance(body_maps, body_mesh):
    # 10 smoothing steps move the surface by well under a pixel: measured 0.73 px
    assert _chamfer(_body_mesh(body_maps, smooth=True), body_mesh) < 1.0 * _pixel(body_maps)


def _fused_arm_error(arm_maps, sharpness):
    """RMS front-depth error, in pixels, of normals integrated with a depth prior carrying
    one pixel of noise (a net's depth)."""
    pixel = _pixel(arm_maps)
    noise = np.random.default_rng(0).normal(0.0, pixel, arm_maps.front_depth.shape)
    depth = integrate_normals(arm_maps.front_normal, arm_maps.mask, arm_maps.rect,
                              depth_prior=arm_maps.front_depth + noise, sharpness=sharpness)
    error = (depth - arm_maps.front_depth)[arm_maps.mask]
    return np.sqrt(np.mean(error ** 2)) / pixel


def test_normals_clean_a_noisy_depth_prior(arm_maps):
    # One pixel of prior noise -> 0.38 px measured; the arm's jump over the torso stays
    assert _fused_arm_error(arm_maps, sharpness=2.0) < 0.5


def test_plain_least_squares_smears_the_arm(arm_maps):
    # Without the bilateral weights the jump around the arm is smeared: 3.1 px measured
    assert _fused_arm_error(arm_maps, sharpness=0.0) > 2.0


def test_arm_over_torso_mesh_is_watertight_after_smoothing(arm_maps):
    m = arm_maps
    mesh = smooth_mesh(reconstruct_mesh(m.mask, m.front_depth, m.back_depth, m.rect).to_trimesh())
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
