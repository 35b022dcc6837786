"""Sampling trios: closed forms, inversion round trips, chi-square goodness of fit."""

from __future__ import annotations

import numpy as np
import pytest

from relightcli.render import sampling as s
from render_testing import chi_square_pvalue

RNG_SEED = 1234


def _uniforms(n, k=2, seed=RNG_SEED):
    return np.random.default_rng(seed).random((n, k))




# ------------------------------------------------------------------ cosine hemisphere
def test_cosine_hemisphere_closed_form():
    u = _uniforms(1000)
    w = s.sample_cosine_hemisphere(u)
    # Malley: z = sqrt(1 - u0) and the directions are unit
    np.testing.assert_allclose(w[:, 2], np.sqrt(1 - u[:, 0]), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(w, axis=1), 1.0, atol=1e-12)


def test_cosine_hemisphere_inversion_round_trip():
    u = _uniforms(1000)
    np.testing.assert_allclose(s.invert_cosine_hemisphere_sample(s.sample_cosine_hemisphere(u)), u, atol=1e-9)


def test_cosine_hemisphere_pdf_integrates_to_one():
    # Quadrature in (cos theta, phi): dw = d(cos theta) d(phi)
    mu = (np.arange(2000) + 0.5) / 2000
    assert np.sum(s.cosine_hemisphere_pdf(mu)) / 2000 * 2 * np.pi == pytest.approx(1.0, rel=1e-6)


def test_cosine_hemisphere_chi_square():
    w = s.sample_cosine_hemisphere(_uniforms(200_000))
    # Under the cosine density, cos^2(theta) is uniform on [0, 1]
    counts, _ = np.histogram(w[:, 2] ** 2, bins=20, range=(0, 1))
    assert chi_square_pvalue(counts, np.full(20, w.shape[0] / 20)) > 1e-3


# ------------------------------------------------------------------ uniform sphere
def test_uniform_sphere_inversion_round_trip():
    u = _uniforms(1000)
    np.testing.assert_allclose(s.invert_uniform_sphere_sample(s.sample_uniform_sphere(u)), u, atol=1e-9)


def test_uniform_sphere_chi_square():
    w = s.sample_uniform_sphere(_uniforms(100_000))
    # Archimedes: z is uniform on [-1, 1]; phi is uniform
    counts, _, _ = np.histogram2d(w[:, 2], np.arctan2(w[:, 1], w[:, 0]), bins=(10, 12),
                               range=((-1, 1), (-np.pi, np.pi)))
    assert chi_square_pvalue(counts, np.full(120, w.shape[0] / 120)) > 1e-3
    np.testing.assert_allclose(s.uniform_sphere_pdf(w), 1 / (4 * np.pi))


# ------------------------------------------------------------------ piecewise constant 1D
FUNCS_1D = {
    "ramp": np.arange(1.0, 9.0),
    "one_hot": np.eye(7)[3],
    "with_zeros": np.array([0.0, 2.0, 0.0, 0.0, 5.0, 1.0, 0.0]),
    "stiff": np.array([1.0, 1e6, 1.0, 1.0]),
    "all_zero": np.zeros(5),
}


@pytest.mark.parametrize("name", sorted(FUNCS_1D))
def test_piecewise_1d_chi_square(name):
    func = FUNCS_1D[name]
    dist = s.build_piecewise_constant_1d(func)
    x, pdf, offset = s.sample_piecewise_constant_1d(dist, _uniforms(50_000, 1)[:, 0])
    expected = func / func.sum() if func.sum() > 0 else np.full(func.size, 1 / func.size)
    counts = np.bincount(offset, minlength=func.size)
    assert np.all(counts[expected == 0] == 0)
    assert chi_square_pvalue(counts, expected * x.size) > 1e-3
    np.testing.assert_allclose(pdf, s.piecewise_constant_1d_pdf(dist, x))
    assert np.all((x >= 0) & (x < 1)) and np.all(pdf > 0)


@pytest.mark.parametrize("name", sorted(FUNCS_1D))
def test_piecewise_1d_inversion_round_trip(name):
    dist = s.build_piecewise_constant_1d(FUNCS_1D[name])
    u = _uniforms(2000, 1)[:, 0]
    x, _, _ = s.sample_piecewise_constant_1d(dist, u)
    np.testing.assert_allclose(s.invert_piecewise_constant_1d_sample(dist, x), u, atol=1e-9)


