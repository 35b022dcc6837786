"""The integrator against closed forms: furnace, cosine law, shadows, error estimate, AO."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from render_testing import merge, one_hot_map, quad
from relightcli.io.envmap import uv_to_direction
from relightcli.render.camera import default_rect, render_pixel_geometry
from relightcli.render.environment import EnvironmentLight, TabulatedSampling
from relightcli.render.integrator import ambient_occlusion, shade_environment
from relightcli.render.scene import Scene

L_CONST = np.array([0.7, 1.4, 2.1], np.float32)


@pytest.fixture(params=["drawn", "tabulated"])
def env_samples(request, monkeypatch):
    """Runs a test twice: environment samples drawn per sample, and drawn ahead in a table
    (environment.TabulatedSampling), which large renders use."""
    import relightcli.render.integrator as integrator

    monkeypatch.setattr(integrator, "SAMPLE_TABLE_MIN_ROWS", 1 if request.param == "tabulated" else 1 << 40)
    return request.param


def _sphere_scene(radius=1.0, offset=(0.0, 0.0, 0.0), smooth=False, subdivisions=3):
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return Scene(mesh.vertices + np.asarray(offset), mesh.faces,
                 vertex_normals=mesh.vertex_normals, smooth_normals=smooth)


def _sphere_geometry(scene, res=24):
    return render_pixel_geometry(scene, default_rect(scene), (res, res))


# ------------------------------------------------------------------ white furnace
def test_furnace_mis_is_exact_for_a_constant_map():
    scene = _sphere_scene()
    geometry = _sphere_geometry(scene)
    result = shade_environment(scene, geometry, EnvironmentLight(np.broadcast_to(L_CONST, (8, 16, 3))), spp=8)
    assert result.strategy == "cosine"
    np.testing.assert_allclose(result.mean[geometry.mask], np.broadcast_to(L_CONST, (geometry.mask.sum(), 3)), rtol=1e-6)
    assert np.all(result.stderr[geometry.mask] < 1e-6)


@pytest.mark.parametrize("strategy", ["env", "uniform", "cosine"])
@pytest.mark.parametrize("sampler", ["sobol", "independent"])
def test_furnace_within_reported_error(strategy, sampler, env_samples):
    scene = _sphere_scene()
    geometry = _sphere_geometry(scene)
    light = EnvironmentLight(np.broadcast_to(L_CONST, (8, 16, 3)))
    result = shade_environment(scene, geometry, light, spp=64, strategy=strategy, sampler=sampler)
    deviation = np.abs(result.mean[geometry.mask] - L_CONST)
    stderr = result.stderr[geometry.mask]
    if strategy == "cosine":
        # Cosine sampling is perfect importance sampling here: every sample equals L
        assert np.all(deviation <= 1e-5 * L_CONST) and np.all(stderr <= 1e-5)
    elif sampler == "independent":
        # 64 passes: |error| / stderr is ~ |N(0,1)|, none of ~380 pixels passes 5 sigma
        assert np.all(deviation <= 5.0 * stderr + 1e-5)
    else:
        # 4 randomisations give a 3-dof stderr per pixel: check it in aggregate
        ratio = np.sqrt(np.mean(deviation ** 2) / np.mean(stderr ** 2))
        assert 0.5 <= ratio <= 2.0
    # No bias: the mean over the pixels (independent estimates) within 5 of its standard errors
    standard_error = np.sqrt(np.mean((stderr / L_CONST) ** 2) / stderr.shape[0])
    assert abs(np.mean(result.mean[geometry.mask] / L_CONST) - 1.0) <= max(5 * standard_error, 1e-5)


# ------------------------------------------------------------------ cosine law
def _texel_moment(height, row, col, n=64):
    """Integral over one texel of w dw (3,), by fine midpoint quadrature in (u, v)."""
    width = 2 * height
    u = (col + (np.arange(n) + 0.5) / n) / width
    v = (row + (np.arange(n) + 0.5) / n) / height
    uu, vv = np.meshgrid(u, v)
    d = uv_to_direction(uu, vv)
    dw = (2 * np.pi / width) * (np.pi / height) * np.sin(np.pi * vv) / (n * n)
    return np.sum(d * dw[..., None], axis=(0, 1))


@pytest.mark.parametrize("texel", [(20, 70), (40, 10), (31, 100)])
def test_single_texel_light_follows_the_cosine_law(texel):
    height = 64
    row, col = texel
    scene = _sphere_scene(subdivisions=4)
    geometry = _sphere_geometry(scene, 32)
    radiance = 1000.0
    result = shade_environment(scene, geometry, EnvironmentLight(one_hot_map(height, row, col, radiance)),
                               spp=64, sampler="independent")
    assert result.strategy == "env"
    n = geometry.normal[geometry.mask].astype(np.float64)
    # Where the whole texel is above the facet, shading = (L / pi) n . integral(w dw)
    centre = uv_to_direction((col + 0.5) / (2 * height), (row + 0.5) / height)
    lit = n @ centre > 0.1
    expected = radiance / np.pi * (n @ _texel_moment(height, row, col))
    got = result.mean[geometry.mask][:, 0]
    stderr = result.stderr[geometry.mask][:, 0]
    # Only the cosine's variation across the texel is noise: within 5 standard errors
    assert np.all(np.abs(got - expected)[lit] <= 5 * stderr[lit] + 1e-4 * expected[lit])
    assert np.median(stderr[lit] / expected[lit]) < 0.01
    np.testing.assert_array_equal(got[n @ centre < -0.1], 0.0)


# ------------------------------------------------------------------ hard shadow
def test_plane_under_occluder_is_dark_exactly_where_geometry_puts_the_shadow():
    height, row, col = 256, 127, 448  # a texel near the horizon, toward +X+Z (u = 0.875)
    d = uv_to_direction((col + 0.5) / (2 * height), (row + 0.5) / height)
    h, a = 1.0, 0.5
    vertices, faces = merge(quad(-4.0, 4.0, -4.0, 4.0, 0.0), quad(-a, a, -a, a, h))
    scene = Scene(vertices, faces)
    geometry = render_pixel_geometry(scene, (-4.0, 4.0, -4.0, 4.0), (96, 96))
    result = shade_environment(scene, geometry, EnvironmentLight(one_hot_map(height, row, col, 50.0)),
                               spp=64, sampler="independent")
    p = scene.to_world(geometry.position.reshape(-1, 3)).reshape(96, 96, 3)
    on_plane = geometry.mask & (np.abs(p[..., 2]) < 1e-4)
    # The ray p + t d meets z = h at p + (h / d_z) d: shadowed if that lands on the occluder
    q = p[..., :2] + (h / d[2]) * d[:2]
    inside = np.max(np.abs(q), axis=-1) - a
    margin = 2 * 8.0 / 96 + h / d[2] * np.pi / height  # two pixels plus the texel's penumbra
    shade = result.mean[..., 0]
    assert np.all(shade[on_plane & (inside < -margin)] == 0.0)
    lit = on_plane & (inside > margin)
    expected = 50.0 / np.pi * _texel_moment(height, row, col)[2]
    stderr = result.stderr[..., 0]
    assert np.all(np.abs(shade[lit] - expected) <= 5 * stderr[lit] + 1e-4 * expected)
    assert (on_plane & (inside < -margin)).sum() > 30 and lit.sum() > 1000


# ------------------------------------------------------------------ scale and translation
@pytest.mark.parametrize("scale, shift", [(1e-3, 0.0), (1e4, 0.0), (1.0, 1e5), (1e-3, 1e5)])
def test_scale_and_translation_give_the_same_image(scale, shift):
    def render(s, t):
        vertices, faces = merge(quad(-4.0, 4.0, -4.0, 4.0, 0.0), quad(-0.5, 0.5, -0.5, 0.5, 1.0),
                                (trimesh.creation.icosphere(2, 0.7).vertices + [2.0, 2.0, 0.7],
                                 trimesh.creation.icosphere(2, 0.7).faces))
        scene = Scene(vertices * s + t, faces)
        geometry = render_pixel_geometry(scene, np.array([-4.0, 4.0, -4.0, 4.0]) * s + t, (40, 40))
        light = EnvironmentLight(_sun_and_sky_map())
        return shade_environment(scene, geometry, light, spp=8, seed=3)

    reference, other = render(1.0, 0.0), render(scale, shift)
    np.testing.assert_array_equal(reference.mask, other.mask)
    differs = np.abs(other.mean - reference.mean) > 1e-3 * (1.0 + np.abs(reference.mean))
    assert differs.any(axis=-1).mean() < 0.005  # a grazing ray or two may flip, no more


def _sun_and_sky_map(height=32):
    env = np.full((height, 2 * height, 3), 0.3, np.float32)
    env[9, 20] = 3e5
    return env


# ------------------------------------------------------------------ error estimate
def _soft_map(height=32):
    v = (np.arange(height)[:, None] + 0.5) / height
    u = (np.arange(2 * height)[None, :] + 0.5) / (2 * height)
    value = 0.2 + 2.0 * np.clip(1 - v, 0, 1) ** 2 * (1 + 0.5 * np.cos(2 * np.pi * u))
    return np.repeat(value[..., None], 3, axis=2).astype(np.float32)


@pytest.mark.parametrize("sampler", ["sobol", "independent"])
@pytest.mark.parametrize("map_name", ["soft", "hard_sun"])
def test_reported_error_is_within_factor_two_of_true_rmse(map_name, sampler, env_samples):
    env = _soft_map() if map_name == "soft" else _sun_and_sky_map()
    vertices, faces = merge(quad(-3.0, 3.0, -3.0, 3.0, 0.0),
                            (trimesh.creation.icosphere(2, 1.0).vertices + [0.0, 0.0, 1.0],
                             trimesh.creation.icosphere(2, 1.0).faces))
    scene = Scene(vertices, faces)
    geometry = render_pixel_geometry(scene, (-3.0, 3.0, -3.0, 3.0), (16, 16))
    light = EnvironmentLight(env)
    reference = shade_environment(scene, geometry, light, spp=2048, seed=100)
    rmse, reported = [], []
    for seed in range(4):
        result = shade_environment(scene, geometry, light, spp=32, sampler=sampler, seed=seed)
        rmse.append(np.mean((result.mean - reference.mean)[geometry.mask] ** 2))
        reported.append(np.mean(result.stderr[geometry.mask] ** 2))
    ratio = np.sqrt(np.mean(reported) / np.mean(rmse))
    assert 0.5 <= ratio <= 2.0


# ------------------------------------------------------------------ adaptive, budget, determinism
def _body_like_scene():
    vertices, faces = merge(quad(-3.0, 3.0, -3.0, 3.0, 0.0),
                            (trimesh.creation.icosphere(2, 1.0).vertices + [0.0, 0.0, 1.0],
                             trimesh.creation.icosphere(2, 1.0).faces))
    scene = Scene(vertices, faces)
    return scene, render_pixel_geometry(scene, (-3.0, 3.0, -3.0, 3.0), (24, 24))


def test_target_error_is_reached_and_samples_go_where_the_error_is():
    scene, geometry = _body_like_scene()
    light = EnvironmentLight(_soft_map())
    result = shade_environment(scene, geometry, light, target_error=0.02, spp=4096)
    assert result.median_relative_error() <= 0.02
    passes = result.passes[geometry.mask]
    assert passes.min() >= 16 and passes.max() > 2 * passes.min()


def test_target_error_holds_against_a_converged_reference_under_a_hard_sun(env_samples):
    """Adaptive stopping must not trust a pixel whose few samples missed a rare occluder
    (with the control variate its own error estimate is then 0): the true median error
    stays within the target and the reported one tells the truth."""
    scene, geometry = _body_like_scene()
    light = EnvironmentLight(_sun_and_sky_map())
    reference = shade_environment(scene, geometry, light, spp=4096, seed=100)
    result = shade_environment(scene, geometry, light, target_error=0.02, spp=4096, seed=1)
    inside = geometry.mask & (reference.mean.mean(axis=-1) > 0.01 * np.median(reference.mean[geometry.mask]))
    truth = reference.mean.mean(axis=-1)[inside]
    true_error = np.median(np.abs(result.mean.mean(axis=-1)[inside] - truth) / truth)
    reported = result.median_relative_error()
    assert true_error <= 0.02
    assert 0.5 <= reported / true_error <= 2.0


def test_stopping_error_is_floored_by_the_neighbourhood():
    from types import SimpleNamespace

    from relightcli.render.integrator import POOL_FLOOR, _Run, _State

    state = _State(9, groups=4)
    state.count[:] = 4
    state.group_total[:] = 1.0                     # every group mean 1: no spread
    state.group_total[:, 0] += 0.4                 # spread in every pixel...
    state.group_total[4] = 1.0                     # ...but the centre one, which saw none
    own = state.relative_error()
    assert own[4] == 0.0 and np.all(own[np.arange(9) != 4] > 0)
    run = SimpleNamespace(pool_shape=(3, 3), pool_index=np.arange(9))
    error = _Run.stopping_error(run, state)
    assert error[4] == pytest.approx(POOL_FLOOR * np.sqrt(np.mean(own ** 2)))
    np.testing.assert_array_equal(error[[0, 8]] >= own[[0, 8]], True)


def test_time_budget_stops_sampling():
    scene, geometry = _body_like_scene()
    result = shade_environment(scene, geometry, EnvironmentLight(_soft_map()), time_budget=0.3, spp=1 << 16)
    assert result.seconds < 0.3 + 0.5
    assert result.passes[geometry.mask].max() < 1 << 16


@pytest.mark.parametrize("sampler", ["sobol", "independent"])
def test_same_seed_same_image(sampler, env_samples):
    scene, geometry = _body_like_scene()
    light = EnvironmentLight(_sun_and_sky_map())
    a = shade_environment(scene, geometry, light, spp=8, seed=5, sampler=sampler)
    b = shade_environment(scene, geometry, light, spp=8, seed=5, sampler=sampler)
    c = shade_environment(scene, geometry, light, spp=8, seed=6, sampler=sampler)
    np.testing.assert_array_equal(a.mean, b.mean)
    assert np.any(a.mean != c.mean)


@pytest.mark.parametrize("round_rays", [None, 2048])  # 2048: many rounds, each capped by its rays
@pytest.mark.parametrize("target_error", [None, 0.05])
def test_two_workers_give_the_same_image_as_one(target_error, round_rays, monkeypatch, env_samples):
    import relightcli.render.integrator as integrator

    if round_rays is not None:
        monkeypatch.setattr(integrator, "ROUND_RAYS", round_rays)
    monkeypatch.setattr(integrator, "FORK_MIN_SAMPLES", 0)  # this small render forks too
    forks = _count_forks(monkeypatch)
    scene, geometry = _body_like_scene()
    light = EnvironmentLight(_sun_and_sky_map())
    one = shade_environment(scene, geometry, light, spp=32, seed=4, target_error=target_error)
    two = shade_environment(scene, geometry, light, spp=32, seed=4, target_error=target_error, workers=2)
    assert forks == [2]
    np.testing.assert_array_equal(two.mean, one.mean)
    np.testing.assert_array_equal(two.stderr, one.stderr)
    assert two.rays == one.rays


def _count_forks(monkeypatch) -> list:
    """The worker counts of the ForkedPasses the integrator opens from now on."""
    import relightcli.render.integrator as integrator

    forks = []

    class Counted(integrator.ForkedPasses):
        def __init__(self, run, workers):
            forks.append(workers)
            super().__init__(run, workers)

    monkeypatch.setattr(integrator, "ForkedPasses", Counted)
    return forks


def test_a_render_forks_only_with_enough_samples_to_gain(monkeypatch):
    import relightcli.render.integrator as integrator

    forks = _count_forks(monkeypatch)
    scene, geometry = _body_like_scene()
    light = EnvironmentLight(_sun_and_sky_map())
    samples = int(geometry.mask.sum()) * 16
    monkeypatch.setattr(integrator, "FORK_MIN_SAMPLES", samples + 1)
    shade_environment(scene, geometry, light, spp=16, seed=4, workers=2)
    assert forks == []
    monkeypatch.setattr(integrator, "FORK_MIN_SAMPLES", samples)
    shade_environment(scene, geometry, light, spp=16, seed=4, workers=2)
    assert forks == [2]


def _stop_dispositions():
    import signal

    return signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)


def test_forked_workers_leave_stopping_to_the_parent():
    """Closing the pool ends the workers by SIGTERM: whatever handler the parent had (the CLI's
    raises batch.Stopped, which printed a traceback from each worker ended), a worker takes the
    default action; Ctrl-C, sent to the whole process group, is the parent's to handle."""
    import signal
    from types import SimpleNamespace

    from relightcli.render.parallel import ForkedPasses

    scene, _ = _body_like_scene()
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: None)
    try:
        with ForkedPasses(SimpleNamespace(scene=scene), 2) as passes:
            dispositions = passes._pool.apply(_stop_dispositions)
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert dispositions == (signal.SIG_DFL, signal.SIG_IGN)


