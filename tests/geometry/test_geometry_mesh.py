"""Depth maps -> watertight, pixel-aligned mesh; atomic mesh files."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from geometry_truth import first_hits, pixel_centres, render_maps, sphere
from relightcli.errors import InputError, OutputError, UsageError
from relightcli.geometry.mesh import covered_pixels, reconstruct_mesh, save_mesh

RECT = (-1.0, 1.0, -1.0, 1.0)


def _disc(n=48, radius=0.8):
    x, y = pixel_centres(RECT, n, n)
    return x ** 2 + y ** 2 < radius ** 2


def _annulus_with_holes(n=48):
    x, y = pixel_centres(RECT, n, n)
    r = np.hypot(x, y)
    mask = (r < 0.9) & (r > 0.3)
    mask &= np.hypot(x - 0.6, y) > 0.1  # a small hole in the ring
    mask[5, 5:40] = True  # a one-pixel line touching nothing else at its left end
    return mask


def _disc_with_limbs(n=48):
    mask = _disc(n, 0.5)
    mask[24, :] = True  # one-pixel limbs both ways
    mask[:, 30] = True
    mask[3, 3] = True  # an isolated pixel
    return mask


def _diagonal_blocks(n=12):
    mask = np.zeros((n, n), bool)
    mask[2:5, 2:5] = True
    mask[5:8, 5:8] = True  # touches the first block at one corner only
    mask[8:10, 3:5] = True
    mask[7, 4] = True  # pinches a third fan onto the second block's corner
    return mask


def _checkerboard_noise(n=40, seed=0):
    return np.random.default_rng(seed).random((n, n)) > 0.3


def _paraboloid_maps(mask):
    x, y = pixel_centres(RECT, *mask.shape)
    front = 1.0 - 0.5 * (x ** 2 + y ** 2)
    back = -0.3 + 0.2 * x
    return front, back


MASKS = {
    "disc": _disc,
    "annulus_with_holes": _annulus_with_holes,
    "one_pixel_limbs": _disc_with_limbs,
    "diagonal_blocks": _diagonal_blocks,
    "noisy": _checkerboard_noise,
}


def _mesh_for(name):
    mask = MASKS[name]()
    return reconstruct_mesh(mask, *_paraboloid_maps(mask), RECT).to_trimesh()


@pytest.mark.parametrize("name", MASKS)
def test_mesh_is_watertight(name):
    assert _mesh_for(name).is_watertight


@pytest.mark.parametrize("name", MASKS)
def test_mesh_winding_is_consistent(name):
    assert _mesh_for(name).is_winding_consistent


@pytest.mark.parametrize("name", MASKS)
def test_mesh_volume_is_positive(name):
    assert _mesh_for(name).volume > 0


def test_body_silhouette_mesh_is_watertight(body_maps):
    mesh = reconstruct_mesh(body_maps.mask, body_maps.front_depth, body_maps.back_depth,
                            body_maps.rect).to_trimesh()
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0


def test_volume_matches_prism():
    # Constant depths over a square of pixel centres: a box of (n-1)^2 pixel cells
    n = 10
    mask = np.zeros((n + 2, n + 2), bool)
    mask[1:-1, 1:-1] = True
    mesh = reconstruct_mesh(mask, np.full(mask.shape, 0.5), np.full(mask.shape, -0.25),
                            (0.0, n + 2.0, 0.0, n + 2.0)).to_trimesh()
    assert mesh.volume == pytest.approx((n - 1) ** 2 * 0.75, rel=1e-12)


def test_sphere_volume_close_to_analytic():
    maps = render_maps(sphere(), RECT, 128, 128)
    mesh = reconstruct_mesh(maps.mask, maps.front_depth, maps.back_depth, RECT).to_trimesh()
    # The pixel-centre surface stops half a pixel inside the silhouette: -3% at 128 px
    assert mesh.volume == pytest.approx(4 / 3 * np.pi, rel=0.03)


def _front_hits(mesh, mask, rect):
    """World z where an orthographic ray through each pixel centre first hits the mesh."""
    x, y = pixel_centres(rect, *mask.shape)
    top = mesh.bounds[1, 2] + 1.0
    origins = np.column_stack([x[mask], y[mask], np.full(mask.sum(), top)])
    t, _ = first_hits(mesh, origins, np.tile([0.0, 0.0, -1.0], (origins.shape[0], 1)))
    return top - t


def _interior(mask):
    """Covered pixels whose 8 neighbours are covered (rays there hit inside triangles)."""
    covered = covered_pixels(mask)
    core = covered.copy()
    core[1:-1, 1:-1] &= np.all([np.roll(np.roll(covered, di, 0), dj, 1)[1:-1, 1:-1]
                                for di in (-1, 0, 1) for dj in (-1, 0, 1)], axis=0)
    core[[0, -1], :] = core[:, [0, -1]] = False
    return core


@pytest.mark.parametrize("name", ["disc", "annulus_with_holes", "one_pixel_limbs"])
def test_front_surface_is_pixel_aligned(name):
    mask = MASKS[name]()
    front, back = _paraboloid_maps(mask)
    mesh = reconstruct_mesh(mask, front, back, RECT).to_trimesh()
    core = _interior(mask)
    # float32 ray tracing over a scene of size ~2: 1e-5 is ~100 ulps
    np.testing.assert_allclose(_front_hits(mesh, core, RECT), front[core], atol=1e-5)


def test_body_front_surface_is_pixel_aligned(body_maps):
    m = body_maps
    mesh = reconstruct_mesh(m.mask, m.front_depth, m.back_depth, m.rect).to_trimesh()
    core = _interior(m.mask)
    np.testing.assert_allclose(_front_hits(mesh, core, m.rect), m.front_depth[core], atol=1e-4)


def test_arm_over_torso_front_surface_is_pixel_aligned(arm_maps):
    m = arm_maps
    mesh = reconstruct_mesh(m.mask, m.front_depth, m.back_depth, m.rect).to_trimesh()
    core = _interior(m.mask)
    np.testing.assert_allclose(_front_hits(mesh, core, m.rect), m.front_depth[core], atol=1e-5)


def test_one_pixel_limbs_are_not_covered():
    mask = _disc_with_limbs()
    covered = covered_pixels(mask)
    assert not covered[24, 0] and not covered[3, 3] and covered[24, 24]


def test_back_depth_in_front_is_clamped():
    mask = _disc()
    front, _ = _paraboloid_maps(mask)
    mesh = reconstruct_mesh(mask, front, front + 1.0, RECT, min_thickness=0.01).to_trimesh()
    assert mesh.is_watertight and mesh.volume > 0


def test_nan_depth_on_mask_raises():
    mask = _disc()
    front, back = _paraboloid_maps(mask)
    front[24, 24] = np.nan
    with pytest.raises(InputError, match="NaN"):
        reconstruct_mesh(mask, front, back, RECT)


def test_nan_depth_off_mask_is_ignored():
    mask = _disc()
    front, back = _paraboloid_maps(mask)
    front[0, 0] = np.nan
    assert reconstruct_mesh(mask, front, back, RECT).to_trimesh().is_watertight


def test_mismatched_shapes_raise():
    mask = _disc()
    front, back = _paraboloid_maps(mask)
    with pytest.raises(InputError, match="shape"):
        reconstruct_mesh(mask, front[:-1], back, RECT)


def test_mask_without_block_raises():
    mask = np.zeros((8, 8), bool)
    mask[4, :] = True
    with pytest.raises(InputError, match="2x2"):
        reconstruct_mesh(mask, np.ones((8, 8)), np.zeros((8, 8)), RECT)


@pytest.mark.parametrize("suffix", [".ply", ".glb", ".obj"])
def test_save_mesh_round_trips(tmp_path, suffix):
    mesh = _mesh_for("disc")
    path = save_mesh(mesh, tmp_path / f"body{suffix}")
    loaded = trimesh.load(path, force="mesh", process=False)
    assert loaded.faces.shape == mesh.faces.shape
    np.testing.assert_allclose(loaded.vertices, mesh.vertices, atol=1e-6)


def test_save_mesh_leaves_no_temporary_file(tmp_path):
    save_mesh(_mesh_for("disc"), tmp_path / "body.ply")
    assert [p.name for p in tmp_path.iterdir()] == ["body.ply"]


def test_save_mesh_unknown_suffix_raises(tmp_path):
    with pytest.raises(UsageError, match="ply"):
        save_mesh(_mesh_for("disc"), tmp_path / "body.stl")


def test_save_mesh_missing_folder_raises(tmp_path):
    with pytest.raises(OutputError):
        save_mesh(_mesh_for("disc"), tmp_path / "missing" / "body.ply")
