"""Real spherical harmonics: the project's one SH basis, projection and irradiance shading.

Convention (../shared/DESIGN.md, "Spherical harmonics"): real, orthonormal SH of bands 0..2
(9 coefficients) or 0..4 (25), coefficient index l * l + l + m for m = -l..l. The basis is
written in the panorama's own spherical coordinates (io/envmap.py): polar axis +Y, theta =
pi v from +Y, azimuth phi = 2 pi (u - 1/2) from -Z toward +X. In Cartesian form it is the
usual table of real SH (no Condon-Shortley phase) in the frame

    x' = sin(theta) cos(phi) = -z,   y' = sin(theta) sin(phi) = x,   z' = cos(theta) = y,

so m > 0 goes with cos(m phi), m < 0 with sin(|m| phi), m = 0 is zonal about +Y, and a turn of
the environment about +Y (`--rotate`) only mixes the (m, -m) pairs (`rotate_sh_y`).

Shading follows DESIGN.md: irradiance by the clamped-cosine convolution with band factors
A0 = pi, A1 = 2 pi / 3, A2 = pi / 4, A3 = 0, A4 = -pi / 24, and shading = irradiance / pi, so a
constant environment L shades every normal with exactly L (white furnace).
"""

from __future__ import annotations

import math

import numpy as np

from relightcli.errors import UsageError
from relightcli.io.envmap import texel_directions, uv_to_direction

MAX_ORDER = 4
# clamped-cosine band factors A_l (Ramamoorthi and Hanrahan 2001), l = 0..4
BAND_FACTORS = (np.pi, 2.0 * np.pi / 3.0, np.pi / 4.0, 0.0, -np.pi / 24.0)
# small maps are integrated on at least this many rows (each texel split into equal cells)
_MIN_PROJECTION_ROWS = 128
_ROWS_PER_CHUNK = 64


def coefficient_count(order):
    """Number of coefficients of bands 0..order: (order + 1) ** 2."""
    return (order + 1) ** 2


def order_of(coeffs):
    """The band limit of an (n, ...) coefficient array, n = (order + 1) ** 2."""
    n = np.shape(coeffs)[0]
    order = math.isqrt(n) - 1
    if coefficient_count(order) != n or not 0 <= order <= MAX_ORDER:
        raise UsageError(f"{n} SH coefficients is not (order + 1)^2 for an order in 0..{MAX_ORDER}",
                         fix="pass 9 (order 2) or 25 (order 4) coefficients")
    return order


def _check_order(order):
    if order not in range(MAX_ORDER + 1):
        raise UsageError(f"SH order must be 0..{MAX_ORDER}, got {order}",
                         fix="use order 2 (9 coefficients) or 4 (25 coefficients)")


def _bands_0_to_2(x, y, z):
    """Real SH of bands 0..2 in the polar frame (z the polar axis), 9 arrays."""
    c1 = math.sqrt(3.0 / (4.0 * math.pi))
    c2 = 0.5 * math.sqrt(15.0 / math.pi)
    return [
        np.full_like(x, 0.5 * math.sqrt(1.0 / math.pi)),
        c1 * y, c1 * z, c1 * x,
        c2 * x * y, c2 * y * z, 0.25 * math.sqrt(5.0 / math.pi) * (3.0 * z * z - 1.0),
        c2 * x * z, 0.5 * c2 * (x * x - y * y),
    ]


def _band_3(x, y, z):
    """Real SH of band 3 (m = -3..3) in the polar frame, 7 arrays."""
    c3 = 0.25 * math.sqrt(35.0 / (2.0 * math.pi))
    c2 = 0.5 * math.sqrt(105.0 / math.pi)
    c1 = 0.25 * math.sqrt(21.0 / (2.0 * math.pi))
    zz = z * z
    return [
        c3 * y * (3.0 * x * x - y * y), c2 * x * y * z, c1 * y * (5.0 * zz - 1.0),
        0.25 * math.sqrt(7.0 / math.pi) * z * (5.0 * zz - 3.0),
        c1 * x * (5.0 * zz - 1.0), 0.5 * c2 * z * (x * x - y * y), c3 * x * (x * x - 3.0 * y * y),
    ]


