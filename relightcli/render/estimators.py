"""One Monte Carlo sample of the shading integral per row: the estimators the integrator runs.

shading(p) = (1/pi) * integral over the hemisphere of L(w) V(p, w) max(0, n.w) dw (DESIGN.md).
Every function takes N surface points in the scene's local frame as ray origins (float (N, 3)
positions already offset by `scene.ray_offset` along the geometric normal, see `ray_origins`),
unit shading normals `n` and geometric normals `g` facing the outgoing side, and uniform
samples u (N, k), and returns (N, 3) estimates in radiance units (float32 per sample for the
shadow-ray terms; the integrator sums them in float64).
"""

from __future__ import annotations

import numpy as np

from relightcli.render.environment import EnvironmentLight
from relightcli.render.sampling import (
    INV_PI,
    cosine_hemisphere_pdf,
    real_array,
    sample_cosine_hemisphere,
    sample_uniform_sphere,
    uniform_sphere_pdf,
)
from relightcli.render.scene import Hits, Scene, orient_normals

# Uniform dimensions each strategy consumes per sample
DIMENSIONS = {"mis": 4, "mis-cv": 4, "env": 2, "cosine": 2, "uniform": 2}
BOUNCE_DIMENSIONS = 4
RAYS_PER_SAMPLE = {"mis": 2, "mis-cv": 2, "env": 1, "cosine": 1, "uniform": 1}
# The control variate's cosine rays are traced before the map is looked up (only blocked rays
# need it: `_blocked_cosine_contribution`) when at most this share of the sphere is black; on
# maps with more, rays toward black texels would be traced for nothing
TRACE_FIRST_MAX_BLACK = 0.02


def dot(a, b):
    """Row-wise dot products of (N, 3) arrays, (N,) (einsum: several times faster than sum)."""
    return np.einsum("ij,ij->i", a, b)


def cosine_directions(n, u):
    """Cosine-weighted world directions (N, 3) about unit normals n (N, 3), u (N, 2), in the
    normals' precision (float32 normals: float32 directions, as the tracer takes them).

    `sample_cosine_hemisphere` in the tangent frame (t, s, n) of Duff et al. 2017 (pbrt's
    CoordinateSystem, branchless), written out per component: no (N, 3, 3) frames.
    """
    n = real_array(n)
    local = sample_cosine_hemisphere(np.asarray(u, dtype=n.dtype))
    x, y, z = local[:, 0], local[:, 1], local[:, 2]
    nx, ny, nz = n[:, 0], n[:, 1], n[:, 2]
    sign = np.where(nz >= 0, 1, -1).astype(n.dtype)
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    out = np.empty_like(n)
    # t = (1 + sign nx^2 a, sign b, -sign nx), s = (b, sign + ny^2 a, -ny)
    out[:, 0] = x * (1.0 + sign * nx * nx * a) + y * b + z * nx
    out[:, 1] = x * (sign * b) + y * (sign + ny * ny * a) + z * ny
    out[:, 2] = -x * (sign * nx) - y * ny + z * nz
    return out


def ray_origins(scene: Scene, points, g):
    """Surface points (N, 3) moved off the surface along the geometric normals g (N, 3) by the
    scene's ray offset, so that rays leaving them do not hit their own triangle."""
    return points + scene.ray_offset * g


def lifted_origins(scene: Scene, points, n, g, lift: float):
    """Shadow-ray origins (N, 3) float64 for surface points (N, 3) with shading normals n and
    geometric normals g (N, 3, on the same side), and the normals (N, 3) whose hemisphere the
    rays leave through (`visible`'s g).

    lift 0: the points off the surface by the scene's ray offset (ray_origins), the triangle's
    own hemisphere: a direction the shading normal faces but the triangle does not is blocked by
    the triangle itself. Where the shading normals are smoother than the triangles (interpolated
    vertex normals, or normals from another source), that puts a jagged shadow terminator on the
    facets. lift > 0: each point also moves along n by lift x the scene's median edge length x
    sin(angle(n, g)), and rays leave through n's hemisphere: a ray below the triangle's plane
    then runs at least lift edge lengths before it crosses it, so the triangle it starts on and
    its neighbours on a convex surface no longer block it, while farther occluders still do.
    Zero where n is g: flat parts keep their contact shadows."""
    origins = ray_origins(scene, points, g)
    if lift <= 0:
        return origins, g
    tilt = np.linalg.norm(np.cross(n, g), axis=1)
    return origins + (lift * scene.edge_length * tilt)[:, None] * n, n


