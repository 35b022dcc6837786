"""Linear-blend skinning of the MakeHuman mesh with the default rig, posed by BVH rotations.

Model. BVH joints carry no rest orientation, so each local rotation R_b acts in a frame parallel
to the world axes with its origin at the bone head h_b. The world transform of bone b is

    G_b = G_parent(b) . T(h_b) . R_b . T(-h_b)            (4x4 affine, rest -> posed)

and a vertex moves to  v' = sum_b w_vb G_b v  (linear-blend skinning). Heads come from the
*shaped* mesh, so one pose fits every body. Root translation in the BVH is ignored; callers put
the feet on the ground afterwards.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .makehuman import BVH_TO_MESH, BvhPose, Skeleton

# Plausible random joint perturbations: standard deviation in degrees per bone-name prefix, applied
# as a rotation about a random axis and clipped at 2.5 sigma. Joints not listed stay as posed.
PERTURB_DEGREES = {
    "spine": 3.0, "neck": 5.0, "head": 8.0, "clavicle": 3.0, "shoulder01": 4.0,
    "upperarm01": 10.0, "lowerarm01": 10.0, "wrist": 10.0,
    "upperleg01": 5.0, "lowerleg01": 5.0, "foot": 5.0,
}


def local_rotations_from_bvh(pose: BvhPose, bone_names: tuple[str, ...]) -> np.ndarray:
    """Per-bone local rotations (B, 3, 3) float64 in the mesh frame (+Y up, facing +Z).

    Bones missing from the BVH keep the identity; BVH joints unknown to the rig are ignored.
    The change of frame is R_mesh = C R_bvh C^T with C = BVH_TO_MESH.
    """
    index = {name: k for k, name in enumerate(pose.names)}
    rotations = np.tile(np.eye(3), (len(bone_names), 1, 1))
    for b, name in enumerate(bone_names):
        if name in index:
            rotations[b] = BVH_TO_MESH @ pose.rotations[index[name]] @ BVH_TO_MESH.T
    return rotations


def axis_angle_matrices(axes: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: rotations (N, 3, 3) about unit `axes` (N, 3) by `angles` (N,) radians."""
    k = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    cross = np.zeros((len(k), 3, 3))
    cross[:, 0, 1], cross[:, 0, 2], cross[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    cross -= cross.transpose(0, 2, 1)
    s, c = np.sin(angles)[:, None, None], np.cos(angles)[:, None, None]
    return np.eye(3) + s * cross + (1.0 - c) * (cross @ cross)


def perturb_rotations(rotations: np.ndarray, bone_names: tuple[str, ...],
                      rng: np.random.Generator, strength: float = 1.0) -> np.ndarray:
    """Compose each listed bone's local rotation with a small random one (see PERTURB_DEGREES).

    rotations: (B, 3, 3). Returns a new (B, 3, 3) array; `strength` scales every sigma.
    """
    sigma = np.array([next((d for p, d in PERTURB_DEGREES.items() if n.startswith(p)), 0.0)
                      for n in bone_names]) * strength
    axes = rng.normal(size=(len(bone_names), 3))
    angles = np.radians(np.clip(rng.normal(size=len(bone_names)), -2.5, 2.5) * sigma)
    return axis_angle_matrices(axes, angles) @ rotations


def bone_transforms(skeleton: Skeleton, heads: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """World affine transforms (B, 3, 4) float64, rest pose -> posed, for bone heads (B, 3) m.

    Identity rotations give identity transforms exactly.
    """
    local = np.tile(np.eye(4), (len(heads), 1, 1))
    local[:, :3, :3] = rotations
    local[:, :3, 3] = heads - np.einsum("bij,bj->bi", rotations, heads)  # T(h) R T(-h)
    world = np.empty_like(local)
    for b, parent in enumerate(skeleton.parents):  # parents come first (topological order)
        world[b] = local[b] if parent < 0 else world[parent] @ local[b]
    return world[:, :3, :]


def skin_vertices(vertices: np.ndarray, weights: sp.spmatrix, transforms: np.ndarray) -> np.ndarray:
    """Linear-blend skinning: posed vertices (V, 3) float64.

    vertices: (V, 3) rest positions; weights: (V, B) sparse, rows summing to 1;
    transforms: (B, 3, 4) bone affines.
    """
    blended = (weights @ transforms.reshape(len(transforms), 12)).reshape(-1, 3, 4)
    return np.einsum("vij,vj->vi", blended[:, :, :3], vertices) + blended[:, :, 3]
