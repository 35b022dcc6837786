"""Shadow rays lifted off the triangles toward smoother shading normals
(relightcli.render.estimators.lifted_origins): no staircase of facets at a sun's terminator,
and the cast shadows of other surfaces kept."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from render_testing import floor_under_a_square, one_hot_map, quad

from relightcli.io.envmap import texel_solid_angles, uv_to_direction
from relightcli.render.camera import render_pixel_geometry
from relightcli.render.environment import EnvironmentLight
from relightcli.render.estimators import lifted_origins
from relightcli.render.integrator import shade_environment
from relightcli.render.inverse import light_transport
from relightcli.render.scene import Scene
from relightcli.stages.shading import SHADOW_LIFT

# A small sun low over the ball's right side, toward the camera (0.88, 0.27, 0.38): its
# terminator crosses what the camera sees
HEIGHT, ROW, COL = 256, 105, 417


def _coarse_ball():
    """A smooth-shaded icosphere of 320 triangles seen from +Z, a lone sun, and the cosine of
    each pixel's shading normal to it."""
    scene = Scene.from_trimesh(trimesh.creation.icosphere(subdivisions=2, radius=1.0))
    hits = render_pixel_geometry(scene, (-1.1, 1.1, -1.1, 1.1), (96, 96))
    light = EnvironmentLight(one_hot_map(HEIGHT, ROW, COL, 1000.0))
    sun = uv_to_direction((COL + 0.5) / (2 * HEIGHT), (ROW + 0.5) / HEIGHT)
    cosine = np.where(hits.mask, hits.normal @ sun, 0.0)
    return scene, hits, light, cosine


def test_the_scene_knows_its_edge_length():
    scene = Scene(*quad(-1.0, 1.0, -1.0, 1.0, 0.0))
    # each triangle has two sides of 2 and a diagonal: the median edge is a side
    assert scene.edge_length == pytest.approx(2.0)


def test_a_coarse_smooth_ball_under_a_low_sun_has_no_facets_at_its_terminator():
    scene, hits, light, cosine = _coarse_ball()
    # the shading of the smooth sphere: the sun's radiance x its solid angle x cos / pi
    scale = 1000.0 * texel_solid_angles(HEIGHT, 2 * HEIGHT)[ROW, COL] / np.pi
    exact = scale * np.maximum(cosine, 0.0)
    near, lit = (cosine > 0.02) & (cosine <= 0.3), cosine > 0.3
    assert near.sum() > 500 and lit.sum() > 2000
    # From the triangles: facets the shading normal turns to the sun but whose own plane
    # faces away are black (the staircase this is about)
    plain = shade_environment(scene, hits, light, spp=8, lift=0.0).mean[..., 0]
    assert (plain[near] < 0.5 * exact[near]).mean() > 0.02
    # Lifted: nothing on a convex ball blocks the sun, every pixel it faces gets it (to within
    # the sun texel's own extent, 0.7 degrees: the cosine varies by up to 0.006 across it)
    lifted = shade_environment(scene, hits, light, spp=8, lift=SHADOW_LIFT).mean[..., 0]
    np.testing.assert_allclose(lifted[near | lit], exact[near | lit], rtol=0.02, atol=0.006 * scale)


def test_lifted_rays_keep_a_cast_shadow_and_its_umbra_black():
    # A floor under a floating square, a sun low in +X+Z; the floor and the square are flat
    # (shading normal = geometric normal): nothing is lifted, the umbra stays exactly black
    scene, hits = floor_under_a_square(64)
    height, row, col = 128, 40, 224
    light = EnvironmentLight(one_hot_map(height, row, col, 50.0))
    plain = shade_environment(scene, hits, light, spp=8, lift=0.0)
    lifted = shade_environment(scene, hits, light, spp=8, lift=SHADOW_LIFT)
    np.testing.assert_array_equal(lifted.mean, plain.mean)
    d = uv_to_direction((col + 0.5) / (2 * height), (row + 0.5) / height)
    p = scene.to_world(hits.position.reshape(-1, 3)).reshape(64, 64, 3)
    floor = hits.mask & (np.abs(p[..., 2]) < 1e-4)
    umbra = floor & (np.max(np.abs(p[..., :2] + (1.0 / d[2]) * d[:2]), axis=-1) < 0.3)
    assert umbra.sum() > 10 and np.all(lifted.mean[umbra] == 0.0)