def _band_4(x, y, z):
    """Real SH of band 4 (m = -4..4) in the polar frame, 9 arrays."""
    c4 = 0.75 * math.sqrt(35.0 / math.pi)
    c3 = 0.75 * math.sqrt(35.0 / (2.0 * math.pi))
    c2 = 0.75 * math.sqrt(5.0 / math.pi)
    c1 = 0.75 * math.sqrt(5.0 / (2.0 * math.pi))
    xx, yy, zz = x * x, y * y, z * z
    return [
        c4 * x * y * (xx - yy), c3 * y * z * (3.0 * xx - yy), c2 * x * y * (7.0 * zz - 1.0),
        c1 * y * z * (7.0 * zz - 3.0),
        (3.0 / 16.0) * math.sqrt(1.0 / math.pi) * (35.0 * zz * zz - 30.0 * zz + 3.0),
        c1 * x * z * (7.0 * zz - 3.0), 0.5 * c2 * (xx - yy) * (7.0 * zz - 1.0),
        c3 * x * z * (xx - 3.0 * yy), 0.25 * c4 * (xx * (xx - 3.0 * yy) - yy * (3.0 * xx - yy)),
    ]


def sh_basis(directions, order):
    """Real orthonormal SH of bands 0..order at unit directions.

    directions: (..., 3) unit vectors in the world frame. order: 0..4 (2 -> 9, 4 -> 25
    coefficients). Returns (..., (order + 1) ** 2) float64.
    """
    _check_order(order)
    d = np.asarray(directions, dtype=np.float64)
    # the panorama's polar frame: x' = -z, y' = x, z' = y (module docstring)
    x, y, z = -d[..., 2], d[..., 0], d[..., 1]
    values = _bands_0_to_2(x, y, z)
    if order >= 3:
        values += _band_3(x, y, z)
    if order >= 4:
        values += _band_4(x, y, z)
    return np.stack(values[:coefficient_count(order)], axis=-1)


def _row_nodes(height, width, rows):
    """Quadrature nodes of the texels in `rows` (a range) of a (height, width) map: 3
    Gauss-Legendre nodes in cos(theta) per row, the column centre in phi. Returns directions
    (r, 3, width, 3) float64 and weights (r, 3, width) float64 (solid angles; over all rows
    they sum to 4 pi).

    Gauss-Legendre with 3 nodes is exact for polynomials of degree 5 in cos(theta), so the
    zonal bands 0..4 of a map that is constant along rows are integrated exactly.
    """
    nodes, node_weights = np.polynomial.legendre.leggauss(3)
    edges = np.cos(np.pi * np.arange(rows.start, rows.stop + 1) / height)
    middle, half = 0.5 * (edges[:-1] + edges[1:]), 0.5 * (edges[:-1] - edges[1:])
    cos_theta = middle[:, None] + half[:, None] * nodes[None, :]
    u = (np.arange(width) + 0.5) / width
    v = np.arccos(np.clip(cos_theta, -1.0, 1.0)) / np.pi
    u, v = np.broadcast_arrays(u[None, None, :], v[:, :, None])
    directions = uv_to_direction(u, v)
    row_weights = (2.0 * np.pi / width) * half[:, None] * node_weights[None, :]
    return directions, np.repeat(row_weights[:, :, None], width, axis=2)


