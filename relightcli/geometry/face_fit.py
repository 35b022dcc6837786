"""Fit the face model to 2D landmarks of a face crop: identity, expression and pose.

Model (face_model.py): landmark l of the face is p_l(c) = mu_l + B_l c in cm, c = [identity,
expression]; the crop sees its weak-perspective image y_l = s R[:2] p_l(c) + t in world units
of the crop (DESIGN.md camera: x right, y up, looking along -Z).

Alternating least squares, each step the exact minimiser of its own sub-problem:
1. pose: the weighted affine camera y = A p + t by linear least squares, then A projected onto
   the nearest scaled orthographic camera s [r1; r2] (orthogonal Procrustes via the SVD of A:
   r1, r2 = rows of U V^T, s = mean singular value), r3 = r1 x r2;
2. shape: the ridge-regularised linear solve for c with expressions bounded to [0, 1]
   (bounded-variable least squares), in cm so the prior does not depend on the image scale;
3. robust weights (Cauchy) from the residuals, so a few wrong landmarks do not pull the fit.
An optional depth map places the face along z (orthographic images do not see depth).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from relightcli.errors import InputError, NumericalError
from relightcli.geometry.face_model import FaceModel, pixel_to_world, transform, world_to_pixel

# Landmark noise (pixels of the crop) that sets the balance between data and the N(0, 1) prior
DEFAULT_LANDMARK_SIGMA_PX = 1.0
# Prior standard deviation of an expression weight (expressions are rare and sparse)
EXPRESSION_PRIOR_SIGMA = 0.5
# Cauchy scale: this many robust standard deviations, at least ROBUST_FLOOR_CM
ROBUST_SCALE = 2.5
ROBUST_FLOOR_CM = 0.15
MIN_LANDMARKS = 8
# Jaw-line landmarks (0-16) sit on the silhouette, not on fixed skin: no depth from them
INTERIOR_LANDMARKS = np.arange(17, 68)


@dataclass
class FaceFit:
    """A fitted face in the crop's camera frame.

    identity (K,) float64 (N(0, 1) units); expression (E,) float64 in [0, 1]; rotation (3, 3)
    float64 model -> camera; scale: world units of the crop per cm; translation (3,) world
    units (z from the depth map, else 0); residual_px: weighted RMS landmark distance in
    pixels of the crop; inliers (68,) bool: landmarks the robust loss kept (weight > 0.5);
    rect (x0, x1, y0, y1) and resolution (W, H) of the crop; iterations run.
    """

    identity: np.ndarray
    expression: np.ndarray
    rotation: np.ndarray
    scale: float
    translation: np.ndarray
    residual_px: float
    inliers: np.ndarray
    rect: tuple
    resolution: tuple
    iterations: int
    model: FaceModel = field(repr=False)

    def vertices(self) -> np.ndarray:
        """(V, 3) float64 vertices in world units of the crop's camera frame."""
        return transform(self.model.vertices(self.identity, self.expression), self.scale,
                         self.rotation, self.translation)

    def landmarks_px(self) -> np.ndarray:
        """(68, 2) float64 (col, row) of the fitted landmarks in the crop."""
        points = transform(self.model.landmarks(self.identity, self.expression), self.scale,
                           self.rotation, self.translation)
        return world_to_pixel(points, self.rect, self.resolution)


