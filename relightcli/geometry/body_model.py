"""The shipped body model (MakeHuman hm08 body, CC0 1.0): a pure function (shape, pose) ->
(vertices, joints, landmarks) by a linear shape space and linear-blend skinning.

`models/body_model.npz` is built by `python -m export.body_model` from the MakeHuman data.
Units metres; frame +Y up, the body facing +Z, its own left side at +X (the project's world
frame). The rest pose is MakeHuman's (arms lowered about 45 degrees).

Shape (rest pose): points = mean + sum_k shape[k] basis[k] for the vertices, the bone heads
(joints) and the 33 BlazePose landmarks alike; coefficients are in units of the shape space's
standard deviation (prior N(0, 1)).

Pose: `rotations` (J, 3, 3) are local bone rotations in frames parallel to the world axes with
their origin at the bone head h_b (MakeHuman BVH poses mapped to the mesh frame, as
export.factory.skinning does). Bone b's world transform is

    G_b = G_parent(b) . T(h_b) . R_b . T(-h_b)                          (rest -> posed)

a vertex moves to v' = sum_b w_vb G_b v, a joint to G_b h_b, a landmark rigidly with its bone;
then world = scale * v' + translation. Everything is linear in the shape coefficients and
polynomial in the rotation entries, so a fit can differentiate through it.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from relightcli.errors import MissingDependencyError, UsageError
from relightcli.nets.manifest import read_data_arrays, verified_file

BODY_MODEL_FILE = "body_model.npz"
FORMAT_VERSION = 1
MAX_SHAPE_SIGMA = 5.0     # |coefficient| beyond this is no body the shape space has seen
ROTATION_TOLERANCE = 1e-4  # max |R^T R - I| entry accepted as a rotation
_FIX_MISSING = ("build it with `python -m export.body_model` (needs ../shared/data/makehuman) "
                "or reinstall the models directory")
_REQUIRED = ("format_version", "mean_vertices", "triangles", "shape_basis", "joint_names",
             "joint_parents", "mean_joints", "joint_basis", "skin_bones", "skin_weights",
             "landmark_names", "landmark_bones", "mean_landmarks", "landmark_basis", "license",
             "heldout_errors_mm")
LANDMARK_NAMES = (
    "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye",
    "right_eye_outer", "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder",
    "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_pinky",
    "right_pinky", "left_index", "right_index", "left_thumb", "right_thumb", "left_hip",
    "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle", "left_heel",
    "right_heel", "left_foot_index", "right_foot_index",
)


@dataclass(frozen=True, eq=False)
class BodyModel:
    """The body model, loaded once per process and read-only afterwards.

    mean_vertices (V, 3) float64 m; triangles (F, 3) int32, outward winding; shape_basis
    (K, V, 3) float64 m per unit coefficient; joint_names (J,) MakeHuman bone names, parents
    before children; joint_parents (J,) int64, -1 for the root; mean_joints (J, 3) and
    joint_basis (K, J, 3) m: the bone heads; skin_bones / skin_weights (V, S) int64 / float64:
    each vertex's bones and weights (rows sum to 1); landmark_bones (33,) int64 the bone each
    BlazePose landmark moves with; mean_landmarks (33, 3), landmark_basis (K, 33, 3) m;
    levels: bone ids grouped by depth in the tree (root first); heldout_errors_mm: the export's
    measured reconstruction error of held-out factory bodies per component count.
    """

    path: Path
    sha256: str
    mean_vertices: np.ndarray
    triangles: np.ndarray
    shape_basis: np.ndarray
    joint_names: tuple
    joint_parents: np.ndarray
    mean_joints: np.ndarray
    joint_basis: np.ndarray
    skin_bones: np.ndarray
    skin_weights: np.ndarray
    landmark_bones: np.ndarray
    mean_landmarks: np.ndarray
    landmark_basis: np.ndarray
    levels: tuple
    heldout_errors_mm: dict
    license: str

    @classmethod
    def load(cls, path: str | Path | None = None) -> "BodyModel":
        """Read `path` (default: the manifest's `body_model` entry, sha256-checked). Raises
        MissingDependencyError naming the file when it is absent, corrupt, unreadable or of
        another format version."""
        path = Path(path) if path is not None else verified_file("body_model")
        if not path.is_file():
            raise MissingDependencyError("body model file not found", path=path, fix=_FIX_MISSING)
        arrays = read_data_arrays(path, _REQUIRED, "body model", _FIX_MISSING)
        version = int(arrays["format_version"])
        if version != FORMAT_VERSION:
            raise MissingDependencyError(f"body model format {version}, expected {FORMAT_VERSION}",
                                         path=path, fix=_FIX_MISSING)
        if tuple(arrays["landmark_names"]) != LANDMARK_NAMES:
            raise MissingDependencyError("body model landmarks are not in BlazePose order",
                                         path=path, fix=_FIX_MISSING)
        parents = arrays["joint_parents"].astype(np.int64)
        return cls(path=path, sha256=hashlib.sha256(path.read_bytes()).hexdigest(),
                   mean_vertices=arrays["mean_vertices"].astype(np.float64),
                   triangles=arrays["triangles"].astype(np.int32),
                   shape_basis=arrays["shape_basis"].astype(np.float64),
                   joint_names=tuple(str(n) for n in arrays["joint_names"]),
                   joint_parents=parents,
                   mean_joints=arrays["mean_joints"].astype(np.float64),
                   joint_basis=arrays["joint_basis"].astype(np.float64),
                   skin_bones=arrays["skin_bones"].astype(np.int64),
                   skin_weights=arrays["skin_weights"].astype(np.float64),
                   landmark_bones=arrays["landmark_bones"].astype(np.int64),
                   mean_landmarks=arrays["mean_landmarks"].astype(np.float64),
                   landmark_basis=arrays["landmark_basis"].astype(np.float64),
                   levels=tree_levels(parents),
                   heldout_errors_mm=json.loads(str(arrays["heldout_errors_mm"])),
                   license=str(arrays["license"]))

    @property
    def n_shape(self) -> int:
        return self.shape_basis.shape[0]

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    def rest_pose(self) -> np.ndarray:
        """(J, 3, 3) float64 identity rotations: MakeHuman's rest pose."""
        return np.tile(np.eye(3), (self.n_joints, 1, 1))

    def shaped(self, shape=None) -> np.ndarray:
        """(V, 3) float64 m: rest-pose vertices of shape coefficients (K,) (None: the mean)."""
        return self.mean_vertices + np.tensordot(self._shape(shape), self.shape_basis, axes=1)

    def rest_joints(self, shape=None) -> np.ndarray:
        """(J, 3) float64 m: rest-pose bone heads of shape coefficients (K,)."""
        return self.mean_joints + np.tensordot(self._shape(shape), self.joint_basis, axes=1)

    def rest_landmarks(self, shape=None) -> np.ndarray:
        """(33, 3) float64 m: rest-pose BlazePose landmarks of shape coefficients (K,)."""
        return self.mean_landmarks + np.tensordot(self._shape(shape), self.landmark_basis, axes=1)

    def posed(self, shape, rotations, translation=(0.0, 0.0, 0.0), scale: float = 1.0):
        """Vertices (V, 3), joints (J, 3) and landmarks (33, 3), float64 m in the world frame,
        of shape coefficients (K,) posed by local rotations (J, 3, 3), then scaled by `scale`
        and moved by `translation` (3,) m. Raises UsageError on a bad argument."""
        coefficients = self._shape(shape)
        rotations = _rotations(rotations, self.n_joints)
        translation = np.asarray(translation, dtype=np.float64)
        if translation.shape != (3,) or not np.all(np.isfinite(translation)):
            raise UsageError(f"translation must be 3 finite numbers, got {translation!r}")
        if not (np.isfinite(scale) and scale > 0):
            raise UsageError(f"scale must be a positive finite number, got {scale!r}")
        heads = self.rest_joints(coefficients)
        transforms = world_transforms(self.levels, self.joint_parents, heads, rotations)
        vertices = skin_points(self.shaped(coefficients), self.skin_bones, self.skin_weights,
                               transforms)
        joints = apply_affine(transforms, heads)
        landmarks = apply_affine(transforms[self.landmark_bones],
                                 self.rest_landmarks(coefficients))
        return tuple(scale * p + translation for p in (vertices, joints, landmarks))

    def _shape(self, shape) -> np.ndarray:
        return shape_vector(shape, self.n_shape)


def shape_vector(shape, size: int) -> np.ndarray:
    """(size,) float64 shape coefficients (None: zeros). UsageError when the shape is not
    `size` finite numbers within +-MAX_SHAPE_SIGMA."""
    if shape is None:
        return np.zeros(size)
    values = np.asarray(shape, dtype=np.float64)
    if values.shape != (size,) or not np.all(np.isfinite(values)):
        raise UsageError(f"body shape must be {size} finite coefficients, got shape "
                         f"{values.shape} with {np.count_nonzero(~np.isfinite(values))} non-finite")
    if np.any(np.abs(values) > MAX_SHAPE_SIGMA):
        raise UsageError(f"body shape coefficients must lie within +-{MAX_SHAPE_SIGMA} standard "
                         f"deviations, got a largest |value| of {np.abs(values).max():.3g}")
    return values


def _rotations(rotations, n_joints: int) -> np.ndarray:
    rotations = np.asarray(rotations, dtype=np.float64)
    if rotations.shape != (n_joints, 3, 3) or not np.all(np.isfinite(rotations)):
        raise UsageError(f"rotations must be ({n_joints}, 3, 3) finite matrices, "
                         f"got shape {rotations.shape}")
    error = np.abs(rotations.transpose(0, 2, 1) @ rotations - np.eye(3)).max()
    if error > ROTATION_TOLERANCE:
        raise UsageError(f"rotations must be orthonormal (largest |R^T R - I| entry {error:.3g})")
    return rotations


def tree_levels(parents: np.ndarray) -> tuple[np.ndarray, ...]:
    """Bone ids (each level an int64 array) grouped by depth: roots, their children, ...

    parents: (J,) int64, -1 for a root, every parent listed before its children."""
    depth = np.zeros(len(parents), dtype=np.int64)
    for b, parent in enumerate(parents):
        if parent >= b:
            raise ValueError(f"bone {b} comes before its parent {parent}")
        depth[b] = 0 if parent < 0 else depth[parent] + 1
    return tuple(np.flatnonzero(depth == d) for d in range(depth.max() + 1))


def world_transforms(levels, parents: np.ndarray, heads: np.ndarray,
                     rotations: np.ndarray) -> np.ndarray:
    """(J, 3, 4) float64 world affines, rest -> posed, of bones with rest heads (J, 3) m and
    local rotations (J, 3, 3): G_b = G_parent(b) T(h_b) R_b T(-h_b), one depth level at a time."""
    local = np.zeros((len(heads), 4, 4))
    local[:, :3, :3] = rotations
    local[:, :3, 3] = heads - np.einsum("bij,bj->bi", rotations, heads)
    local[:, 3, 3] = 1.0
    world = local.copy()
    for level in levels[1:]:
        world[level] = world[parents[level]] @ local[level]
    return world[:, :3, :]


def apply_affine(transforms: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 3) float64: each point (N, 3) moved by its own affine (N, 3, 4)."""
    return np.einsum("nij,nj->ni", transforms[:, :, :3], points) + transforms[:, :, 3]


def skin_points(points: np.ndarray, bones: np.ndarray, weights: np.ndarray,
                transforms: np.ndarray) -> np.ndarray:
    """Linear-blend skinning: (V, 3) float64 posed points of rest points (V, 3), with bone ids
    and weights (V, S) per point and bone affines (J, 3, 4)."""
    blended = np.einsum("vs,vsij->vij", weights, transforms[bones])
    return apply_affine(blended, points)
