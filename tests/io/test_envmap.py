"""Environment maps: the direction convention, validation and repair, loading, rotation,
resampling, the background view and the planning facts. Analytic where possible: closed-form
directions, exact energy sums, independent re-implementations of the simple cases."""

from __future__ import annotations

import csv
import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from exr_testing import write_windowed_exr
from relightcli.errors import InputError, RelightWarning, UsageError
from relightcli.io import envmap as em

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
HDRI = DATA / "hdri"
needs_hdri = pytest.mark.skipif(not (HDRI / "index.csv").is_file(),
                                reason="shared HDRI data not found")


def random_env(height, seed=0):
    """(H, 2H, 3) float32 positive random radiance."""
    rng = np.random.default_rng(seed)
    return rng.uniform(0.1, 2.0, size=(height, 2 * height, 3)).astype(np.float32)


def energy(env):
    return np.einsum("hwc,hw->c", env.astype(np.float64), em.texel_solid_angles(*env.shape[:2]))


def write_float_image(path, pixels):
    """Write (H, W, 3) float32 with OpenImageIO directly (independent of io/images.py)."""
    oiio = pytest.importorskip("OpenImageIO")
    height, width, channels = pixels.shape
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), oiio.ImageSpec(width, height, channels, oiio.FLOAT))
    out.write_image(np.ascontiguousarray(pixels, dtype=np.float32))
    out.close()
    return path


def rotation_y(degrees):
    """R_y: counter-clockwise seen from above, +X toward -Z."""
    a = math.radians(degrees)
    return np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0],
                     [-math.sin(a), 0.0, math.cos(a)]])


# --- convention -------------------------------------------------------------------------------

@pytest.mark.parametrize("u, v, expected", [
    (0.5, 0.5, (0.0, 0.0, -1.0)),   # centre column: what the camera looks at
    (0.75, 0.5, (1.0, 0.0, 0.0)),   # +X, right in the image
    (0.25, 0.5, (-1.0, 0.0, 0.0)),
    (0.0, 0.5, (0.0, 0.0, 1.0)),    # the seam: behind the camera
    (0.3, 0.0, (0.0, 1.0, 0.0)),    # top row: straight up, whatever u
    (0.3, 1.0, (0.0, -1.0, 0.0)),
])
def test_uv_to_direction_landmarks(u, v, expected):
    np.testing.assert_allclose(em.uv_to_direction(u, v), expected, atol=1e-15)


@pytest.mark.parametrize("u, v", [
    (0.5, 0.5), (0.0, 0.5), (1e-12, 0.3), (1.0 - 1e-12, 0.7), (0.123, 1e-6), (0.877, 1 - 1e-6),
])
def test_uv_direction_uv_round_trip(u, v):
    u_back, v_back = em.direction_to_uv(em.uv_to_direction(u, v))
    assert abs(v_back - v) < 1e-9
    # u is periodic: compare on the circle so the seam (0 == 1) counts as equal
    assert abs((u_back - u + 0.5) % 1.0 - 0.5) < 1e-9
    assert 0.0 <= u_back < 1.0


@pytest.mark.parametrize("v", [0.0, 1.0])
def test_direction_round_trip_at_poles(v):
    # u is undefined at a pole; the direction must still come back
    d = em.uv_to_direction(0.37, v)
    np.testing.assert_allclose(em.uv_to_direction(*em.direction_to_uv(d)), d, atol=1e-12)


def test_float32_arctan2_is_numpys_within_float32_round_off():
    rng = np.random.default_rng(4)
    y = (rng.standard_normal(200_000) * np.exp(rng.uniform(-30, 30, 200_000))).astype(np.float32)
    x = (rng.standard_normal(200_000) * np.exp(rng.uniform(-30, 30, 200_000))).astype(np.float32)
    edges = np.array([0.0, -0.0, 1.0, -1.0, 1e-38, -1e-38], np.float32)
    y = np.concatenate([y, np.repeat(edges, edges.size)])
    x = np.concatenate([x, np.tile(edges, edges.size)])
    got = em.arctan2_float32(y, x)
    exact = np.arctan2(y.astype(np.float64), x.astype(np.float64))
    assert got.dtype == np.float32
    assert np.abs(got - exact).max() < 4e-7
    np.testing.assert_array_equal(np.signbit(got), np.signbit(np.arctan2(y, x)))  # -0, -pi
    assert np.isnan(em.arctan2_float32(np.float32([np.nan, 1.0]), np.float32([1.0, np.nan]))).all()


