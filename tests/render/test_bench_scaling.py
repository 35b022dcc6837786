"""Scaling of the integrator from 1 to 2 worker processes (benchmark: needs 2 idle cores).

Run with `pytest -m bench tests/render/test_bench_scaling.py` on an otherwise idle machine;
on a machine shared with other jobs the measurement says nothing.
"""

from __future__ import annotations

import time

import pytest

from render_testing import body_mesh, load_hdr
from relightcli.render.camera import default_rect, render_pixel_geometry
from relightcli.render.environment import EnvironmentLight
from relightcli.render.integrator import shade_environment
from relightcli.render.scene import Scene

pytestmark = pytest.mark.bench


def _best_of(repeats, render):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        render()
        times.append(time.perf_counter() - start)
    return min(times)


def test_two_workers_scale_at_least_1_8x():
    # 512x512, the benchmark's size (~4 s on one worker). A 256x256 render (0.8 s) measured
    # 1.61x: its per-render setup (forking, control-variate lookups) and per-round merging are
    # serial and weigh more in a short render.
    scene = Scene.from_trimesh(body_mesh())
    geometry = render_pixel_geometry(scene, default_rect(scene), (512, 512))
    light = EnvironmentLight(load_hdr("noon_grass_1k.hdr"))
    light.sun_and_sky()
    one = _best_of(3, lambda: shade_environment(scene, geometry, light, spp=64, workers=1))
    two = _best_of(3, lambda: shade_environment(scene, geometry, light, spp=64, workers=2))
    print(f"1 worker {one:.2f} s, 2 workers {two:.2f} s: {one / two:.2f}x")
    assert one / two >= 1.8