@pytest.mark.parametrize("name", sorted(FUNCS_1D))
def test_piecewise_1d_pdf_integrates_to_one(name):
    dist = s.build_piecewise_constant_1d(FUNCS_1D[name])
    x = (np.arange(7000) + 0.5) / 7000
    assert np.mean(s.piecewise_constant_1d_pdf(dist, x)) == pytest.approx(1.0, rel=1e-9)


# ------------------------------------------------------------------ piecewise constant 2D
FUNCS_2D = {
    "smooth": np.outer(np.linspace(1, 3, 6), np.linspace(2, 1, 10)),
    "one_hot": np.eye(60)[17].reshape(6, 10),
    "empty_rows": np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 3.0], [0.0, 0.0, 0.0], [2.0, 2.0, 0.0]]),
    "stiff": np.where(np.arange(60).reshape(6, 10) == 23, 1e6, 1.0),
}


@pytest.mark.parametrize("name", sorted(FUNCS_2D))
def test_piecewise_2d_chi_square(name):
    func = FUNCS_2D[name]
    dist = s.build_piecewise_constant_2d(func)
    xy, pdf = s.sample_piecewise_constant_2d(dist, _uniforms(60_000))
    nv, nu = func.shape
    cell = (xy[:, 1] * nv).astype(int) * nu + (xy[:, 0] * nu).astype(int)
    counts = np.bincount(cell, minlength=func.size)
    assert chi_square_pvalue(counts, func.ravel() / func.sum() * xy.shape[0]) > 1e-3
    np.testing.assert_allclose(pdf, s.piecewise_constant_2d_pdf(dist, xy))


@pytest.mark.parametrize("name", sorted(FUNCS_2D))
def test_piecewise_2d_inversion_round_trip(name):
    dist = s.build_piecewise_constant_2d(FUNCS_2D[name])
    u = _uniforms(2000)
    xy, _ = s.sample_piecewise_constant_2d(dist, u)
    np.testing.assert_allclose(s.invert_piecewise_constant_2d_sample(dist, xy), u, atol=1e-9)


@pytest.mark.parametrize("name", sorted(FUNCS_2D))
def test_piecewise_2d_pdf_integrates_to_one(name):
    dist = s.build_piecewise_constant_2d(FUNCS_2D[name])
    g = (np.arange(600) + 0.5) / 600
    xx, yy = np.meshgrid(g, g)
    pdf = s.piecewise_constant_2d_pdf(dist, np.stack([xx, yy], axis=-1))
    assert pdf.mean() == pytest.approx(1.0, rel=1e-9)


def test_piecewise_rejects_negative_values():
    with pytest.raises(ValueError):
        s.build_piecewise_constant_2d(np.array([[1.0, -1.0]]))


@pytest.mark.parametrize("name", ["sun", "sky", "zero_bins", "one_bin"])
def test_guided_search_finds_what_the_binary_search_finds(name):
    rng = np.random.default_rng(7)
    func = {"sun": np.r_[np.full(500, 1e-6), 1e6, 3e5, np.full(500, 1e-6)],
            "sky": rng.random(20_000) ** 8,  # many dim bins: most keys need the search
            "zero_bins": np.r_[0.0, 0.0, 1.0, 0.0, 2.0, 0.0, 0.0, 1.0, 0.0],
            "one_bin": np.ones(1)}[name]
    cdf = s.build_piecewise_constant_1d(func).cdf
    keys = np.r_[rng.random(50_000), cdf, np.nextafter(cdf, 0.0), np.nextafter(cdf, 2.0), 0.0,
                 np.nextafter(1.0, 0.0), 1.0, -0.5, 1.5]
    guide = s.guide_table(cdf)
    assert guide.shape == cdf.shape
    expected = np.searchsorted(cdf, keys, side="right") - 1
    np.testing.assert_array_equal(s.search_cdf(cdf, keys, guide), expected)
    np.testing.assert_array_equal(s.search_cdf(cdf, keys), expected)
    np.testing.assert_array_equal(s.search_cdf(cdf, keys.reshape(-1, 1), guide), expected.reshape(-1, 1))