def test_float32_directions_find_the_float64_texel():
    d = em.texel_directions(512, 1024).reshape(-1, 3)  # texel centres: far from every edge
    u64, v64 = em.direction_to_uv(d)
    u32, v32 = em.direction_to_uv(d.astype(np.float32))
    assert u32.dtype == np.float32
    np.testing.assert_array_equal((v32 * 512).astype(int), (v64 * 512).astype(int))
    np.testing.assert_array_equal((u32 * 1024).astype(int), (u64 * 1024).astype(int))


def test_texel_directions_are_unit_and_uv_inverts():
    d = em.texel_directions(8, 16)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-14)
    u, v = em.texel_centres_uv(8, 16)
    u_back, v_back = em.direction_to_uv(d)
    np.testing.assert_allclose(u_back, u, atol=1e-12)
    np.testing.assert_allclose(v_back, v, atol=1e-12)


@pytest.mark.parametrize("height, width", [(1, 2), (2, 4), (512, 1024)])
def test_solid_angles_sum_to_4pi(height, width):
    assert em.texel_solid_angles(height, width).sum() == pytest.approx(4 * np.pi, rel=1e-12)


# --- validation and repair --------------------------------------------------------------------

@pytest.mark.parametrize("shape", [(4, 12, 3), (4, 4, 3), (8, 16), (8, 16, 4), (0, 0, 3)])
def test_validate_rejects_bad_shapes(shape):
    with pytest.raises(InputError, match="width = 2 x height"):
        em.validate_envmap(np.ones(shape, np.float32), path="sky.hdr")


def test_validate_names_file_and_size():
    with pytest.raises(InputError) as caught:
        em.validate_envmap(np.ones((4, 12, 3), np.float32), path="wide_sky.hdr")
    assert "wide_sky.hdr" in str(caught.value) and "12x4" in str(caught.value)


def test_validate_accepts_2x1_and_black_without_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env = em.validate_envmap(np.zeros((1, 2, 3), np.float64))
    assert env.dtype == np.float32 and env.shape == (1, 2, 3) and not env.any()


def test_validate_repairs_and_counts_each_kind():
    env = np.full((4, 8, 3), 0.5, np.float32)
    env[0, 0] = [np.nan, np.nan, 1.0]           # 2 NaN
    env[1, 1, 0] = np.inf                       # 1 +Inf
    env[2, 2] = [-np.inf, -np.inf, -np.inf]     # 3 -Inf
    env[3, 3, :2] = -0.25                       # 2 negative
    env[3, 4, 1] = 7.0                          # largest finite value
    with pytest.warns(RelightWarning) as record:
        fixed = em.validate_envmap(env, path="broken.exr")
    assert len(record) == 1
    message = str(record[0].message)
    for text in ("broken.exr", "2 NaN", "1 +Inf", "3 -Inf", "2 negative"):
        assert text in message
    assert np.isfinite(fixed).all() and (fixed >= 0).all()
    assert fixed[0, 0].tolist() == [0.0, 0.0, 1.0]
    assert fixed[1, 1, 0] == 7.0
    assert not fixed[2, 2].any() and not fixed[3, 3, :2].any()
    assert fixed[3, 3, 2] == 0.5


def test_validate_all_infinite_becomes_black():
    env = np.full((2, 4, 3), np.inf, np.float32)
    with pytest.warns(RelightWarning, match="24 \\+Inf"):
        fixed = em.validate_envmap(env)
    assert not fixed.any()


# --- loading (through io/images.py) -------------------------------------------------------------

@needs_hdri
def test_load_real_hdr():
    env = em.load_envmap(HDRI / "aerodynamics_workshop_1k.hdr")
    assert env.shape == (512, 1024, 3) and env.dtype == np.float32
    assert np.isfinite(env).all() and (env >= 0).all() and env.max() > 1.0


def test_load_3to1_file_is_refused(tmp_path):
    path = write_float_image(tmp_path / "three_to_one.exr", np.ones((4, 12, 3), np.float32))
    with pytest.raises(InputError) as caught:
        em.load_envmap(path)
    text = str(caught.value)
    assert "three_to_one.exr" in text and "12x4" in text and "width = 2 x height" in text


