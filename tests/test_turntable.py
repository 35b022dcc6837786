"""--turntable N: the turned maps are made one frame at a time, so memory does not grow with N,
and N has a cap a typo cannot pass."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from relightcli import pipeline
from relightcli.batch import Item
from relightcli.cli import MAX_TURNTABLE, main, relight_parser
from relightcli.io.images import write_image
from relightcli.pipeline import RelightOptions, relight_item
from tests.test_pipeline import SphereModels


def ball_photo(path: Path) -> Path:
    """A grey 64 x 64 photo whose alpha is the person: a square the stand-in ball fills."""
    alpha = np.zeros((64, 64), np.float32)
    alpha[8:56, 8:56] = 1.0
    write_image(path, np.full((64, 64, 3), 0.3, np.float32), alpha)
    return path


def sun_map(height: int = 8) -> np.ndarray:
    env = np.full((height, 2 * height, 3), 0.2, np.float32)
    env[height // 4, height // 2] = 500.0
    return env


def turntable_options(frames: int) -> RelightOptions:
    return RelightOptions(outputs=("shading",), method="raytrace-norefine", resolution=32, spp=1, turntable=frames)


def test_each_turned_map_is_made_when_its_frame_is_shaded(tmp_path, monkeypatch, stand_in_normals):
    from relightcli.io import envmap

    events = []
    rotate = envmap.rotate_envmap
    monkeypatch.setattr(envmap, "rotate_envmap", lambda env, degrees: events.append(("made", degrees)) or rotate(env, degrees))
    monkeypatch.setattr(pipeline, "write_layer", lambda name, path, frame, options: events.append(("written", path.name)))
    outputs = {f"shading#{k:03d}": tmp_path / f"s_shading_turn{k:03d}.exr" for k in range(4)}
    relight_item(Item(ball_photo(tmp_path / "s.png"), outputs), sun_map(), turntable_options(4), SphereModels())
    assert events == [("made", 0.0), ("written", "s_shading_turn000.exr"), ("made", 90.0),
                      ("written", "s_shading_turn001.exr"), ("made", 180.0), ("written", "s_shading_turn002.exr"),
                      ("made", 270.0), ("written", "s_shading_turn003.exr")]


def traced_peak(photo: Path, env: np.ndarray, frames: int) -> int:
    """Peak bytes numpy and Python allocate while relight_item makes `frames` frames."""
    tracemalloc.start()
    try:
        relight_item(Item(photo, {}), env, turntable_options(frames), SphereModels())
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_memory_does_not_grow_with_the_frames(tmp_path, stand_in_normals):
    # Every turned map held at once would add (frames - 2) maps of 1.5 MB each: 15 MB for 12.
    photo, env = ball_photo(tmp_path / "s.png"), sun_map(256)
    few, many = traced_peak(photo, env, 2), traced_peak(photo, env, 12)
    assert many < few + env.nbytes, (few, many)


@pytest.mark.parametrize("frames", [str(MAX_TURNTABLE + 1), "100000", "0"])
def test_a_turntable_beyond_the_cap_is_a_usage_error(frames, capsys):
    assert main(["a.png", "--hdr", "env.hdr", "-o", "out/", "--turntable", frames]) == 2
    err = capsys.readouterr().err
    assert "--turntable" in err and f"1..{MAX_TURNTABLE}" in err


def test_a_turntable_at_the_cap_is_accepted():
    args = relight_parser().parse_args(["a.png", "--hdr", "env.hdr", "-o", "out/", "--turntable", str(MAX_TURNTABLE)])
    assert args.turntable == MAX_TURNTABLE


@pytest.mark.parametrize("frames, first, last", [(36, "turn000", "turn035"), (1000, "turn000", "turn999"),
                                                  (1500, "turn0000", "turn1499")])
def test_frame_names_sort_in_frame_order(frames, first, last):
    from relightcli.cli import _lighting_names

    args = relight_parser().parse_args(["a.png", "--hdr", "env.hdr", "-o", "out/", "--turntable", str(frames)])
    names = _lighting_names(args)
    assert (len(names), names[0], names[-1]) == (frames, first, last)
    assert sorted(names) == names