def visible(scene: Scene, origins, g, directions, active, max_distance=None):
    """(N,) bool: unoccluded rays, traced only where `active`; rays below the surface (g.w <=
    0, g the geometric normal, or the shading normal for lifted origins: lifted_origins) are
    blocked by the surface itself and never traced."""
    todo = np.flatnonzero(active & (dot(g, directions) > 0))  # indices: gathers ~5x faster than a mask
    result = np.zeros(origins.shape[0], dtype=bool)
    if todo.size:
        result[todo] = ~scene.occluded(np.take(origins, todo, axis=0), np.take(directions, todo, axis=0),
                                       max_distance)
    return result


def direct_lighting(scene, light: EnvironmentLight, points, n, g, u, strategy, max_distance=None,
                    unoccluded=None):
    """One-sample (two for MIS) estimate of the direct shading (N, 3).

    mis: balance heuristic over one environment and one cosine sample,
    sum_i f(w_i) V(w_i) / (p_env(w_i) + p_cos(w_i)), f = L max(0, n.w) / pi.
    mis-cv: the unoccluded shading as a control variate: `unoccluded` (N, 3) (the light's
    `irradiance(n)`) minus the MIS estimate of what occluders take away, f (1 - V). Where
    nothing is in the way this is exact; noise comes only from the occluded directions.
    """
    if strategy == "mis-cv":
        return unoccluded + _direct(scene, light, points, n, g, u, "mis", max_distance,
                                    complement=True)
    return _direct(scene, light, points, n, g, u, strategy, max_distance, complement=False)


def _direct(scene, light, points, n, g, u, strategy, max_distance, complement):
    """`direct_lighting` for the plain strategies; complement: estimate -f (1 - V) instead."""
    if strategy == "mis":
        # Two shadow-ray sets, one per technique; each weighted by the summed pdfs
        w_env, pdf_env, radiance_env = light.sample_radiance(u[:, 0:2], np.float32)
        cos_env = dot(n, w_env)
        from_env = _unoccluded_contribution(
            scene, points, g, w_env, cos_env, pdf_env + cosine_hemisphere_pdf(cos_env),
            radiance_env, max_distance, complement)
        w_cos = cosine_directions(n, u[:, 2:4])
        cos_cos = dot(n, w_cos)
        if complement and light.black_fraction <= TRACE_FIRST_MAX_BLACK:
            return from_env + _blocked_cosine_contribution(scene, light, points, g, w_cos, cos_cos,
                                                           max_distance)
        radiance_cos, pdf_env_cos = light.eval_pdf(w_cos)
        return from_env + _unoccluded_contribution(
            scene, points, g, w_cos, cos_cos, pdf_env_cos + cosine_hemisphere_pdf(cos_cos),
            radiance_cos, max_distance, complement)
    if strategy == "env":
        directions, pdf, radiance = light.sample_radiance(u[:, 0:2], np.float32)
        cosine = dot(n, directions)
    elif strategy == "cosine":
        directions = cosine_directions(n, u[:, 0:2])
        cosine = dot(n, directions)
        pdf = cosine_hemisphere_pdf(cosine)
        radiance = light.eval(directions)
    elif strategy == "uniform":
        directions = sample_uniform_sphere(u[:, 0:2])
        cosine = dot(n, directions)
        pdf = uniform_sphere_pdf(directions)
        radiance = light.eval(directions)
    else:
        raise ValueError(f"unknown strategy {strategy!r}")
    return _unoccluded_contribution(scene, points, g, directions, cosine, pdf, radiance,
                                    max_distance, complement)