def test_load_2x1_file(tmp_path):
    pixels = np.array([[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]], np.float32)
    env = em.load_envmap(write_float_image(tmp_path / "tiny.exr", pixels))
    np.testing.assert_array_equal(env, pixels)


def test_load_repairs_nonfinite_file(tmp_path):
    pixels = np.ones((2, 4, 3), np.float32)
    pixels[0, 0, 0], pixels[1, 1, 1], pixels[1, 2, 2] = np.nan, np.inf, -3.0
    path = write_float_image(tmp_path / "holes.exr", pixels)
    with pytest.warns(RelightWarning, match="1 NaN, 1 \\+Inf, 0 -Inf, 1 negative"):
        env = em.load_envmap(path)
    assert env[0, 0, 0] == 0.0 and env[1, 1, 1] == 1.0 and env[1, 2, 2] == 0.0


def test_load_8bit_warns_srgb(tmp_path):
    oiio = pytest.importorskip("OpenImageIO")
    path = str(tmp_path / "clipped_sky.png")
    out = oiio.ImageOutput.create(path)
    out.open(path, oiio.ImageSpec(8, 4, 3, oiio.UINT8))
    out.write_image(np.full((4, 8, 3), 255, np.uint8))
    out.close()
    with pytest.warns(RelightWarning, match="sRGB"):
        env = em.load_envmap(path)
    np.testing.assert_allclose(env, 1.0, atol=1e-6)


def test_load_applies_rotation_then_exposure(tmp_path):
    pixels = random_env(4)
    env = em.load_envmap(write_float_image(tmp_path / "sky.exr", pixels),
                         rotate_deg=90.0, exposure_ev=-2.0)
    np.testing.assert_allclose(env, np.roll(pixels, -2, axis=1) / 4.0, rtol=1e-6)


# --- rotation and exposure ----------------------------------------------------------------------

def test_rotate_plus_90_brings_light_from_plus_x_to_minus_z():
    env = np.zeros((8, 16, 3), np.float32)
    u, v = em.direction_to_uv([1.0, 0.0, 0.0])          # texel whose corner is +X
    env[:, int(u * 16) - 1:int(u * 16) + 1] = 1.0       # the two columns around +X
    rotated = em.rotate_envmap(env, 90.0)
    lit = em.texel_directions(8, 16)[rotated[..., 0] > 0]
    mean_direction = lit.mean(axis=0)
    np.testing.assert_allclose(mean_direction / np.linalg.norm(mean_direction),
                               [0.0, 0.0, -1.0], atol=1e-12)


@pytest.mark.parametrize("degrees", [90.0, -45.0, 180.0, 22.5])
def test_rotate_whole_texels_moves_every_direction(degrees):
    # new(R d) == old(d) for every texel centre d, with R the turn about +Y
    env = random_env(8)
    rotated = em.rotate_envmap(env, degrees)
    d = em.texel_directions(8, 16)
    u, v = em.direction_to_uv(d @ rotation_y(degrees).T)
    cols = np.floor(u * 16).astype(int) % 16
    rows = np.floor(v * 8).astype(int)
    np.testing.assert_array_equal(rotated[rows, cols], env)


@pytest.mark.parametrize("degrees", [360.0, -360.0, 720.0])
def test_rotate_full_turns_is_identity(degrees):
    env = random_env(8)
    np.testing.assert_array_equal(em.rotate_envmap(env, degrees), env)


def test_rotate_half_texel_is_mean_of_neighbours():
    env = random_env(8)
    half_texel = 0.5 * 360.0 / 16
    expected = 0.5 * (env + np.roll(env, -1, axis=1))
    np.testing.assert_allclose(em.rotate_envmap(env, half_texel), expected, rtol=1e-6)


def test_rotate_fractional_keeps_row_energy():
    env = random_env(8)
    rotated = em.rotate_envmap(env, 17.3)
    np.testing.assert_allclose(rotated.sum(axis=1), env.sum(axis=1), rtol=1e-5)


@pytest.mark.parametrize("ev", [-3.0, 0.0, 1.5])
def test_expose_is_power_of_two(ev):
    env = random_env(4)
    np.testing.assert_allclose(em.expose(env, ev), env * 2.0 ** ev, rtol=1e-6)


