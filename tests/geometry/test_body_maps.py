"""The fitted bodies' prior maps (relightcli.geometry.body_maps): front and back depth and
normals in the crop camera, the body_maps stage that makes them once per photo, and the
body_normal / body_depth layers."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from relightcli import compose
from relightcli.compose import CROP_RECT
from relightcli.geometry.body_maps import bodies_scene, render_body_maps
from relightcli.pipeline import RelightOptions
from relightcli.render.camera import pixel_centres
from relightcli.render.scene import Scene
from relightcli.stages.body import stage_body_maps
from relightcli.stages.compose import body_layer
from relightcli.stages.frame import Frame, Models

RADIUS, CENTRE_Z = 0.5, 0.2


@pytest.fixture(scope="module")
def ball_maps():
    ball = trimesh.creation.icosphere(subdivisions=5, radius=RADIUS)
    ball.apply_translation((0.0, 0.0, CENTRE_Z))
    with Scene(ball.vertices, ball.faces) as scene:
        return render_body_maps(scene, 64)


def _disc(radius, resolution=64):
    xy = pixel_centres(CROP_RECT, (resolution, resolution))
    return np.hypot(xy[..., 0], xy[..., 1]) < radius


def test_a_ball_covers_its_disc(ball_maps):
    # The icosphere's polygon lies a hair inside the sphere: its silhouette by 0.3% of r
    assert ball_maps.mask[_disc(0.99 * RADIUS)].all()
    assert not ball_maps.mask[~_disc(1.01 * RADIUS)].any()


def test_a_ball_is_traced_only_where_asked():
    ball = trimesh.creation.icosphere(subdivisions=3, radius=RADIUS)
    where = _disc(0.3, 32) | (np.arange(32)[:, None] < 4)
    with Scene(ball.vertices, ball.faces) as scene:
        maps = render_body_maps(scene, 32, where=where)
    np.testing.assert_array_equal(maps.mask, _disc(0.3, 32))
    assert not maps.front_depth[~where].any() and not maps.back_normal[~where].any()


def test_a_balls_depth_is_the_sphere_front_and_back(ball_maps):
    xy = pixel_centres(CROP_RECT, (64, 64))
    inner = _disc(0.9 * RADIUS)
    height = np.sqrt(RADIUS**2 - xy[..., 0] ** 2 - xy[..., 1] ** 2, where=inner, out=np.zeros((64, 64)))
    np.testing.assert_allclose(ball_maps.front_depth[inner], CENTRE_Z + height[inner], atol=2e-3)
    np.testing.assert_allclose(ball_maps.back_depth[inner], CENTRE_Z - height[inner], atol=2e-3)
    assert (ball_maps.front_depth[ball_maps.mask] >= ball_maps.back_depth[ball_maps.mask]).all()
    assert not ball_maps.front_depth[~ball_maps.mask].any() and not ball_maps.back_depth[~ball_maps.mask].any()


def test_a_balls_normals_are_unit_radial_and_face_the_cameras(ball_maps):
    xy = pixel_centres(CROP_RECT, (64, 64))
    inner = _disc(0.9 * RADIUS)
    for normals, depth, side in ((ball_maps.front_normal, ball_maps.front_depth, 1.0),
                                 (ball_maps.back_normal, ball_maps.back_depth, -1.0)):
        np.testing.assert_allclose(np.linalg.norm(normals[ball_maps.mask], axis=-1), 1.0, atol=1e-5)
        radial = np.dstack([xy, depth - CENTRE_Z])[inner] / RADIUS
        np.testing.assert_allclose(normals[inner], radial, atol=0.02)
        assert (side * normals[inner][:, 2] > 0).all()
        assert not normals[~ball_maps.mask].any()


def test_two_bodies_share_one_scene():
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.2)
    left, right = ball.vertices - (0.5, 0.0, 0.0), ball.vertices + (0.5, 0.0, 0.0)
    with bodies_scene([left, right], ball.faces) as scene:
        maps = render_body_maps(scene, 32)
    assert maps.mask[:, :16].any() and maps.mask[:, 16:].any()
    assert bodies_scene([], ball.faces) is None


class _BallBodyModels(Models):
    def __init__(self):
        super().__init__(threads=1)
        self.ball = trimesh.creation.icosphere(subdivisions=3, radius=RADIUS)

    def body_model(self):
        return SimpleNamespace(triangles=self.ball.faces)


def _frame(converged):
    frame = Frame(image=np.zeros((40, 40, 3), np.float32), mask=None, env=None,
                  crop_mask=_disc(0.4, 32).astype(np.float32), box=compose.CropBox(4, 4, 32, 32))
    models = _BallBodyModels()
    frame.bodies = [SimpleNamespace(vertices=models.ball.vertices, converged=converged)]
    return frame, models


def test_the_stage_traces_a_converged_body_on_the_persons_pixels():
    frame, models = _frame(converged=True)
    try:
        stage_body_maps(frame, RelightOptions(resolution=32), models)
    finally:
        frame.body_scene.close()
    person = frame.crop_mask > 0
    # The ball (r 0.5) is larger than the person (r 0.4): the maps stop at the person
    np.testing.assert_array_equal(frame.body_maps.mask, person)
    assert frame.body_hits is frame.body_maps.front
    assert frame.body_maps.front_depth[person].min() > 0.0  # the ball's front half
    assert frame.notes["body_maps"] == {"bodies": 1, "person_pixels_covered": 1.0}


def test_no_converged_fit_gives_no_maps_and_says_why():
    frame, models = _frame(converged=False)
    stage_body_maps(frame, RelightOptions(resolution=32), models)
    assert frame.body_maps is None and frame.body_scene is None and frame.body_hits is None
    assert frame.notes["body_maps"] == {"skipped": "no converged body fit"}
    for name in ("body_normal", "body_depth"):
        layer = body_layer(name, None, 32)
        assert layer.shape == (32, 32, 3) and not layer.any()


def test_the_layers_hold_the_normals_and_both_depths(ball_maps):
    normal = body_layer("body_normal", ball_maps, 64)
    np.testing.assert_allclose(normal[ball_maps.mask], (ball_maps.front_normal[ball_maps.mask] + 1) / 2)
    assert not normal[~ball_maps.mask].any()
    depth = body_layer("body_depth", ball_maps, 64)
    np.testing.assert_array_equal(depth[..., 0], ball_maps.front_depth)
    np.testing.assert_array_equal(depth[..., 1], ball_maps.back_depth)
    np.testing.assert_array_equal(depth[..., 2], ball_maps.mask)


def test_a_body_off_the_asked_pixels_gives_empty_maps():
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.2)
    where = np.zeros((32, 32), bool)
    where[0, 0] = True  # a corner pixel, far from the ball
    with Scene(ball.vertices, ball.faces) as scene:
        maps = render_body_maps(scene, 32, where=where)
    assert not maps.mask.any() and not maps.front_depth.any() and not maps.back_normal.any()
