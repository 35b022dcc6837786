"""Compiled direct-lighting passes (numba): sampling, shadow rays and sums fused per pixel.

The same estimators as relightcli.render.estimators (`direct_lighting` for the strategies
env / cosine / uniform / mis / mis-cv, randomised-QMC uniforms as `_Run.uniforms` makes them)
written as one loop per pixel and pass: no arrays in flight and no GIL (the shadow rays go to
Embree through relightcli.render.embree), so threads share a round's pixels. A pixel's sums
run in pass order whichever thread takes it: the result does not depend on the threads.

What the measurements chose (107k-triangle body, MIS plan of the noon map, 256 x 256, 64
passes, CPU time on a loaded machine):
- Helpers inline into one kernel compiled without numba's reference counting (`_nrt=False`;
  only the entry point allocates): an array passed to a helper costs two atomic operations
  per call, which threads contend for. 1.2 us -> 0.45 us per pass without rays.
- Compact light tables (`EnvironmentLight.sampling_tables`): the lookups are dependent loads
  into a 1k map, so a sample waits on the last-level cache; the loop is memory-bound (0.48
  us per pass with a 1024 x 512 map, 0.18 us with 64 x 32).
- Cached on disk (`cache=True`: next to this module, or under NUMBA_CACHE_DIR): compiling
  takes ~7-9 s, loading the cache ~0.2 s of numba's own imports (0.3 s more when
  scipy.linalg is not imported yet).
"""

from __future__ import annotations

import math

import numpy as np
from llvmlite import binding
from numba import njit, types

from relightcli.render import embree

# Strategy codes the kernel branches on (the names are estimators.DIMENSIONS' keys)
STRATEGY_CODES = {"env": 0, "cosine": 1, "uniform": 2, "mis": 3, "mis-cv": 4}
_ENV, _COSINE, _UNIFORM, _MIS, _MIS_CV = range(5)
_ONE_MINUS = float(np.nextafter(1.0, 0.0))
_INV_PI = 1.0 / math.pi
_FAR = np.float32(1e30)
# Passes of a pixel whose samples are drawn before their shadow rays are traced
BATCH = 16

binding.load_library_permanently(embree.library_path() or "")
# void rtcOccluded1(RTCScene, RTCRay*, RTCOccludedArguments*): pointers passed as integers
_occluded1 = types.ExternalFunction("rtcOccluded1", types.void(types.uintp, types.uintp, types.uintp))
# The per-sample helpers read arrays and allocate none: they compile without numba's
# reference counting, which costs two atomic operations per array argument and call
# (measured, MIS plan, no rays traced: 743 -> 455 ns per pass)
_helper = njit(cache=True, nogil=True, _nrt=False)
# Helpers inline into the kernel that calls them (one function to cache and load)
_inline = njit(cache=True, nogil=True, _nrt=False, inline="always")


@_inline
def _occluded(scene, ray, ray_bits, at, address, ox, oy, oz, dx, dy, dz, tmax):
    """Trace one shadow ray. ray (16,) float32, ray_bits: its uint32 view, at: the offset of
    the 16-byte aligned RTCRay in it, address: the RTCRay's; RTCRay: org, tnear, dir, time,
    tfar, mask, id, flags."""
    ray[at], ray[at + 1], ray[at + 2], ray[at + 3] = ox, oy, oz, 0.0
    ray[at + 4], ray[at + 5], ray[at + 6], ray[at + 7] = dx, dy, dz, 0.0
    ray[at + 8] = tmax
    ray_bits[at + 9], ray_bits[at + 10], ray_bits[at + 11] = 0xFFFFFFFF, 0, 0
    _occluded1(scene, address, 0)
    return ray[at + 8] < 0.0  # Embree sets tfar to -inf on a hit


