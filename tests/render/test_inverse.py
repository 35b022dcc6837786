"""The input light by inverse rendering (relightcli.render.inverse): a known light is recovered
from rendered scenes, a cast shadow leaves the albedo, and degenerate inputs stay finite."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from relightcli.io.envmap import texel_directions
from relightcli.io.images import LUMINANCE
from relightcli.render.camera import default_rect, render_pixel_geometry
from relightcli.render.environment import EnvironmentLight
from relightcli.render.integrator import shade_environment
from relightcli.render.inverse import exact_unoccluded_transport, light_transport, solve_light, unoccluded_transport
from relightcli.render.scene import Scene
from relightcli.render.sh import project_sh, sh_irradiance_shading

from render_testing import body_mesh, merge, quad

RES = 64


def sky_light(sun=(0.5, 0.5, 0.7), sun_radiance=5.0) -> np.ndarray:
    """(16, 32, 3) a sky brighter above (+Y), a warm lobe toward `sun`, a dark ground."""
    directions = texel_directions(16, 32)
    up = directions[..., 1]
    sky = 0.2 + 0.8 * np.clip(up, 0.0, None)
    toward = np.asarray(sun, float) / np.linalg.norm(sun)
    lobe = sun_radiance * np.exp((directions @ toward - 1.0) / 0.05)
    light = sky[..., None] * np.array([0.6, 0.8, 1.0]) + lobe[..., None] * np.array([1.0, 0.9, 0.7])
    return light.astype(np.float32)


def render(scene, light, spp=256):
    geometry = render_pixel_geometry(scene, default_rect(scene), (RES, RES))
    result = shade_environment(scene, geometry, EnvironmentLight(light), spp=spp, seed=1)
    return geometry, result.mean


def seen_level(transport, light) -> np.ndarray:
    """Per channel, the light as the pixels see it: the transport's column sums weighting the
    texels (a light behind the object is not observable and does not count)."""
    weights = transport.matrix.sum(axis=0)
    return weights @ light.reshape(-1, 3)


def sphere_scene():
    return Scene.from_trimesh(trimesh.creation.icosphere(subdivisions=4, radius=1.0))


@pytest.mark.parametrize("make_scene", [sphere_scene, lambda: Scene.from_trimesh(body_mesh())],
                         ids=["sphere", "body"])
def test_a_known_light_is_recovered_from_a_rendered_object(make_scene):
    scene = make_scene()
    truth = sky_light()
    geometry, shading = render(scene, truth)
    pixels = np.flatnonzero(geometry.mask)
    albedo = np.full((pixels.size, 3), 0.5)
    photo = albedo * shading.reshape(-1, 3)[pixels]
    transport = light_transport(scene, geometry, pixels, samples=256, seed=3)
    prior = np.full_like(truth, 0.3 * truth.mean())  # the wrong level and no shape
    solved = solve_light(transport, photo, albedo, np.ones(pixels.size), prior).light
    level = seen_level(transport, solved) / seen_level(transport, truth)
    assert np.all(np.abs(level - 1.0) < 0.10), level
    # the shading it gives matches the photo's within a few percent over the object
    _, resolved = render(scene, solved, spp=128)
    error = np.abs(resolved.reshape(-1, 3)[pixels] - shading.reshape(-1, 3)[pixels]).mean()
    assert error < 0.06 * shading.reshape(-1, 3)[pixels].mean()
    scene.close()


def test_an_albedo_pattern_the_solve_does_not_know_leaves_a_sky_not_noise():
    # The photo's albedo varies +-30% from pixel to pixel while the solve assumes a flat one
    # (as the net's albedo misses the clothes' pattern), and the transport has few samples: the
    # light must stay a smooth sky with its sun, not texel-to-texel noise with black holes
    scene = Scene.from_trimesh(body_mesh())
    truth = sky_light()
    geometry, shading = render(scene, truth)
    pixels = np.flatnonzero(geometry.mask)
    pattern = np.random.default_rng(0).uniform(0.7, 1.3, (pixels.size, 1))
    photo = 0.5 * pattern * shading.reshape(-1, 3)[pixels]
    transport = light_transport(scene, geometry, pixels, samples=32, seed=3)
    prior = np.full_like(truth, 0.3 * truth.mean())
    solved = solve_light(transport, photo, np.full((pixels.size, 3), 0.5), np.ones(pixels.size), prior).light
    luminance, true_luminance = solved @ LUMINANCE, truth @ LUMINANCE
    roughness = lambda x: np.abs(np.diff(x, axis=1)).mean() / x.mean()  # noqa: E731
    assert roughness(luminance) < 2.0 * roughness(true_luminance)
    assert (luminance <= 0).mean() <= 0.05
    seen = transport.matrix.sum(axis=0).reshape(16, 32) > 0.2 * transport.matrix.sum(axis=0).max()
    assert np.corrcoef(luminance[seen], true_luminance[seen])[0, 1] > 0.7
    scene.close()


def shadow_scene():
    """A wall (the torso) facing the camera, a bar (an arm) in front of it, and a ball at the
    top right (a head: the many normals a body shows, which tell the light's directions)."""
    wall = quad(-1.0, 1.0, -1.0, 1.0, 0.0)
    bar = quad(-0.15, 0.15, -1.0, 1.0, 0.5)
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.25)
    vertices, faces = merge(wall, bar, (ball.vertices + (0.55, 0.6, 0.35), ball.faces))
    return Scene(vertices, faces)


