"""Normal maps -> depth maps: bilateral normal integration (after Cao et al., ECCV 2022, "BiNI"),
orthographic case, solved directly (sparse LU) inside iteratively reweighted least squares.

Under DESIGN.md's orthographic camera a surface z(x, y) with normal n has dz/dx = -n_x / n_z and
dz/dy = -n_y / n_z, the same for a front (n_z > 0) and a back (n_z < 0) surface. On the pixel
grid (column j -> x grows by h_x, row i -> y falls by h_y) each pixel p with a neighbour q in
the mask gives one equation, multiplied through by n_z so that edge-on normals (n_z -> 0)
weaken an equation instead of dividing by zero:

    right: n_z (z_q - z_p) = -n_x h_x        left:  n_z (z_p - z_q) = -n_x h_x
    down:  n_z (z_q - z_p) =  n_y h_y        up:    n_z (z_p - z_q) =  n_y h_y

BiNI weights the two one-sided equations of each axis, w+ = sigmoid(k ((D- z)^2 - (D+ z)^2)),
w- = 1 - w+, so that across a depth jump (an arm in front of the body) the side that jumps
stops pulling: the jump stays sharp instead of being smeared. Depths are in units of h_x while
solving, so the sharpness k (BiNI's default 2) does not depend on the crop's world size.

Normals fix depth up to one constant per connected region. A term prior_weight (z - prior)^2
per pixel sets it: toward a given depth prior (e.g. the net's depth), otherwise toward 0 with a
negligible weight, and each region is then shifted to zero mean. The term also makes the
system positive definite on any mask (single pixels, one-pixel limbs, holes).
"""

from __future__ import annotations

import warnings

import numpy as np
import scipy.ndimage
import scipy.sparse
import scipy.sparse.linalg

from relightcli.errors import InputError, NumericalError, RelightWarning

SHARPNESS = 2.0
NO_PRIOR_WEIGHT = 1e-8
# A direct solve whose relative residual exceeds this has failed
MAX_RELATIVE_RESIDUAL = 1e-6


def integrate_normals(normals, mask, rect, *, depth_prior=None, prior_weight: float = 1e-3,
                      sharpness: float = SHARPNESS, max_iterations: int = 10,
                      tolerance: float = 1e-4, mask_threshold: float = 0.5) -> np.ndarray:
    """Depth map whose surface has the given normals.

    normals: (H, W, 3) float, unit vectors in the camera frame (+Z toward the viewer), front
    (n_z > 0) or back (n_z < 0) surface. mask: (H, W) bool or float in [0, 1]. rect:
    (x0, x1, y0, y1) world rectangle of the crop. depth_prior: (H, W) float world z or None;
    prior_weight: its weight per pixel relative to one normal equation (ignored without prior).
    sharpness: BiNI's k (0 gives plain least squares, no jump detection). max_iterations and
    tolerance: reweighting stops when the relative energy change is below tolerance.
    Returns (H, W) float32 world z on the mask, 0 outside. Without a prior each connected
    region has mean depth 0.
    Raises InputError for bad shapes or non-finite inputs on the mask, NumericalError when the
    linear solve fails or the result is not finite.
    """
    inside, normals, prior = _check_inputs(normals, mask, depth_prior, mask_threshold)
    x0, x1, y0, y1 = (float(c) for c in rect)
    height, width = inside.shape
    h_x, h_y = (x1 - x0) / width, (y1 - y0) / height
    if not (h_x > 0 and h_y > 0):
        raise InputError(f"rectangle must have x1 > x0 and y1 > y0, got {rect}")
    system = _difference_system(inside, normals[inside], h_y / h_x)
    weight = prior_weight if prior is not None else NO_PRIOR_WEIGHT
    target = np.zeros(system.n) if prior is None else prior[inside] / h_x
    z = _reweighted_solve(system, weight, target, prior is not None, sharpness, max_iterations,
                          tolerance)
    if prior is None:
        z = _zero_mean_per_region(z, inside)
    depth = np.zeros((height, width), np.float32)
    depth[inside] = (z * h_x).astype(np.float32)
    return depth


