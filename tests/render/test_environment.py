"""The environment light: chi-square of its sampler, eval/pdf consistency, inversion, extremes."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from render_testing import chi_square_pvalue, load_hdr
from relightcli.errors import RelightWarning
from relightcli.io.envmap import direction_to_uv, texel_solid_angles
from relightcli.render.environment import EnvironmentLight, TabulatedSampling


def _one_hot(height=16, row=5, col=9, value=100.0):
    env = np.zeros((height, 2 * height, 3), np.float32)
    env[row, col] = value
    return env


def _sun_and_sky(height=64):
    env = np.full((height, 2 * height, 3), 0.5, np.float32)
    env[10, 40] = 0.5e6
    return env


def _gradient(height=16):
    v = (np.arange(height)[:, None, None] + 0.5) / height
    return np.broadcast_to(1.0 + 3.0 * (1 - v), (height, 2 * height, 3)).astype(np.float32)


def _real(height=None):
    env = load_hdr("noon_grass_1k.hdr")
    return env[::4, ::4].copy()  # 128 x 256: keeps the test fast, still a hard sun


MAPS = {"one_hot": _one_hot, "constant": lambda: np.full((8, 16, 3), 2.0, np.float32),
        "gradient": _gradient, "sun_and_sky": _sun_and_sky, "real_hdr": _real}


def _expected_texel_probabilities(env):
    energy = env.mean(axis=2).astype(np.float64) * texel_solid_angles(*env.shape[:2])
    return energy / energy.sum()




@pytest.mark.parametrize("name", sorted(MAPS))
def test_environment_sampler_chi_square(name):
    env = MAPS[name]()
    light = EnvironmentLight(env)
    directions, _ = light.sample(np.random.default_rng(7).random((200_000, 2)))
    u, v = direction_to_uv(directions)
    height, width = env.shape[:2]
    texel = np.clip((v * height).astype(int), 0, height - 1) * width + np.clip((u * width).astype(int), 0, width - 1)
    counts = np.bincount(texel, minlength=height * width).astype(float)
    expected = _expected_texel_probabilities(env).ravel() * directions.shape[0]
    assert chi_square_pvalue(counts, expected) > 1e-3


@pytest.mark.parametrize("name", sorted(MAPS))
def test_sample_weight_equals_eval_over_pdf(name):
    light = EnvironmentLight(MAPS[name]())
    u = np.random.default_rng(3).random((5000, 2))
    directions, pdf, radiance = light.sample_radiance(u)
    radiance_eval, pdf_eval = light.eval_pdf(directions)
    np.testing.assert_allclose(radiance, light.eval(directions))
    np.testing.assert_allclose(radiance_eval, radiance)
    np.testing.assert_allclose(pdf_eval, pdf, rtol=1e-9)
    np.testing.assert_allclose(light.pdf(directions), pdf, rtol=1e-9)
    # The estimator of the total power E[L / pdf] = integral of L over the sphere
    weight = radiance.mean(axis=1) / pdf
    assert np.all(np.isfinite(weight)) and np.all(pdf > 0)


@pytest.mark.parametrize("name", sorted(MAPS))
def test_perfect_importance_sampling_gives_zero_variance_per_texel(name):
    env = MAPS[name]()
    light = EnvironmentLight(env)
    directions, pdf, radiance = light.sample_radiance(np.random.default_rng(5).random((20_000, 2)))
    # mean-RGB L / pdf is the map's total energy up to the sin(theta) change within a texel
    total = light.total_energy
    ratio = radiance.mean(axis=1) / pdf / total
    height = env.shape[0]
    assert np.mean(ratio) == pytest.approx(1.0, rel=2.0 / height)


@pytest.mark.parametrize("name", sorted(MAPS))
def test_environment_inversion_round_trip(name):
    light = EnvironmentLight(MAPS[name]())
    u = np.random.default_rng(11).random((2000, 2))
    directions, _ = light.sample(u)
    np.testing.assert_allclose(light.invert_sample(directions), u, atol=1e-6)


@pytest.mark.parametrize("name", sorted(MAPS))
def test_sampling_over_cells_is_the_cells_energy_uniform_within(name):
    # A light sampled over 4x4-texel cells: each cell as often as its energy says, its
    # texels by their share of its (u, v) area; sample, eval, pdf and inversion agree
    env = MAPS[name]()
    cell = 2 if env.shape[0] < 16 else 4
    light = EnvironmentLight(env, cell)
    assert light.cell == cell and light._lit_radiance is None
    u = np.random.default_rng(13).random((200_000, 2))
    directions, pdf, radiance = light.sample_radiance(u)
    uu, vv = direction_to_uv(directions)
    height, width = env.shape[:2]
    row, col = np.clip((vv * height).astype(int), 0, height - 1), np.clip((uu * width).astype(int), 0, width - 1)
    rows, cols = height // cell, width // cell
    cell_energy = _expected_texel_probabilities(env).reshape(rows, cell, cols, cell).sum(axis=(1, 3))
    expected = np.repeat(np.repeat(cell_energy / cell ** 2, cell, axis=0), cell, axis=1).ravel() * u.shape[0]
    counts = np.bincount(row * width + col, minlength=height * width).astype(float)
    assert chi_square_pvalue(counts, expected) > 1e-3
    np.testing.assert_array_equal(radiance, env[row, col])
    radiance_eval, pdf_eval = light.eval_pdf(directions)
    np.testing.assert_array_equal(radiance_eval, radiance)
    np.testing.assert_allclose(pdf_eval, pdf, rtol=1e-9)
    np.testing.assert_allclose(light.pdf(directions), pdf, rtol=1e-9)
    np.testing.assert_allclose(light.invert_sample(directions[:2000]), u[:2000], atol=1e-6)
    # unbiased: E[L / pdf] is the map's energy (within 5 standard errors)
    weight = radiance.mean(axis=1) / pdf
    assert abs(weight.mean() - light.total_energy) < 5 * weight.std() / np.sqrt(weight.size) + 1e-9 * light.total_energy
    from relightcli.io.envmap import texel_directions

    fine = light.pdf(texel_directions(256, 512))
    assert np.sum(fine * texel_solid_angles(256, 512)) == pytest.approx(1.0, rel=1e-3)


def test_a_sky_is_sampled_over_cells_and_a_sun_texel_by_texel():
    from relightcli.render.environment import SAMPLING_ROWS, sampling_cell

    assert sampling_cell(4 * SAMPLING_ROWS, 8 * SAMPLING_ROWS) == 4
    assert sampling_cell(SAMPLING_ROWS, 2 * SAMPLING_ROWS) == 1
    assert sampling_cell(3 * SAMPLING_ROWS, 6 * SAMPLING_ROWS) == 2  # halving again leaves too few rows
    assert sampling_cell(1000, 2000) == 4  # 8 does not divide 1000
    with pytest.raises(ValueError, match="cell"):
        EnvironmentLight(_gradient(), 3)
    sun, sky = EnvironmentLight(_sun_and_sky(4 * SAMPLING_ROWS)).sun_and_sky()
    assert sun.cell == 1 and sky.cell == 4
    # A map without a sun: its MIS term samples a coarse copy that shares the irradiance table
    from relightcli.render.integrator import plan_lighting

    light = EnvironmentLight(_gradient(4 * SAMPLING_ROWS))
    coarse = light.coarse_sampling()
    assert coarse.cell == 4 and coarse is light.coarse_sampling() and coarse.radiance is light.radiance
    normals = np.array([[0.0, 1.0, 0.0], [0.6, 0.0, -0.8]])
    np.testing.assert_array_equal(coarse.irradiance(normals), light.irradiance(normals))
    assert coarse._tables["irradiance"] is light._tables["irradiance"]  # one table, the light's
    assert plan_lighting(light, "mis").terms[0][0] is coarse
    small = EnvironmentLight(_gradient())
    assert small.coarse_sampling() is small


def test_pdf_integrates_to_one_over_the_sphere():
    light = EnvironmentLight(_gradient())
    height, width = 256, 512
    from relightcli.io.envmap import texel_directions

    pdf = light.pdf(texel_directions(height, width))
    assert np.sum(pdf * texel_solid_angles(height, width)) == pytest.approx(1.0, rel=1e-3)


def test_plan_flags():
    assert EnvironmentLight(np.zeros((4, 8, 3), np.float32)).is_black
    assert EnvironmentLight(np.full((4, 8, 3), 3.0, np.float32)).is_constant
    assert EnvironmentLight(_one_hot()).is_sun_only
    sunny = EnvironmentLight(_sun_and_sky())
    assert not sunny.is_sun_only and sunny.sun_fraction > 0.5


def test_top_energy_fraction_counts_the_brightest_texels_among_zeros():
    from relightcli.render.environment import _top_energy_fraction

    energy = np.zeros((64, 128))
    energy[3, 5:9] = [8.0, 4.0, 2.0, 1.0]   # 8 brightest texels (0.1%): four lit, four zeros
    assert _top_energy_fraction(energy, 0.001) == 1.0
    energy[10:20, :] = 0.01                 # 1280 dim texels: the top 8 are the four and four dim
    assert _top_energy_fraction(energy, 0.001) == pytest.approx(15.04 / (15.0 + 12.8))
    sun, _ = EnvironmentLight(_sun_and_sky()).sun_and_sky()
    assert sun.sun_fraction == pytest.approx(1.0, abs=1e-3) and sun.is_sun_only


def test_sun_and_sky_add_up_to_the_map():
    light = EnvironmentLight(_sun_and_sky())
    sun, sky = light.sun_and_sky()
    np.testing.assert_array_equal(sun.radiance + sky.radiance, light.radiance)
    assert sun.total_energy + sky.total_energy == pytest.approx(light.total_energy, rel=1e-9)


EXTREMES = {
    "black": lambda: np.zeros((8, 16, 3), np.float32),
    "tiny_2x1": lambda: np.array([[[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]]], np.float32),
    "single_texel": lambda: _one_hot(64, 0, 0, 1e30),
    "sun_1e6": _sun_and_sky,
    "pole_texel": lambda: _one_hot(8, 7, 15, 5.0),
}


@pytest.mark.parametrize("name", sorted(EXTREMES))
def test_extreme_maps_sample_finite_values(name):
    light = EnvironmentLight(EXTREMES[name]())
    directions, pdf, radiance = light.sample_radiance(np.random.default_rng(0).random((4000, 2)))
    assert np.all(np.isfinite(directions)) and np.all(np.isfinite(pdf)) and np.all(np.isfinite(radiance))
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0, atol=1e-9)


def test_nan_inf_negative_texels_are_zeroed_with_a_warning():
    env = np.ones((4, 8, 3), np.float32)
    env[0, 0, 0], env[1, 1, 1], env[2, 2, 2] = np.nan, np.inf, -1.0
    with pytest.warns(RelightWarning):
        light = EnvironmentLight(env)
    assert np.all(np.isfinite(light.radiance)) and light.radiance.min() >= 0
    assert light.radiance[0, 0, 0] == 0 and light.radiance[3, 3, 0] == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        EnvironmentLight(np.ones((4, 8, 3), np.float32))


# ------------------------------------------------------------------ unoccluded shading table
def _brute_force_irradiance(radiance, normals):
    """(1/pi) sum over every texel of L max(0, n.w) dOmega at the texel centres."""
    from relightcli.io.envmap import texel_directions

    height, width = radiance.shape[:2]
    directions = texel_directions(height, width).reshape(-1, 3).astype(np.float32)
    weighted = (radiance.reshape(-1, 3) * texel_solid_angles(height, width).reshape(-1, 1) / np.pi)
    chunks = [np.maximum(part.astype(np.float32) @ directions.T, 0.0) @ weighted
              for part in np.array_split(normals, max(1, len(normals) // 32))]
    return np.concatenate(chunks)


def _unit_normals(count, seed=0):
    normals = np.random.default_rng(seed).normal(size=(count, 3))
    normals[:4] = [[0, 1, 0], [0, -1, 0], [1, 0, 0], [0, 0, -1]]  # poles and the seam
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


@pytest.mark.parametrize("name", ["kloofendal_overcast_1k.hdr", "noon_grass_1k.hdr",
                                  "brown_photostudio_02_1k.hdr"])
def test_irradiance_table_matches_the_full_resolution_sum(name):
    # What the control variate relies on: within 0.5% anywhere (studio lights and a sky with
    # the sun taken out; a sun is never tabulated, it is sampled on its own)
    light = EnvironmentLight(load_hdr(name))
    if light.sun_fraction >= 0.1:
        light = light.sun_and_sky()[1]
    normals = _unit_normals(400)
    table = light.irradiance(normals)
    exact = _brute_force_irradiance(light.radiance, normals)
    relative = np.abs(table - exact).mean(axis=1) / exact.mean(axis=1)
    assert relative.max() <= 0.005 and np.median(relative) <= 0.0005


def test_irradiance_of_a_constant_map_is_the_constant_and_black_is_zero():
    normals = _unit_normals(200)
    constant = EnvironmentLight(np.full((16, 32, 3), [0.5, 1.0, 2.0], np.float32))
    np.testing.assert_allclose(constant.irradiance(normals), np.broadcast_to([0.5, 1.0, 2.0], (200, 3)),
                               rtol=1e-3)
    black = EnvironmentLight(np.zeros((16, 32, 3), np.float32))
    assert not black.irradiance(normals).any()


def test_irradiance_of_one_bright_texel_follows_the_cosine_law():
    # A 64x128 map resamples exactly onto the table's texels: only the interpolation between
    # normals remains, so away from the terminator the table is the cosine law
    radiance = np.zeros((64, 128, 3), np.float32)
    radiance[20, 40] = 1000.0
    light = EnvironmentLight(radiance)
    normals = _unit_normals(400, seed=1)
    exact = _brute_force_irradiance(radiance, normals)
    lit = exact[:, 0] > 0.2 * exact[:, 0].max()
    np.testing.assert_allclose(light.irradiance(normals)[lit], exact[lit], rtol=0.01)


@pytest.mark.parametrize("name", sorted(MAPS))
def test_float32_sampling_picks_the_same_texels(name):
    """The renderer samples float32 directions (what the tracer takes): the same texel, so
    the same radiance, as float64 sampling; directions and pdfs differ by float32 round-off."""
    light = EnvironmentLight(MAPS[name]())
    u = np.random.default_rng(5).random((5000, 2))
    d64, pdf64, radiance64 = light.sample_radiance(u)
    d32, pdf32, radiance32 = light.sample_radiance(u, np.float32)
    assert d32.dtype == np.float32
    np.testing.assert_array_equal(radiance32, radiance64)
    np.testing.assert_allclose(d32, d64, atol=8 * np.finfo(np.float32).eps)
    np.testing.assert_allclose(pdf32, pdf64, rtol=32 * np.finfo(np.float32).eps)
    radiance_eval, pdf_eval = light.eval_pdf(d32)
    np.testing.assert_array_equal(radiance_eval, radiance32)
    np.testing.assert_allclose(pdf_eval, pdf64, rtol=32 * np.finfo(np.float32).eps)


# ------------------------------------------------------------------ samples drawn ahead
@pytest.mark.parametrize("name", ["sun_and_sky", "real_hdr", "gradient"])
def test_a_tabulated_sample_is_the_lights_own_sample_of_a_point_in_the_same_cell(name):
    light = EnvironmentLight(MAPS[name]())
    shape = (64, 4)
    table = TabulatedSampling(light, shape, np.random.default_rng(0))
    u = np.random.default_rng(1).random((3000, 2))
    directions, pdf, radiance = table.sample_radiance(u)
    assert directions.dtype == np.float32 and pdf.dtype == np.float64
    # The light's u behind each sample lies in the cell of the u that asked for it ...
    behind = light.invert_sample(directions.astype(np.float64))
    cell = np.floor(u * shape)
    assert np.all(np.abs(behind * shape - (cell + 0.5)) <= 0.5 + 1e-3)
    # ... and its pdf and radiance are the light's at the sampled direction
    np.testing.assert_allclose(pdf, light.pdf(directions.astype(np.float64)), rtol=1e-5)
    np.testing.assert_array_equal(radiance, light.eval(directions))


def _texel_cosine_integrals(height, normal, n=24):
    """(height, 2 height) integral over each texel of max(0, w . normal) dw, by midpoint
    quadrature in (u, v)."""
    from relightcli.io.envmap import uv_to_direction

    width = 2 * height
    u = (np.arange(width * n) + 0.5) / (width * n)
    v = (np.arange(height * n) + 0.5) / (height * n)
    uu, vv = np.meshgrid(u, v)
    cosine = np.maximum(uv_to_direction(uu, vv) @ normal, 0.0)
    dw = (2 * np.pi / (width * n)) * (np.pi / (height * n)) * np.sin(np.pi * vv)
    return (cosine * dw).reshape(height, n, width, n).sum(axis=(1, 3))


@pytest.mark.parametrize("name", ["sun_and_sky", "gradient"])
def test_samples_drawn_ahead_are_unbiased(name):
    # The irradiance of a tilted normal estimated from a whole table (one sample per cell):
    # over fresh draws the mean is the exact value, though one table's error is shared by all
    # the pixels that read it; the sun of 1e6 x the sky stays finite
    env = MAPS[name]()
    height = env.shape[0]
    light = EnvironmentLight(env)
    normal = np.array([0.6, 0.48, 0.64])
    exact = float((env.mean(axis=2) * _texel_cosine_integrals(height, normal)).sum())
    estimates = []
    for seed in range(300):
        table = TabulatedSampling(light, (32, 2), np.random.default_rng(seed))
        cosine = np.maximum(table.directions.astype(np.float64) @ normal, 0.0)
        estimates.append(np.mean(table.radiance_table.mean(axis=1) * cosine / table.pdf_table))
    estimates = np.array(estimates)
    assert np.all(np.isfinite(estimates))
    standard_error = estimates.std(ddof=1) / np.sqrt(estimates.size)
    assert abs(estimates.mean() - exact) <= 4 * standard_error + 1e-9 * exact