@pytest.mark.parametrize("ev", [float("nan"), float("inf"), 200.0])
def test_expose_refuses_unusable_stops(ev):
    with pytest.raises(UsageError):
        em.expose(random_env(2), ev)


# --- resampling ---------------------------------------------------------------------------------

@pytest.mark.parametrize("source, target", [(64, 16), (64, 48), (48, 20), (16, 64), (1, 8), (8, 1)])
def test_resample_keeps_energy(source, target):
    env = random_env(source)
    out = em.resample_envmap(env, target)
    assert out.shape == (target, 2 * target, 3) and out.dtype == np.float32
    np.testing.assert_allclose(energy(out), energy(env), rtol=1e-5)


def test_resample_halving_is_solid_angle_weighted_block_mean():
    env = random_env(16).astype(np.float64)
    weights = em.texel_solid_angles(16, 32)[..., None]
    blocks = (env * weights).reshape(8, 2, 16, 2, 3).sum(axis=(1, 3))
    expected = blocks / weights.reshape(8, 2, 16, 2, 1).sum(axis=(1, 3))
    np.testing.assert_allclose(em.resample_envmap(env, 8), expected, rtol=1e-5)


@pytest.mark.parametrize("target", [1, 5, 16, 40])
def test_resample_keeps_constant(target):
    out = em.resample_envmap(np.full((16, 32, 3), 0.7, np.float32), target)
    np.testing.assert_allclose(out, 0.7, rtol=1e-6)


def test_resample_same_size_is_identity():
    env = random_env(16)
    np.testing.assert_allclose(em.resample_envmap(env, 16), env, rtol=1e-6)


def test_pyramid_keeps_constant_and_shape():
    out = em.gaussian_pyramid_downsample(np.full((64, 128, 3), 3.0, np.float32), 16)
    assert out.shape == (16, 32, 3)
    np.testing.assert_allclose(out, 3.0, rtol=1e-6)


@pytest.mark.parametrize("row", [0, 1, 20, 63])
def test_pyramid_spreads_a_point_light_and_keeps_its_energy(row):
    # rows 0 and 63 touch the poles, where a plain radiance blur would triple the energy
    env = np.zeros((64, 128, 3), np.float32)
    env[row, 40] = 1000.0
    pyramid = em.gaussian_pyramid_downsample(env, 16)
    assert np.count_nonzero(pyramid[..., 0]) > np.count_nonzero(em.resample_envmap(env, 16)[..., 0])
    np.testing.assert_allclose(energy(pyramid), energy(env), rtol=1e-5)


@pytest.mark.parametrize("source, target", [(64, 16), (48, 5), (2, 1)])
def test_pyramid_keeps_energy_of_random_maps(source, target):
    env = random_env(source)
    np.testing.assert_allclose(energy(em.gaussian_pyramid_downsample(env, target)), energy(env),
                               rtol=1e-5)


# --- looking up and the background view ---------------------------------------------------------

def test_lookup_at_texel_centres_returns_texels():
    env = random_env(4)
    u, v = em.texel_centres_uv(4, 8)
    np.testing.assert_array_equal(em.lookup_bilinear(env, u, v), env)


def test_lookup_is_periodic_across_the_seam():
    env = random_env(4)
    v = (1 + 0.5) / 4
    np.testing.assert_allclose(em.lookup_bilinear(env, 0.0, v), 0.5 * (env[1, 0] + env[1, -1]),
                               rtol=1e-6)


def test_view_centre_pixel_looks_at_uv_centre():
    d = em.view_directions(width=33, height=21, fov_deg=70.0)
    np.testing.assert_allclose(d[10, 16], [0.0, 0.0, -1.0], atol=1e-15)
    u, v = em.direction_to_uv(d[10, 16])
    assert (u, v) == pytest.approx((0.5, 0.5))


def test_view_right_edge_is_toward_plus_x_at_half_fov():
    width, fov = 64, 90.0
    d = em.view_directions(width=width, height=32, fov_deg=fov)
    edge = d[16, -1]
    # the last pixel centre sits (1 - 1/W) of the way to the edge of the image plane
    expected = math.atan((1.0 - 1.0 / width) * math.tan(math.radians(fov / 2)))
    assert edge[0] > 0
    assert math.atan2(edge[0], -edge[2]) == pytest.approx(expected, rel=1e-12)


