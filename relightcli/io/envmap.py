"""Environment maps: the direction convention (the single source of truth), and maps.

Convention (../shared/DESIGN.md): an equirectangular map has W = 2H. Texel coordinates
(u, v) in [0, 1)^2 with v = 0 at the top row; polar angle theta = pi * v measured from +Y,
azimuth phi = 2 pi (u - 0.5), direction

    d = (sin(theta) sin(phi), cos(theta), -sin(theta) cos(phi)).

The centre column (u = 0.5) is -Z (what the camera looks at), u = 0.75 is +X, u = 0 and 1
are +Z (behind the camera). Values are linear RGB radiance.
"""

from __future__ import annotations

import numpy as np


def uv_to_direction(u, v):
    """Unit direction for texel coordinates.

    u, v: arrays of the same shape, in [0, 1]. Returns (..., 3) float64 unit vectors.
    """
    theta = np.pi * np.asarray(v, dtype=np.float64)
    phi = 2.0 * np.pi * (np.asarray(u, dtype=np.float64) - 0.5)
    sin_theta = np.sin(theta)
    return np.stack(
        [sin_theta * np.sin(phi), np.cos(theta), -sin_theta * np.cos(phi)], axis=-1
    )


def direction_to_uv(d):
    """Texel coordinates of directions, the inverse of `uv_to_direction`.

    d: (..., 3) array (need not be unit length, must be non-zero). Returns (u, v), each (...)
    float64, u in [0, 1), v in [0, 1].
    """
    d = np.asarray(d, dtype=np.float64)
    norm = np.linalg.norm(d, axis=-1)
    y = np.clip(d[..., 1] / np.where(norm > 0, norm, 1.0), -1.0, 1.0)
    v = np.arccos(y) / np.pi
    # phi = atan2(x, -z): x = sin(theta) sin(phi), -z = sin(theta) cos(phi)
    u = np.arctan2(d[..., 0], -d[..., 2]) / (2.0 * np.pi) + 0.5
    u = np.where(u >= 1.0, u - 1.0, u)
    return u, v


def texel_centres_uv(height: int, width: int):
    """(u, v) of every texel centre, each (height, width) float64."""
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    return np.meshgrid(u, v)


def texel_directions(height: int, width: int):
    """Unit directions of every texel centre, (height, width, 3) float64."""
    u, v = texel_centres_uv(height, width)
    return uv_to_direction(u, v)


def texel_solid_angles(height: int, width: int):
    """Solid angle of every texel, (height, width) float64, summing to 4 pi.

    Exact per-row integral (2 pi / W)(cos(theta_top) - cos(theta_bottom)), which is what
    DESIGN.md's (2 pi / W)(pi / H) sin(theta) approximates at the row centre; the exact form
    keeps the sum at 4 pi for tiny maps (a 2x1 map) too.
    """
    edges = np.pi * np.arange(height + 1) / height
    rows = (2.0 * np.pi / width) * (np.cos(edges[:-1]) - np.cos(edges[1:]))
    return np.repeat(rows[:, None], width, axis=1)
