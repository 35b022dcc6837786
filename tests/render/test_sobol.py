"""Our Sobol points: the right sequence, and a scramble that keeps it a net."""

import numpy as np
import pytest

from relightcli.render.sobol import MAX_DIMENSIONS, sobol_points


def test_unscrambled_points_are_joe_kuo_sobol_as_scipy_makes_them():
    qmc = pytest.importorskip("scipy.stats").qmc
    ours = sobol_points(MAX_DIMENSIONS, 10)
    reference = qmc.Sobol(d=MAX_DIMENSIONS, scramble=False).random_base2(10)
    np.testing.assert_array_equal(ours, reference)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_scrambled_set_keeps_one_point_per_elementary_interval(seed):
    points = sobol_points(6, 10, np.random.default_rng(seed))
    assert points.min() >= 0.0 and points.max() < 1.0
    # 1024 points: one per 1/1024 slice of each dimension, one per 32x32 cell of the first two
    for d in range(6):
        np.testing.assert_array_equal(np.bincount((points[:, d] * 1024).astype(int), minlength=1024), 1)
    cells = np.histogram2d(points[:, 0], points[:, 1], bins=32, range=[[0, 1], [0, 1]])[0]
    np.testing.assert_array_equal(cells, 1)


def test_scrambles_differ_by_seed_and_repeat_by_seed():
    a = sobol_points(4, 6, np.random.default_rng(5))
    np.testing.assert_array_equal(a, sobol_points(4, 6, np.random.default_rng(5)))
    assert not np.array_equal(a, sobol_points(4, 6, np.random.default_rng(6)))


def test_scrambled_points_integrate_without_bias():
    # the mean of a smooth function over many independent scrambles is its integral
    estimates = [np.prod(np.sin(np.pi * sobol_points(3, 6, np.random.default_rng(seed))), axis=1).mean()
                 for seed in range(200)]
    exact = (2 / np.pi) ** 3
    assert abs(np.mean(estimates) - exact) < 4 * np.std(estimates) / np.sqrt(len(estimates))


def test_dimensions_out_of_range_are_refused():
    with pytest.raises(ValueError, match="dimensions"):
        sobol_points(MAX_DIMENSIONS + 1, 4)
