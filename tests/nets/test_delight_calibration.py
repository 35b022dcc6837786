"""The manifest's `calibration.albedo_gain` scales the de-lighting net's albedo, and nothing else."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from relightcli.nets.delight import DelightNet

MODELS = Path(__file__).resolve().parents[2] / "models"


def models_with_gain(folder: Path, gain: float | None) -> Path:
    folder.mkdir()
    manifest = json.loads((MODELS / "manifest.json").read_text())
    entry = manifest["models"]["delight"]
    entry.pop("calibration", None)
    if gain is not None:
        entry["calibration"] = {"albedo_gain": gain}
    manifest["models"] = {"delight": entry}
    (folder / "manifest.json").write_text(json.dumps(manifest))
    shutil.copy(MODELS / entry["file"], folder / entry["file"])
    return folder


def test_the_albedo_is_scaled_by_the_gain_and_the_light_is_not(tmp_path):
    rng = np.random.default_rng(0)
    image = rng.uniform(0.1, 0.9, (64, 64, 3)).astype(np.float32)
    normal = np.tile(np.float32([0.0, 0.0, 1.0]), (64, 64, 1))
    plain = DelightNet(models_dir=models_with_gain(tmp_path / "plain", None), threads=1).predict(image, normal)
    halved = DelightNet(models_dir=models_with_gain(tmp_path / "halved", 0.5), threads=1).predict(image, normal)
    assert plain.albedo.max() > 0.05
    assert halved.albedo == pytest.approx(0.5 * plain.albedo, rel=1e-6, abs=1e-7)
    assert halved.albedo.dtype == np.float32
    assert np.array_equal(halved.light, plain.light)