@_inline
def _search(cdf, guide, key):
    """o with cdf[o] <= key < cdf[o + 1] (searchsorted "right" minus one), searched only
    between the guide table's bounds for key's bucket (guide[j]: the o of key j / G)."""
    bucket = min(int(key * (guide.size - 1)), guide.size - 2)
    lo, hi = guide[bucket], min(guide[bucket + 1] + 2, cdf.size)
    while lo < hi:
        mid = (lo + hi) >> 1
        if cdf[mid] <= key:
            lo = mid + 1
        else:
            hi = mid
    return lo - 1


@_inline
def _uv_to_direction(x, y):
    """io.envmap.uv_to_direction in float32 (angles from float64, as there)."""
    theta = np.float32(math.pi * min(y, 1.0 - y))
    sin_theta, cos_theta = math.sin(theta), math.cos(theta)
    if y > 0.5:
        cos_theta = -cos_theta
    phi = np.float32(2.0 * math.pi * (x - 0.5))
    return sin_theta * math.sin(phi), cos_theta, -sin_theta * math.cos(phi)


@_inline
def _solid_angle_pdf(pdf_uv, dx, dz):
    """p(w) = p(u, v) / (2 pi^2 sin(theta)); zero exactly at a pole."""
    sin_theta = np.float64(math.hypot(dx, dz))
    if sin_theta <= 1e-12:
        return 0.0
    return pdf_uv / (2.0 * math.pi * math.pi * sin_theta)


