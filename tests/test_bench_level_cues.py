"""bench/level_cues.py: its features ignore the albedo's level, and its regressor fits what it should."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
import level_cues  # noqa: E402


def person(seed: int = 0):
    rng = np.random.default_rng(seed)
    albedo = rng.uniform(0.02, 0.8, (64, 64, 3)).astype(np.float32)
    mask = np.zeros((64, 64), np.float32)
    mask[8:60, 20:44] = 1.0
    face = np.zeros((11, 2), np.float32)
    face[[0, 2, 5, 9, 10]] = [[32, 14], [30, 12], [34, 12], [31, 17], [33, 17]]
    return albedo, mask, face


def test_relative_features_do_not_see_one_gain():
    albedo, mask, face = person()
    plain = level_cues.relative_features(albedo, mask, face)
    assert plain[18] == 1.0  # the face was found
    np.testing.assert_allclose(level_cues.relative_features(albedo * 0.05, mask, face), plain, atol=1e-6)
    # ... but they see the spread: a flatter albedo has narrower quantiles
    flatter = level_cues.relative_features(0.3 + 0.1 * albedo, mask, face)
    assert flatter[7] - flatter[0] < plain[7] - plain[0]


def test_relative_features_without_a_face():
    albedo, mask, _ = person()
    features = level_cues.relative_features(albedo, mask, np.zeros((11, 2), np.float32))
    assert features[18] == 0.0 and len(features) == 22


def test_quadratic_ridge_fits_a_quadratic():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(400, 3))
    y = 0.5 * x[:, 0] - x[:, 1] * x[:, 2] + 2.0
    model = level_cues.QuadraticRidge(1e-3).fit(x, y)
    test = rng.normal(size=(50, 3))
    np.testing.assert_allclose(model.predict(test), 0.5 * test[:, 0] - test[:, 1] * test[:, 2] + 2.0, atol=0.01)