def test_view_yaw_plus_90_looks_toward_minus_x():
    d = em.view_directions(width=3, height=3, fov_deg=60.0, yaw_deg=90.0)
    np.testing.assert_allclose(d[1, 1], [-1.0, 0.0, 0.0], atol=1e-15)


def test_environment_view_sees_plus_x_on_the_right():
    env = np.zeros((32, 64, 3), np.float32)
    env[:, 32:] = 1.0                        # u in [0.5, 1): the +X half of the sphere
    view = em.environment_view(env, width=40, height=30, fov_deg=90.0)
    assert view.shape == (30, 40, 3) and view.dtype == np.float32
    assert (view[:, 21:] == 1.0).all() and (view[:, :19] == 0.0).all()


def test_environment_view_centre_is_mean_of_central_texels():
    env = random_env(8)
    view = em.environment_view(env, width=5, height=5, fov_deg=40.0)
    expected = env[3:5, 7:9].mean(axis=(0, 1))
    np.testing.assert_allclose(view[2, 2], expected, rtol=1e-6)


@pytest.mark.parametrize("degrees", [90.0, -22.5])
def test_view_of_rotated_map_equals_yawed_camera(degrees):
    env = random_env(16)
    rotated_view = em.environment_view(em.rotate_envmap(env, degrees), width=24, height=16)
    yawed_view = em.environment_view(env, width=24, height=16, yaw_deg=-degrees)
    np.testing.assert_allclose(rotated_view, yawed_view, rtol=1e-5, atol=1e-6)


# --- planning facts -------------------------------------------------------------------------

def test_sun_share_of_a_single_texel_is_one():
    env = np.zeros((16, 32, 3), np.float32)
    env[3, 7] = [5.0, 4.0, 3.0]
    assert em.sun_share(env) == pytest.approx(1.0)


def test_sun_share_of_a_sun_over_a_sky():
    env = np.full((16, 32, 3), 1.0, np.float32)
    env[5, 9] = 1e5
    weights = em.texel_solid_angles(16, 32)
    sun = 1e5 * weights[5, 9]
    expected = sun / (sun + weights.sum() - weights[5, 9])
    assert em.sun_share(env) == pytest.approx(expected, rel=1e-9)


def test_sun_share_of_black_map_is_zero():
    assert em.sun_share(np.zeros((2, 4, 3), np.float32)) == 0.0


def read_index():
    with open(HDRI / "index.csv", newline="") as handle:
        return list(csv.DictReader(handle))


@needs_hdri
@pytest.mark.parametrize("name", ["aerodynamics_workshop_1k.hdr", "drachenfels_cellar_1k.hdr",
                                  "noon_grass_1k.hdr", "pmndrs_lab.hdr"])
def test_sun_share_matches_data_index(name):
    # independent reference: the data set's own "energy in the brightest 0.1% of pixels",
    # given to 3 digits (the largest gap over all 40 maps is 7.7e-4)
    entry = next(row for row in read_index() if row["file"] == name)
    env = em.load_envmap(HDRI / name)
    assert em.sun_share(env, 0.001) == pytest.approx(float(entry["energy_frac_top0.1pct_pixels"]),
                                                     abs=1e-3)


@needs_hdri
@pytest.mark.parametrize("name", ["aerodynamics_workshop_1k.hdr", "noon_grass_1k.hdr"])
def test_energy_matches_data_index_mean_luminance(name):
    # lum_mean_solidangle = luminance integrated over the sphere / 4 pi, given to 4 digits
    entry = next(row for row in read_index() if row["file"] == name)
    luminance = em.envmap_energy(em.load_envmap(HDRI / name)) @ [0.2126, 0.7152, 0.0722]
    assert luminance / (4 * np.pi) == pytest.approx(float(entry["lum_mean_solidangle"]), rel=2e-4)


def test_is_constant_true_for_constant_and_black():
    assert em.is_constant(np.full((4, 8, 3), [0.2, 0.3, 0.4], np.float32))
    assert em.is_constant(np.zeros((1, 2, 3), np.float32))


def test_is_constant_false_for_small_bump():
    env = np.full((4, 8, 3), 0.5, np.float32)
    env[2, 3, 1] = 0.5005
    assert not em.is_constant(env, rtol=1e-4)


