"""Fit the body model (body_model.py) to one person's BlazePose output: pose, shape, scale and
placement in the working crop's orthographic camera (compose.py: world square [-1, 1]^2,
looking along -Z, +Y up).

A fit is a sum of named residual terms, each a small function of the batched parameters,
their weights in `FitConfig`:

    keypoints   the model's 33 landmarks projected into the crop vs BlazePose's 2D landmarks,
                crop pixels, weighted by visibility;
    world       the hip-centred 3D landmarks (metres) vs BlazePose's world landmarks;
    pose_prior  the rotation away from the closed-form initialisation (radians);
    shape_prior the shape coefficients (units of their N(0, 1) prior);
    joint_limit the part of each bone's rotation from rest beyond its limit (radians);
    silhouette  two directions against the person's mask, crop pixels: `inside`, the mask's
                outside distance transform sampled at projected body points (the body may
                not leave the mask), and `cover`, each sampled mask contour point's distance
                to the nearest projected body point under a Geman-McClure loss (the body
                should reach the contour, but clothes and hair make the mask larger than the
                body, so this direction is weaker and robust).

Stages (SMPLify): 1. initial pose in closed form from the world landmarks' bone directions and
placement (scale, 2D offset) by weighted linear least squares against the 2D keypoints;
2. pose + placement; 3. pose + placement + shape, the silhouette terms added when there is a
usable mask; each by Levenberg-Marquardt (`levenberg_marquardt`) with a Jacobian by forward
differences evaluated as one batch of parameter vectors.

The turn's sign: the orthographic crop shows how far the torso is turned (the shoulders'
width), not which way, and BlazePose's world landmarks, which set the start, often say it
wrong. Its image landmarks' depths say it more often (`depth_side`): when they say the other
way firmly (TURN_WITNESS_MIN), the body is fitted again from the world landmarks turned to the
mirrored turn, and that fit is kept if it converges (`fit_body`'s `turn_witness`).

Only FIT_BONES rotate; every other bone keeps the identity, so its world transform is that of
its nearest rotating ancestor and the fit needs the transforms of those ~20 bones only.

Conventions: BlazePose world landmarks are x right, y down, z away from the camera (checked
on examples/skier.jpg: the nose at y -0.6, the near shoulder at negative z), so the model
frame (+Y up, facing +Z towards the camera) is (x, -y, -z). Crop pixels are (col, row) with
pixel (i, j)'s centre at x = -1 + (j + 0.5) 2/R, y = 1 - (i + 0.5) 2/R.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import lru_cache

import cv2
import numpy as np

from relightcli.compose import CROP_RECT
from relightcli.geometry.body_model import LANDMARK_NAMES, BodyModel
from relightcli.geometry.face_model import pixel_to_world, world_to_pixel

# The rotating bones and each one's limit (degrees of rotation away from MakeHuman's rest pose)
FIT_BONES = {
    "root": 180.0, "spine04": 35.0, "spine02": 30.0, "spine01": 30.0, "neck01": 45.0,
    "head": 60.0, "clavicle.L": 25.0, "clavicle.R": 25.0, "upperarm01.L": 160.0,
    "upperarm01.R": 160.0, "lowerarm01.L": 160.0, "lowerarm01.R": 160.0, "wrist.L": 90.0,
    "wrist.R": 90.0, "upperleg01.L": 140.0, "upperleg01.R": 140.0, "lowerleg01.L": 160.0,
    "lowerleg01.R": 160.0, "foot.L": 60.0, "foot.R": 60.0,
}
# Closed-form initialisation: (bone, landmarks its head sits on, landmarks it points to),
# parents first; a segment's ends are the mean of the named landmarks
LIMB_SEGMENTS = (
    ("upperarm01.L", ("left_shoulder",), ("left_elbow",)),
    ("upperarm01.R", ("right_shoulder",), ("right_elbow",)),
    ("lowerarm01.L", ("left_elbow",), ("left_wrist",)),
    ("lowerarm01.R", ("right_elbow",), ("right_wrist",)),
    ("wrist.L", ("left_wrist",), ("left_index", "left_pinky")),
    ("wrist.R", ("right_wrist",), ("right_index", "right_pinky")),
    ("upperleg01.L", ("left_hip",), ("left_knee",)),
    ("upperleg01.R", ("right_hip",), ("right_knee",)),
    ("lowerleg01.L", ("left_knee",), ("left_ankle",)),
    ("lowerleg01.R", ("right_knee",), ("right_ankle",)),
    ("foot.L", ("left_heel",), ("left_foot_index",)),
    ("foot.R", ("right_heel",), ("right_foot_index",)),
)
# Landmarks that must be present for a fit: the torso and the limbs' main joints
CORE_LANDMARKS = tuple(LANDMARK_NAMES.index(n) for n in (
    "left_shoulder", "right_shoulder", "left_elbow", "right_elbow", "left_wrist", "right_wrist",
    "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle"))
_L = {name: i for i, name in enumerate(LANDMARK_NAMES)}
_HIPS = (_L["left_hip"], _L["right_hip"])
_SHOULDERS = (_L["left_shoulder"], _L["right_shoulder"])


@dataclass(frozen=True)
class FitConfig:
    """Term weights (each residual is sqrt(weight) times the quantity in its unit) and the
    optimiser's settings. Defaults balance a 2 px keypoint error, a 3 cm world error and
    about 10 degrees of pose change from the initialisation."""

    keypoints: float = 1.0 / 2.0 ** 2       # per crop pixel^2
    world: float = 1.0 / 0.03 ** 2          # per m^2
    pose_prior: float = 1.0 / 0.5 ** 2      # per rad^2 away from the initialisation
    shape_prior: float = 1.0                # per unit coefficient^2
    joint_limit: float = 1.0 / 0.02 ** 2    # per rad^2 beyond a bone's limit
    pose_iterations: int = 20               # residual evaluations (max_nfev), stage 2
    shape_iterations: int = 15              # stage 3
    min_visibility: float = 0.5             # a keypoint counts as seen above this
    min_core_seen: int = 8                  # of the 12 CORE_LANDMARKS, else no fit
    max_residual_px: float = 6.0            # RMS keypoint residual at 512 px of a converged fit
    bone_limits: dict = field(default_factory=lambda: dict(FIT_BONES))
    # Silhouette (stage 3 only): weights per mean squared crop pixel over the points of a
    # direction, so the terms' pull does not grow with the number of points sampled
    silhouette_inside: float = 32.0         # body points outside the mask, per px^2
    silhouette_cover: float = 8.0           # mask contour away from the body, per px^2
    silhouette_cover_scale: float = 3.0     # px, the Geman-McClure loss's scale for `cover`
    silhouette_spacing: float = 0.06        # m between the body vertices projected (~600)
    silhouette_contour: int = 300           # mask contour points sampled
    silhouette_threshold: float = 0.5       # person probability counted as the mask
    silhouette_min_area: float = 0.005      # mask fraction of the crop below which none is used


@dataclass(frozen=True)
class BodyFit:
    """A fitted body: shape (K,) coefficients; rotations (J, 3, 3) local; translation (3,) and
    scale (crop world units per metre) such that `model.posed(shape, rotations, translation,
    scale)` gives vertices (V, 3) float64 in the crop's world frame (the photo's person under
    the orthographic crop camera, hips at depth 0); residual_px: RMS visible-keypoint error
    in crop pixels (nan when nothing was fitted); converged False with a reason on a fallback;
    silhouette_used: whether the silhouette terms took part (a usable mask was given);
    faces_camera: whether the fitted torso faces the camera (False: seen from behind);
    turn_mirrored: whether this is the refit to the mirrored turn the image landmarks' depths
    asked for (fit_body's `turn_witness`)."""

    shape: np.ndarray
    rotations: np.ndarray
    translation: np.ndarray
    scale: float
    vertices: np.ndarray
    residual_px: float
    converged: bool
    reason: str
    silhouette_used: bool = False
    faces_camera: bool = True
    turn_mirrored: bool = False


def blazepose_world_to_model(world: np.ndarray) -> np.ndarray:
    """(N, 3) model-frame points (+Y up, facing +Z) of BlazePose world landmarks (N, 3) m."""
    return np.asarray(world, np.float64) * np.array([1.0, -1.0, -1.0])


def crop_pixels_to_world(pixels: np.ndarray, resolution: int) -> np.ndarray:
    """(N, 2) crop world (x, y) of (N, 2) (col, row) pixels of an R x R crop."""
    return pixel_to_world(pixels, CROP_RECT, (resolution, resolution))


def observe_landmarks(model: BodyModel, shape, rotations, translation, scale: float,
                      resolution: int):
    """What a perfect BlazePose would report for a posed body: (33, 2) crop pixels (col, row)
    and (33, 3) hip-centred world landmarks in BlazePose's frame (x right, y down, m). The
    inverse of the conventions `fit_body` reads; the tests' and benchmark's ground truth."""
    _, _, landmarks = model.posed(shape, rotations, translation, scale)
    pixels = world_to_pixel(landmarks, CROP_RECT, (resolution, resolution))
    _, _, metric = model.posed(shape, rotations)
    metric = metric - metric[list(_HIPS)].mean(axis=0)
    return pixels, blazepose_world_to_model(metric)


# --- rotations -------------------------------------------------------------------------------

def axis_angle_to_matrix(vectors: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations of axis-angle vectors (..., 3) rad (Rodrigues)."""
    theta = np.linalg.norm(vectors, axis=-1)[..., None, None]
    k = np.zeros(vectors.shape[:-1] + (3, 3))
    x, y, z = vectors[..., 0], vectors[..., 1], vectors[..., 2]
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -z, y, -x
    k[..., 1, 0], k[..., 2, 0], k[..., 2, 1] = z, -y, x
    # sin(t)/t and (1 - cos t)/t^2 by their series near 0
    small = theta < 1e-6
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta ** 2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta ** 2 / 24.0, (1.0 - np.cos(safe)) / safe ** 2)
    return np.eye(3) + a * k + b * (k @ k)


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) the smallest rotation taking direction a (3,) to direction b (3,)."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    axis, cosine = np.cross(a, b), float(np.clip(a @ b, -1.0, 1.0))
    sine = np.linalg.norm(axis)
    if sine < 1e-9:
        if cosine > 0:
            return np.eye(3)
        # Opposite directions: half a turn about any axis perpendicular to a
        other = np.eye(3)[np.argmin(np.abs(a))]
        perpendicular = np.cross(a, other)
        return axis_angle_to_matrix(np.pi * perpendicular / np.linalg.norm(perpendicular))
    return axis_angle_to_matrix(axis / sine * np.arctan2(sine, cosine))


def rotation_angle(rotations: np.ndarray) -> np.ndarray:
    """(...,) rad angle of rotations (..., 3, 3), from |R - I|_F = 2 sqrt(2) sin(theta / 2)."""
    frobenius = np.linalg.norm(rotations - np.eye(3), axis=(-2, -1))
    return 2.0 * np.arcsin(np.clip(frobenius / (2.0 * np.sqrt(2.0)), 0.0, 1.0))


def _torso_frame(points: np.ndarray) -> np.ndarray:
    """(3, 3) columns: the person's left (hip to hip), up (hips to shoulders), forward."""
    left = points[_HIPS[0]] - points[_HIPS[1]]
    up = points[list(_SHOULDERS)].mean(axis=0) - points[list(_HIPS)].mean(axis=0)
    left = left / np.linalg.norm(left)
    up = up - (up @ left) * left
    up = up / np.linalg.norm(up)
    return np.stack([left, up, np.cross(left, up)], axis=1)


# --- the reduced skeleton --------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class _Skeleton:
    """The FIT_BONES of a model: ids (B,), each one's nearest rotating ancestor as an index
    into ids (-1 for the root), depth levels, and for each landmark the index of the rotating
    bone it moves with."""

    ids: np.ndarray
    parents: np.ndarray
    levels: tuple
    landmark_bone: np.ndarray
    limits: np.ndarray


def _skeleton(model: BodyModel, limits: dict) -> _Skeleton:
    ids = np.array([model.joint_names.index(name) for name in limits])
    order = np.argsort(ids)  # parents before children, as in the model
    ids, limit = ids[order], np.radians(np.array(list(limits.values())))[order]
    slot = {int(b): i for i, b in enumerate(ids)}

    def rotating_ancestor(bone: int) -> int:
        while bone >= 0 and bone not in slot:
            bone = int(model.joint_parents[bone])
        if bone < 0:
            raise ValueError("the model's root bone must be among the fit bones")
        return slot[bone]

    parents = np.array([-1 if model.joint_parents[b] < 0 else
                        rotating_ancestor(int(model.joint_parents[b])) for b in ids])
    depth = np.zeros(len(ids), np.int64)
    for i, p in enumerate(parents):
        depth[i] = 0 if p < 0 else depth[p] + 1
    levels = tuple(np.flatnonzero(depth == d) for d in range(depth.max() + 1))
    landmark_bone = np.array([rotating_ancestor(int(b)) for b in model.landmark_bones])
    return _Skeleton(ids, parents, levels, landmark_bone, limit)


# --- the closed-form initialisation ----------------------------------------------------------

def initial_pose(model: BodyModel, world_landmarks: np.ndarray, shape=None,
                 limits: dict | None = None) -> np.ndarray:
    """(J, 3, 3) local rotations that point the body's limbs along BlazePose world landmarks
    (33, 3) m (BlazePose frame). The root turns the rest torso frame (hips, shoulders) onto
    the landmarks'; then each LIMB_SEGMENTS bone, parents first, gets the smallest rotation
    taking its rest direction to the landmark segment seen through its parent's rotation.
    Spine, neck, head and clavicles stay at rest. Needs finite, non-collapsed landmarks."""
    target = blazepose_world_to_model(world_landmarks)
    rotations = model.rest_pose()
    rotations[0] = _torso_frame(target) @ _torso_frame(model.rest_landmarks(shape)).T
    directions = {bone: target[[_L[n] for n in tips]].mean(axis=0)
                  - target[[_L[n] for n in heads]].mean(axis=0)
                  for bone, heads, tips in LIMB_SEGMENTS}
    return aim_limbs(model, rotations, directions, shape)


def aim_limbs(model: BodyModel, rotations: np.ndarray, directions: dict, shape=None) -> np.ndarray:
    """(J, 3, 3) a copy of local rotations (J, 3, 3) with each LIMB_SEGMENTS bone named in
    `directions` (bone name -> (3,) model-frame direction), parents first, turned by the
    smallest rotation that points its rest segment along the direction given its parent's
    posed rotation. Near-zero directions leave the bone as it is."""
    rest = model.rest_landmarks(shape)
    rotations = np.array(rotations, np.float64)
    for bone, heads, tips in LIMB_SEGMENTS:
        direction = np.asarray(directions.get(bone, np.zeros(3)), np.float64)
        if np.linalg.norm(direction) < 1e-6:
            continue
        b = model.joint_names.index(bone)
        rest_direction = (rest[[_L[n] for n in tips]].mean(axis=0)
                          - rest[[_L[n] for n in heads]].mean(axis=0))
        parent = _global_rotation(model, rotations, int(model.joint_parents[b]))
        rotations[b] = rotation_between(rest_direction, parent.T @ direction)
    return rotations


def _global_rotation(model: BodyModel, rotations: np.ndarray, bone: int) -> np.ndarray:
    """(3, 3) the product of the local rotations from the root down to `bone`."""
    chain = []
    while bone >= 0:
        chain.append(bone)
        bone = int(model.joint_parents[bone])
    total = np.eye(3)
    for b in reversed(chain):
        total = total @ rotations[b]
    return total


# --- the silhouette ---------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class _BodyPoints:
    """The body points projected for the silhouette terms: rest (S, 3) m mean positions,
    basis (K, 3S) m per shape coefficient, weights (S, B) skinning weights over the fit
    bones (each skin bone's weight given to its nearest rotating ancestor)."""

    rest: np.ndarray
    basis: np.ndarray
    weights: np.ndarray


@dataclass(frozen=True, eq=False)
class _Silhouette:
    """A usable person mask: outside (R, R) float64 crop pixels, each pixel's distance to the
    mask (0 inside); contour (C, 2) crop world units, sampled mask contour points."""

    outside: np.ndarray
    contour: np.ndarray
    points: _BodyPoints


@lru_cache(maxsize=4)
def silhouette_vertices(model: BodyModel, spacing: float) -> np.ndarray:
    """(S,) int64 vertex ids spread evenly over the mean rest body: the first vertex in each
    cube of side `spacing` m, so the densely meshed face and hands get no more points than
    the limbs (0.06 m: about 600 of 13k)."""
    cells = np.floor(model.mean_vertices / spacing).astype(np.int64)
    _, first = np.unique(cells, axis=0, return_index=True)
    return np.sort(first)


def _body_points(model: BodyModel, skeleton: _Skeleton, spacing: float) -> _BodyPoints:
    ids = silhouette_vertices(model, spacing)
    slot = {int(b): i for i, b in enumerate(skeleton.ids)}

    def rotating_ancestor(bone: int) -> int:
        while bone not in slot:
            bone = int(model.joint_parents[bone])
        return slot[bone]

    ancestor = np.array([rotating_ancestor(b) for b in range(model.n_joints)])
    weights = np.zeros((len(ids), len(skeleton.ids)))
    rows = np.repeat(np.arange(len(ids)), model.skin_bones.shape[1])
    np.add.at(weights, (rows, ancestor[model.skin_bones[ids]].ravel()),
              model.skin_weights[ids].ravel())
    basis = model.shape_basis[:, ids].reshape(model.n_shape, -1)
    return _BodyPoints(model.mean_vertices[ids], basis, weights)


def body_silhouette(model: BodyModel, vertices: np.ndarray, resolution: int) -> np.ndarray:
    """(R, R) bool: the crop pixels whose centres the body's triangles cover, for posed
    vertices (V, 3) in the crop's world frame (one convex fill per triangle: cv2.fillPoly
    on many polygons fills by the even-odd rule, so overlaps would cancel)."""
    pixels = world_to_pixel(vertices, CROP_RECT, (resolution, resolution))
    triangles = np.round(pixels[model.triangles] * 16).astype(np.int32)  # 4 fraction bits
    image = np.zeros((resolution, resolution), np.uint8)
    for triangle in triangles:
        cv2.fillConvexPoly(image, triangle, 1, lineType=cv2.LINE_8, shift=4)
    return image > 0


def mask_contour(mask: np.ndarray, count: int, keep: np.ndarray | None = None) -> np.ndarray:
    """(C <= count, 2) float64 (col, row) pixels evenly spaced along the contours (outer and
    holes) of a bool mask (R, R), those on the crop's border left out (a person cut by the
    frame has no contour there) and, given keep (4,) = (col0, row0, col1, row1), those
    outside that box (other people in the same mask)."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return np.zeros((0, 2))
    points = np.concatenate([c.reshape(-1, 2) for c in contours]).astype(np.float64)
    border = (points == 0).any(axis=1) | (points == mask.shape[0] - 1).any(axis=1)
    if keep is not None:
        border |= ((points < keep[:2]) | (points > keep[2:])).any(axis=1)
    points = points[~border]
    if len(points) > count:
        points = points[np.linspace(0, len(points) - 1, count).round().astype(np.int64)]
    return points


def _silhouette(silhouette, model: BodyModel, skeleton: _Skeleton, keypoints, weight,
                config: FitConfig, resolution: int) -> _Silhouette | None:
    """The silhouette terms' data for a person probability map (R, R), or None when there is
    none to use: no map, non-finite values, a mask under config.silhouette_min_area or one
    with too few contour points off the crop's border."""
    if silhouette is None:
        return None
    probability = np.asarray(silhouette, np.float64)
    if not np.isfinite(probability).all():
        return None
    mask = probability > config.silhouette_threshold
    if mask.mean() < config.silhouette_min_area:
        return None
    # The contour near this person only: the seen keypoints' box, grown by a quarter of its
    # size for the head, hands and feet beyond the landmarks
    seen = world_to_pixel(keypoints[weight > 0], CROP_RECT, (resolution, resolution))
    low, high = seen.min(axis=0), seen.max(axis=0)
    margin = 0.25 * (high - low).max()
    contour = mask_contour(mask, config.silhouette_contour,
                           np.concatenate([low - margin, high + margin]))
    if len(contour) < 16:
        return None
    outside = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2,
                                    cv2.DIST_MASK_PRECISE).astype(np.float64)
    return _Silhouette(outside, crop_pixels_to_world(contour, resolution),
                       _body_points(model, skeleton, config.silhouette_spacing))


# --- the batched forward model and the named terms -------------------------------------------

@dataclass(frozen=True, eq=False)
class _Problem:
    """Everything a residual evaluation reads. Parameters: rotation vectors (B, 3) rad applied
    after the initial rotations, log scale (crop units per metre), 2D offset, shape (K,)."""

    model: BodyModel
    skeleton: _Skeleton
    initial: np.ndarray        # (B, 3, 3) initial local rotations of the fit bones
    keypoints: np.ndarray      # (33, 2) crop world units (0 where unseen)
    keypoint_weight: np.ndarray  # (33,) visibility, 0 where unseen
    world: np.ndarray          # (33, 3) model frame, hip-centred, m
    world_weight: np.ndarray   # (33,)
    pixels_per_unit: float
    config: FitConfig
    silhouette: _Silhouette | None = None  # stage 3 only

    @property
    def n_params(self) -> int:
        return 3 * len(self.skeleton.ids) + 3 + self.model.n_shape


def _unpack(problem: _Problem, params: np.ndarray):
    n_bones = len(problem.skeleton.ids)
    vectors = params[:, :3 * n_bones].reshape(len(params), n_bones, 3)
    scale = np.exp(params[:, 3 * n_bones])
    offset = params[:, 3 * n_bones + 1:3 * n_bones + 3]
    shape = params[:, 3 * n_bones + 3:]
    return vectors, scale, offset, shape


def _bone_transforms(problem: _Problem, local: np.ndarray, shape: np.ndarray):
    """Rotations (N, B, 3, 3) and translations (N, B, 3) m, rest -> posed, of the fit bones for
    local rotations (N, B, 3, 3) and shapes (N, K): G_b = G_a T(h_b) R_b T(-h_b), i.e.
    Q_b = Q_a R_b and t_b = Q_a (h_b - R_b h_b) + t_a for the nearest rotating ancestor a."""
    model, skeleton = problem.model, problem.skeleton
    heads = model.mean_joints[skeleton.ids] + np.einsum(
        "nk,kbc->nbc", shape, model.joint_basis[:, skeleton.ids])
    offsets = heads - np.einsum("nbij,nbj->nbi", local, heads)
    rotation, translation = local.copy(), offsets.copy()
    for level in skeleton.levels[1:]:
        parent = skeleton.parents[level]
        rotation[:, level] = rotation[:, parent] @ local[:, level]
        translation[:, level] = (np.einsum("nbij,nbj->nbi", rotation[:, parent], offsets[:, level])
                                 + translation[:, parent])
    return rotation, translation


def _posed_landmarks(problem: _Problem, rotation: np.ndarray, translation: np.ndarray,
                     shape: np.ndarray) -> np.ndarray:
    """(N, 33, 3) m, model frame: the landmarks, each moving rigidly with its rotating bone,
    of bone transforms (N, B, 3, 3), (N, B, 3) and shapes (N, K)."""
    model, bone = problem.model, problem.skeleton.landmark_bone
    rest = model.mean_landmarks + np.einsum("nk,klc->nlc", shape, model.landmark_basis)
    return np.einsum("nlij,nlj->nli", rotation[:, bone], rest) + translation[:, bone]


def _posed_body_points(points: _BodyPoints, rotation: np.ndarray, translation: np.ndarray,
                       shape: np.ndarray) -> np.ndarray:
    """(S, N, 2) m, model frame x, y of the silhouette body points for N parameter sets:
    linear-blend skinning over the fit bones' transforms (N, B, 3, 3), (N, B, 3), the x and
    y rows only, blended by one matrix product over the bones."""
    n, n_bones = rotation.shape[:2]
    affine = np.concatenate([rotation[:, :, :2], translation[:, :, :2, None]], axis=3)
    blended = (points.weights @ affine.transpose(1, 0, 2, 3).reshape(n_bones, n * 8))
    blended = blended.reshape(len(points.rest), n, 2, 4)
    rest = points.rest[:, None, :] + (shape @ points.basis).reshape(n, -1, 3).transpose(1, 0, 2)
    return (blended[..., 0] * rest[:, :, None, 0] + blended[..., 1] * rest[:, :, None, 1]
            + blended[..., 2] * rest[:, :, None, 2] + blended[..., 3])


def keypoint_residuals(projected, keypoints, weight, pixels_per_unit) -> np.ndarray:
    """(N, 66) crop pixels: projected landmarks (N, 33, 2) vs keypoints (33, 2), crop world
    units, times sqrt(weight) (33,)."""
    error = (projected - keypoints) * pixels_per_unit * np.sqrt(weight)[:, None]
    return error.reshape(len(projected), -1)


def world_residuals(landmarks, world, weight) -> np.ndarray:
    """(N, 99) m: hip-centred landmarks (N, 33, 3) vs world landmarks (33, 3), times
    sqrt(weight) (33,)."""
    centred = landmarks - landmarks[:, list(_HIPS)].mean(axis=1, keepdims=True)
    return ((centred - world) * np.sqrt(weight)[:, None]).reshape(len(landmarks), -1)


def pose_prior_residuals(vectors) -> np.ndarray:
    """(N, 3B) rad: the rotation vectors (N, B, 3) away from the initialisation."""
    return vectors.reshape(len(vectors), -1)


def shape_prior_residuals(shape) -> np.ndarray:
    """(N, K): shape coefficients in units of their N(0, 1) prior."""
    return shape


def joint_limit_residuals(local, limits) -> np.ndarray:
    """(N, B) rad: each bone's rotation from rest (N, B, 3, 3) beyond its limit (B,) rad."""
    return np.maximum(rotation_angle(local) - limits, 0.0)


def silhouette_inside_residuals(pixels, outside) -> np.ndarray:
    """(N, S) crop pixels: the distance of projected body points (N, S, 2) (col, row) beyond the
    mask's edge, by its outside distance transform (R, R) (distance to the nearest mask pixel
    centre, 0 inside) sampled bilinearly, at the nearest border pixel beyond the crop."""
    size = outside.shape[0]
    # Beyond the crop, the border's value: a mask touching the border may go on past it
    clamped = np.clip(pixels, 0.0, size - 1.0)
    base = np.minimum(np.floor(clamped).astype(np.int64), size - 2)
    fx, fy = (clamped - base).transpose(2, 0, 1)
    col, row = base[..., 0], base[..., 1]
    top = (1 - fx) * outside[row, col] + fx * outside[row, col + 1]
    bottom = (1 - fx) * outside[row + 1, col] + fx * outside[row + 1, col + 1]
    # The mask's edge lies half a pixel beyond its outermost pixel centres
    return np.maximum((1 - fy) * top + fy * bottom - 0.5, 0.0)


def silhouette_cover_residuals(points, contour, pixels_per_unit, loss_scale) -> np.ndarray:
    """(N, C) crop pixels: each mask contour point's (C, 2) distance d to the nearest projected
    body point (N, S, 2), both crop world units, under a Geman-McClure loss of scale c =
    `loss_scale` px (residual d c / sqrt(d^2 + c^2), at most c): gaps much wider than c, such
    as loose clothes or hair, hardly pull. The nearest point is found for the first parameter
    set and kept for the others: they are its forward-difference neighbours, and a minimum's
    derivative is the derivative at its minimiser."""
    body = points[0]
    nearest = np.argmin((body ** 2).sum(axis=1)[:, None] - 2.0 * body @ contour.T, axis=0)  # + |contour|^2
    distance = np.linalg.norm(points[:, nearest] - contour, axis=-1) * pixels_per_unit
    return distance * loss_scale / np.sqrt(distance ** 2 + loss_scale ** 2)


def _silhouette_residuals(problem: _Problem, rotation, translation, shape, scale,
                          offset) -> np.ndarray:
    """(N, S + C) the weighted silhouette terms of N parameter sets, in the crop camera."""
    cfg, silhouette = problem.config, problem.silhouette
    body = _posed_body_points(silhouette.points, rotation, translation, shape)
    projected = (scale[:, None] * body + offset).transpose(1, 0, 2)
    # Crop world -> (col, row) pixels, centres at integers (face_model.world_to_pixel)
    pixels = np.stack([(projected[..., 0] + 1.0) * problem.pixels_per_unit - 0.5,
                       (1.0 - projected[..., 1]) * problem.pixels_per_unit - 0.5], axis=-1)
    inside = silhouette_inside_residuals(pixels, silhouette.outside)
    cover = silhouette_cover_residuals(projected, silhouette.contour, problem.pixels_per_unit,
                                       cfg.silhouette_cover_scale)
    return np.concatenate([np.sqrt(cfg.silhouette_inside / inside.shape[1]) * inside,
                           np.sqrt(cfg.silhouette_cover / cover.shape[1]) * cover], axis=1)


def _residuals(problem: _Problem, params: np.ndarray) -> np.ndarray:
    """(N, M) the weighted sum-of-squares terms of N parameter sets (N, P)."""
    cfg = problem.config
    vectors, scale, offset, shape = _unpack(problem, params)
    local = problem.initial @ axis_angle_to_matrix(vectors)
    rotation, translation = _bone_transforms(problem, local, shape)
    landmarks = _posed_landmarks(problem, rotation, translation, shape)
    projected = scale[:, None, None] * landmarks[..., :2] + offset[:, None, :]
    terms = [
        np.sqrt(cfg.keypoints) * keypoint_residuals(projected, problem.keypoints,
                                                    problem.keypoint_weight,
                                                    problem.pixels_per_unit),
        np.sqrt(cfg.world) * world_residuals(landmarks, problem.world, problem.world_weight),
        np.sqrt(cfg.pose_prior) * pose_prior_residuals(vectors),
        np.sqrt(cfg.shape_prior) * shape_prior_residuals(shape),
        np.sqrt(cfg.joint_limit) * joint_limit_residuals(local, problem.skeleton.limits),
    ]
    if problem.silhouette is not None:
        terms.append(_silhouette_residuals(problem, rotation, translation, shape, scale,
                                           offset))
    return np.concatenate(terms, axis=1)


def _solve_stage(problem: _Problem, params: np.ndarray, free: np.ndarray,
                 iterations: int) -> np.ndarray:
    """(P,) the parameters after least squares over the `free` (P,) bool entries, the rest
    held; the Jacobian by forward differences, all perturbations in one batch."""
    step = 1e-6

    def full(x):
        batch = np.repeat(params[None], len(x), axis=0)
        batch[:, free] = x
        return batch

    def fun(x):
        return _residuals(problem, full(x[None]))[0]

    def jac(x):
        batch = np.vstack([x, x + step * np.eye(len(x))])
        values = _residuals(problem, full(batch))
        return ((values[1:] - values[0]) / step).T

    out = params.copy()
    out[free] = levenberg_marquardt(fun, jac, params[free], iterations)
    return out


def levenberg_marquardt(fun, jac, x: np.ndarray, evaluations: int) -> np.ndarray:
    """x (P,) lowering |fun(x)|^2 by Levenberg-Marquardt, from x: steps dx solving
    (J^T J + mu D) dx = -J^T r, D the running maximum of diag(J^T J) (Marquardt's scaling: each
    parameter's step in the units its residuals see it in, as MINPACK's with x_scale="jac"),
    mu lowered after a step that lowers the cost (Nielsen's rule, by how well the linear model
    predicted it) and raised, doubling its factor, after one that does not. At most
    `evaluations` calls of fun (the Jacobians not counted, as MINPACK counts them); stops
    early when the gradient or the step vanishes. fun: x (P,) -> r (M,); jac: x -> J (M, P).

    Written here (issue 50): scipy.optimize, for its MINPACK least_squares alone, took 0.11-0.19
    s of every process's start; measured against it on the eval scenes in docs/RESULTS.md."""
    x = np.asarray(x, np.float64).copy()
    r = fun(x)
    cost, calls = float(r @ r), 1
    jacobian = jac(x)
    normal, gradient = jacobian.T @ jacobian, jacobian.T @ r
    scale = np.where(np.diag(normal) > 0, np.diag(normal), 1.0)
    mu, raise_by = 1e-3, 2.0
    while calls < evaluations:
        try:
            step = np.linalg.solve(normal + mu * np.diag(scale), -gradient)
        except np.linalg.LinAlgError:
            break
        trial = fun(x + step)
        calls += 1
        trial_cost = float(trial @ trial)
        predicted = -(2.0 * step @ gradient + step @ normal @ step)
        if not (np.isfinite(trial_cost) and trial_cost < cost and predicted > 0):
            mu, raise_by = mu * raise_by, 2.0 * raise_by
            continue
        ratio = (cost - trial_cost) / predicted
        x, r, cost = x + step, trial, trial_cost
        jacobian = jac(x)
        normal, gradient = jacobian.T @ jacobian, jacobian.T @ r
        scale = np.maximum(scale, np.diag(normal))
        mu, raise_by = mu * max(1.0 / 3.0, 1.0 - (2.0 * ratio - 1.0) ** 3), 2.0
        if np.abs(step).max() <= 1e-8 * (np.abs(x).max() + 1e-8) or np.abs(gradient).max() <= 1e-12:
            break
    return x


# --- the fit ---------------------------------------------------------------------------------

# The image landmarks' depth difference, left minus right, over these pairs; firm when at
# least TURN_WITNESS_MIN torso lengths. Chosen on the 60 validation people (docs/RESULTS.md,
# "The fit's turn: its sign": its sign agrees with the true turn's more often than BlazePose's
# world torso's or the fit's, and where it is large it is right).
TURN_WITNESS_PAIRS = tuple((_L[f"left_{n}"], _L[f"right_{n}"])
                           for n in ("shoulder", "elbow", "wrist", "hip", "knee", "ankle"))
TURN_WITNESS_MIN = 0.5


def depth_side(landmarks) -> float:
    """BlazePose's image landmarks (33, >= 3: x, y, z in one pixel unit, z toward the camera
    negative) -> the mean depth of the left limbs' landmarks minus the right's, in 2D torso
    lengths (hips' midpoint to shoulders'): > 0 when the left side is farther, i.e. the torso
    turned toward the viewer's right (a positive yaw about +Y in the model frame); nan when
    not finite."""
    points = np.asarray(landmarks, np.float64)[:, :3]
    torso = np.linalg.norm(points[list(_SHOULDERS), :2].mean(axis=0) - points[list(_HIPS), :2].mean(axis=0))
    side = np.mean([points[left, 2] - points[right, 2] for left, right in TURN_WITNESS_PAIRS]) / max(torso, 1e-9)
    return float(side) if np.isfinite(side) else float("nan")


def torso_yaw(points: np.ndarray) -> float:
    """Radians the torso of model-frame landmarks (33, 3) is turned about +Y, 0 facing +Z."""
    forward = _torso_frame(points)[:, 2]
    return float(np.arctan2(forward[0], forward[2]))


def turn_world(world: np.ndarray, yaw: float) -> np.ndarray:
    """BlazePose world landmarks (33, 3) turned about the vertical through the hips so that
    their torso's yaw (torso_yaw) is `yaw` radians."""
    points = blazepose_world_to_model(world)
    angle = yaw - torso_yaw(points)
    cos, sin = np.cos(angle), np.sin(angle)
    turned = points @ np.array([[cos, 0.0, sin], [0.0, 1.0, 0.0], [-sin, 0.0, cos]]).T
    return turned * np.array([1.0, -1.0, -1.0])


def fit_body(model: BodyModel, keypoints_2d, visibility, world, silhouette=None,
             config: FitConfig = FitConfig(), resolution: int | None = None,
             turn_witness: float | None = None) -> BodyFit:
    """Fit pose, shape, scale and placement to one person.

    keypoints_2d (33, 2) crop pixels (col, row) of an R x R crop; visibility (33,) in [0, 1];
    world (33, 3) BlazePose world landmarks, m, hip-centred, y down (None: missing);
    silhouette (R, R) person probability or None (sets R; the mask is where it exceeds
    config.silhouette_threshold; non-finite or nearly empty maps are not used, see
    BodyFit.silhouette_used); resolution R when there is no silhouette. Never raises on
    missing, NaN or collapsed landmarks: those, a person too little seen, and 2D keypoints
    and world landmarks with left and right on opposite sides give a rest-pose body with
    converged False and the reason; a fit whose keypoint residual stays above
    config.max_residual_px (at 512 px) comes back with converged False too. A person seen
    from behind or sitting is fitted like any other (BodyFit.faces_camera False from behind).
    turn_witness: the image landmarks' witness of the turn's sign (depth_side above; None or
    nan: none): a converged fit facing the camera whose turn it firmly contradicts is fitted again
    from the world landmarks turned to the mirrored turn (turn_world), kept if that converges.
    """
    fit = _fit(model, keypoints_2d, visibility, world, silhouette, config, resolution)
    if turn_witness is None or not np.isfinite(turn_witness) or abs(turn_witness) < TURN_WITNESS_MIN:
        return fit
    if not (fit.converged and fit.faces_camera):
        return fit
    _, _, landmarks = model.posed(fit.shape, fit.rotations)
    yaw = torso_yaw(landmarks)
    if np.sign(yaw) == np.sign(turn_witness):
        return fit
    mirrored = _fit(model, keypoints_2d, visibility, turn_world(world, -yaw), silhouette, config, resolution)
    return replace(mirrored, turn_mirrored=True) if mirrored.converged else fit


def _fit(model: BodyModel, keypoints_2d, visibility, world, silhouette, config: FitConfig,
         resolution: int | None) -> BodyFit:
    """fit_body without the turn's witness."""
    resolution = _resolution(silhouette, resolution)
    keypoints, weight = _seen_keypoints(keypoints_2d, visibility, resolution, config)
    reason = _input_problem(keypoints, weight, world, config)
    if reason is not None:
        return _fallback(model, keypoints, weight, resolution, reason)
    world = np.asarray(world, np.float64)
    skeleton = _skeleton(model, config.bone_limits)
    rotations = initial_pose(model, world)
    problem = _Problem(model, skeleton, rotations[skeleton.ids], keypoints, weight,
                       _hip_centred(blazepose_world_to_model(world)), np.ones(33),
                       resolution / 2.0, config)
    # Stage 1: placement in closed form for the initial pose
    _, _, landmarks = model.posed(None, rotations)
    scale, offset = _placement(landmarks[:, :2], keypoints, weight)
    params = np.zeros(problem.n_params)
    n_rot = 3 * len(problem.skeleton.ids)
    params[n_rot], params[n_rot + 1:n_rot + 3] = np.log(scale), offset
    # Stage 2: pose and placement; stage 3: everything, shape included
    free = np.arange(problem.n_params) < n_rot + 3
    params = _solve_stage(problem, params, free, config.pose_iterations)
    mask = _silhouette(silhouette, model, skeleton, keypoints, weight, config, resolution)
    params = _solve_stage(replace(problem, silhouette=mask), params, np.ones_like(free),
                          config.shape_iterations)
    return replace(_finish(problem, params, resolution), silhouette_used=mask is not None)


def _resolution(silhouette, resolution) -> int:
    if silhouette is not None:
        silhouette = np.asarray(silhouette)
        if silhouette.ndim != 2 or silhouette.shape[0] != silhouette.shape[1]:
            raise ValueError(f"silhouette must be a square (R, R) map, got {silhouette.shape}")
        if resolution is not None and resolution != silhouette.shape[0]:
            raise ValueError(f"resolution {resolution} differs from the silhouette's "
                             f"{silhouette.shape[0]}")
        return silhouette.shape[0]
    if resolution is None or resolution < 8:
        raise ValueError(f"fit_body needs the crop resolution (>= 8), got {resolution!r}")
    return int(resolution)


def _seen_keypoints(keypoints_2d, visibility, resolution: int, config: FitConfig):
    """(33, 2) crop world units (0 where unusable) and (33,) weights: the visibility where
    it passes config.min_visibility and the keypoint is finite, else 0."""
    pixels = np.asarray(keypoints_2d, np.float64)
    seen = np.asarray(visibility, np.float64)
    if pixels.shape != (33, 2) or seen.shape != (33,):
        raise ValueError(f"keypoints must be (33, 2) and visibility (33,), got {pixels.shape} "
                         f"and {seen.shape}")
    usable = np.isfinite(pixels).all(axis=1) & np.isfinite(seen) & (seen > config.min_visibility)
    pixels = np.where(usable[:, None], pixels, 0.0)
    return crop_pixels_to_world(pixels, resolution), np.where(usable, seen, 0.0)


def _input_problem(keypoints, weight, world, config: FitConfig) -> str | None:
    """Why these inputs cannot be fitted, or None."""
    core = list(CORE_LANDMARKS)
    n_seen = int(np.count_nonzero(weight[core]))
    if n_seen < config.min_core_seen:
        return (f"only {n_seen} of the 12 main joints seen (person cut by the frame or "
                f"occluded)")
    seen = keypoints[core][weight[core] > 0]
    if np.ptp(seen, axis=0).max() < 1e-3:
        return "the 2D keypoints collapse to a point"
    if world is None:
        return "no world landmarks"
    world = np.asarray(world, np.float64)
    if world.shape != (33, 3) or not np.isfinite(world).all():
        return "world landmarks missing or not finite"
    points = blazepose_world_to_model(world)
    hips = np.linalg.norm(points[_HIPS[0]] - points[_HIPS[1]])
    torso = np.linalg.norm(points[list(_SHOULDERS)].mean(0) - points[list(_HIPS)].mean(0))
    if hips < 0.02 or torso < 0.1:
        return "world landmarks collapsed (hips or torso shorter than 2 cm / 10 cm)"
    if _sides_disagree(keypoints, weight, points):
        return "the 2D keypoints and the world landmarks put left and right on opposite sides"
    return None


def _sides_disagree(keypoints, weight, points, clear: float = 0.2) -> bool:
    """Whether the 2D keypoints and the world landmarks (model frame) place the person's left
    on opposite sides of the image: each side's left-minus-right x of hips plus shoulders,
    over its torso length, beyond `clear` and of opposite signs (a side view, where both are
    near 0, never disagrees). A person seen from behind agrees: both have the left on the
    image's left. Keypoints not seen leave the 2D side undecided."""
    pairs = (_HIPS, _SHOULDERS)
    if not all(weight[i] > 0 for pair in pairs for i in pair):
        return False

    def side(p):
        across = sum(p[left, 0] - p[right, 0] for left, right in pairs)
        torso = np.linalg.norm(p[list(_SHOULDERS), :2].mean(0) - p[list(_HIPS), :2].mean(0))
        return across / max(torso, 1e-9)

    flat, deep = side(keypoints), side(points)
    return flat * deep < 0 and min(abs(flat), abs(deep)) > clear


def _hip_centred(points: np.ndarray) -> np.ndarray:
    return points - points[list(_HIPS)].mean(axis=0)


def _placement(points: np.ndarray, keypoints: np.ndarray, weight: np.ndarray):
    """Scale s and offset o (2,) minimising sum w |s p + o - y|^2 for model points p (33, 2)
    and keypoints y (33, 2): weighted linear least squares, centred."""
    total = weight.sum()
    p_mean = (weight[:, None] * points).sum(0) / total
    y_mean = (weight[:, None] * keypoints).sum(0) / total
    p, y = points - p_mean, keypoints - y_mean
    scale = float((weight[:, None] * p * y).sum() / max((weight[:, None] * p * p).sum(), 1e-12))
    return scale, y_mean - scale * p_mean


def _finish(problem: _Problem, params: np.ndarray, resolution: int) -> BodyFit:
    model, skeleton, cfg = problem.model, problem.skeleton, problem.config
    vectors, scale, offset, shape = _unpack(problem, params[None])
    rotations = model.rest_pose()
    rotations[skeleton.ids] = problem.initial @ axis_angle_to_matrix(vectors[0])
    # Re-orthonormalise (the posed model checks) and keep the shape inside its prior's range
    u, _, vt = np.linalg.svd(rotations)
    rotations = u @ vt
    shape = np.clip(shape[0], -4.0, 4.0)
    scale = float(scale[0])
    if not np.all(np.isfinite(params)) or not (0 < scale < 1e3):
        return _fallback(model, problem.keypoints, problem.keypoint_weight, resolution,
                         "the fit diverged")
    _, _, landmarks = model.posed(shape, rotations)
    hips_z = landmarks[list(_HIPS), 2].mean()
    translation = np.array([offset[0, 0], offset[0, 1], -scale * hips_z])
    vertices, _, landmarks = model.posed(shape, rotations, translation, scale)
    residual = _residual_px(landmarks, problem.keypoints, problem.keypoint_weight, resolution)
    limit = cfg.max_residual_px * resolution / 512.0
    converged = residual <= limit
    reason = "" if converged else (f"fit did not converge: {residual:.1f} px RMS keypoint "
                                   f"error, limit {limit:.1f}")
    return BodyFit(shape, rotations, translation, scale, vertices, residual, converged, reason,
                   faces_camera=bool(_torso_frame(landmarks)[2, 2] >= 0.0))


def _residual_px(landmarks, keypoints, weight, resolution: int) -> float:
    """RMS crop-pixel distance of the seen keypoints, weighted by visibility."""
    error = np.linalg.norm(landmarks[:, :2] - keypoints, axis=1) * resolution / 2.0
    return float(np.sqrt((weight * error ** 2).sum() / max(weight.sum(), 1e-12)))


def _fallback(model: BodyModel, keypoints, weight, resolution: int, reason: str) -> BodyFit:
    """The rest-pose mean body, placed on the seen keypoints when they allow it (else
    filling the crop), converged False with `reason`."""
    _, _, landmarks = model.posed(None, model.rest_pose())
    scale, offset = 1.0, np.zeros(2)
    if np.count_nonzero(weight) >= 2:
        s, o = _placement(landmarks[:, :2], keypoints, weight)
        if np.isfinite(s) and s > 1e-3 and np.all(np.isfinite(o)):
            scale, offset = s, o
    translation = np.array([offset[0], offset[1], 0.0])
    vertices, _, _ = model.posed(None, model.rest_pose(), translation, scale)
    return BodyFit(np.zeros(model.n_shape), model.rest_pose(), translation, scale, vertices,
                   float("nan"), False, reason)
