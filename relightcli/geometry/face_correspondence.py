"""MediaPipe's 468 face mesh points -> the ICT face model's 68 iBUG landmarks, through the
shipped table models/face_correspondence.npz (made by `python -m export.face_correspondence`,
which measures it on renders of the face model; its manifest entry gives the distances)."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from relightcli.errors import MissingDependencyError
from relightcli.nets.manifest import MODELS_FIX, verified_file

MESH_POINTS, IBUG_LANDMARKS = 468, 68


@dataclass(frozen=True)
class Correspondence:
    """iBUG landmark i = sum_k weights[i, k] * mesh[mesh_points[i, k]]: mesh_points (68, K)
    int64 indices into the 468 mesh points, weights (68, K) float64, rows summing to 1."""

    mesh_points: np.ndarray
    weights: np.ndarray

    def landmarks(self, mesh: np.ndarray) -> np.ndarray:
        """(68, C) float64 iBUG landmarks from the (468, C) mesh points (any coordinates)."""
        mesh = np.asarray(mesh, np.float64)
        if mesh.shape[0] != MESH_POINTS:
            raise MissingDependencyError(f"face mesh has {mesh.shape[0]} points, the table expects {MESH_POINTS}",
                                         fix=MODELS_FIX)
        return np.einsum("ikc,ik->ic", mesh[self.mesh_points], self.weights)


@functools.lru_cache(maxsize=2)
def load_correspondence(models_dir: str | None = None) -> Correspondence:
    """The shipped table (sha256-checked against the manifest)."""
    path = verified_file("face_correspondence", models_dir)
    with np.load(path) as arrays:
        points, weights = arrays["mesh_points"].astype(np.int64), arrays["weights"].astype(np.float64)
    valid = (points.shape == weights.shape and points.shape[0] == IBUG_LANDMARKS
             and points.min() >= 0 and points.max() < MESH_POINTS and np.allclose(weights.sum(axis=1), 1.0))
    if not valid:
        raise MissingDependencyError("face correspondence table is malformed", path=path, fix=MODELS_FIX)
    return Correspondence(points, weights)
