"""Embree scene and the orthographic camera: geometry against closed forms, frames, threads."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from render_testing import quad
from relightcli.errors import InputError
from relightcli.render.camera import default_rect, pixel_centres, render_pixel_geometry
from relightcli.render.scene import Scene


def test_pixel_centres_follow_design_convention():
    centres = pixel_centres((0.0, 2.0, 0.0, 1.0), (4, 2))
    # x = x0 + (j + 0.5)(x1 - x0)/W, y = y1 - (i + 0.5)(y1 - y0)/H, row 0 at the top
    np.testing.assert_allclose(centres[0, :, 0], [0.25, 0.75, 1.25, 1.75])
    np.testing.assert_allclose(centres[:, 0, 1], [0.75, 0.25])


def test_mask_sits_where_the_geometry_is():
    # A unit square in the lower-left quarter of a 2x2 rectangle: rows 2-3, columns 0-1
    scene = Scene(*quad(0.0, 1.0, 0.0, 1.0, 0.0))
    geometry = render_pixel_geometry(scene, (0.0, 2.0, 0.0, 2.0), (4, 4))
    expected = np.zeros((4, 4), bool)
    expected[2:, :2] = True
    np.testing.assert_array_equal(geometry.mask, expected)
    np.testing.assert_allclose(geometry.normal[geometry.mask], [[0, 0, 1]] * 4, atol=1e-6)


@pytest.mark.parametrize("radius", [1e-3, 1.0, 1e4])
def test_sphere_hits_lie_on_the_sphere(radius):
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=radius)
    scene = Scene.from_trimesh(mesh)
    rect = (-1.2 * radius, 1.2 * radius, -1.2 * radius, 1.2 * radius)
    geometry = render_pixel_geometry(scene, rect, (48, 48))
    centres = pixel_centres(rect, (48, 48))
    r_xy = np.linalg.norm(centres, axis=-1)
    # The polyhedron is inscribed: inside 0.995 r always hit, outside r never
    assert np.all(geometry.mask[r_xy < 0.995 * radius]) and not np.any(geometry.mask[r_xy > radius])
    world = scene.to_world(geometry.position[geometry.mask])
    np.testing.assert_allclose(np.linalg.norm(world, axis=1), radius, rtol=2e-3)
    np.testing.assert_allclose(geometry.normal[geometry.mask], world / np.linalg.norm(world, axis=1, keepdims=True), atol=0.02)
    assert np.all(geometry.normal[geometry.mask][:, 2] > 0)


def test_tracing_only_where_asked_gives_the_same_hits_there_and_nothing_elsewhere():
    scene = Scene.from_trimesh(trimesh.creation.icosphere(subdivisions=3))
    rect = (-1.2, 1.2, -1.2, 1.2)
    rows, cols = np.mgrid[:40, :40]
    where = (rows < 25) & (cols > 8)
    full = render_pixel_geometry(scene, rect, (40, 40))
    part = render_pixel_geometry(scene, rect, (40, 40), where=where)
    np.testing.assert_array_equal(part.mask, full.mask & where)
    for name in ("position", "normal", "geometric_normal"):
        np.testing.assert_array_equal(getattr(part, name)[where], getattr(full, name)[where])
        assert np.all(getattr(part, name)[~where] == 0)
    assert not render_pixel_geometry(scene, rect, (40, 40), where=np.zeros((40, 40), bool)).mask.any()


def test_back_faces_are_flipped_toward_the_camera():
    vertices, faces = quad(-1.0, 1.0, -1.0, 1.0, 0.0)
    scene = Scene(vertices, faces[:, ::-1])  # winding faces -Z
    geometry = render_pixel_geometry(scene, (-1.0, 1.0, -1.0, 1.0), (4, 4))
    np.testing.assert_allclose(geometry.geometric_normal[geometry.mask], [[0, 0, 1]] * 16)
    np.testing.assert_allclose(geometry.normal[geometry.mask], [[0, 0, 1]] * 16)


def test_shading_normal_facing_away_falls_back_to_the_geometric_normal():
    vertices, faces = quad(-1.0, 1.0, -1.0, 1.0, 0.0)
    normals = np.tile([0.0, 0.0, -1.0], (4, 1))  # vertex normals pointing into the surface
    scene = Scene(vertices, faces, vertex_normals=normals)
    geometry = render_pixel_geometry(scene, (-1.0, 1.0, -1.0, 1.0), (4, 4))
    np.testing.assert_allclose(geometry.normal[geometry.mask], [[0, 0, 1]] * 16)


def test_translation_by_1e5_keeps_positions_exact_in_the_local_frame():
    mesh = trimesh.creation.icosphere(subdivisions=3)
    near = Scene.from_trimesh(mesh)
    far = Scene(mesh.vertices + 1e5, mesh.faces)
    rect = np.array([-1.1, 1.1, -1.1, 1.1])
    a = render_pixel_geometry(near, rect, (32, 32))
    b = render_pixel_geometry(far, rect + 1e5, (32, 32))
    np.testing.assert_array_equal(a.mask, b.mask)
    np.testing.assert_allclose(a.position, b.position, atol=1e-6)


def test_default_rect_pads_bounds_by_five_percent():
    scene = Scene(*quad(0.0, 2.0, 0.0, 1.0, 0.0))
    np.testing.assert_allclose(default_rect(scene), (-0.1, 2.1, -0.05, 1.05))


def test_occlusion_respects_tmax():
    scene = Scene(*quad(-1.0, 1.0, -1.0, 1.0, 0.0))
    origins = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [5.0, 0.0, 1.0]])
    directions = np.array([[0.0, 0.0, -1.0]] * 3)
    np.testing.assert_array_equal(scene.occluded(origins, directions, [2.0, 0.5, 2.0]), [True, False, False])


@pytest.mark.parametrize("parallel", ["process", "thread"])
def test_parallel_tracing_matches_one_thread(parallel):
    mesh = trimesh.creation.icosphere(subdivisions=3)
    rng = np.random.default_rng(0)
    origins = rng.normal(size=(20_000, 3)) * 0.7
    directions = rng.normal(size=(20_000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    one = Scene.from_trimesh(mesh)
    with Scene.from_trimesh(mesh, threads=2, parallel=parallel) as two:
        np.testing.assert_array_equal(two.occluded(origins, directions), one.occluded(origins, directions))
        hits_two, hits_one = two.intersect(origins, directions), one.intersect(origins, directions)
        np.testing.assert_array_equal(hits_two.prim, hits_one.prim)
        assert two.rays_traced == 40_000


@pytest.mark.parametrize("bad", ["nan_vertex", "bad_index", "no_faces"])
def test_broken_meshes_raise_input_error(bad):
    vertices, faces = quad(0.0, 1.0, 0.0, 1.0, 0.0)
    if bad == "nan_vertex":
        vertices[0, 0] = np.nan
    elif bad == "bad_index":
        faces = faces + 10
    else:
        faces = np.zeros((0, 3), int)
    with pytest.raises(InputError):
        Scene(vertices, faces)


def test_other_shading_normals_replace_the_mesh_normals_only_where_allowed():
    scene = Scene(*quad(0.0, 2.0, 0.0, 2.0, 0.0))   # fills the frame
    geometry = render_pixel_geometry(scene, (0.0, 2.0, 0.0, 2.0), (4, 4))
    assert geometry.mask.all()
    tilted = np.zeros((4, 4, 3), np.float32)
    tilted[...] = (0.0, 3.0, 4.0)                    # unit after normalising: (0, 0.6, 0.8)
    tilted[0, 0] = (0.0, 0.0, -1.0)                  # faces away from the surface: refused
    where = np.ones((4, 4), bool)
    where[3, 3] = False                              # not asked for
    shaded = geometry.with_shading_normals(tilted, where)
    inside = geometry.mask.copy()
    inside[0, 0] = inside[3, 3] = False
    np.testing.assert_allclose(shaded.normal[inside], np.tile([0.0, 0.6, 0.8], (inside.sum(), 1)), atol=1e-6)
    for kept in ((0, 0), (3, 3)):
        np.testing.assert_array_equal(shaded.normal[kept], geometry.normal[kept])
    np.testing.assert_array_equal(shaded.geometric_normal, geometry.geometric_normal)
    np.testing.assert_array_equal(shaded.position, geometry.position)
