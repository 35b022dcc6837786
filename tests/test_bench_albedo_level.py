"""bench/albedo_level.py's measures: the front light's units and the background fit."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from albedo_level import front_irradiance, summarise  # noqa: E402

from relightcli.io.envmap import texel_directions  # noqa: E402


def test_a_white_sky_gives_a_camera_facing_normal_unit_irradiance_and_the_light_behind_none():
    white = np.ones((16, 32, 3), np.float32)
    assert abs(front_irradiance(white) - 1.0) < 0.01
    behind = white * (texel_directions(16, 32)[..., 2:3] < 0)
    assert front_irradiance(behind) == 0.0


def test_the_fit_credits_the_background_only_when_it_carries_what_our_light_misses():
    rng = np.random.default_rng(0)
    ours, missed = rng.normal(0, 1, 200), rng.normal(0, 0.5, 200)
    rows = [{"albedo_level_error": 0.0, "front_ours": 2.0 ** o, "front_true": 2.0 ** (o + m),
             "background": 2.0 ** (m + b)} for o, m, b in zip(ours, missed, rng.normal(0, 0.05, 200))]
    carried = summarise(rows)
    assert carried["fit_residual_with_background"] < 0.5 * carried["fit_residual_without_background"]
    for row, noise in zip(rows, rng.normal(0, 1, 200)):
        row["background"] = 2.0 ** noise
    unrelated = summarise(rows)
    assert unrelated["fit_residual_with_background"] > 0.9 * unrelated["fit_residual_without_background"]
