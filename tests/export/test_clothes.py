"""Garments stay attached to the body under shape and pose changes."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from export.factory import clothes, skinning
from export.factory.person import pose_rotations, sample_body

ITEMS = ["clothes/male_casualsuit01", "clothes/female_elegantsuit01", "clothes/shoes03",
         "hair/long01", "clothes/fedora01/fedora"]


@pytest.fixture(scope="module")
def shaped_body(base):
    return sample_body(np.random.default_rng(11), base)[1]


def _anchor_distance(garment, body_vertices, garment_vertices):
    anchors = np.einsum("nk,nkd->nd", garment.weights, body_vertices[garment.ids])
    return np.linalg.norm(garment_vertices - anchors, axis=1)


@pytest.mark.parametrize("item", ITEMS)
def test_fit_on_base_mesh_matches_binding_offsets(item, base):
    garment = clothes.read_mhclo(clothes.garment_path(item))
    fitted = clothes.fit_garment(garment, base.mesh.vertices)
    scale = clothes.offset_scale(garment, base.mesh.vertices)
    np.testing.assert_allclose(_anchor_distance(garment, base.mesh.vertices, fitted),
                               np.linalg.norm(garment.offsets * scale, axis=1), atol=1e-12)


def _posed(item, pose, base, shaped_body):
    garment = clothes.read_mhclo(clothes.garment_path(item))
    rest = clothes.fit_garment(garment, shaped_body)
    heads, _ = base.skeleton.joint_positions(shaped_body)
    rotations = skinning.perturb_rotations(pose_rotations(pose, base.skeleton),
                                           base.skeleton.names, np.random.default_rng(0))
    transforms = skinning.bone_transforms(base.skeleton, heads, rotations)
    body_posed = skinning.skin_vertices(shaped_body, base.weights, transforms)
    weights = clothes.garment_skin_weights(garment, base.weights, base.skeleton.names)
    return garment, rest, body_posed, skinning.skin_vertices(rest, weights, transforms)


@pytest.mark.parametrize("item", [i for i in ITEMS if "shoes" not in i])
@pytest.mark.parametrize("pose", ["fight01", "sit01"])
def test_garment_stays_on_its_triangles_after_shape_and_pose(item, pose, base, shaped_body):
    garment, rest, body_posed, posed = _posed(item, pose, base, shaped_body)
    # Bindings that interpolate inside their triangle (weights in [0, 1]); extrapolating ones
    # use far-apart vertex triples as a frame and are judged by the skin distance below.
    local = np.all((garment.weights >= 0) & (garment.weights <= 1), axis=1)
    before = _anchor_distance(garment, shaped_body, rest)[local]
    after = _anchor_distance(garment, body_posed, posed)[local]
    assert np.abs(after - before).max() < 0.03  # metres
    assert np.linalg.norm(posed - rest, axis=1).max() > 0.05  # the pose did move it


@pytest.mark.parametrize("item", ITEMS)
@pytest.mark.parametrize("pose", ["fight01", "sit01"])
def test_garment_keeps_its_distance_to_the_skin(item, pose, base, shaped_body):
    garment, rest, body_posed, posed = _posed(item, pose, base, shaped_body)
    body = np.unique(base.mesh.faces[base.body_faces])
    before = cKDTree(shaped_body[body]).query(rest)[0]
    after = cKDTree(body_posed[body]).query(posed)[0]
    assert np.percentile(np.abs(after - before), 99) < 0.03  # metres


@pytest.mark.parametrize("item", ITEMS)
def test_garment_weights_rows_sum_to_one(item, base):
    garment = clothes.read_mhclo(clothes.garment_path(item))
    weights = clothes.garment_skin_weights(garment, base.weights, base.skeleton.names)
    np.testing.assert_allclose(np.asarray(weights.sum(axis=1)).ravel(), 1.0, atol=1e-9)
