"""The shipped linear face model (ICT FaceKit light, trimmed): shape, landmarks, projection.

`models/face_model.npz` is built by `python -m export.face_model` from the ICT FaceKit data
(MIT License, Copyright (c) 2020 USC Institute for Creative Technologies). Model units are
centimetres; the model frame has +X to the subject's left (image right in a frontal view), +Y
up and +Z out of the face, so an identity rotation shows the face frontally to DESIGN.md's
camera (which looks along -Z).

Shape: vertices = neutral + sum_k identity[k] identity_basis[k] + sum_j expression[j]
expression_basis[j]. Identity coefficients are in units of the PCA mode (prior N(0, 1));
expression coefficients are blendshape weights in [0, 1].

Weak-perspective (scaled orthographic) projection onto the image plane of the camera:
world = scale * rotation @ vertex + translation, and the image sees (world x, world y).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from relightcli.errors import MissingDependencyError, UsageError
from relightcli.nets.manifest import read_data_arrays, verified_file

FACE_MODEL_FILE = "face_model.npz"
FORMAT_VERSION = 1
_FIX_MISSING = ("build it with `python -m export.face_model` (needs ../shared/data/ict_facekit) "
                "or reinstall the models directory")
_REQUIRED = ("format_version", "neutral_vertices", "triangles", "face_region", "identity_basis",
             "identity_names", "expression_basis", "expression_names", "landmark_indices",
             "license")


@dataclass(frozen=True, eq=False)
class FaceModel:
    """The linear face model, loaded once per process and read-only afterwards.

    neutral (V, 3) float32 cm; triangles (F, 3) int32, outward winding; face_region (V,) bool
    (the face proper, without the back of the head and the neck); identity_basis (K, V, 3) and
    expression_basis (E, V, 3) float32 cm per unit coefficient; landmark_indices (68,) int32
    vertices in iBUG-68 order; sha256 of the file.
    """

    path: Path
    sha256: str
    neutral: np.ndarray
    triangles: np.ndarray
    face_region: np.ndarray
    identity_basis: np.ndarray
    identity_names: tuple
    expression_basis: np.ndarray
    expression_names: tuple
    landmark_indices: np.ndarray
    license: str
    _landmark_basis: np.ndarray = field(repr=False, default=None)

    @classmethod
    def load(cls, path: str | Path | None = None) -> "FaceModel":
        """Read `path` (default: the manifest's `face_model` entry, sha256-checked). Raises
        MissingDependencyError naming the file when it is absent, corrupt, unreadable or of
        another format version."""
        path = Path(path) if path is not None else verified_file("face_model")
        if not path.is_file():
            raise MissingDependencyError("face model file not found", path=path, fix=_FIX_MISSING)
        payload = path.read_bytes()
        arrays = read_data_arrays(path, _REQUIRED, "face model", _FIX_MISSING)
        version = int(arrays["format_version"])
        if version != FORMAT_VERSION:
            raise MissingDependencyError(f"face model format {version}, expected {FORMAT_VERSION}",
                                         path=path, fix=_FIX_MISSING)
        identity = arrays["identity_basis"].astype(np.float32)
        expression = arrays["expression_basis"].astype(np.float32)
        landmarks = arrays["landmark_indices"].astype(np.int64)
        stacked = np.concatenate([identity[:, landmarks], expression[:, landmarks]])
        return cls(path=path, sha256=hashlib.sha256(payload).hexdigest(),
                   neutral=arrays["neutral_vertices"].astype(np.float32),
                   triangles=arrays["triangles"].astype(np.int32),
                   face_region=arrays["face_region"].astype(bool),
                   identity_basis=identity, identity_names=tuple(arrays["identity_names"]),
                   expression_basis=expression,
                   expression_names=tuple(arrays["expression_names"]),
                   landmark_indices=landmarks, license=str(arrays["license"]),
                   _landmark_basis=np.moveaxis(stacked, 0, -1).astype(np.float64))

    @property
    def n_identity(self) -> int:
        return self.identity_basis.shape[0]

    @property
    def n_expression(self) -> int:
        return self.expression_basis.shape[0]

    @property
    def landmark_neutral(self) -> np.ndarray:
        """(68, 3) float64 cm: the landmarks of the neutral face."""
        return self.neutral[self.landmark_indices].astype(np.float64)

    @property
    def landmark_basis(self) -> np.ndarray:
        """(68, 3, K + E) float64 cm per unit coefficient: identity modes, then expressions."""
        return self._landmark_basis

    def coefficients(self, identity=None, expression=None) -> np.ndarray:
        """(K + E,) float64: identity (K,) and expression (E,) stacked; None means zeros."""
        identity = _vector(identity, self.n_identity, "identity")
        expression = _vector(expression, self.n_expression, "expression")
        return np.concatenate([identity, expression])

    def vertices(self, identity=None, expression=None) -> np.ndarray:
        """(V, 3) float32 cm: the model's vertices for identity (K,) and expression (E,)."""
        c = self.coefficients(identity, expression)
        k = self.n_identity
        offset = np.tensordot(c[:k], self.identity_basis, axes=1)
        offset += np.tensordot(c[k:], self.expression_basis, axes=1)
        return (self.neutral + offset).astype(np.float32)

    def landmarks(self, identity=None, expression=None) -> np.ndarray:
        """(68, 3) float64 cm: the landmark vertices for identity (K,) and expression (E,)."""
        return self.landmark_neutral + self.landmark_basis @ self.coefficients(identity, expression)


def _vector(values, size: int, name: str) -> np.ndarray:
    if values is None:
        return np.zeros(size)
    values = np.asarray(values, dtype=np.float64)
    if values.shape != (size,) or not np.all(np.isfinite(values)):
        raise UsageError(f"{name} coefficients must be {size} finite numbers, "
                         f"got shape {values.shape}")
    return values


# --- weak-perspective projection and the pixel grid (DESIGN.md camera) ----------------

def rotation_matrix(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """(3, 3) float64 rotation from angles in degrees: R = Rz(roll) Rx(pitch) Ry(yaw).

    yaw turns about +Y (positive: the face turns toward image right, +X), pitch about +X
    (positive: the face looks down, the nose toward -Y), roll about +Z (positive:
    counter-clockwise in the image).
    """
    y, p, r = np.radians([yaw, pitch, roll])
    ry = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
    rx = np.array([[1, 0, 0], [0, np.cos(p), -np.sin(p)], [0, np.sin(p), np.cos(p)]])
    rz = np.array([[np.cos(r), -np.sin(r), 0], [np.sin(r), np.cos(r), 0], [0, 0, 1]])
    return rz @ rx @ ry


def rotation_angles_deg(rotation) -> tuple[float, float, float]:
    """(yaw, pitch, roll) in degrees of a rotation R = Rz(roll) Rx(pitch) Ry(yaw), the inverse
    of `rotation_matrix` for |pitch| < 90. Its third row is (-cos p sin y, sin p, cos p cos y)
    and its second column (-sin r cos p, cos r cos p, sin p)."""
    r = np.asarray(rotation, dtype=np.float64)
    pitch = np.arcsin(np.clip(r[2, 1], -1.0, 1.0))
    yaw = np.arctan2(-r[2, 0], r[2, 2])
    roll = np.arctan2(-r[0, 1], r[1, 1])
    return tuple(float(v) for v in np.degrees([yaw, pitch, roll]))


def rotation_angle_deg(a, b) -> float:
    """Angle in degrees of the rotation a^T b between two (3, 3) rotations."""
    cos = (np.trace(np.asarray(a).T @ np.asarray(b)) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def transform(points, scale: float, rotation, translation) -> np.ndarray:
    """(N, 3) float64 world points scale * R @ p + t of model points (N, 3) in cm."""
    return scale * np.asarray(points, np.float64) @ np.asarray(rotation).T + np.asarray(translation)


def world_to_pixel(xy, rect, resolution) -> np.ndarray:
    """(N, 2) float64 (col, row) image coordinates of world points (N, 2+) on an image of
    resolution (W, H) covering rect (x0, x1, y0, y1). Pixel (i, j)'s centre is at (j, i)."""
    xy = np.asarray(xy, np.float64)
    x0, x1, y0, y1 = (float(c) for c in rect)
    width, height = resolution
    col = (xy[:, 0] - x0) * width / (x1 - x0) - 0.5
    row = (y1 - xy[:, 1]) * height / (y1 - y0) - 0.5
    return np.stack([col, row], axis=1)


def pixel_to_world(pixels, rect, resolution) -> np.ndarray:
    """(N, 2) float64 world (x, y) of image coordinates (N, 2) (col, row); inverse of
    `world_to_pixel`, so pixel centres land on DESIGN.md's x0 + (j + 0.5)(x1 - x0)/W."""
    pixels = np.asarray(pixels, np.float64)
    x0, x1, y0, y1 = (float(c) for c in rect)
    width, height = resolution
    x = x0 + (pixels[:, 0] + 0.5) * (x1 - x0) / width
    y = y1 - (pixels[:, 1] + 0.5) * (y1 - y0) / height
    return np.stack([x, y], axis=1)
