"""Environment maps: the direction convention (the single source of truth), and maps.

Convention (../shared/DESIGN.md): an equirectangular map has W = 2H. Texel coordinates
(u, v) in [0, 1)^2 with v = 0 at the top row; polar angle theta = pi * v measured from +Y,
azimuth phi = 2 pi (u - 0.5), direction

    d = (sin(theta) sin(phi), cos(theta), -sin(theta) cos(phi)).

The centre column (u = 0.5) is -Z (what the camera looks at), u = 0.75 is +X, u = 0 and 1
are +Z (behind the camera). Values are linear RGB radiance.

Environment maps in memory are plain (H, 2H, 3) float32 arrays of linear radiance, finite and
>= 0 (`validate_envmap` makes them so). A texel holds constant radiance over its cell, so the
energy of a map is sum(L * texel_solid_angles) and every resampling here keeps it.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import OpenImageIO as oiio
import scipy.sparse

from relightcli.errors import InputError, RelightWarning, UsageError
from relightcli.io.images import (
    _FIX_UNREADABLE,
    _is_integer,
    _open_input,
    _oriented_size,
    LUMINANCE,
    channel_layout,
    check_decoded_size,
    read_channels,
    read_image,
    srgb_to_linear,
)

ENVMAP_MAX_PIXELS = 16384 * 8192
# Maps are used at most this tall (2H x H texels): see load_envmap and ENVMAP_WORKING_HEIGHT's
# measurement in tests/io/test_envmap_reduce.py
ENVMAP_WORKING_HEIGHT = 1024
_MAX_STOPS = 64
# The brightest radiance a map may hold (after --exposure): the renderer's float32 estimates
# of one texel (at most 4 pi L, (4 pi)^2 L with a second bounce) and their squares (variances)
# then stay below float32's largest value, 3.4e38. Real maps reach ~1e6 (a sun); 2**56 ~ 7.2e16.
MAX_RADIANCE = 2.0 ** 56
_FIX_ASPECT = "use an equirectangular (latitude-longitude) map with width = 2 x height"
# Rec. 709 / sRGB primaries: luminance of linear RGB


def _real(x) -> np.ndarray:
    """x as a float32 array when it is one, else float64."""
    x = np.asarray(x)
    return x if x.dtype == np.float32 else x.astype(np.float64, copy=False)


def uv_to_direction(u, v, dtype=np.float64):
    """Unit direction for texel coordinates.

    u, v: arrays of the same shape, in [0, 1]. Returns (..., 3) unit vectors of `dtype`: the
    angles are formed in float64 (theta from the nearer pole, so both poles keep full
    relative precision), the trig runs in `dtype` (float32 for the ray tracer: ~10x faster).
    """
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    below = 0.5 - v  # > 0 in the upper hemisphere
    theta_near = (np.pi * (0.5 - np.abs(below))).astype(dtype)
    phi = (2.0 * np.pi * (u - 0.5)).astype(dtype)
    sin_theta = np.sin(theta_near)
    out = np.empty(np.broadcast_shapes(u.shape, v.shape) + (3,), dtype)
    np.multiply(sin_theta, np.sin(phi), out=out[..., 0])
    np.copysign(np.cos(theta_near), below.astype(dtype), out=out[..., 1])
    np.multiply(sin_theta, np.cos(phi), out=out[..., 2])
    np.negative(out[..., 2], out=out[..., 2])
    return out


def direction_to_uv(d):
    """Texel coordinates of directions, the inverse of `uv_to_direction`.

    d: (..., 3) array (need not be unit length, must be non-zero). Returns (u, v), each (...)
    float32 for float32 directions, float64 otherwise; u in [0, 1), v in [0, 1].
    """
    d = _real(d)
    # float32 (the renderer's hot path): a polynomial arctan2 within float32 round-off, ~3x
    # faster than numpy's
    atan2 = arctan2_float32 if d.dtype == np.float32 else np.arctan2
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    # theta = atan2(|(x, z)|, y): accurate near the poles, where arccos(y) loses digits
    v = atan2(np.sqrt(x * x + z * z), y) / np.pi
    # phi = atan2(x, -z): x = sin(theta) sin(phi), -z = sin(theta) cos(phi)
    u = atan2(x, -z) / (2.0 * np.pi) + 0.5
    u = np.where(u >= 1.0, u - 1.0, u)
    return u, v


# arctan on [0, 1] as a x P(a^2): coefficients fitted here (iteratively reweighted least
# squares toward the minimax fit, degree 15), |error| < 4e-8 rad, below float32's round-off
_ATAN_COEFFICIENTS = np.array([0.9999993356200118, -0.333298608672505, 0.1994656615395977,
                               -0.1390863077486887, 0.09642198322468784, -0.055912320129723234,
                               0.021862943122605755, -0.004054561031840223], np.float32)


def arctan2_float32(y, x) -> np.ndarray:
    """np.arctan2 for float32 arrays (same signs, zeros and quadrants), within 4e-7 rad of the
    float64 result (numpy's own float32 arctan2: 2.5e-7); no vector arctan2 in numpy, this
    runs in a few fused passes. NaN in, NaN out."""
    ax, ay = np.abs(x), np.abs(y)
    a = np.minimum(ax, ay)
    hi = np.maximum(ax, ay)
    a /= hi + (hi == 0)  # 0 / 0 -> 0
    s = a * a
    r = s * _ATAN_COEFFICIENTS[-1]
    for c in _ATAN_COEFFICIENTS[-2:0:-1]:
        r += c
        r *= s
    r += _ATAN_COEFFICIENTS[0]
    r *= a
    # Octants without branches: pi/2 - r where |y| > |x|, then pi - r where x < 0 (or -0)
    r += (ay > ax).astype(np.float32) * (np.float32(np.pi / 2) - 2 * r)
    r += np.signbit(x).astype(np.float32) * (np.float32(np.pi) - 2 * r)
    return np.copysign(r, y, out=r)


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


# --- validation and loading -----------------------------------------------------------------

def _repair_counts(env):
    """Counts of NaN, +Inf, -Inf and negative finite values in a float32 array."""
    return {
        "NaN": int(np.count_nonzero(np.isnan(env))),
        "+Inf": int(np.count_nonzero(np.isposinf(env))),
        "-Inf": int(np.count_nonzero(np.isneginf(env))),
        "negative": int(np.count_nonzero(np.isfinite(env) & (env < 0))),
    }


def repair_radiance(env, path=None, stacklevel=2):
    """Radiance made finite and >= 0: NaN, -Inf and negatives become 0, +Inf the largest finite
    value (0 if none: a blown-out sun stays the brightest light), with one RelightWarning
    counting each kind, attributed `stacklevel` frames up. env: (..., 3) array; returns
    float32 of the same shape (env itself, as float32, when nothing needed repair). The one
    rule for every map (docs/CLI.md, --hdr), the renderer's too."""
    env = np.asarray(env, dtype=np.float32)
    counts = _repair_counts(env)
    if not any(counts.values()):
        return env
    finite = np.isfinite(env)
    largest = float(env[finite].max()) if finite.any() else 0.0
    largest = max(largest, 0.0)
    repaired = np.where(np.isposinf(env), np.float32(largest), env)
    repaired = np.where(np.isnan(repaired) | (repaired < 0), np.float32(0.0), repaired)
    _warn_repaired(counts, largest, path, stacklevel=stacklevel + 1)
    return repaired.astype(np.float32)


def _warn_repaired(counts, largest, path, stacklevel=3):
    where = "" if path is None else f"{path}: "
    found = ", ".join(f"{n} {kind}" for kind, n in counts.items())
    warnings.warn(
        f"{where}environment map had {found} values; set NaN, -Inf and negatives to 0 and "
        f"+Inf to the largest finite value ({largest:g})", RelightWarning, stacklevel=stacklevel)


def validate_envmap(env, path=None):
    """Check an environment map's shape and repair its texels.

    env: (H, W, 3) array of linear radiance with W = 2H (a 2x1 map is valid). path: the file
    it came from, named in messages. Returns (H, W, 3) float32, finite and >= 0; NaN, -Inf and
    negative values become 0, +Inf the largest finite value of the map (0 if it has none),
    with one RelightWarning that counts each kind. All-black maps are allowed.
    Raises InputError for any other shape.
    """
    env = np.asarray(env)
    if env.ndim != 3 or env.shape[2] != 3 or env.shape[0] == 0:
        raise InputError(f"environment map must be an (H, W, 3) RGB image, got shape "
                         f"{env.shape}", path=path, fix=_FIX_ASPECT)
    height, width = env.shape[:2]
    if width != 2 * height:
        raise InputError(f"environment map is {width}x{height} (width x height), not 2:1",
                         path=path, fix=_FIX_ASPECT)
    return repair_radiance(np.array(env, dtype=np.float32), path, stacklevel=3)


def load_envmap(path, *, rotate_deg=0.0, exposure_ev=0.0, max_pixels=ENVMAP_MAX_PIXELS,
                working_height=ENVMAP_WORKING_HEIGHT):
    """Read an equirectangular environment map from a file, at most `working_height` rows.

    .hdr and .exr hold linear radiance. An 8/16-bit file (PNG, JPEG, TIFF) is decoded from
    sRGB and accepted with a RelightWarning: its clipped highlights cannot light like an HDR.
    A map taller than `working_height` is area-resampled down to it while it is read, a band
    of rows at a time (`read_reduced_envmap`): radiance x solid angle is kept per channel and
    per output texel, so a sun keeps all its energy in the texel(s) it falls in. Then
    `validate_envmap` (NaN, Inf, negatives repaired with a warning; an all-black map warns),
    `rotate_envmap` by `rotate_deg` degrees and `expose` by `exposure_ev` stops.
    Returns (h, 2h, 3) float32 linear radiance, h = min(H, working_height).
    Raises InputError when the file cannot be read or is not 2:1.
    """
    image_input = _open_input(path)
    try:
        spec = image_input.spec()
        width, height = _oriented_size(spec)
        _check_map_header(spec, width, height, path, max_pixels)
        if height > working_height and _plain_scanlines(spec):
            rgb, counts, largest = read_reduced_envmap(image_input, path, working_height)
            encoded, bits = _is_integer(spec), int(spec.format.size()) * 8
        else:
            rgb = counts = None
    finally:
        image_input.close()
    if rgb is None:
        image = read_image(path, max_pixels=max_pixels)
        rgb, encoded, bits = image.rgb, image.encoded, image.bits
    if encoded:
        warnings.warn(
            f"{path}: {bits}-bit environment map read as sRGB and decoded to linear; its "
            "clipped highlights (sun, lamps) cannot light like an HDR: use an .hdr or .exr map "
            "for faithful lighting", RelightWarning, stacklevel=2)
    if counts is not None and any(counts.values()):
        _warn_repaired(counts, largest, path)
    return envmap_from_array(rgb, rotate_deg=rotate_deg, exposure_ev=exposure_ev,
                             working_height=working_height, path=path)


def envmap_from_array(env, *, rotate_deg=0.0, exposure_ev=0.0, working_height=ENVMAP_WORKING_HEIGHT,
                      path=None):
    """An environment map held in memory, made ready as `load_envmap` makes a file's:
    `validate_envmap`, area-resampled to at most `working_height` rows, a warning when it is
    all black, turned by `rotate_deg` and scaled by 2 ** `exposure_ev`. env: (H, 2H, 3) linear
    radiance; path: the file it came from, named in messages (None: an array).
    Returns (h, 2h, 3) float32. Raises InputError for a map brighter than MAX_RADIANCE,
    UsageError when `exposure_ev` would make it so (`check_radiance`)."""
    env = validate_envmap(env, path=path)
    if env.shape[0] > working_height:  # a file read whole (an unusual layout): reduce now
        env = resample_envmap(env, working_height)
    check_radiance(env, exposure_ev, path)
    if not env.any():
        where = "environment map" if path is None else f"{path}: environment map"
        warnings.warn(f"{where} is all black (no light): the relit person will be black",
                      RelightWarning, stacklevel=3)
    if rotate_deg:
        env = rotate_envmap(env, rotate_deg)
    if exposure_ev:
        env = expose(env, exposure_ev)
    return env


def _check_map_header(spec, width, height, path, max_pixels):
    """Refuse, from the header alone, a map that is not 2:1 or would decode more than
    max_pixels (its display window, data window or one tile: check_decoded_size)."""
    check_decoded_size(spec, str(path), max_pixels, what="environment map", raise_limit=None,
                       fix="downscale the map (it is used at most "
                           f"{2 * ENVMAP_WORKING_HEIGHT}x{ENVMAP_WORKING_HEIGHT})")
    if width != 2 * height:
        raise InputError(f"environment map is {width}x{height} (width x height), not 2:1",
                         path=path, fix=_FIX_ASPECT)


def _plain_scanlines(spec) -> bool:
    """True when rows can be read in bands as they are: no EXIF turn, data window = display
    window (anything else is read whole by read_image, which handles it)."""
    full = (spec.full_x, spec.full_y, spec.full_width, spec.full_height)
    return (spec.get_int_attribute("Orientation", 1) == 1
            and (spec.x, spec.y, spec.width, spec.height) == full)


def read_reduced_envmap(image_input, path, height, band_rows=64):
    """Read an open map a band of rows at a time, area-resampling it to (height, 2 height).

    Each band is repaired (NaN, -Inf and negatives -> 0), resampled in u, then added into the
    output rows it overlaps in t = (1 - cos theta) / 2 (`_area_matrix`): the result equals
    `resample_envmap` of the whole repaired map, while memory holds one band, never the map.
    +Inf texels become the largest finite value of the map, as `validate_envmap` does: their
    cover of each output texel is resampled alongside and scaled at the end.
    Returns ((height, 2 height, 3) float32, counts of each repaired kind, the largest finite
    value).
    """
    spec = image_input.spec()
    in_height, in_width = spec.height, spec.width
    width = 2 * height
    rows = _area_matrix(_cell_edges_t(height), _cell_edges_t(in_height)).tocsc()
    cols = _area_matrix(_cell_edges_u(width), _cell_edges_u(in_width))
    rgb_index, _ = channel_layout(spec, str(path))
    decode = _is_integer(spec)
    out = np.zeros((height, width * 3), np.float64)
    inf_cover = None
    counts = {"NaN": 0, "+Inf": 0, "-Inf": 0, "negative": 0}
    largest = 0.0
    for top in range(0, in_height, band_rows):
        bottom = min(top + band_rows, in_height)
        band = read_channels(lambda first, stop: _read_band(image_input, path, top, bottom, first, stop),
                             rgb_index)
        if decode:
            band = srgb_to_linear(band)
        for kind, n in _repair_counts(band).items():
            counts[kind] += n
        finite = np.isfinite(band)
        if finite.any():
            largest = max(largest, float(band[finite].max()))
        infinite = np.isposinf(band)
        band = np.where(finite & (band > 0), band, np.float32(0.0))
        # columns first (in_width -> width), then the rows' share of each output row
        by_cols = (cols @ band.transpose(1, 0, 2).reshape(in_width, -1)).reshape(width, -1, 3)
        by_cols = by_cols.transpose(1, 0, 2).reshape(bottom - top, width * 3)
        out += rows[:, top:bottom] @ by_cols
        if infinite.any():
            inf_cover = np.zeros_like(out) if inf_cover is None else inf_cover
            cover = (cols @ infinite.transpose(1, 0, 2).reshape(in_width, -1).astype(np.float64))
            cover = cover.reshape(width, -1, 3).transpose(1, 0, 2).reshape(bottom - top, -1)
            inf_cover += rows[:, top:bottom] @ cover
    if inf_cover is not None:
        out += largest * inf_cover
    return out.reshape(height, width, 3).astype(np.float32), counts, largest


def _read_band(image_input, path, top, bottom, first, stop):
    """Rows top..bottom - 1, channels first..stop - 1 of an open map, (rows, W, channels) float32."""
    band = image_input.read_scanlines(0, 0, top, bottom, 0, first, stop, oiio.FLOAT)
    if band is None or image_input.has_error:
        reason = image_input.geterror() or "read failed"
        raise InputError(f"cannot decode pixels (truncated or corrupt?): {reason}",
                         path=str(path), fix=_FIX_UNREADABLE)
    return np.asarray(band, np.float32).reshape(bottom - top, image_input.spec().width, stop - first)


# --- rotation and exposure --------------------------------------------------------------------

def _finite_number(value, name, fix):
    value = float(value)
    if not math.isfinite(value):
        raise UsageError(f"{name} must be a finite number, got {value}", fix=fix)
    return value


def rotate_envmap(env, degrees):
    """Turn the environment about +Y by `degrees`, counter-clockwise seen from above.

    env: (H, W, 3) float32 linear radiance. Returns a new (H, W, 3) float32 map: exact
    (np.roll) when the turn is a whole number of texels, otherwise linearly interpolated in
    u (periodically), which keeps every row's energy. Rotating by 360 is the identity.
    """
    # fmod is exact: any finite angle (1e308 too) becomes its turn within one revolution
    degrees = math.fmod(_finite_number(degrees, "rotation", "give the rotation in degrees, e.g. 90"), 360.0)
    env = np.asarray(env, dtype=np.float32)
    width = env.shape[1]
    # Counter-clockwise seen from +Y takes +X (phi = pi/2) toward -Z (phi = 0): phi drops by
    # alpha. The radiance arriving from phi now arrives from phi - alpha, so the new map is
    # new(phi) = old(phi + alpha), and with phi = 2 pi (u - 1/2): new(u) = old(u + alpha/2pi),
    # i.e. new[:, j] = old[:, j + s] with s = W alpha / 360 texels: a roll by -s.
    shift = (degrees / 360.0 * width) % width
    whole = round(shift)
    if abs(shift - whole) < 1e-9:
        return np.roll(env, -whole, axis=1)
    low = math.floor(shift)
    frac = np.float32(shift - low)
    return ((1 - frac) * np.roll(env, -low, axis=1)
            + frac * np.roll(env, -(low + 1), axis=1)).astype(np.float32)


def _stops(ev) -> float:
    """An exposure in stops, checked: finite and within +-_MAX_STOPS."""
    ev = _finite_number(ev, "exposure", "give the exposure in stops, e.g. -1.5")
    if abs(ev) > _MAX_STOPS:
        # beyond this float32 radiance overflows to Inf or underflows to 0
        raise UsageError(f"exposure of {ev:g} stops is outside +-{_MAX_STOPS}",
                         fix="give the exposure in stops, e.g. -1.5")
    return ev


def expose(env, ev):
    """Scale radiance by 2 ** ev (exposure in stops). (H, W, 3) float32 -> same. Raises
    UsageError when the result would be brighter than MAX_RADIANCE (`check_radiance`)."""
    ev = _stops(ev)
    env = np.asarray(env, dtype=np.float32)
    check_radiance(env, ev)
    return (env * np.float32(2.0 ** ev)).astype(np.float32)


def check_radiance(env, exposure_ev=0.0, path=None) -> None:
    """Refuse a map that, scaled by 2 ** exposure_ev, would be brighter than MAX_RADIANCE (the
    renderer's float32 sums would overflow: a uniform 3e38 map drew NaN). env: (H, W, 3)
    radiance, finite (validate_envmap). Raises InputError when the map itself is too bright
    (exposure_ev 0), else UsageError naming the exposure; each says how many stops to drop."""
    ev = _stops(exposure_ev)
    brightest = float(np.max(env)) if np.size(env) else 0.0
    exposed = brightest * 2.0 ** ev
    if not exposed > MAX_RADIANCE:
        return
    above = f"above {MAX_RADIANCE:.3g}, the most the renderer integrates without overflowing float32"
    stops = math.ceil(math.log2(exposed / MAX_RADIANCE))  # down to MAX_RADIANCE or below
    scale = f"scale the map's values down by 2^{stops} or more"
    if ev == 0:
        option = f", e.g. relight --exposure -{stops}" if stops <= _MAX_STOPS else ""
        raise InputError(f"the environment map's brightest texel is {brightest:.3g}, {above}",
                         path=path, fix=scale + option)
    where = "the environment map" if path is None else str(path)
    raise UsageError(f"--exposure {ev:g} takes the brightest texel of {where} from {brightest:.3g} to "
                     f"{exposed:.3g}, {above}",
                     fix=f"use --exposure {ev - stops:g} or less" if ev - stops >= -_MAX_STOPS else scale)


# --- resampling ---------------------------------------------------------------------------------

def _cell_edges_u(width):
    """Column edges in u, (width + 1,) float64 from 0 to 1."""
    return np.arange(width + 1, dtype=np.float64) / width


def _cell_edges_t(height):
    """Row edges in t = (1 - cos theta) / 2, (height + 1,) float64 from 0 to 1.

    Solid angle is uniform in (u, t): d omega = 4 pi du dt, so area averages in (u, t) are
    radiance averages weighted by solid angle.
    """
    return 0.5 * (1.0 - np.cos(np.pi * np.arange(height + 1, dtype=np.float64) / height))


def _area_matrix(edges_out, edges_in):
    """Sparse (n_out, n_in) matrix of overlap(out cell, in cell) / length(out cell).

    Both edge arrays increase from the same start to the same end. Applied to a piecewise-
    constant function it gives the exact average of that function over each output cell.
    """
    merged = np.union1d(edges_in, edges_out)
    lengths = np.diff(merged)
    middles = 0.5 * (merged[:-1] + merged[1:])
    n_in, n_out = len(edges_in) - 1, len(edges_out) - 1
    rows = np.clip(np.searchsorted(edges_out, middles, side="right") - 1, 0, n_out - 1)
    cols = np.clip(np.searchsorted(edges_in, middles, side="right") - 1, 0, n_in - 1)
    weights = lengths / np.diff(edges_out)[rows]
    return scipy.sparse.csr_matrix((weights, (rows, cols)), shape=(n_out, n_in))


def resample_envmap(env, height):
    """Area-resample a map to (height, 2 * height), keeping its energy exactly.

    env: (H, 2H, 3) float linear radiance. Each output texel is the solid-angle-weighted mean
    of the input texels it overlaps (the map is constant per texel), so the integral of
    radiance x solid angle is unchanged, down (e.g. to 16x32) or up (blocks, no new detail).
    Returns (height, 2 * height, 3) float32.
    """
    if int(height) != height or height < 1:
        raise UsageError(f"environment map height must be a whole number >= 1, got {height}",
                         fix="give a height such as 16, 64 or 256")
    env = np.asarray(env, dtype=np.float64)
    in_height, in_width = env.shape[:2]
    height, width = int(height), 2 * int(height)
    rows = _area_matrix(_cell_edges_t(height), _cell_edges_t(in_height))
    cols = _area_matrix(_cell_edges_u(width), _cell_edges_u(in_width))
    # rows first: (height, W * 3); then columns on the transposed (W, height * 3)
    by_rows = (rows @ env.reshape(in_height, in_width * 3)).reshape(height, in_width, 3)
    by_cols = cols @ by_rows.transpose(1, 0, 2).reshape(in_width, height * 3)
    return by_cols.reshape(width, height, 3).transpose(1, 0, 2).astype(np.float32)


_BINOMIAL = {-2: 1.0 / 16.0, -1: 4.0 / 16.0, 1: 4.0 / 16.0, 2: 1.0 / 16.0}  # centre: 6/16


def _blur_u(env):
    """Periodic 5-tap binomial blur along u; keeps each row's sum. (H, W, 3) -> same."""
    return 0.375 * env + sum(k * np.roll(env, offset, axis=1) for offset, k in _BINOMIAL.items())


def _blur_v(env):
    """5-tap binomial blur along v that keeps both constants and energy exactly.

    Rows have different solid angles, so a plain blur of radiance would carry energy from
    the large equator rows into the tiny pole rows and back (a point light in the top row
    gains 3x). Instead the move from row i to row j has weight g_k min(W_i, W_j) / W_i
    (Metropolis, W = row solid angle, g the binomial weight of offset k = j - i) and the rest
    stays put: rows of weights sum to 1 (constants kept) and W_i K_ij is symmetric (energy
    kept). Across a pole the neighbour rows are those on the other side, half a turn away
    (row -1 is row 0 rolled by W/2). Needs H >= 2. (H, W, 3) float64 -> same.
    """
    height, width = env.shape[:2]
    row_weights = texel_solid_angles(height, width)[:, 0]
    rows = np.arange(height)
    blurred = env.copy()
    for offset, g in _BINOMIAL.items():
        target = rows + offset
        over_pole = (target < 0) | (target >= height)
        target = np.where(target < 0, -1 - target, target)
        target = np.where(target >= height, 2 * height - 1 - target, target)
        neighbours = env[target]
        neighbours[over_pole] = np.roll(neighbours[over_pole], width // 2, axis=1)
        move = g * np.minimum(row_weights, row_weights[target]) / row_weights
        blurred += move[:, None, None] * (neighbours - env)
    return blurred


def gaussian_pyramid_downsample(env, height):
    """Downsample by a Gaussian pyramid to (height, 2 * height), as the paper prepares its
    ground-truth light (16x32) for the lighting loss.

    env: (H, 2H, 3) float linear radiance, H >= height. Each level blurs with the 5-tap
    binomial kernel (periodic in u; across the poles in v, weighted by solid angle, see
    `_blur_v`) and then halves the height by `resample_envmap`; a last area step reaches
    `height` when H / height is not a power of 2. Constant maps stay constant and the energy
    (radiance x solid angle) is kept exactly. Returns (height, 2 * height, 3) float32.
    """
    env = np.asarray(env, dtype=np.float64)
    if int(height) != height or not 1 <= height <= env.shape[0]:
        raise UsageError(f"pyramid target height must be a whole number in 1..{env.shape[0]}, "
                         f"got {height}", fix="use resample_envmap to upsample")
    while env.shape[0] >= 2 * height:
        env = resample_envmap(_blur_v(_blur_u(env)), env.shape[0] // 2).astype(np.float64)
    if env.shape[0] != height:
        env = resample_envmap(env, height)
    return env.astype(np.float32)


# --- looking up and viewing -----------------------------------------------------------------

def lookup_bilinear(env, u, v):
    """Bilinear radiance at texel coordinates (u, v), periodic in u, clamped in v.

    env: (H, W, 3) linear radiance. u, v: arrays of the same shape (...). Returns (..., 3)
    float32. Texel centres (u, v) = ((j + 0.5) / W, (i + 0.5) / H) return the texel itself.
    """
    env = np.asarray(env, dtype=np.float32)
    height, width = env.shape[:2]
    x = np.asarray(u, dtype=np.float64) * width - 0.5
    y = np.clip(np.asarray(v, dtype=np.float64) * height - 0.5, 0.0, height - 1.0)
    col0 = np.floor(x)
    fx = (x - col0)[..., None]
    col0 = col0.astype(np.int64) % width
    col1 = (col0 + 1) % width
    row0 = np.minimum(np.floor(y).astype(np.int64), max(height - 2, 0))
    row1 = np.minimum(row0 + 1, height - 1)
    fy = (y - row0)[..., None]
    top = (1 - fx) * env[row0, col0] + fx * env[row0, col1]
    bottom = (1 - fx) * env[row1, col0] + fx * env[row1, col1]
    return ((1 - fy) * top + fy * bottom).astype(np.float32)


def view_directions(*, width, height, fov_deg=60.0, yaw_deg=0.0):
    """Unit ray directions of a pinhole camera at the origin, (height, width, 3) float64.

    At yaw 0 it looks toward -Z with +Y up and +X to the right; `fov_deg` is the horizontal
    field of view, pixels are square. `yaw_deg` turns the camera about +Y counter-clockwise
    seen from above (the same sense as `rotate_envmap`): yaw 90 looks toward -X.
    """
    fov_deg = _finite_number(fov_deg, "field of view", "give a field of view in degrees")
    if not 0.0 < fov_deg < 180.0 or width < 1 or height < 1:
        raise UsageError(f"need 0 < field of view < 180 degrees and a size >= 1x1, got "
                         f"{fov_deg} degrees and {width}x{height}", fix="e.g. --fov 60")
    half_width = math.tan(math.radians(fov_deg) / 2.0)
    # pixel centres on the image plane z = -1 (row 0 is the top)
    x = (2.0 * (np.arange(width) + 0.5) / width - 1.0) * half_width
    y = (1.0 - 2.0 * (np.arange(height) + 0.5) / height) * half_width * height / width
    xx, yy = np.meshgrid(x, y)
    # rotate about +Y: R_y(a) takes +X to (cos a, 0, -sin a)
    a = math.radians(_finite_number(yaw_deg, "yaw", "give the yaw in degrees"))
    directions = np.stack([math.cos(a) * xx - math.sin(a), yy,
                           -math.sin(a) * xx - math.cos(a)], axis=-1)
    return directions / np.linalg.norm(directions, axis=-1, keepdims=True)


def environment_view(env, *, width, height, fov_deg=60.0, yaw_deg=0.0):
    """What a pinhole camera at the origin sees of the environment (the `--background env`
    image): see `view_directions` for the camera. env: (H, 2H, 3) linear radiance.
    Returns (height, width, 3) float32 linear radiance, bilinear, periodic in u.
    """
    u, v = direction_to_uv(view_directions(width=width, height=height, fov_deg=fov_deg,
                                           yaw_deg=yaw_deg))
    return lookup_bilinear(env, u, v)


# --- facts for planning -------------------------------------------------------------------------

def envmap_energy(env):
    """Integral of radiance over the sphere, sum(L * solid angle), (3,) float64 per channel."""
    env = np.asarray(env, dtype=np.float64)
    weights = texel_solid_angles(*env.shape[:2])
    return np.einsum("hwc,hw->c", env, weights)


def sun_share(env, top_fraction=0.001):
    """Share of the map's luminous energy held by its most energetic texels.

    env: (H, W, 3) linear radiance. A texel's energy is its luminance (Rec. 709 weights) times
    its solid angle; the max(1, ceil(top_fraction * H * W)) texels of most energy are summed.
    This is the data index's "energy in the brightest 0.1% of pixels" (hdri/index.csv).
    Returns a float in [0, 1]: near 1 for a hard sun, about top_fraction for a uniform sky, 0
    for an all-black map.
    """
    env = np.asarray(env, dtype=np.float64)
    energy = (env @ LUMINANCE).ravel() * texel_solid_angles(*env.shape[:2]).ravel()
    total = energy.sum()
    if total <= 0:
        return 0.0
    count = max(1, math.ceil(top_fraction * energy.size))
    largest = np.argpartition(-energy, count - 1)[:count]
    return float(energy[largest].sum() / total)


def is_constant(env, rtol=1e-6):
    """True when every channel's texels agree to within rtol of that channel's largest value
    (an all-black map is constant). env: (H, W, 3) linear radiance."""
    env = np.asarray(env, dtype=np.float64).reshape(-1, 3)
    spread = env.max(axis=0) - env.min(axis=0)
    return bool(np.all(spread <= rtol * np.abs(env).max(axis=0)))