# ------------------------------------------------------------------ doing only what is needed
@pytest.mark.parametrize("spp, tables", [(8, 0), (64, 2)])
def test_renders_with_enough_samples_draw_the_environments_samples_ahead(spp, tables, monkeypatch):
    # sun + sky: two environment-sampled terms, a table each, once per render, of about one
    # entry per SAMPLE_TABLE_SHARE samples: 576 pixels x 8 samples make 576 entries, fewer than
    # SAMPLE_TABLE_MIN_ROWS rows of 4; x 64 samples 4608, 1024 rows of 4
    import relightcli.render.integrator as integrator

    made = []
    monkeypatch.setattr(integrator, "TabulatedSampling",
                        lambda *args: made.append(args) or TabulatedSampling(*args))
    scene, geometry = _body_like_scene()
    result = shade_environment(scene, geometry, EnvironmentLight(_sun_and_sky_map()), spp=spp)
    assert result.strategy == "sun+mis-cv" and len(made) == tables
    assert all(shape == (1024, 4) for _, shape, _ in made)


def test_black_map_traces_nothing():
    scene, geometry = _body_like_scene()
    result = shade_environment(scene, geometry, EnvironmentLight(np.zeros((8, 16, 3), np.float32)))
    assert result.rays == 0 and result.strategy == "none" and not result.mean.any()