def _unoccluded_contribution(scene, points, g, directions, cosine, pdf, radiance,
                             max_distance, complement=False):
    """f(w) V(w) / pdf per row, f = L max(0, cos) / pi: (N, 3) float32; zero where f or
    the pdf is zero, and no ray is traced there. complement: -f(w) (1 - V(w)) / pdf."""
    weight = _weight(cosine, pdf)
    lit = (radiance[:, 0] > 0) | (radiance[:, 1] > 0) | (radiance[:, 2] > 0)
    v = visible(scene, points, g, directions, (weight > 0) & lit, max_distance)
    # float32 per sample (radiance is float32); the running sums are float64
    return radiance * (weight * (v - 1.0 if complement else v)).astype(np.float32)[:, None]


def _blocked_cosine_contribution(scene, light, points, g, directions, cosine, max_distance):
    """The cosine technique's share of `_unoccluded_contribution(..., complement=True)`:
    -f(w) (1 - V(w)) over the summed pdfs, which is zero wherever the ray gets through, so the
    rays are traced first and the map is looked up (radiance, environment pdf) only for the
    blocked ones (on a body, most cosine rays escape). The same values as computed for every
    row, but rays toward black texels are traced too (their rows add zero): for lights with
    little black (TRACE_FIRST_MAX_BLACK)."""
    result = np.zeros((points.shape[0], 3), np.float32)
    up = cosine > 0
    blocked = np.flatnonzero(up & ~visible(scene, points, g, directions, up, max_distance))
    if blocked.size:
        radiance, pdf_env = light.eval_pdf(np.take(directions, blocked, axis=0))
        cosine = np.take(cosine, blocked)
        weight = _weight(cosine, pdf_env + cosine_hemisphere_pdf(cosine))
        result[blocked] = radiance * (-weight).astype(np.float32)[:, None]
    return result


def _weight(cosine, pdf):
    """max(0, cos) / pi over the pdf, float64 as the pdfs (a cosine-sampled weight is then
    exactly 1), zero where the pdf is."""
    cosine = np.maximum(cosine, 0.0).astype(np.float64)
    return np.where(pdf > 0, cosine * INV_PI / np.where(pdf > 0, pdf, 1.0), 0.0)


def indirect_lighting(scene, light, points, n, g, u, albedo_at):
    """One-sample estimate (N, 3) of the light one diffuse bounce brings in.

    A cosine-sampled ray from each point; where it hits a surface q, the radiance leaving q
    is albedo(q) * direct_shading(q) (Lambertian), estimated with one environment sample;
    the cosine pdf cancels the (1/pi) cos term. Rays that escape add nothing here (the
    environment seen directly is in `direct_lighting`).
    """
    directions = cosine_directions(n, u[:, 0:2])
    result = np.zeros((points.shape[0], 3))
    up = dot(g, directions) > 0
    if not up.any():
        return result
    hits = scene.intersect(points[up], directions[up])
    rows = np.flatnonzero(up)[hits.hit]
    if rows.size == 0:
        return result
    d = directions[rows]
    q = points[rows] + hits.t[hits.hit, None].astype(np.float64) * d
    nq, gq = orient_normals(hits.geometric_normal[hits.hit],
                            scene.shading_normals(_select(hits, hits.hit)), d)
    shading_q = direct_lighting(scene, light, ray_origins(scene, q, gq), nq, gq, u[rows, 2:4], "env")
    result[rows] = albedo_at(q) * shading_q
    return result


def _select(hits, keep):
    return Hits(prim=hits.prim[keep], t=hits.t[keep], bary=hits.bary[keep],
                geometric_normal=hits.geometric_normal[keep])