def test_a_ball_over_a_floor_still_shadows_it_when_lifted():
    # Smooth normals on the ball (lifted rays leave it), flat floor: the ball's shadow stays
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    ball.apply_translation([0.0, 0.0, 1.0])
    floor = trimesh.Trimesh(*quad(-4.0, 4.0, -4.0, 4.0, 0.0), process=False)
    scene = Scene.from_trimesh(trimesh.util.concatenate([floor, ball]))
    hits = render_pixel_geometry(scene, (-4.0, 4.0, -4.0, 4.0), (64, 64))
    height, row, col = 64, 20, 112  # 38 degrees over the floor
    light = EnvironmentLight(one_hot_map(height, row, col, 50.0))
    lifted = shade_environment(scene, hits, light, spp=8, lift=SHADOW_LIFT)
    d = uv_to_direction((col + 0.5) / (2 * height), (row + 0.5) / height)
    p = scene.to_world(hits.position.reshape(-1, 3)).reshape(64, 64, 3)
    on_floor = hits.mask & (np.abs(p[..., 2]) < 1e-4)
    # the floor points whose ray toward the sun passes within 0.35 of the ball's centre
    t = (1.0 - p[..., 2]) / d[2]
    miss = np.linalg.norm(p[..., :2] + t[..., None] * d[:2], axis=-1)
    umbra, lit = on_floor & (miss < 0.35), on_floor & (miss > 0.8)
    assert umbra.sum() > 5 and lit.sum() > 1000
    assert np.all(lifted.mean[umbra] == 0.0) and np.all(lifted.mean[lit] > 0.0)


def test_the_lift_follows_the_tilt_between_shading_and_geometric_normals():
    scene = Scene(*quad(-1.0, 1.0, -1.0, 1.0, 0.0))
    points = np.zeros((3, 3))
    g = np.tile([0.0, 0.0, 1.0], (3, 1))
    n = np.array([[0.0, 0.0, 1.0], [np.sin(0.3), 0.0, np.cos(0.3)], [0.0, np.sin(1.2), np.cos(1.2)]])
    origins, horizon = lifted_origins(scene, points, n, g, 1.0)
    lift = origins - (points + scene.ray_offset * g)
    np.testing.assert_allclose(lift[0], 0.0, atol=1e-15)
    np.testing.assert_allclose(lift[1], scene.edge_length * np.sin(0.3) * n[1], rtol=1e-12)
    np.testing.assert_allclose(lift[2], scene.edge_length * np.sin(1.2) * n[2], rtol=1e-12)
    np.testing.assert_array_equal(horizon, n)
    # lift 0: the triangles' own hemisphere, as before
    origins, horizon = lifted_origins(scene, points, n, g, 0.0)
    np.testing.assert_array_equal(origins, points + scene.ray_offset * g)
    np.testing.assert_array_equal(horizon, g)


def test_the_light_transport_lifts_its_rays_too():
    # On the coarse ball every texel's transport is its unoccluded one when lifted (nothing
    # blocks a convex surface); from the triangles, facets near the terminator lose some
    scene, hits, _, _ = _coarse_ball()
    pixels = np.flatnonzero(hits.mask.ravel() & (hits.normal[..., 2].ravel() < 0.5))[::7]
    plain = light_transport(scene, hits, pixels, samples=16, lift=0.0)
    lifted = light_transport(scene, hits, pixels, samples=16, lift=SHADOW_LIFT)
    unoccluded = light_transport(scene, hits, pixels, samples=0)
    assert np.abs(lifted.matrix - unoccluded.matrix).max() == 0.0
    assert (plain.matrix < unoccluded.matrix - 1e-6).any()


@pytest.mark.parametrize("size", [1e-3, 1e4])
def test_the_lifted_terminator_is_the_same_at_tiny_and_huge_scales(size):
    # Same ball, same sun, same pixels, every length times `size`: the lift follows the edges
    _, hits, light, _ = _coarse_ball()
    ball = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    reference = shade_environment(Scene.from_trimesh(ball), hits, light, spp=8, lift=SHADOW_LIFT)
    ball.apply_scale(size)
    scene = Scene.from_trimesh(ball)
    scaled = render_pixel_geometry(scene, tuple(size * c for c in (-1.1, 1.1, -1.1, 1.1)), (96, 96))
    np.testing.assert_array_equal(scaled.mask, hits.mask)
    result = shade_environment(scene, scaled, light, spp=8, lift=SHADOW_LIFT)
    assert np.isfinite(result.mean).all() and np.isfinite(result.stderr).all()
    np.testing.assert_allclose(result.mean, reference.mean, rtol=1e-3, atol=1e-6 * float(reference.mean.max()))
