"""The compiled direct-light passes against the numpy estimators they mirror, and the
GIL-free Embree scene against embreex."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from render_testing import merge, quad
from relightcli.render.camera import default_rect, render_pixel_geometry
from relightcli.render.environment import EnvironmentLight
from relightcli.render.scene import Scene

kernels = pytest.importorskip("relightcli.render.kernels")


def _scene_with_occluders():
    """A floor, a sphere resting on it and a slab above one side: shadows of every size."""
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    vertices, faces = merge(quad(-2, 2, -2, 2, 0.0), (sphere.vertices + [0.0, 0.0, 0.5], sphere.faces),
                            quad(0.5, 2, -2, 2, 1.5))
    return Scene(vertices, faces)


def _sun_and_sky_map():
    env = np.full((16, 32, 3), 0.3, np.float32)
    env[:8] = [0.4, 0.6, 0.9]
    env[3, 20] = 4000.0  # a sun of one texel, most of the energy
    return env


def test_native_scene_occlusion_matches_embreex():
    scene = _scene_with_occluders()
    rng = np.random.default_rng(0)
    origins = rng.uniform(-1.5, 1.5, (20000, 3)).astype(np.float32)
    directions = rng.normal(size=(20000, 3))
    directions = (directions / np.linalg.norm(directions, axis=1, keepdims=True)).astype(np.float32)
    tmax = rng.uniform(0.1, 5.0, 20000).astype(np.float32)
    ours = np.zeros(20000, bool)
    kernels.occluded_rays(scene.native().handle, origins, directions, tmax, ours)
    theirs = scene.occluded(origins, directions, tmax)
    assert 0.2 < theirs.mean() < 0.8
    np.testing.assert_array_equal(ours, theirs)


@pytest.mark.parametrize("strategy", ["env", "cosine", "uniform", "mis", "mis-nocv"])
def test_compiled_passes_match_the_numpy_estimators(strategy, monkeypatch):
    """Same uniforms, same estimator: the compiled passes equal the numpy ones up to float
    round-off (a direction's float32 rounding can flip a grazing shadow ray or a texel at an
    edge: a few pixels may differ by one sample's share)."""
    import relightcli.render.integrator as integrator

    scene = _scene_with_occluders()
    geometry = render_pixel_geometry(scene, default_rect(scene), (48, 48))
    light = EnvironmentLight(_sun_and_sky_map())
    options = dict(spp=32, seed=3, strategy=strategy.removesuffix("-nocv"),
                   control_variate=not strategy.endswith("-nocv"))
    compiled = integrator.shade_environment(scene, geometry, light, **options)
    monkeypatch.setattr(integrator, "_kernels", lambda: None)
    reference = integrator.shade_environment(scene, geometry, light, **options)
    mask = geometry.mask
    assert compiled.rays == reference.rays
    close = np.isclose(compiled.mean[mask], reference.mean[mask], rtol=1e-4, atol=1e-6).all(axis=1)
    assert close.mean() >= 0.99
    np.testing.assert_allclose(compiled.mean[mask].mean(axis=0), reference.mean[mask].mean(axis=0), rtol=2e-3)


def test_threads_give_the_same_sums_as_one():
    scene = _scene_with_occluders()
    geometry = render_pixel_geometry(scene, default_rect(scene), (40, 40))
    light = EnvironmentLight(_sun_and_sky_map())
    from relightcli.render.integrator import shade_environment

    one = shade_environment(scene, geometry, light, spp=16, seed=1, workers=1)
    three = shade_environment(scene, geometry, light, spp=16, seed=1, workers=3)
    np.testing.assert_array_equal(one.mean, three.mean)
    np.testing.assert_array_equal(one.stderr, three.stderr)