# --- hostile maps: too bright to integrate, huge turns, data windows (hostile sweep) -----------

def test_map_too_bright_to_integrate_is_refused_naming_the_file(tmp_path):
    # a uniform 3e38 map: its irradiance (pi L) and the estimates' squares overflow float32
    path = write_float_image(tmp_path / "blinding.exr", np.full((4, 8, 3), 3e38, np.float32))
    with pytest.raises(InputError) as caught:
        em.load_envmap(path)
    message = str(caught.value)
    assert "blinding.exr" in message and "3e+38" in message and "2^72" in message
    assert "--exposure" not in message  # 72 stops is beyond what --exposure may take


def test_map_at_the_radiance_ceiling_is_accepted_and_just_above_refused():
    at = np.full((2, 4, 3), em.MAX_RADIANCE, np.float32)
    assert em.envmap_from_array(at).max() == em.MAX_RADIANCE
    above = np.full((2, 4, 3), np.nextafter(np.float32(em.MAX_RADIANCE), np.float32(np.inf)))
    with pytest.raises(InputError, match=r"--exposure -1\b"):
        em.envmap_from_array(above)


def test_exposure_past_the_ceiling_is_a_usage_error_saying_how_far_to_go():
    env = np.full((2, 4, 3), 1e3, np.float32)
    with pytest.raises(UsageError, match=r"--exposure 64 takes .* to 1\.84e\+22.*use --exposure 46 or less"):
        em.envmap_from_array(env, exposure_ev=64.0)
    assert em.envmap_from_array(env, exposure_ev=46.0).max() == pytest.approx(1e3 * 2.0 ** 46)
    with pytest.raises(UsageError):
        em.expose(env, 64.0)  # the function on its own, too: no Inf texels


def test_exposure_can_bring_a_too_bright_map_under_the_ceiling():
    env = np.full((2, 4, 3), 1e18, np.float32)
    np.testing.assert_array_equal(em.envmap_from_array(env, exposure_ev=-4.0), env / np.float32(16.0))


@pytest.mark.parametrize("degrees", [1e308, -1e308, 3.6e6 + 90.0, 2.0 ** 60 + 45.0])
def test_rotation_by_any_finite_angle_is_its_turn_within_a_revolution(degrees):
    env = random_env(8)
    np.testing.assert_array_equal(em.rotate_envmap(env, degrees), em.rotate_envmap(env, math.fmod(degrees, 360.0)))


def test_rotation_by_ten_thousand_turns_and_a_quarter_is_a_quarter_turn():
    env = random_env(8)
    np.testing.assert_array_equal(em.rotate_envmap(env, 360.0 * 10_000 + 90.0), em.rotate_envmap(env, 90.0))


@pytest.mark.parametrize("degrees", [float("nan"), float("inf"), float("-inf")])
def test_rotation_refuses_non_finite(degrees):
    with pytest.raises(UsageError, match="rotation must be a finite number"):
        em.rotate_envmap(random_env(2), degrees)


def test_map_is_its_display_window_cut_from_the_data_window(tmp_path):
    # a 16 x 8 map storing 20 x 5 texels from (-2, 0): the sky rows, two columns spilling over
    # each side; the ground rows hold nothing (black)
    stored = random_env(10)[:5, :20]
    env = em.load_envmap(write_windowed_exr(tmp_path / "sky_only.exr", stored, (-2, 0), (16, 8)))
    expected = np.zeros((8, 16, 3), np.float32)
    expected[:5] = stored[:, 2:18]
    np.testing.assert_array_equal(env, expected)


def test_map_data_window_over_the_limit_is_refused_from_the_header(tmp_path):
    stored = np.ones((40, 80, 3), np.float32)
    path = write_windowed_exr(tmp_path / "overscan.exr", stored, (-24, -12), (32, 16))
    with pytest.raises(InputError) as caught:
        em.load_envmap(path, max_pixels=3000)  # the 32 x 16 map fits, its 80 x 40 stored texels not
    message = str(caught.value)
    assert "overscan.exr" in message and "data window" in message and "80x40 = 3200" in message
    assert "--crop 32x16+0+0" in message and "--max-pixels" not in message  # the map limit is fixed