def double_sided_depth(front_normals, back_normals, mask, rect, *, front_prior=None,
                       back_prior=None, **options):
    """Front and back depth maps from front and back normal maps.

    Arguments as `integrate_normals` (options are passed on). Without priors the back surface
    is shifted, per connected region, so front and back meet on the region's silhouette
    (median over its boundary pixels), as they do on a closed body seen edge-on there.
    Returns (front, back), each (H, W) float32 world z, 0 outside the mask.
    """
    front = integrate_normals(front_normals, mask, rect, depth_prior=front_prior, **options)
    back = integrate_normals(back_normals, mask, rect, depth_prior=back_prior, **options)
    if back_prior is None:
        back = _meet_on_silhouette(front, back, np.asarray(mask) > options.get(
            "mask_threshold", 0.5))
    return front, back


# ---------------------------------------------------------------------------- internals

class _System:
    """The four one-sided difference equations of every mask pixel.

    operators: four (n, n) csr matrices, rows of pixels without that neighbour are zero;
    targets: four (n,) right-hand sides (n_z folded into the operators). In units of h_x.
    """

    def __init__(self, operators, targets):
        self.operators = operators
        self.targets = targets
        self.n = operators[0].shape[1]


def _difference_system(inside, normals, aspect):
    """_System for mask `inside` (H, W) bool, normals (n, 3) of its pixels in row-major
    order, aspect = h_y / h_x."""
    height, width = inside.shape
    index = np.full((height + 2, width + 2), -1, dtype=np.int64)
    index[1:-1, 1:-1][inside] = np.arange(np.count_nonzero(inside))
    rows, cols = np.nonzero(inside)
    nx, ny, nz = normals[:, 0], normals[:, 1], normals[:, 2]
    n = rows.size
    operators, targets = [], []
    # (neighbour offset, sign of z_q - z_p in the equation, right-hand side)
    for (di, dj), sign, rhs in (((0, 1), 1.0, -nx), ((0, -1), -1.0, -nx),
                                ((1, 0), 1.0, ny * aspect), ((-1, 0), -1.0, ny * aspect)):
        neighbour = index[rows + 1 + di, cols + 1 + dj]
        has = neighbour >= 0
        p = np.flatnonzero(has)
        data = sign * nz[p]
        operator = scipy.sparse.csr_matrix(
            (np.concatenate([data, -data]), (np.concatenate([p, p]),
                                             np.concatenate([neighbour[p], p]))), shape=(n, n))
        operators.append(operator)
        targets.append(np.where(has, rhs, 0.0))
    return _System(operators, targets)


def _reweighted_solve(system, prior_weight, target, has_prior, sharpness, max_iterations,
                      tolerance):
    """IRLS of BiNI: solve the weighted normal equations, update the one-sided weights from
    the new depth, until the energy settles. Returns (n,) float64 depth in units of h_x."""
    if has_prior and sharpness > 0:
        # The prior's own jumps (where the net saw one surface in front of another) start
        # the one-sided weights, so equations across them are off from the first solve
        weights = _bilateral_weights(system, target, sharpness)
    else:
        weights = [np.full(system.n, 0.5) for _ in range(4)]
    energy = np.inf
    z = target
    for _ in range(max(1, int(max_iterations))):
        matrix, rhs = _normal_equations(system, weights, prior_weight, target)
        z = _solve(matrix, rhs)
        new_energy = _energy(system, weights, z, prior_weight, target)
        if sharpness > 0:
            weights = _bilateral_weights(system, z, sharpness)
        if abs(energy - new_energy) <= tolerance * max(new_energy, 1e-30):
            break
        energy = new_energy
    return z


def _normal_equations(system, weights, prior_weight, target):
    """(A^T W A + prior_weight I, A^T W b + prior_weight target): the minimiser of
    sum_d w_d |A_d z - b_d|^2 + prior_weight |z - target|^2. Matrix (n, n) csc."""
    matrix = prior_weight * scipy.sparse.identity(system.n, format="csr")
    rhs = prior_weight * target
    for operator, b, w in zip(system.operators, system.targets, weights):
        weighted = scipy.sparse.diags(w) @ operator
        matrix = matrix + operator.T @ weighted
        rhs = rhs + weighted.T @ b
    return matrix.tocsc(), rhs


def _solve(matrix, rhs):
    """Direct sparse LU solve of one SPD system, checked: (n,) float64 or NumericalError.
    (Conjugate gradients preconditioned by the previous iteration's factor was tried: the
    BiNI weights move too much between iterations, CG stalled and it ran 3x slower.)"""
    z = _factorise(matrix).solve(rhs)
    residual = _relative_residual(matrix, z, rhs)
    if not np.all(np.isfinite(z)) or not residual <= MAX_RELATIVE_RESIDUAL:
        raise NumericalError(
            f"normal integration did not converge (relative residual {residual:.2e})",
            fix="pass a depth prior (depth_prior=...) or a larger prior_weight")
    return z