def fit_face(landmarks_px, model: FaceModel, rect, resolution, *, weights=None, depth=None,
             landmark_sigma_px: float = DEFAULT_LANDMARK_SIGMA_PX, robust: bool = True,
             iterations: int = 15, tolerance: float = 1e-4) -> FaceFit:
    """Fit identity, expression and pose to 68 landmarks of a crop.

    landmarks_px (68, 2) float (col, row), iBUG-68 order, pixel (i, j)'s centre at (j, i); NaN
    rows are missing landmarks. rect (x0, x1, y0, y1): the world rectangle the crop covers;
    resolution (W, H) of the crop. weights (68,) >= 0: per-landmark confidence (default 1).
    depth (H, W) float32 world z of the visible surface (NaN where unknown), optional.
    landmark_sigma_px: landmark noise; larger trusts the shape prior more.
    Raises InputError when fewer than 8 usable landmarks are given, NumericalError when the
    fit degenerates.
    """
    observed, base_weights = _check_landmarks(landmarks_px, weights, model)
    y = pixel_to_world(np.nan_to_num(observed), rect, resolution)
    pixel_size = (float(rect[1]) - float(rect[0])) / resolution[0]
    state = _initial_state(model, y, base_weights)
    w = base_weights.copy()
    for iteration in range(1, iterations + 1):
        sigma_cm = max(landmark_sigma_px, 1e-3) * pixel_size / state.scale
        step = _gauss_newton_step(state, model, y, w, sigma_cm)
        if robust and iteration > 1:
            w = base_weights * _cauchy_weights(_residual_cm(state, model, y), base_weights)
        if step < tolerance:
            break
    fit = FaceFit(identity=state.c[:model.n_identity], expression=state.c[model.n_identity:],
                  rotation=state.rotation, scale=float(state.scale),
                  translation=np.array([state.t[0], state.t[1], 0.0]), residual_px=0.0,
                  inliers=w > 0.5 * base_weights, rect=tuple(float(v) for v in rect),
                  resolution=tuple(resolution), iterations=iteration, model=model)
    if depth is not None:
        fit.translation[2] = _depth_offset(fit, depth, base_weights)
    fit.residual_px = _weighted_rms(fit.landmarks_px() - observed, w)
    return fit


def face_mesh(fit: FaceFit, *, face_only: bool = False):
    """The fitted face as a geometry.mesh.TriangleMesh in the crop's camera frame (world units,
    +Z to the viewer), pixel-aligned with the crop. face_only keeps the face region (no back of
    head, no neck)."""
    from relightcli.geometry.mesh import TriangleMesh

    vertices, triangles = fit.vertices(), fit.model.triangles
    if face_only:
        keep = np.all(fit.model.face_region[triangles], axis=1)
        used, triangles = np.unique(triangles[keep], return_inverse=True)
        vertices, triangles = vertices[used], triangles.reshape(-1, 3)
    return TriangleMesh(vertices, triangles)


# ---------------------------------------------------------------------------- steps

def _check_landmarks(landmarks_px, weights, model):
    points = np.asarray(landmarks_px, dtype=np.float64)
    n = model.landmark_indices.size
    if points.shape != (n, 2):
        raise InputError(f"face landmarks must have shape ({n}, 2), got {points.shape}",
                         fix="pass the 68 iBUG-order landmarks as (col, row) pixels")
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w < 0):
        raise InputError(f"landmark weights must be {n} finite numbers >= 0",
                         fix="pass one confidence per landmark, 0 for a missing one")
    w = np.where(np.all(np.isfinite(points), axis=1), w, 0.0)
    if np.count_nonzero(w) < MIN_LANDMARKS:
        raise InputError(f"only {np.count_nonzero(w)} usable face landmarks "
                         f"(at least {MIN_LANDMARKS} needed)", fix="skip the face stage")
    return points, w / w[w > 0].mean()


@dataclass
class _State:
    """Current estimate: rotation (3, 3), scale (world per cm), t (2,) world, c (K + E,)."""

    rotation: np.ndarray
    scale: float
    t: np.ndarray
    c: np.ndarray