def test_a_cast_shadow_leaves_the_albedo_without_a_step():
    scene = shadow_scene()
    # a sun from the front right: the bar's shadow falls on the wall at x in [-0.53, -0.22]
    truth = sky_light(sun=(0.6, 0.0, 0.8), sun_radiance=200.0) * np.float32(0.2)
    geometry, shading = render(scene, truth)
    photo = 0.6 * shading
    pixels = np.flatnonzero(geometry.mask)
    transport = light_transport(scene, geometry, pixels, samples=256, seed=3)
    prior = np.full_like(truth, truth.mean())
    solved = solve_light(transport, photo.reshape(-1, 3)[pixels], np.full((pixels.size, 3), 0.6),
                         np.ones(pixels.size), prior).light
    _, input_shading = render(scene, solved)
    albedo = photo / np.maximum(input_shading, 1e-6)
    x = geometry.position[..., 0] + scene.centre[0]
    on_wall = geometry.mask & (geometry.position[..., 2] + scene.centre[2] < 0.25)
    y = geometry.position[..., 1] + scene.centre[1]
    shadow, lit = on_wall & (x > -0.48) & (x < -0.27), on_wall & (x > 0.3) & (x < 0.9) & (y < 0.0)
    photo_step = photo[shadow].mean() / photo[lit].mean()
    assert photo_step < 0.5  # the shadow is a real step in the photo
    sh_albedo = photo / sh_irradiance_shading(project_sh(solved, 2), geometry.normal)
    assert sh_albedo[shadow].mean() / sh_albedo[lit].mean() < 0.6  # no visibility: the step stays
    step = albedo[shadow].mean(axis=0) / albedo[lit].mean(axis=0)
    assert np.all(np.abs(step - 1.0) < 0.1), step
    scene.close()


@pytest.mark.parametrize("case", ["black photo", "clipped photo", "single-texel sun", "flat wall"])
def test_degenerate_inputs_stay_finite(case):
    scene = sphere_scene() if case != "flat wall" else Scene(*quad(-1, 1, -1, 1, 0.0))
    truth = sky_light()
    if case == "single-texel sun":
        truth = np.full_like(truth, 1e-3)
        truth[4, 20] = 1e6  # a million times the sky
    geometry, shading = render(scene, truth, spp=64)
    pixels = np.flatnonzero(geometry.mask)
    photo = 0.5 * shading.reshape(-1, 3)[pixels]
    weights = np.ones(pixels.size)
    if case == "black photo":
        photo = np.zeros_like(photo)
    if case == "clipped photo":
        weights = np.zeros(pixels.size)  # every pixel clipped: nothing to fit
    transport = light_transport(scene, geometry, pixels, samples=64, seed=0)
    prior = sky_light()
    solve = solve_light(transport, photo, np.full((pixels.size, 3), 0.5), weights, prior)
    assert np.all(np.isfinite(solve.light)) and np.all(solve.light >= 0)
    assert np.all(np.isfinite(solve.residual))
    if case == "black photo":  # ~no light on what the pixels see (the prior stays behind them)
        assert np.all(seen_level(transport, solve.light) < 1e-2 * seen_level(transport, prior))
    if case == "clipped photo":
        assert solve.pixels == 0 and np.array_equal(solve.light, prior)
    if case == "single-texel sun":  # found where it is, though smoothed over its neighbours
        row, col = np.unravel_index(np.argmax(solve.light.sum(axis=-1)), solve.light.shape[:2])
        assert abs(row - 4) <= 1 and min(abs(col - 20), 32 - abs(col - 20)) <= 1
    if case == "flat wall":
        fit = transport.shading(solve.light) * 0.5
        assert np.abs(fit - photo).mean() < 0.1 * photo.mean()
    scene.close()


