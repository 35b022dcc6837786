"""bench/light_solve.py's `solve-level-from`: the ratio albedo's gain taken to another net's
albedo, the rest of the stage as it was."""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
import light_solve  # noqa: E402

from relightcli import compose  # noqa: E402
from relightcli.nets.delight import DelightResult  # noqa: E402
from relightcli.stages import delight  # noqa: E402


def test_the_level_comes_from_the_other_net_and_everything_is_restored(monkeypatch):
    frame, options, level_net = SimpleNamespace(), SimpleNamespace(), object()
    solved = []
    monkeypatch.setattr(delight, "solve_input_light", lambda *args: solved.append(args) or ("light", "layer"))

    def estimate(seen_frame, net, seen_options):
        assert (seen_frame, net, seen_options) == (frame, level_net, options)
        return DelightResult(albedo=np.full((8, 8, 3), 0.4, np.float32), light=np.zeros((16, 32, 3), np.float32))
    monkeypatch.setattr(delight, "net_estimate", estimate)
    ratio, own = np.full((8, 8, 3), 0.1, np.float32), np.full((8, 8, 3), 0.2, np.float32)
    mask = np.ones((8, 8), np.float32)
    before = delight.solve_input_light, compose.albedo_gain
    with light_solve.substituted(light_solve.LEVEL_FROM, np.zeros((16, 32, 3)), level_net):
        assert delight.solve_input_light(frame, own, options, "models") == ("light", "layer")
        assert compose.albedo_gain(ratio, own, mask) == pytest.approx(4.0)
    assert solved == [(frame, own, options, "models")]
    assert (delight.solve_input_light, compose.albedo_gain) == before
    assert compose.albedo_gain(ratio, own, mask) == pytest.approx(2.0)


def test_delight_once_runs_the_net_on_the_photo_alone(monkeypatch):
    calls = []

    class Net:
        trained_resolution = 8

        def predict(self, image, normal):
            calls.append(image)
            return DelightResult(albedo=image, light=np.zeros((16, 32, 3), np.float32))

    frame = SimpleNamespace(crop=np.random.default_rng(0).uniform(size=(8, 8, 3)).astype(np.float32),
                            normal=np.tile(np.float32([0.0, 0.0, 1.0]), (8, 8, 1)))
    options = SimpleNamespace(resolution=8)
    delight.net_estimate(frame, Net(), options)
    assert len(calls) == 2  # the photo and its mirror
    monkeypatch.setattr(delight, "MIRROR_AVERAGED", delight.MIRROR_AVERAGED)
    light_solve.delight_once()
    calls.clear()
    assert delight.net_estimate(frame, Net(), options).albedo == pytest.approx(frame.crop)
    assert len(calls) == 1
