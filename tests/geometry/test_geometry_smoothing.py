"""Cotangent-weighted Laplacian smoothing: flattens noise, keeps planes and spheres, survives
slivers."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.spatial
import trimesh

from relightcli.errors import InputError
from relightcli.geometry.mesh import reconstruct_mesh
from relightcli.geometry.smoothing import (
    cotangent_weights,
    smooth_depth,
    smooth_mesh,
    smooth_normals,
    smooth_vertices,
)


def _jittered_grid(n=12, jitter=0.25, seed=0):
    """Delaunay triangulation of a jittered n x n grid (spacing 1) in the plane z = 0.
    Returns vertices (n*n, 3), faces, interior (n*n,) bool (not on the outer ring)."""
    rng = np.random.default_rng(seed)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    xy = np.column_stack([j.ravel(), i.ravel()]).astype(float)
    interior = ((i > 0) & (i < n - 1) & (j > 0) & (j < n - 1)).ravel()
    xy[interior] += rng.uniform(-jitter, jitter, (interior.sum(), 2))
    faces = scipy.spatial.Delaunay(xy).simplices
    return np.column_stack([xy, np.zeros(n * n)]), faces, interior


def _uniform_step(vertices, faces, step=0.5):
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    total = np.zeros_like(vertices)
    count = np.zeros(len(vertices))
    for a, b in (edges.T, edges[:, ::-1].T):
        np.add.at(total, a, vertices[b])
        np.add.at(count, a, 1)
    return vertices + step * (total / count[:, None] - vertices)


def test_cotangent_weight_matches_closed_form():
    vertices = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.3, 0.7, 0.0]])
    weights = cotangent_weights(vertices, np.array([[0, 1, 2]])).toarray()
    # Edge 1-2 is opposite the corner at vertex 0: cot = (1, 0).(0.3, 0.7) / |cross| = 0.3 / 0.7
    assert weights[1, 2] == pytest.approx(0.5 * 0.3 / 0.7, rel=1e-12)


def test_flat_mesh_does_not_drift():
    # Cotangent weights reproduce linear functions: a step leaves interior vertices of a plane
    # in place (only the boundary ring, which has no linear precision, moves)
    vertices, faces, interior = _jittered_grid()
    moved = smooth_vertices(vertices, faces, steps=1) - vertices
    assert np.abs(moved[interior]).max() < 1e-4


def test_uniform_laplacian_would_drift():
    # The same mesh under the umbrella operator: shows the previous test can fail
    vertices, faces, interior = _jittered_grid()
    moved = _uniform_step(vertices, faces) - vertices
    assert np.abs(moved[interior]).max() > 1e-2


def test_noisy_plane_moves_toward_plane():
    vertices, faces, interior = _jittered_grid(n=30, jitter=0.1)
    noisy = vertices.copy()
    noisy[:, 2] = np.random.default_rng(1).normal(0.0, 0.1, len(vertices))
    smoothed = smooth_vertices(noisy, faces)
    before = np.sqrt(np.mean(noisy[interior, 2] ** 2))
    after = np.sqrt(np.mean(smoothed[interior, 2] ** 2))
    assert after < 0.25 * before


def test_sphere_shrinks_less_than_one_and_a_half_percent():
    # Mean-curvature flow shrinks a sphere; 10 steps of 0.5 on a 2562-vertex sphere: 1.4 %
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    radius = np.linalg.norm(smooth_mesh(sphere).vertices, axis=1)
    assert 1.0 - radius.mean() < 0.015


def test_sphere_stays_round():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    radius = np.linalg.norm(smooth_mesh(sphere).vertices, axis=1)
    assert radius.std() < 1e-3


def _sliver_mesh():
    """A jittered grid made hostile: needles (a vertex 1e-12 from its neighbour), caps (a
    vertex almost on the opposite edge), zero-area triangles and repeated vertices."""
    vertices, faces, _ = _jittered_grid(n=10, jitter=0.0)
    vertices = vertices.copy()
    vertices[11] = vertices[12] + [1e-12, 0.0, 0.0]  # needle
    vertices[33] = (vertices[32] + vertices[34]) / 2 + [0.0, 1e-13, 1e-13]  # caps
    vertices[55] = vertices[56]  # coincident: zero-length edge, zero-area triangles
    collinear = np.array([[0.0, 20.0, 0.0], [1.0, 20.0, 0.0], [2.0, 20.0, 0.0]])
    extra = np.arange(len(vertices), len(vertices) + 3)[None, :]
    return np.concatenate([vertices, collinear]), np.concatenate([faces, extra])


def test_slivers_give_finite_vertices():
    vertices, faces = _sliver_mesh()
    assert np.all(np.isfinite(smooth_vertices(vertices, faces)))


def test_slivers_stay_in_bounding_box():
    vertices, faces = _sliver_mesh()
    smoothed = smooth_vertices(vertices, faces)
    assert np.all(smoothed >= vertices.min(axis=0) - 1e-12)
    assert np.all(smoothed <= vertices.max(axis=0) + 1e-12)


def test_slivers_weights_are_bounded():
    vertices, faces = _sliver_mesh()
    weights = cotangent_weights(vertices, faces)
    assert np.all(np.isfinite(weights.data))
    assert weights.data.min() >= 0 and weights.data.max() <= 100.0


def test_smoothing_keeps_reconstruction_watertight():
    mask = np.zeros((32, 32), bool)
    mask[4:28, 6:26] = True
    mesh = reconstruct_mesh(mask, np.full(mask.shape, 0.5), np.full(mask.shape, -0.5),
                            (0.0, 1.0, 0.0, 1.0)).to_trimesh()
    smoothed = smooth_mesh(mesh)
    assert smoothed.is_watertight and smoothed.volume > 0.8 * mesh.volume


@pytest.mark.parametrize("step_size", [0.0, 1.5, float("nan")])
def test_bad_step_size_raises(step_size):
    vertices, faces, _ = _jittered_grid(n=4)
    with pytest.raises(InputError, match="step size"):
        smooth_vertices(vertices, faces, step_size=step_size)


def test_nan_vertices_raise():
    vertices, faces, _ = _jittered_grid(n=4)
    vertices[0, 0] = np.nan
    with pytest.raises(InputError, match="NaN"):
        smooth_vertices(vertices, faces)


# ------------------------------------------------------------------ depth before meshing
def test_smooth_depth_keeps_constants_and_ignores_the_background():
    mask = np.zeros((64, 64), np.float32)
    mask[10:50, 20:40] = 1.0
    depth = np.where(mask > 0, 0.3, -5.0).astype(np.float32)  # far background
    out = smooth_depth(depth, mask, sigma=6.0)
    np.testing.assert_allclose(out[mask > 0], 0.3, rtol=1e-5)
    np.testing.assert_array_equal(out[mask == 0], depth[mask == 0])


def test_smooth_depth_keeps_a_plane_inside_and_removes_ridges():
    rows, cols = np.mgrid[0:96, 0:96].astype(np.float32)
    mask = np.ones((96, 96), np.float32)
    plane = 0.01 * cols - 0.02 * rows
    ridges = 0.05 * np.sin(cols * 2 * np.pi / 8)  # cloth stripes painted into depth
    out = smooth_depth(plane + ridges, mask, sigma=4.0)
    interior = (slice(20, 76), slice(20, 76))
    np.testing.assert_allclose(out[interior], plane[interior], atol=0.05 * 0.01)


@pytest.mark.parametrize("case", ["empty", "one_pixel", "sliver"])
def test_smooth_depth_is_finite_on_tiny_masks(case):
    mask = np.zeros((32, 32), np.float32)
    if case == "one_pixel":
        mask[5, 7] = 1.0
    elif case == "sliver":
        mask[3:29, 16] = 1.0
    depth = np.random.default_rng(0).normal(size=(32, 32)).astype(np.float32)
    out = smooth_depth(depth, mask, sigma=5.0)
    assert np.all(np.isfinite(out))
    if case == "one_pixel":
        assert out[5, 7] == pytest.approx(depth[5, 7], rel=1e-5)


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_smooth_normals_keeps_a_constant_field_and_the_background():
    mask = np.zeros((48, 48), np.float32)
    mask[8:40, 12:30] = 1.0
    normals = np.where(mask[..., None] > 0, _unit(np.array([0.3, -0.2, 0.9])), 0.0).astype(np.float32)
    out = smooth_normals(normals, mask, sigma=4.0)
    np.testing.assert_allclose(out[mask > 0], normals[mask > 0], atol=1e-6)
    np.testing.assert_array_equal(out[mask == 0], normals[mask == 0])


def test_smooth_normals_brings_noisy_normals_closer_and_keeps_them_unit():
    rng = np.random.default_rng(1)
    rows, cols = np.mgrid[0:96, 0:96].astype(np.float32)
    truth = _unit(np.stack([(cols - 48) / 96, (48 - rows) / 96, np.ones_like(cols)], axis=-1))
    noisy = _unit(truth + rng.normal(0, 0.2, truth.shape)).astype(np.float32)
    mask = np.ones((96, 96), np.float32)
    out = smooth_normals(noisy, mask, sigma=2.0)

    def angle(a):
        return np.degrees(np.arccos(np.clip((a * truth).sum(-1), -1, 1)))[10:86, 10:86].mean()

    assert angle(out) < 0.4 * angle(noisy)
    np.testing.assert_allclose(np.linalg.norm(out, axis=-1), 1.0, atol=1e-5)


def test_smooth_normals_is_finite_with_nan_normals_and_an_empty_mask():
    normals = np.random.default_rng(2).normal(size=(24, 24, 3)).astype(np.float32)
    normals[5:9, 5:9] = np.nan
    mask = np.zeros((24, 24), np.float32)
    mask[2:20, 2:20] = 1.0
    assert np.isfinite(smooth_normals(normals, mask, sigma=3.0)[mask > 0]).all()
    empty = smooth_normals(np.nan_to_num(normals), np.zeros((24, 24), np.float32), sigma=3.0)
    np.testing.assert_array_equal(empty, np.nan_to_num(normals))