def _initial_state(model: FaceModel, y, w) -> _State:
    """Pose of the neutral face: the weighted affine camera y = A p + t by least squares,
    projected onto the nearest scaled orthographic camera s [r1; r2] (orthogonal Procrustes:
    U V^T of the SVD of A, s its mean singular value), r3 = r1 x r2."""
    points = model.landmark_neutral
    total = w.sum()
    p_mean, y_mean = w @ points / total, w @ y / total
    pc, yc = points - p_mean, y - y_mean
    gram = pc.T @ (w[:, None] * pc)
    affine = np.linalg.solve(gram, pc.T @ (w[:, None] * yc)).T
    u, singular, vt = np.linalg.svd(affine, full_matrices=False)
    scale = singular.mean()
    if not np.isfinite(scale) or scale <= 0:
        raise NumericalError("face pose fit degenerated (landmarks collinear or coincident)",
                             fix="check the landmarks, or skip the face stage")
    r2 = u @ vt
    rotation = np.vstack([r2, np.cross(r2[0], r2[1])])
    c = np.zeros(model.landmark_basis.shape[-1])
    return _State(rotation, float(scale), y_mean - scale * r2 @ p_mean, c)


def _residual_cm(state: _State, model: FaceModel, y) -> np.ndarray:
    """(L, 2) landmark residuals (y - s R2 p(c) - t) / s, in cm."""
    q = (model.landmark_neutral + model.landmark_basis @ state.c) @ state.rotation.T
    return (y - state.scale * q[:, :2] - state.t) / state.scale


def _gauss_newton_step(state: _State, model: FaceModel, y, w, sigma_cm) -> float:
    """One regularised Gauss-Newton step on (rotation, log scale, t, c), in place.

    Minimises sum_l w_l |r_l - J_l d|^2 / sigma^2 + |P (c + dc)|^2, expressions kept in
    [0, 1]; in cm units, J_l = [-[q_l]x[:2], q_l[:2], I2, R2 B_l] for q_l = R p_l.
    Returns the largest coefficient change."""
    k = model.n_identity
    q = (model.landmark_neutral + model.landmark_basis @ state.c) @ state.rotation.T
    r = _residual_cm(state, model, y)
    jacobian = np.empty((q.shape[0], 2, 6 + state.c.size))
    jacobian[:, 0, :3] = np.stack([np.zeros_like(q[:, 0]), q[:, 2], -q[:, 1]], axis=1)
    jacobian[:, 1, :3] = np.stack([-q[:, 2], np.zeros_like(q[:, 0]), q[:, 0]], axis=1)
    jacobian[:, :, 3] = q[:, :2]
    jacobian[:, :, 4:6] = np.eye(2)
    jacobian[:, :, 6:] = np.einsum("ij,ljm->lim", state.rotation[:2], model.landmark_basis)
    root = np.sqrt(w)[:, None, None] / sigma_cm
    design = (root * jacobian).reshape(-1, jacobian.shape[-1])
    target = (root[:, :, 0] * r).reshape(-1)
    prior = np.zeros(jacobian.shape[-1])
    prior[6:6 + k], prior[6 + k:] = 1.0, 1.0 / EXPRESSION_PRIOR_SIGMA
    hessian = design.T @ design + np.diag(prior ** 2 + 1e-9)
    gradient = design.T @ target - prior ** 2 * np.concatenate([np.zeros(6), state.c])
    lower = np.full(hessian.shape[0], -np.inf)
    upper = np.full(hessian.shape[0], np.inf)
    lower[6 + k:], upper[6 + k:] = -state.c[k:], 1.0 - state.c[k:]
    delta = solve_box_qp(hessian, gradient, lower, upper)
    state.rotation = _rodrigues(delta[:3]) @ state.rotation
    state.scale *= float(np.exp(delta[3]))
    state.t = state.t + state.scale * delta[4:6]
    state.c = state.c + delta[6:]
    state.c[k:] = np.clip(state.c[k:], 0.0, 1.0)
    if not (np.all(np.isfinite(state.c)) and np.isfinite(state.scale)):
        raise NumericalError("face fit produced non-finite values",
                             fix="check the landmarks, or skip the face stage")
    return float(np.max(np.abs(delta)))


