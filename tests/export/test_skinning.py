"""Linear-blend skinning and BVH-driven bone transforms."""

import numpy as np
import pytest
import scipy.sparse as sp

from export.factory import skinning
from export.factory.makehuman import Skeleton, axis_rotation


def _chain() -> tuple[Skeleton, np.ndarray]:
    # Two bones along +X: heads at the origin and at (1, 0, 0).
    skeleton = Skeleton(names=("a", "b"), parents=np.array([-1, 0]),
                        head_vertices=(np.array([0]), np.array([1])),
                        tail_vertices=(np.array([1]), np.array([2])))
    return skeleton, np.array([[0.0, 0, 0], [1.0, 0, 0]])


def test_identity_rotations_reproduce_rest_pose(base):
    heads, _ = base.skeleton.joint_positions(base.mesh.vertices)
    rotations = np.tile(np.eye(3), (len(heads), 1, 1))
    transforms = skinning.bone_transforms(base.skeleton, heads, rotations)
    np.testing.assert_array_equal(transforms[:, :, :3], np.tile(np.eye(3), (len(heads), 1, 1)))
    np.testing.assert_array_equal(transforms[:, :, 3], 0.0)
    posed = skinning.skin_vertices(base.mesh.vertices, base.weights, transforms)
    np.testing.assert_allclose(posed, base.mesh.vertices, rtol=0, atol=1e-12)


def test_child_follows_parent_rotation():
    skeleton, heads = _chain()
    rotations = np.stack([axis_rotation("z", 90.0), np.eye(3)])
    transforms = skinning.bone_transforms(skeleton, heads, rotations)
    tip = np.array([2.0, 0, 0, 1.0])
    np.testing.assert_allclose(transforms[1] @ tip, [0, 2, 0], atol=1e-12)


def test_rotation_pivots_about_the_bone_head():
    skeleton, heads = _chain()
    rotations = np.stack([np.eye(3), axis_rotation("z", 90.0)])
    transforms = skinning.bone_transforms(skeleton, heads, rotations)
    np.testing.assert_allclose(transforms[1] @ [1.0, 0, 0, 1], [1, 0, 0], atol=1e-12)  # head fixed
    np.testing.assert_allclose(transforms[1] @ [2.0, 0, 0, 1], [1, 1, 0], atol=1e-12)


def test_blend_of_two_bones_is_the_weighted_average():
    skeleton, heads = _chain()
    rotations = np.stack([np.eye(3), axis_rotation("z", 90.0)])
    transforms = skinning.bone_transforms(skeleton, heads, rotations)
    weights = sp.csr_matrix(np.array([[0.25, 0.75]]))
    vertex = np.array([[2.0, 0, 0]])
    expected = 0.25 * vertex[0] + 0.75 * np.array([1.0, 1, 0])
    np.testing.assert_allclose(skinning.skin_vertices(vertex, weights, transforms)[0], expected)


@pytest.mark.parametrize("angle", [0.1, 1.0, 3.0])
def test_rodrigues_matches_axis_rotation(angle):
    got = skinning.axis_angle_matrices(np.array([[0.0, 0.0, 2.0]]), np.array([angle]))[0]
    np.testing.assert_allclose(got, axis_rotation("z", np.degrees(angle)), atol=1e-12)


def test_perturbation_stays_within_limits(base):
    names = base.skeleton.names
    identity = np.tile(np.eye(3), (len(names), 1, 1))
    perturbed = skinning.perturb_rotations(identity, names, np.random.default_rng(3))
    angles = np.degrees(np.arccos(np.clip((np.trace(perturbed, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    limits = np.array([next((2.5 * d for p, d in skinning.PERTURB_DEGREES.items()
                             if n.startswith(p)), 0.0) for n in names])
    assert np.all(angles <= limits + 1e-6)
    assert angles.max() > 1.0  # something did move
