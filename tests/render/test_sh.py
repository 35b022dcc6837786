"""Real SH: the basis against scipy's complex SH, orthonormality by quadrature, the white
furnace, rotation about +Y, and shading against brute-force integration of DESIGN.md's
shading integral (1/pi) * integral of L(w) max(0, n.w) dw (no visibility)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.special

from relightcli.errors import UsageError
from relightcli.io import envmap as em
from relightcli.render import sh


def random_unit_vectors(count, seed=0):
    v = np.random.default_rng(seed).normal(size=(count, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def random_env(height, seed=0):
    """(H, 2H, 3) float32 positive random radiance (float32 like every loaded map)."""
    rng = np.random.default_rng(seed)
    return rng.uniform(0.1, 2.0, size=(height, 2 * height, 3)).astype(np.float32)


def rotation_y(degrees):
    """R_y: counter-clockwise seen from above, +X toward -Z (as rotate_envmap)."""
    a = math.radians(degrees)
    return np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0],
                     [-math.sin(a), 0.0, math.cos(a)]])


def brute_force_shading(radiance, normals):
    """(1/pi) sum over texels of L max(0, n.w) solid angle; radiance (H, 2H, 3)."""
    height, width = radiance.shape[:2]
    directions = em.texel_directions(height, width).reshape(-1, 3)
    weights = em.texel_solid_angles(height, width).reshape(-1)
    cosines = np.maximum(normals @ directions.T, 0.0) * weights
    return cosines @ radiance.reshape(-1, 3) / np.pi


@pytest.mark.parametrize("band", [0, 1, 2, 3, 4])
def test_basis_matches_scipy_real_sh(band):
    # independent reference: real SH built from scipy's complex Y_l^m (Condon-Shortley phase
    # included there, cancelled by (-1)^m) at the panorama's theta = pi v, phi = 2 pi (u - 1/2)
    rng = np.random.default_rng(band)
    u, v = rng.random(200), rng.random(200)
    basis = sh.sh_basis(em.uv_to_direction(u, v), 4)
    theta, phi = np.pi * v, 2 * np.pi * (u - 0.5)
    for m in range(-band, band + 1):
        complex_sh = scipy.special.sph_harm_y(band, abs(m), theta, phi)
        if m > 0:
            expected = math.sqrt(2) * (-1) ** m * complex_sh.real
        elif m < 0:
            expected = math.sqrt(2) * (-1) ** m * complex_sh.imag
        else:
            expected = complex_sh.real
        np.testing.assert_allclose(basis[:, band * band + band + m], expected, atol=1e-12)


@pytest.mark.parametrize("order, count", [(0, 1), (1, 4), (2, 9), (3, 16), (4, 25)])
def test_basis_shape_and_dtype(order, count):
    basis = sh.sh_basis(random_unit_vectors(7).reshape(7, 1, 3), order)
    assert basis.shape == (7, 1, count) and basis.dtype == np.float64


def test_basis_is_orthonormal_by_quadrature():
    height, width = 256, 512
    basis = sh.sh_basis(em.texel_directions(height, width), 4).reshape(-1, 25)
    weights = em.texel_solid_angles(height, width).reshape(-1, 1)
    gram = basis.T @ (basis * weights)
    # midpoint quadrature in theta: error ~ (pi / H)^2 times the band's curvature
    np.testing.assert_allclose(gram, np.eye(25), atol=2e-4)


@pytest.mark.parametrize("bad", [5, -1])
def test_basis_rejects_unsupported_order(bad):
    with pytest.raises(UsageError):
        sh.sh_basis([0.0, 1.0, 0.0], bad)


def test_order_of_rejects_non_square_count():
    with pytest.raises(UsageError, match="9 \\(order 2\\)"):
        sh.order_of(np.zeros((10, 3)))


@pytest.mark.parametrize("height", [1, 2, 16, 200])
@pytest.mark.parametrize("order", [2, 4])
def test_constant_map_is_dc_only_and_white_furnace(height, order):
    radiance = np.array([0.3, 1.0, 2.5])
    env = np.broadcast_to(radiance, (height, 2 * height, 3))
    coeffs = sh.project_sh(env, order)
    np.testing.assert_allclose(coeffs[0], radiance * math.sqrt(4 * math.pi), rtol=1e-12)
    np.testing.assert_allclose(coeffs[1:], 0.0, atol=1e-12)
    shading = sh.sh_irradiance_shading(coeffs, random_unit_vectors(50))
    np.testing.assert_allclose(shading, np.broadcast_to(radiance, (50, 3)), rtol=1e-6)


def test_rotating_map_by_360_keeps_coefficients():
    env = random_env(16)
    np.testing.assert_array_equal(sh.project_sh(em.rotate_envmap(env, 360.0), 4),
                                  sh.project_sh(env, 4))


@pytest.mark.parametrize("degrees", [90.0, -45.0, 180.0])
def test_rotating_coefficients_matches_projecting_rotated_map(degrees):
    env = random_env(16)
    rotated_then_projected = sh.project_sh(em.rotate_envmap(env, degrees), 4)
    projected_then_rotated = sh.rotate_sh_y(sh.project_sh(env, 4), degrees)
    np.testing.assert_allclose(projected_then_rotated, rotated_then_projected, atol=1e-10)


def test_rotated_lighting_shades_rotated_normals_alike():
    # the environment turned by R lights R n as the original lit n
    coeffs = sh.project_sh(random_env(16), 4)
    normals = random_unit_vectors(20)
    turned = sh.rotate_sh_y(coeffs, 33.0)
    np.testing.assert_allclose(sh.sh_irradiance_shading(turned, normals @ rotation_y(33.0).T),
                               sh.sh_irradiance_shading(coeffs, normals), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("order", [2, 4])
def test_single_texel_shading_matches_brute_force_of_band_limited_light(order):
    # the SH shading of a map is the exact shading integral of its band-limited light
    env = np.zeros((8, 16, 3))
    env[2, 5] = [100.0, 50.0, 10.0]
    coeffs = sh.project_sh(env, order)
    band_limited = sh.sh_to_envmap(coeffs, 256, clip_negative=False).astype(np.float64)
    normals = random_unit_vectors(12, seed=3)
    expected = brute_force_shading(band_limited, normals)
    # quadrature of the max(0, n.w) kink on 256 rows: ~1e-4 of the mean shading
    scale = np.abs(expected).mean()
    np.testing.assert_allclose(sh.sh_irradiance_shading(coeffs, normals), expected,
                               atol=2e-4 * scale)


@pytest.mark.parametrize("band", [0, 1, 2, 3, 4])
def test_band_factors_by_funk_hecke(band):
    # integral of Y_lm(w) max(0, n.w) dw = A_l Y_lm(n), checked by quadrature for m = 0..l
    height = 256
    directions = em.texel_directions(height, 2 * height).reshape(-1, 3)
    weights = em.texel_solid_angles(height, 2 * height).reshape(-1)
    normals = random_unit_vectors(6, seed=band)
    basis = sh.sh_basis(directions, 4)[:, band * band:(band + 1) ** 2]
    integral = (np.maximum(normals @ directions.T, 0.0) * weights) @ basis
    expected = sh.BAND_FACTORS[band] * sh.sh_basis(normals, 4)[:, band * band:(band + 1) ** 2]
    np.testing.assert_allclose(integral, expected, atol=1e-4)


def test_linear_map_shading_is_exact():
    # L = 1 + a.w has shading 1 + (2/3) a.n exactly (integral of w max(0, n.w) = 2 pi n / 3)
    height = 128
    a = np.array([0.5, 0.3, -0.2])
    env = 1.0 + em.texel_directions(height, 2 * height) @ a
    env = np.repeat(env[..., None], 3, axis=-1)
    normals = random_unit_vectors(40, seed=5)
    expected = 1.0 + (2.0 / 3.0) * normals @ a
    # the map holds L at texel centres only: a discretisation error ~ (2 / H)^2 / 12
    np.testing.assert_allclose(sh.sh_irradiance_shading(sh.project_sh(env, 2), normals),
                               np.repeat(expected[:, None], 3, axis=1), atol=5e-5)


def test_band_limited_map_projects_back_to_its_coefficients():
    rng = np.random.default_rng(7)
    coeffs = rng.normal(size=(9, 3))
    env = sh.sh_to_envmap(coeffs, 128, clip_negative=False).astype(np.float64)
    # piecewise-constant texels of a smooth function: error ~ (pi / H)^2
    np.testing.assert_allclose(sh.project_sh(env, 2), coeffs, atol=5e-4)


def test_sh_to_envmap_clips_negative_lobes():
    coeffs = np.zeros((9, 3))
    coeffs[1] = 1.0                          # a pure band-1 lobe: half the sphere negative
    env = sh.sh_to_envmap(coeffs, 8)
    assert env.shape == (8, 16, 3) and env.dtype == np.float32
    assert env.min() == 0.0 and env.max() > 0.0