def _rodrigues(omega) -> np.ndarray:
    """(3, 3) rotation exp([omega]x) for a rotation vector omega (3,) in radians."""
    angle = np.linalg.norm(omega)
    if angle < 1e-12:
        return np.eye(3)
    kx, ky, kz = omega / angle
    cross = np.array([[0, -kz, ky], [kz, 0, -kx], [-ky, kx, 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def solve_box_qp(hessian, gradient, lower, upper, max_iterations: int = 200) -> np.ndarray:
    """argmin 0.5 x^T H x - g^T x subject to lower <= x <= upper (primal active set).

    hessian (n, n) symmetric positive definite, gradient (n,), bounds (n,) with lower <= 0 <=
    upper (x = 0 is feasible; infinite bounds allowed). Returns x (n,) float64; raises
    NumericalError when the active set has not settled after max_iterations solves."""
    x = np.zeros(gradient.size)
    # Start with every variable that sits on a bound held there (warm start: expressions at
    # 0 usually stay there, and releasing a few is cheaper than blocking many)
    at_lower = lower == 0.0
    at_upper = (upper == 0.0) & ~at_lower
    for _ in range(max_iterations):
        fixed = at_lower | at_upper
        free = ~fixed
        target = np.where(at_lower, lower, np.where(at_upper, upper, 0.0))
        rhs = gradient[free] - hessian[np.ix_(free, fixed)] @ target[fixed]
        candidate = target.copy()
        candidate[free] = np.linalg.solve(hessian[np.ix_(free, free)], rhs)
        below, above = free & (candidate < lower), free & (candidate > upper)
        if below.any() or above.any():
            # Walk from x toward the candidate until the first bound blocks the way
            direction = candidate - x
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.where(below, (lower - x) / direction,
                                 np.where(above, (upper - x) / direction, np.inf))
            blocking = int(np.argmin(ratio))
            x = np.clip(x + max(ratio[blocking], 0.0) * direction, lower, upper)
            at_lower[blocking], at_upper[blocking] = below[blocking], above[blocking]
            continue
        x = candidate
        # KKT: the objective's gradient must point into the bound for every fixed variable
        slope = hessian @ x - gradient
        wrong = np.where(at_lower, -slope, 0.0) + np.where(at_upper, slope, 0.0)
        if not np.any(wrong > 1e-12):
            return x
        release = int(np.argmax(wrong))
        at_lower[release] = at_upper[release] = False
    raise NumericalError("bounded least squares did not converge",
                         fix="check the landmarks, or skip the face stage")


def _cauchy_weights(residual_cm, base_weights):
    """(L,) Cauchy weights 1 / (1 + (|r| / c)^2), c from the median absolute residual."""
    norm = np.linalg.norm(residual_cm, axis=1)
    sigma = 1.4826 * np.median(norm[base_weights > 0])
    c = max(ROBUST_SCALE * sigma, ROBUST_FLOOR_CM)
    return 1.0 / (1.0 + (norm / c) ** 2)


def _weighted_rms(residual, w) -> float:
    valid = w > 0
    squared = np.sum(np.nan_to_num(residual[valid]) ** 2, axis=1)
    return float(np.sqrt(w[valid] @ squared / w[valid].sum()))


def _depth_offset(fit: FaceFit, depth, base_weights) -> float:
    """z translation (world units) that puts the interior landmarks on the depth map:
    the median of depth - model z over the landmarks that fall on known depth."""
    depth = np.asarray(depth, dtype=np.float64)
    width, height = fit.resolution
    if depth.shape != (height, width):
        raise InputError(f"face depth map must be {height}x{width}, got {depth.shape}",
                         fix="pass the depth of the same crop as the landmarks")
    points = transform(fit.model.landmarks(fit.identity, fit.expression), fit.scale,
                       fit.rotation, fit.translation)[INTERIOR_LANDMARKS]
    cols, rows = np.rint(world_to_pixel(points, fit.rect, fit.resolution)).astype(int).T
    inside = (cols >= 0) & (cols < width) & (rows >= 0) & (rows < height)
    inside &= base_weights[INTERIOR_LANDMARKS] > 0
    z = np.full(points.shape[0], np.nan)
    z[inside] = depth[rows[inside], cols[inside]]
    known = np.isfinite(z)
    if not np.any(known):
        return 0.0
    return float(np.median(z[known] - points[known, 2]))