def test_pixels_outside_the_mask_trace_nothing():
    scene = _sphere_scene()
    geometry = render_pixel_geometry(scene, (5.0, 6.0, 5.0, 6.0), (8, 8))
    result = shade_environment(scene, geometry, EnvironmentLight(_soft_map()), spp=8)
    assert not geometry.mask.any() and result.rays == 0


def test_sun_only_map_uses_one_ray_per_sample():
    scene = _sphere_scene()
    geometry = _sphere_geometry(scene)
    result = shade_environment(scene, geometry, EnvironmentLight(one_hot_map(16, 4, 3, 10.0)), spp=8)
    assert result.strategy == "env" and result.rays <= 8 * geometry.mask.sum()


def test_sunny_map_samples_sun_and_sky_apart():
    scene = _sphere_scene()
    result = shade_environment(scene, _sphere_geometry(scene), EnvironmentLight(_sun_and_sky_map()), spp=4)
    assert result.strategy == "sun+mis-cv"


# ------------------------------------------------------------------ control variate
def _sky_gradient(height=32):
    """A smooth, non-constant sky: bright above, dim below, warmer toward +X."""
    v = (np.arange(height) + 0.5) / height
    u = (np.arange(2 * height) + 0.5) / (2 * height)
    up = np.cos(np.pi * v)[:, None] * 0.5 + 0.6
    side = 1.0 + 0.5 * np.sin(2 * np.pi * u)[None, :]
    up = np.broadcast_to(up, (height, 2 * height))
    return np.stack([up * side, up, up / side], axis=-1).astype(np.float32)