def _factorise(matrix):
    try:
        return scipy.sparse.linalg.splu(matrix, permc_spec="MMD_AT_PLUS_A")
    except RuntimeError as error:  # SuperLU reports a singular factor this way
        raise NumericalError(f"normal integration: the linear solve failed ({error})",
                             fix="check the normal map and mask for garbage values") from error


def _relative_residual(matrix, z, rhs):
    return float(np.linalg.norm(matrix @ z - rhs) / max(np.linalg.norm(rhs), 1e-300))


def _energy(system, weights, z, prior_weight, target):
    total = prior_weight * float(np.sum((z - target) ** 2))
    for operator, b, w in zip(system.operators, system.targets, weights):
        total += float(np.sum(w * (operator @ z - b) ** 2))
    return total


def _bilateral_weights(system, z, sharpness):
    """BiNI's w+ = sigmoid(k ((D- z)^2 - (D+ z)^2)), w- = 1 - w+, per axis, where D are the
    n_z-scaled one-sided differences (operators 0, 1: right, left; 2, 3: down, up)."""
    weights = []
    for forward, backward in ((0, 1), (2, 3)):
        d_forward = system.operators[forward] @ z
        d_backward = system.operators[backward] @ z
        w_forward = _sigmoid(sharpness * (d_backward ** 2 - d_forward ** 2))
        weights += [w_forward, 1.0 - w_forward]
    return [weights[0], weights[1], weights[2], weights[3]]


def _sigmoid(x):
    # 1 / (1 + exp(-x)) written to not overflow for large |x|
    return 0.5 * (1.0 + np.tanh(0.5 * x))


def _zero_mean_per_region(z, inside):
    """Shift each 4-connected region of the mask to mean depth 0."""
    labels, count = scipy.ndimage.label(inside)
    region = labels[inside] - 1
    means = np.bincount(region, weights=z, minlength=count) / np.bincount(region, minlength=count)
    return z - means[region]


def _meet_on_silhouette(front, back, inside):
    """back shifted per 4-connected region so median(front - back) = 0 on its boundary."""
    labels, count = scipy.ndimage.label(inside)
    boundary = inside & ~scipy.ndimage.binary_erosion(inside, border_value=0)
    region = labels[boundary] - 1  # every region has boundary pixels
    gap = front[boundary].astype(np.float64) - back[boundary]
    # Median per region: sort by (region, gap), take the middle of each region's run
    order = np.lexsort((gap, region))
    sizes = np.bincount(region, minlength=count)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    median = 0.5 * (gap[order][starts + (sizes - 1) // 2] + gap[order][starts + sizes // 2])
    shifted = back.astype(np.float64)
    shifted[inside] += median[labels[inside] - 1]
    return shifted.astype(np.float32)


def _check_inputs(normals, mask, depth_prior, mask_threshold):
    """(inside (H, W) bool, normals (H, W, 3) float64, prior (H, W) float64 or None)."""
    mask = np.asarray(mask)
    normals = np.asarray(normals, dtype=np.float64)
    if mask.ndim != 2 or normals.shape != mask.shape + (3,):
        raise InputError(f"normals must be (H, W, 3) and the mask (H, W); got {normals.shape} "
                         f"and {mask.shape}", fix="pass maps of the same crop")
    inside = mask > mask_threshold
    if not inside.any():
        raise InputError("the mask is empty: no pixel to integrate",
                         fix="pass the person's mask")
    bad = np.count_nonzero(~np.all(np.isfinite(normals[inside]), axis=1))
    if bad:
        raise InputError(f"the normal map has {bad} NaN or Inf pixels inside the mask",
                         fix="fill or mask out those pixels")
    prior = None
    if depth_prior is not None:
        prior = np.asarray(depth_prior, dtype=np.float64)
        if prior.shape != mask.shape or not np.all(np.isfinite(prior[inside])):
            raise InputError("the depth prior must be (H, W) like the mask and finite on it",
                             fix="pass the net's depth map of the same crop")
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    if np.any(length[inside] == 0):
        warnings.warn(f"{np.count_nonzero(length[inside] == 0)} zero-length normals inside "
                      "the mask carry no slope information", RelightWarning, stacklevel=3)
    return inside, normals / np.where(length > 0, length, 1.0), prior
