"""bench/delight_level.py: the net's albedo level error and the level the albedo PSNR prefers."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
import delight_level  # noqa: E402

from relightcli.nets.delight import DelightResult  # noqa: E402


def sample(rng: np.random.Generator) -> dict:
    mask = np.zeros((32, 32, 1), np.float32)
    mask[4:28, 8:24] = 1.0
    return {"albedo": rng.uniform(0.05, 0.6, (32, 32, 3)).astype(np.float32) * mask, "mask": mask,
            "input": rng.uniform(0.0, 1.0, (32, 32, 3)).astype(np.float32),
            "normal_pred": np.tile(np.float32([0.0, 0.0, 2.0]), (32, 32, 1))}


def test_a_uniformly_dark_albedo_is_measured_and_its_best_shift_undoes_it():
    rng = np.random.default_rng(0)
    rows = []
    for _ in range(3):
        truth = sample(rng)
        rows.append(delight_level.sample_row(truth, truth["albedo"] * np.float32(2.0 ** -0.3)))
    assert [r["level"] for r in rows] == pytest.approx([0.3] * 3, abs=1e-5)
    summary = delight_level.summarise(rows)
    assert summary["best_shift"] == pytest.approx(0.3)
    assert summary["level_median"] == pytest.approx(0.3, abs=1e-5)
    assert summary["psnr"][summary["shifts"].index(0.3)] > summary["psnr_unshifted"] + 10


def test_the_net_is_fed_the_photo_and_unit_normals_as_the_stage_feeds_it():
    seen = []

    class Net:
        trained_resolution = 32

        def predict(self, image, normal):
            seen.append(normal)
            return DelightResult(albedo=image * np.float32(0.5), light=np.zeros((16, 32, 3), np.float32))

    truth = sample(np.random.default_rng(1))
    albedo = delight_level.net_albedo(Net(), truth)
    assert albedo == pytest.approx(0.5 * truth["input"], abs=1e-6)  # the photo and its mirror, averaged back
    assert np.linalg.norm(seen[0], axis=-1) == pytest.approx(1.0)


def test_the_calibration_moves_a_nets_median_level_onto_the_references():
    net = {"samples": 200, "level_median": -0.05}
    calibration = delight_level.calibration(net, {"level_median": 0.19}, "somewhere")
    assert calibration["albedo_gain"] == pytest.approx(2.0 ** -0.24, abs=1e-4)
    rng = np.random.default_rng(2)
    truth = sample(rng)
    light_albedo = truth["albedo"] * np.float32(2.0 ** 0.05)  # a net 0.05 stops light: level -0.05
    level = delight_level.sample_row(truth, light_albedo * np.float32(calibration["albedo_gain"]))["level"]
    assert level == pytest.approx(0.19, abs=1e-3)