@_inline
def _sample_light(cdf, guide, texels, width, height, u0, u1):
    """EnvironmentLight.sample_radiance: (direction (3 float32), pdf, texel index)."""
    u0 = min(u0, _ONE_MINUS)
    texel = min(max(_search(cdf, guide, u0), 0), texels.shape[0] - 1)
    lo = cdf[texel]
    span = cdf[texel + 1] - lo
    offset = min(max((u0 - lo) / (span if span > 0 else 1.0), 0.0), 1.0)
    x = min((texel % width + offset) / width, _ONE_MINUS)
    y = min((texel // width + u1) / height, _ONE_MINUS)
    dx, dy, dz = _uv_to_direction(x, y)
    return dx, dy, dz, _solid_angle_pdf(np.float64(texels[texel, 3]), dx, dz), texel


@_inline
def _texel(width, height, dx, dy, dz):
    """Row-major texel index of a direction (io.envmap.direction_to_uv, nearest texel)."""
    v = math.atan2(math.hypot(dx, dz), dy) / np.float32(math.pi)
    u = math.atan2(dx, -dz) / np.float32(2.0 * math.pi) + np.float32(0.5)
    if u >= 1.0:
        u -= np.float32(1.0)
    row = min(max(int(v * np.float32(height)), 0), height - 1)
    col = min(max(int(u * np.float32(width)), 0), width - 1)
    return row * width + col


@_inline
def _cosine_direction(nx, ny, nz, u0, u1):
    """estimators.cosine_directions for one normal (float32)."""
    u0, u1 = np.float32(u0), np.float32(u1)
    r = math.sqrt(u0)
    phi = np.float32(2.0 * math.pi) * u1
    x, y = r * math.cos(phi), r * math.sin(phi)
    z = math.sqrt(max(np.float32(0.0), np.float32(1.0) - u0))
    sign = np.float32(1.0) if nz >= 0 else np.float32(-1.0)
    a = np.float32(-1.0) / (sign + nz)
    b = nx * ny * a
    return (x * (np.float32(1.0) + sign * nx * nx * a) + y * b + z * nx,
            x * (sign * b) + y * (sign + ny * ny * a) + z * ny,
            -x * (sign * nx) - y * ny + z * nz)


@_inline
def _record(samples, slot, dx, dy, dz, cosine, pdf, red, green, blue, g):
    """Store one sample's direction, weight max(0, cos) / (pi pdf), radiance and what to do
    with it in samples[slot] (see `_shade_term`): trace it (1), count it as blocked by its
    own surface (2: below the geometric normal g), or nothing (0: no weight or no light)."""
    weight = max(np.float64(cosine), 0.0) * _INV_PI / pdf if pdf > 0 else 0.0
    samples[slot, 0], samples[slot, 1], samples[slot, 2] = dx, dy, dz
    samples[slot, 3], samples[slot, 4], samples[slot, 5], samples[slot, 6] = weight, red, green, blue
    if weight <= 0 or not (red > 0 or green > 0 or blue > 0):
        samples[slot, 7] = 0.0
    else:
        samples[slot, 7] = 1.0 if g[0] * dx + g[1] * dy + g[2] * dz > 0 else 2.0


@_inline
def _sample_term(code, cdf, guide, texels, width, height, nx, ny, nz, g, u, samples, slot):
    """The directions of one sample of a plan term (estimators.direct_lighting: one, two for
    MIS), recorded from samples[slot] on; u: the term's uniforms, the light:
    `EnvironmentLight.sampling_tables`. Returns how many."""
    count = 0
    if code == _ENV or code == _MIS or code == _MIS_CV:
        dx, dy, dz, pdf, texel = _sample_light(cdf, guide, texels, width, height, u[0], u[1])
        cosine = nx * dx + ny * dy + nz * dz
        if code != _ENV:
            pdf += max(np.float64(cosine), 0.0) * _INV_PI
        _record(samples, slot, dx, dy, dz, cosine, pdf, texels[texel, 0], texels[texel, 1],
                texels[texel, 2], g)
        count += 1
    if code == _COSINE or code == _MIS or code == _MIS_CV:
        first = 0 if code == _COSINE else 2
        dx, dy, dz = _cosine_direction(nx, ny, nz, u[first], u[first + 1])
        cosine = nx * dx + ny * dy + nz * dz
        texel = _texel(width, height, dx, dy, dz)
        pdf = max(np.float64(cosine), 0.0) * _INV_PI
        if code != _COSINE:
            pdf += _solid_angle_pdf(np.float64(texels[texel, 3]), dx, dz)
        _record(samples, slot + count, dx, dy, dz, cosine, pdf, texels[texel, 0],
                texels[texel, 1], texels[texel, 2], g)
        count += 1
    if code == _UNIFORM:
        z = 1.0 - 2.0 * u[0]
        r, phi = math.sqrt(max(0.0, 1.0 - z * z)), 2.0 * math.pi * u[1]
        x, y = r * math.cos(phi), r * math.sin(phi)
        dx, dy, dz = np.float32(x), np.float32(y), np.float32(z)
        texel = _texel(width, height, dx, dy, dz)
        _record(samples, slot, dx, dy, dz, nx * x + ny * y + nz * z, 1.0 / (4.0 * math.pi),
                texels[texel, 0], texels[texel, 1], texels[texel, 2], g)
        count += 1
    return count


@njit(cache=True, nogil=True)
def shade_rows(scene, rows, first_pass, passes, groups, sobol, shift, origins, normals,
               geometric, unoccluded, lights, codes, tmax, group_sums):
    """Passes first_pass .. first_pass + passes - 1 of the pixels `rows` (int64), summed per
    randomisation group into group_sums (len(rows), groups, 3) float64 (pass k: group k %
    groups). sobol (points, dims) and shift (groups, pixels, dims): the Cranley-Patterson
    rotated Sobol points, as `_Run.uniforms`. origins, normals, geometric (pixels, 3)
    float32; unoccluded (terms, pixels, 3) float64 (the control variate of mis-cv terms);
    lights: two `EnvironmentLight.sampling_tables` (the second repeats the first for a
    one-term plan), codes (terms,) int64. Returns the rays traced."""
    ray = np.empty(16, np.float32)  # one RTCRay, 16-byte aligned within the buffer
    at = ((16 - ray.ctypes.data % 16) % 16) // 4
    scratch = (ray, ray.view(np.uint32), at, ray.ctypes.data + 4 * at, np.empty(4),
               np.empty((2 * BATCH, 8)))
    rays, first = 0, 0
    # One term at a time: its light is picked out of the tuple once, not per sample
    for term in range(codes.size):
        light = lights[0] if term == 0 else lights[1]
        rays += _shade_term(light, codes[term], first, scene, scratch, rows, first_pass, passes,
                            groups, sobol, shift, origins, normals, geometric, unoccluded[term],
                            tmax, group_sums)
        first += 4 if codes[term] >= _MIS else 2
    return rays


@_helper
def _shade_term(light, code, first, scene, scratch, rows, first_pass, passes, groups, sobol,
                shift, origins, normals, geometric, unoccluded, tmax, group_sums):
    """`shade_rows` for one plan term, whose uniforms start at dimension `first`; scratch:
    the ray buffer (see `_occluded`), room for u and for BATCH passes' samples. A pixel's
    passes go in batches: first every sample's direction and radiance (table lookups that
    do not wait on each other), then the shadow rays."""
    cdf, guide, texels, width, height = light
    ray, ray_bits, at, address, u, samples = scratch
    dims, complement = (4 if code >= _MIS else 2), code == _MIS_CV
    rays = 0
    for i in range(rows.size):
        pixel = rows[i]
        o, g = origins[pixel], geometric[pixel]
        nx, ny, nz = normals[pixel, 0], normals[pixel, 1], normals[pixel, 2]
        for start in range(first_pass, first_pass + passes, BATCH):
            stop = min(start + BATCH, first_pass + passes)
            slots = 0
            for k in range(start, stop):
                point, group = k // groups, k % groups
                for j in range(dims):  # (point + shift) mod 1
                    u[j] = sobol[point, first + j] + shift[group, pixel, first + j]
                    if u[j] >= 1.0:
                        u[j] -= 1.0
                per_pass = _sample_term(code, cdf, guide, texels, width, height, nx, ny, nz, g, u,
                                        samples, slots)
                slots += per_pass
            for k in range(start, stop):
                value_r = value_g = value_b = np.float32(0.0)
                for slot in range((k - start) * per_pass, (k - start + 1) * per_pass):
                    todo = samples[slot, 7]
                    if todo == 0.0:
                        continue
                    visible = 0.0
                    if todo == 1.0:
                        rays += 1
                        if not _occluded(scene, ray, ray_bits, at, address, o[0], o[1], o[2],
                                         np.float32(samples[slot, 0]), np.float32(samples[slot, 1]),
                                         np.float32(samples[slot, 2]), tmax):
                            visible = 1.0
                    factor = np.float32(samples[slot, 3] * (visible - 1.0 if complement else visible))
                    value_r += np.float32(samples[slot, 4]) * factor
                    value_g += np.float32(samples[slot, 5]) * factor
                    value_b += np.float32(samples[slot, 6]) * factor
                group = k % groups
                group_sums[i, group, 0] += unoccluded[pixel, 0] + value_r
                group_sums[i, group, 1] += unoccluded[pixel, 1] + value_g
                group_sums[i, group, 2] += unoccluded[pixel, 2] + value_b
    return rays


@njit(cache=True, nogil=True)
def occluded_rays(scene, origins, directions, tmax, out):
    """out[i] = does the segment origins[i] + t directions[i], 0 < t < tmax[i], hit
    anything: the shadow-ray query alone, (N, 3) float32 rays, (N,) float32 tmax, (N,) bool
    out, no GIL (for tests and the raw tracing rate)."""
    ray = np.empty(16, np.float32)
    at = ((16 - ray.ctypes.data % 16) % 16) // 4
    ray_bits, address = ray.view(np.uint32), ray.ctypes.data + 4 * at
    for i in range(origins.shape[0]):
        out[i] = _occluded(scene, ray, ray_bits, at, address, origins[i, 0], origins[i, 1],
                           origins[i, 2], directions[i, 0], directions[i, 1], directions[i, 2],
                           tmax[i])