def test_control_variate_is_exact_where_nothing_occludes(env_samples):
    # A convex sphere with flat normals: no shadow ray is blocked, so every sample of the
    # occluded part is zero and the estimate is the tabulated unoccluded shading itself
    scene = _sphere_scene()
    geometry = _sphere_geometry(scene)
    light = EnvironmentLight(_sky_gradient())
    result = shade_environment(scene, geometry, light, spp=8)
    assert result.strategy == "mis-cv"
    assert not result.stderr[geometry.mask].any()
    normals = geometry.normal[geometry.mask].astype(np.float64)
    np.testing.assert_allclose(result.mean[geometry.mask], light.irradiance(normals), rtol=1e-5)
    # ... which agrees with plain MIS, converged, within its error and the table's 0.5%
    plain = shade_environment(scene, geometry, light, spp=1024, control_variate=False)
    # A pixel's standard error comes from RQMC_GROUPS = 4 group means: its error over it follows
    # Student's t with 3 degrees of freedom, beyond 5 on ~1.5% of pixels. A bias fails most.
    deviation = np.abs(result.mean - plain.mean)[geometry.mask]
    outside = deviation > 5 * plain.stderr[geometry.mask] + 0.005 * plain.mean[geometry.mask]
    assert outside.mean() <= 0.03


