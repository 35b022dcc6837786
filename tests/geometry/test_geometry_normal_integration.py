"""Normal maps -> depth: recovers analytic surfaces, keeps jumps, never returns NaN."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage
import scipy.sparse.linalg

from geometry_truth import pixel_centres
from relightcli.errors import InputError, NumericalError
from relightcli.geometry import normal_integration
from relightcli.geometry.normal_integration import double_sided_depth, integrate_normals

RECT = (-1.2, 1.2, -1.2, 1.2)
N = 64


def _centred_error(depth, truth, mask):
    """Max |error| on the mask after removing the mean offset (normals fix depth up to it)."""
    error = (depth - truth)[mask]
    return np.abs(error - error.mean()).max()


def _sphere_cap(side=1.0):
    """Unit sphere, front (side 1) or back (side -1) cap where |n_z| >= 0.6."""
    x, y = pixel_centres(RECT, N, N)
    mask = x ** 2 + y ** 2 < 0.8 ** 2
    z = side * np.sqrt(np.clip(1.0 - x ** 2 - y ** 2, 0.0, None))
    return np.dstack([x, y, z]), mask, z


def _paraboloid():
    """z = 0.3 (x^2 - 2 y^2) + 0.1 x over a disc: normal (-z_x, -z_y, 1) normalised."""
    x, y = pixel_centres(RECT, N, N)
    mask = x ** 2 + y ** 2 < 1.0
    z = 0.3 * (x ** 2 - 2 * y ** 2) + 0.1 * x
    normals = np.dstack([-(0.6 * x + 0.1), 1.2 * y, np.ones_like(x)])
    return normals / np.linalg.norm(normals, axis=-1, keepdims=True), mask, z


@pytest.mark.parametrize("side", [1.0, -1.0], ids=["front", "back"])
def test_sphere_cap_is_recovered(side):
    normals, mask, z = _sphere_cap(side)
    # Discretisation error of the one-sided differences at 64 px: ~5e-4 of the radius
    assert _centred_error(integrate_normals(normals, mask, RECT), z, mask) < 2e-3


def test_paraboloid_is_recovered():
    normals, mask, z = _paraboloid()
    assert _centred_error(integrate_normals(normals, mask, RECT), z, mask) < 2e-3


def test_depth_prior_sets_the_offset():
    normals, mask, z = _paraboloid()
    depth = integrate_normals(normals, mask, RECT, depth_prior=z + 5.0)
    assert np.abs(depth - (z + 5.0))[mask].max() < 2e-3


def test_no_prior_gives_zero_mean():
    normals, mask, _ = _paraboloid()
    assert abs(integrate_normals(normals, mask, RECT)[mask].mean()) < 1e-6


def test_outside_mask_is_zero():
    normals, mask, _ = _paraboloid()
    assert np.all(integrate_normals(normals, mask, RECT)[~mask] == 0)


def _two_planes():
    """Two planes facing the camera, z = 0 left and z = 1 right of a vertical jump; a depth
    prior with the jump and noise (a net's depth), normals all +Z."""
    mask = np.ones((40, 40), bool)
    normals = np.zeros((40, 40, 3))
    normals[..., 2] = 1.0
    truth = np.zeros((40, 40))
    truth[:, 20:] = 1.0
    prior = truth + np.random.default_rng(0).normal(0.0, 0.05, truth.shape)
    return normals, mask, truth, prior


def test_jump_stays_sharp():
    normals, mask, truth, prior = _two_planes()
    depth = integrate_normals(normals, mask, (0.0, 1.0, 0.0, 1.0), depth_prior=prior)
    # Each side flat to the prior's noise averaged out, the jump within one pixel
    assert np.abs(depth - truth).max() < 0.02


def test_plain_least_squares_smears_the_jump():
    # sharpness 0 is plain least squares: shows the previous test can fail
    normals, mask, truth, prior = _two_planes()
    depth = integrate_normals(normals, mask, (0.0, 1.0, 0.0, 1.0), depth_prior=prior,
                              sharpness=0.0)
    assert np.abs(depth - truth).max() > 0.2


def test_double_sided_depth_meets_on_silhouette():
    front_n, mask, z = _sphere_cap(1.0)
    back_n, _, _ = _sphere_cap(-1.0)
    front, back = double_sided_depth(front_n, back_n, mask, RECT)
    # True thickness 2 z; meeting on the rim (median over its pixels) takes that away
    rim = mask & ~scipy.ndimage.binary_erosion(mask)
    expected = 2 * z - np.median(2 * z[rim])
    assert np.abs(front - back - expected)[mask].max() < 5e-3


def _hostile_cases():
    rng = np.random.default_rng(3)
    noisy = rng.normal(size=(N, N, 3))
    edge_on = np.zeros((N, N, 3))
    edge_on[..., 0] = 1.0
    limbs = np.zeros((N, N), bool)
    limbs[10:40, 10:40] = True
    limbs[25, :] = True
    limbs[:, 50] = True
    holes = limbs.copy()
    holes[15:18, 15:18] = False
    holes[30, 30] = False
    single = np.zeros((N, N), bool)
    single[5, 7] = True
    pair = np.zeros((N, N), bool)
    pair[5, 7:9] = True
    speckle = rng.random((N, N)) > 0.5
    cap, disc, _ = _sphere_cap()
    flipped = cap.copy()
    flipped[::3, ::3, 2] *= -1.0  # normals that disagree about front and back
    return {
        "noisy_normals": (noisy, np.ones((N, N), bool)),
        "edge_on_normals": (edge_on, disc),
        "one_pixel_limbs": (noisy, limbs),
        "holes": (cap, holes),
        "single_pixel": (cap, single),
        "two_pixels": (noisy, pair),
        "speckle_mask": (noisy, speckle),
        "flipped_normals": (flipped, disc),
    }


@pytest.mark.parametrize("case", list(_hostile_cases()))
def test_hostile_input_gives_finite_depth(case):
    normals, mask = _hostile_cases()[case]
    assert np.all(np.isfinite(integrate_normals(normals, mask, RECT)))


@pytest.mark.parametrize("case", ["one_pixel_limbs", "holes", "speckle_mask"])
def test_hostile_input_with_prior_gives_finite_depth(case):
    normals, mask = _hostile_cases()[case]
    prior = np.random.default_rng(4).normal(size=mask.shape)
    depth = integrate_normals(normals, mask, RECT, depth_prior=prior)
    assert np.all(np.isfinite(depth))


def test_empty_mask_raises():
    normals, _, _ = _paraboloid()
    with pytest.raises(InputError, match="empty"):
        integrate_normals(normals, np.zeros((N, N), bool), RECT)


def test_nan_normals_on_mask_raise():
    normals, mask, _ = _paraboloid()
    normals[32, 32] = np.nan
    with pytest.raises(InputError, match="NaN"):
        integrate_normals(normals, mask, RECT)


def test_failed_solve_raises_numerical_error(monkeypatch):
    def singular(*args, **kwargs):
        raise RuntimeError("Factor is exactly singular")

    monkeypatch.setattr(scipy.sparse.linalg, "splu", singular)
    normals, mask, _ = _paraboloid()
    with pytest.raises(NumericalError, match="normal integration"):
        integrate_normals(normals, mask, RECT)


def test_non_finite_solution_raises_numerical_error(monkeypatch):
    class Garbage:
        def __init__(self, *args, **kwargs):
            pass

        def solve(self, rhs):
            return np.full_like(rhs, np.nan)

    monkeypatch.setattr(normal_integration.scipy.sparse.linalg, "splu", Garbage)
    normals, mask, _ = _paraboloid()
    with pytest.raises(NumericalError, match="converge"):
        integrate_normals(normals, mask, RECT)