def project_sh(env, order):
    """SH coefficients of an environment map: the integral of L * Y over the sphere.

    env: (H, 2H, C) linear radiance (C = 3 for RGB), constant over each texel. Returns
    ((order + 1) ** 2, C) float64. Each texel row is integrated with 3 Gauss-Legendre nodes in cos(theta) (exact
    for zonal terms) and column centres in phi; maps with fewer than 128 rows are first split
    into equal cells (np.repeat) so tiny maps (2x1) do not alias in phi. A constant map gives
    exactly its DC term.
    """
    _check_order(order)
    env = np.asarray(env, dtype=np.float64)
    split = max(1, math.ceil(_MIN_PROJECTION_ROWS / env.shape[0]))
    env = np.repeat(np.repeat(env, split, axis=0), split, axis=1)
    height, width = env.shape[:2]
    coeffs = np.zeros((coefficient_count(order), env.shape[-1]))
    # row chunks bound the (rows, 3, W, n) basis array for large maps
    for start in range(0, height, _ROWS_PER_CHUNK):
        stop = min(start + _ROWS_PER_CHUNK, height)
        directions, weights = _row_nodes(height, width, range(start, stop))
        basis = sh_basis(directions, order) * weights[..., None]
        coeffs += np.einsum("hqwk,hwc->kc", basis, env[start:stop])
    return coeffs


def _band_of_each_coefficient(order):
    """(n,) int: the band l of every coefficient index."""
    return np.repeat(np.arange(order + 1), 2 * np.arange(order + 1) + 1)


def irradiance_basis(normals, order=2):
    """(..., (order + 1) ** 2) float64: the SH basis at unit normals times each band's
    irradiance factor / pi, so that sh_irradiance_shading(coeffs, normals) = basis @ coeffs
    (linear in the lighting: what a trainer differentiates through)."""
    factors = np.asarray(BAND_FACTORS)[_band_of_each_coefficient(order)] / np.pi
    return sh_basis(normals, order) * factors


def sh_irradiance_shading(coeffs, normals):
    """Diffuse shading (irradiance / pi) from SH lighting coefficients.

    coeffs: (n, 3) from `project_sh`, n = 9 or 25 (any (order + 1) ** 2 up to 25).
    normals: (..., 3) unit normals in the world frame. Returns (..., 3) float32 linear
    shading; band-limited, so it can dip below 0 for very directional light.
    """
    coeffs = np.asarray(coeffs, dtype=np.float64)
    return (irradiance_basis(normals, order_of(coeffs)) @ coeffs).astype(np.float32)


def sh_to_envmap(coeffs, height, *, clip_negative=True):
    """Radiance of SH lighting at texel centres, for previews.

    coeffs: (n, 3) SH coefficients. Returns (height, 2 * height, 3) float32 linear radiance;
    negative lobes of the band-limited light are set to 0 unless `clip_negative` is False.
    """
    coeffs = np.asarray(coeffs, dtype=np.float64)
    basis = sh_basis(texel_directions(height, 2 * height), order_of(coeffs))
    radiance = basis @ coeffs
    if clip_negative:
        radiance = np.maximum(radiance, 0.0)
    return radiance.astype(np.float32)


def rotate_sh_y(coeffs, degrees):
    """Coefficients of the environment turned about +Y as `rotate_envmap` turns it.

    coeffs: (n, ...) SH coefficients. Returns a new float64 array of the same shape.
    """
    coeffs = np.array(coeffs, dtype=np.float64)
    order = order_of(coeffs)
    alpha = math.radians(float(degrees))
    rotated = coeffs.copy()
    # new(phi) = old(phi + alpha) (see rotate_envmap), so with Y_m ~ cos(m phi) and
    # Y_-m ~ sin(m phi): c'_m = cos(m a) c_m + sin(m a) c_-m, c'_-m = cos(m a) c_-m - sin(m a) c_m
    for band in range(1, order + 1):
        for m in range(1, band + 1):
            plus, minus = band * band + band + m, band * band + band - m
            cos_ma, sin_ma = math.cos(m * alpha), math.sin(m * alpha)
            rotated[plus] = cos_ma * coeffs[plus] + sin_ma * coeffs[minus]
            rotated[minus] = cos_ma * coeffs[minus] - sin_ma * coeffs[plus]
    return rotated