def test_control_variate_is_unbiased_and_less_noisy_under_occlusion(env_samples):
    # A plane under a square roof: every plane pixel is partly occluded
    vertices, faces = merge(quad(-4.0, 4.0, -4.0, 4.0, 0.0), quad(-1.5, 1.5, -1.5, 1.5, 1.0))
    scene = Scene(vertices, faces)
    geometry = render_pixel_geometry(scene, (-4.0, 4.0, -4.0, 4.0), (48, 48))
    light = EnvironmentLight(_sky_gradient())
    with_cv = shade_environment(scene, geometry, light, spp=64, seed=1)
    plain = shade_environment(scene, geometry, light, spp=64, seed=2, control_variate=False)
    m = geometry.mask
    difference = (with_cv.mean - plain.mean)[m]
    combined = np.sqrt(with_cv.stderr[m] ** 2 + plain.stderr[m] ** 2)
    # 3-dof error estimates per pixel: check the ratio in aggregate, and no systematic offset
    ratio = np.sqrt(np.mean(difference ** 2) / np.mean(combined ** 2))
    assert 0.5 <= ratio <= 2.0
    assert abs(difference.mean()) <= 5 * np.sqrt(np.mean(combined ** 2) / difference.size)
    assert np.median(with_cv.stderr[m]) < 0.5 * np.median(plain.stderr[m])