def test_the_transport_is_the_same_for_the_same_seed():
    scene = shadow_scene()  # occluders: the Monte Carlo part of the transport is not empty
    geometry = render_pixel_geometry(scene, default_rect(scene), (32, 32))
    pixels = np.flatnonzero(geometry.mask)
    first = light_transport(scene, geometry, pixels, samples=16, seed=5).matrix
    again = light_transport(scene, geometry, pixels, samples=16, seed=5).matrix
    other = light_transport(scene, geometry, pixels, samples=16, seed=6).matrix
    assert np.array_equal(first, again) and not np.array_equal(first, other)
    scene.close()


def test_an_unoccluded_pixel_sees_its_whole_hemisphere():
    scene = sphere_scene()
    geometry = render_pixel_geometry(scene, default_rect(scene), (32, 32))
    pixels = np.flatnonzero(geometry.mask)
    rows = light_transport(scene, geometry, pixels, samples=16, seed=5).matrix.sum(axis=1)
    # 1 under unit radiance everywhere (to the texel quadrature's 0.1%), less only where the
    # tessellated sphere's shading normal tips a sample below its flat triangle
    assert np.all(rows <= 1.0 + 1e-3) and np.median(rows) > 0.99
    scene.close()


def test_the_tabulated_unoccluded_transport_matches_the_direct_sum():
    rng = np.random.default_rng(0)
    normals = rng.normal(size=(500, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    normals[:4] = [[0, 1, 0], [0, -1, 0], [0, 0, 1], [1, 0, 0]]  # the poles and the seam's side
    table, exact = unoccluded_transport(normals), exact_unoccluded_transport(normals)
    assert np.abs(table - exact).sum(axis=1).max() < 0.005
    np.testing.assert_allclose(exact.sum(axis=1), 1.0, atol=1e-3)  # the whole hemisphere (4x4 quadrature)
    light = rng.random((512, 3))
    assert np.abs(table @ light - exact @ light).max() < 1e-3 * (exact @ light).mean()


@pytest.mark.parametrize("fixed_share", [0.0, 0.05, 0.5, 1.0])
def test_the_nonnegative_solve_is_scipys_nnls(fixed_share, monkeypatch):
    """The active-set solve finds scipy's NNLS minimum (its fallback), whether no texel, a
    few, half or all of them end at zero, and the fallback itself runs when the swaps do not
    settle."""
    from scipy.optimize import nnls

    from relightcli.render import inverse

    rng = np.random.default_rng(int(fixed_share * 100))
    n = 200
    basis = rng.normal(size=(n + 50, n))
    gram = basis.T @ basis + 0.1 * np.eye(n)
    truth = rng.uniform(0.5, 2.0, n) * (rng.random(n) >= fixed_share)
    rhs = gram @ truth - (truth == 0) * rng.uniform(0.1, 1.0, n)  # a positive multiplier where x = 0
    upper = np.linalg.cholesky(gram).T
    expected, _ = nnls(upper, np.linalg.solve(upper.T, rhs), maxiter=50 * n)
    solved = inverse._nonnegative_quadratic(gram, rhs)
    assert (solved >= 0).all()
    np.testing.assert_allclose(solved, expected, atol=1e-9 * max(expected.max(), 1.0))
    np.testing.assert_array_equal(solved > 0, truth > 0)
    monkeypatch.setattr(inverse, "ACTIVE_SET_ROUNDS", 0)
    np.testing.assert_allclose(inverse._nonnegative_quadratic(gram, rhs), expected, atol=1e-9 * max(expected.max(), 1.0))


def test_the_solved_light_keeps_a_floor_under_the_prior_where_the_pixels_ask_for_less_than_none():
    # A sphere lit from above only, seen with a noisy albedo: unfloored, the solve blacks out
    # texels; with the default floor every texel keeps at least that share of the prior's
    # light (times the solve's colour gains), and the pixels are fitted about as well
    scene = sphere_scene()
    truth = sky_light()
    truth[8:] = 0.0  # no light from below the horizon
    geometry, shading = render(scene, truth, spp=64)
    pixels = np.flatnonzero(geometry.mask)
    albedo = np.random.default_rng(0).uniform(0.3, 0.7, (pixels.size, 3))
    photo = albedo * shading.reshape(-1, 3)[pixels]
    transport = light_transport(scene, geometry, pixels, samples=64, seed=0)
    prior = sky_light()
    unfloored = solve_light(transport, photo, np.full((pixels.size, 3), 0.5), np.ones(pixels.size), prior, floor=0.0)
    floored = solve_light(transport, photo, np.full((pixels.size, 3), 0.5), np.ones(pixels.size), prior)
    assert (unfloored.light.sum(axis=-1) == 0).any()
    grey_prior = prior.mean(axis=-1)
    share = floored.light.mean(axis=-1) / grey_prior
    assert share.min() > 0.0 and np.all(np.isfinite(floored.light))
    # the texels the pixels pushed down sit on the floor: one share of the prior for all of them
    assert (share <= share.min() * (1 + 1e-6)).sum() >= 2
    assert max(floored.residual) <= max(unfloored.residual) + 0.02
    scene.close()


def shading_spread(transport, light, shading) -> float:
    """The spread (std) of log2 of a light's shading over the true one at the pixels, level apart."""
    ratio = np.log2(np.maximum(transport.shading(light) @ LUMINANCE, 1e-9) / np.maximum(shading @ LUMINANCE, 1e-9))
    return float(ratio.std())


@pytest.mark.parametrize("rounds", [0, 1])
def test_one_colour_per_garment_takes_the_shading_the_net_left_in_its_albedo_back_out(rounds):
    # Two garments of one colour each; the net's albedo keeps a third of the log shading (as
    # the shipped net does, docs/RESULTS.md): dividing by it, the solve explains that part of
    # the shading away; one colour per region gives it back
    from relightcli.render.inverse import albedo_regions, solve_light_by_regions

    scene = Scene.from_trimesh(body_mesh())
    truth = sky_light()
    geometry, shading = render(scene, truth)
    pixels = np.flatnonzero(geometry.mask)
    shading = shading.reshape(-1, 3)[pixels]
    left = geometry.position.reshape(-1, 3)[pixels, 0] < np.median(geometry.position.reshape(-1, 3)[pixels, 0])
    albedo = np.where(left[:, None], [0.6, 0.25, 0.2], [0.15, 0.3, 0.55])
    photo = albedo * shading
    level = shading @ LUMINANCE
    net_albedo = albedo * ((level / np.median(level)) ** 0.35)[:, None]
    transport = light_transport(scene, geometry, pixels, samples=64, seed=3)
    prior = np.full_like(truth, 0.3 * truth.mean())
    weights = np.ones(pixels.size)
    labels = albedo_regions(photo, net_albedo, 2)
    assert min(np.mean(labels[left] == labels[left][0]), np.mean(labels[~left] == labels[~left][0])) > 0.95
    assert labels[left][0] != labels[~left][0]
    plain = solve_light(transport, photo, net_albedo, weights, prior).light
    regions = solve_light_by_regions(transport, photo, net_albedo, weights, prior, 2, rounds).light
    assert shading_spread(transport, regions, shading) < 0.5 * shading_spread(transport, plain, shading)
    scene.close()


def test_regions_of_degenerate_inputs():
    # fewer pixels than regions, one colour everywhere, black and NaN-free zeros: labels in range,
    # and a solve with no usable pixel is the prior
    from relightcli.render.inverse import Transport, albedo_regions, solve_light_by_regions

    assert set(albedo_regions(np.ones((3, 3)), np.ones((3, 3)), 6).tolist()) <= {0, 1, 2}
    assert albedo_regions(np.zeros((5, 3)), np.zeros((5, 3)), 1).tolist() == [0] * 5
    labels = albedo_regions(np.zeros((40, 3)), np.zeros((40, 3)), 6)
    assert labels.min() >= 0 and labels.max() < 6
    transport = Transport(np.full((40, 512), 1.0 / 512, np.float32), np.arange(40), (16, 32))
    prior = np.full((16, 32, 3), 0.7, np.float32)
    solved = solve_light_by_regions(transport, np.zeros((40, 3)), np.zeros((40, 3)), np.zeros(40), prior, 6, 1)
    assert solved.pixels == 0 and np.array_equal(solved.light, prior)


def test_a_regions_colour_comes_from_its_usable_pixels():
    # Half of one garment's pixels are clipped (weight 0) and the net's albedo there is wrong
    # (10x): the region's colour is the net's mean over the usable half, so the light comes out
    # at the true level (the mean over all of it would put it 5.5x too dark)
    from relightcli.render.inverse import Transport, solve_light_by_regions

    transport = Transport(np.full((40, 512), 1.0 / 512, np.float32), np.arange(40), (16, 32))
    weights = np.repeat([1.0, 0.0], 20)
    net_albedo = np.where(weights[:, None] > 0, 0.5, 5.0) * np.ones((40, 3))
    photo = np.where(weights[:, None] > 0, 0.5, 1.0) * np.ones((40, 3))  # the true light: 1 everywhere
    prior = np.full((16, 32, 3), 0.5, np.float32)
    solved = solve_light_by_regions(transport, photo, net_albedo, weights, prior, 1, 0)
    assert abs(float(transport.shading(solved.light).mean()) - 1.0) < 0.1