# ------------------------------------------------------------------ robustness
EXTREME_MAPS = {
    "tiny_2x1": lambda: np.array([[[1.0, 2.0, 3.0], [0.0, 0.5, 0.0]]], np.float32),
    "single_texel_1e30": lambda: one_hot_map(64, 0, 0, 1e30),
    "sun_1e6": lambda: _sun_and_sky_map(128),
    "nan_inf_negative": lambda: np.where(np.arange(128).reshape(8, 16, 1) % 3 == 0,
                                         np.array([np.nan, np.inf, -1.0], np.float32), 1.0).astype(np.float32),
    "large_1k": lambda: np.random.default_rng(0).random((512, 1024, 3)).astype(np.float32) ** 8,
}


@pytest.mark.parametrize("name", sorted(EXTREME_MAPS))
@pytest.mark.parametrize("strategy", ["mis", "cosine"])
def test_no_nan_or_inf_on_extreme_maps(name, strategy):
    scene, geometry = _body_like_scene()
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        light = EnvironmentLight(EXTREME_MAPS[name]())
    result = shade_environment(scene, geometry, light, spp=8, strategy=strategy)
    assert np.all(np.isfinite(result.mean)) and np.all(np.isfinite(result.stderr))
    assert result.mean.min() >= 0


# ------------------------------------------------------------------ second bounce
def test_second_bounce_of_a_black_albedo_changes_nothing():
    scene, geometry = _body_like_scene()
    light = EnvironmentLight(_soft_map())
    one = shade_environment(scene, geometry, light, spp=8, seed=2)
    two = shade_environment(scene, geometry, light, spp=8, seed=2, bounces=2, albedo=0.0)
    np.testing.assert_allclose(two.mean, one.mean, rtol=1e-6)


def _floor_and_wall():
    """An (effectively) infinite floor z = 0 and wall x = -0.2, and the floor next to it."""
    floor = quad(-1000.0, 1000.0, -1000.0, 1000.0, 0.0)
    wall = np.array([[-0.2, -1000.0, 0.0], [-0.2, 1000.0, 0.0], [-0.2, 1000.0, 1000.0], [-0.2, -1000.0, 1000.0]])
    scene = Scene(*merge(floor, (wall, np.array([[0, 1, 2], [0, 2, 3]]))))
    return scene, render_pixel_geometry(scene, (0.0, 0.1, -0.05, 0.05), (2, 2))


@pytest.mark.parametrize("albedo", [0.3, 1.0])
def test_second_bounce_next_to_a_wall_matches_the_closed_form(albedo):
    # White sky L = 1: the wall hides half the floor's cosine lobe (direct 1/2); every wall
    # point has half its lobe under the floor (direct 1/2), so it sends radiance albedo / 2
    # into the hidden half: shading = 1/2 + albedo / 4.
    scene, geometry = _floor_and_wall()
    light = EnvironmentLight(np.ones((16, 32, 3), np.float32))
    result = shade_environment(scene, geometry, light, spp=2048, bounces=2, albedo=albedo,
                               sampler="independent")
    expected = 0.5 + albedo / 4
    assert np.all(np.abs(result.mean[geometry.mask] - expected) <= 5 * result.stderr[geometry.mask] + 1e-3)


def test_albedo_image_is_read_at_the_pixel_the_bounce_hits():
    # Floor and wall seen from above: a camera-aligned albedo image that is 0.3 on the wall's
    # column of pixels and 1.0 elsewhere must act like albedo 0.3 (only the wall reflects)
    scene, _ = _floor_and_wall()
    rect = (-0.4, 0.4, -0.4, 0.4)
    geometry = render_pixel_geometry(scene, rect, (8, 8))
    columns = -0.4 + (np.arange(8) + 0.5) * 0.1
    image = np.ones((8, 8, 3))
    image[:, np.abs(columns + 0.2) < 0.06] = 0.3  # the wall x = -0.2 projects into column 1
    light = EnvironmentLight(np.ones((16, 32, 3), np.float32))
    with_image = shade_environment(scene, geometry, light, spp=64, bounces=2, albedo=image, seed=3)
    constant = shade_environment(scene, geometry, light, spp=64, bounces=2, albedo=0.3, seed=3)
    right = geometry.mask & (columns[None, :] > -0.1)
    np.testing.assert_allclose(with_image.mean[right], constant.mean[right], rtol=1e-6)


# ------------------------------------------------------------------ ambient occlusion
def test_ambient_occlusion_of_an_open_plane_is_one():
    scene = Scene(*quad(-1.0, 1.0, -1.0, 1.0, 0.0))
    geometry = render_pixel_geometry(scene, (-1.0, 1.0, -1.0, 1.0), (8, 8))
    result = ambient_occlusion(scene, geometry, spp=16)
    np.testing.assert_allclose(result.mean[geometry.mask], 1.0)


def test_ambient_occlusion_next_to_a_tall_wall_is_one_half():
    # Directions toward an (effectively) infinite wall are blocked: half the cosine lobe
    scene, geometry = _floor_and_wall()
    result = ambient_occlusion(scene, geometry, spp=4096)
    np.testing.assert_allclose(result.mean[geometry.mask], 0.5, atol=4 * result.stderr.max() + 1e-3)


@pytest.mark.parametrize("max_distance, expected", [(0.1, 1.0), (1e6, 0.5)])
def test_ambient_occlusion_ignores_occluders_beyond_max_distance(max_distance, expected):
    # The wall is 0.2 away: beyond a 0.1 reach nothing occludes
    scene, geometry = _floor_and_wall()
    result = ambient_occlusion(scene, geometry, spp=4096, max_distance=max_distance)
    np.testing.assert_allclose(result.mean[geometry.mask], expected, atol=4 * result.stderr.max() + 1e-3)


# ------------------------------------------------------------------ trace first, look up after
def test_the_control_variates_cosine_rays_are_traced_before_the_map_is_read(monkeypatch):
    # Only blocked cosine rays carry the control variate's correction: looking the map up
    # after tracing gives the same image bit for bit ...
    import relightcli.render.estimators as estimators

    scene, geometry = _body_like_scene()
    light = EnvironmentLight(_sun_and_sky_map())
    after = shade_environment(scene, geometry, light, spp=16, seed=2)
    monkeypatch.setattr(estimators, "TRACE_FIRST_MAX_BLACK", -1.0)
    before = shade_environment(scene, geometry, light, spp=16, seed=2)
    np.testing.assert_array_equal(after.mean, before.mean)
    np.testing.assert_array_equal(after.stderr, before.stderr)
    # ... tracing more rays only where texels are black (the sun's, taken out of the sky)
    assert before.rays <= after.rays <= 1.01 * before.rays


def test_a_map_with_a_black_half_is_read_before_its_rays_are_traced(monkeypatch):
    # Rays toward the black lower half would be traced for nothing: that map is read first
    import relightcli.render.estimators as estimators

    env = _soft_map()
    env[env.shape[0] // 2:] = 0.0
    light = EnvironmentLight(env)
    assert light.black_fraction == pytest.approx(0.5)
    scene = _sphere_scene(smooth=True)
    geometry = _sphere_geometry(scene)
    read_first = shade_environment(scene, geometry, light, spp=16, seed=2)
    monkeypatch.setattr(estimators, "TRACE_FIRST_MAX_BLACK", 1.0)
    traced_first = shade_environment(scene, geometry, light, spp=16, seed=2)
    np.testing.assert_array_equal(read_first.mean, traced_first.mean)
    assert read_first.strategy == "mis-cv" and read_first.rays < traced_first.rays
