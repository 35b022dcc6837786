"""Scenes, lightings, the camera model and per-sample rendering (export/factory).

Rendering tests use a sphere dressed as a Person (constant albedo), so answers are analytic.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh

from export.factory import camera_model, lighting, render, scenes
from relightcli.io.envmap import direction_to_uv, texel_solid_angles
from relightcli.io.images import linear_to_srgb

RADIUS, CENTRE = 0.5, np.array([0.0, 1.0, 0.0])
SETTINGS = render.RenderSettings(resolution=48, spp=16, target_error=None, ao_spp=8, bounces=1)


def sphere_person(albedo=0.5):
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=RADIUS)
    vertices = (mesh.vertices + CENTRE).astype(np.float32)
    faces = mesh.faces.astype(np.int32)
    front_cap = np.flatnonzero(mesh.vertices[:, 2] > 0.8 * RADIUS)
    return SimpleNamespace(vertices=vertices, faces=faces,
                           face_uv=np.full((len(faces), 3, 2), 0.5, np.float32),
                           texture=np.full((2, 2, 3), albedo, np.float32),
                           face_vertex_ids=front_cap, metadata={"seed": 0})


def sky(azimuth=90.0, elevation=10.0):
    params = dict(sun_elevation_deg=elevation, sun_azimuth_deg=azimuth, sun_to_sky=1e5,
                  sun_radius_deg=1.0, haze=0.2, ground_albedo=0.2)
    return lighting.LightingSpec("sky", "sky", 0.0, params)


def sphere_spec(pitch=0.0, yaw=0.0, light=None, index=0):
    light = light or sky()
    return scenes.SceneSpec(split="train", index=index, person_seed=0, pitch_deg=pitch,
                            yaw_deg=yaw, scale=1.0, lighting_a=light, lighting_b=sky(-90.0, 30.0),
                            background=light, background_fov_deg=60.0, exposure_key=0.8)


@pytest.fixture(scope="module")
def sphere_sample():
    return render.render_sample(sphere_spec(), sphere_person(), SETTINGS)


# --- HDRI split ------------------------------------------------------------------------------

def test_hdri_splits_are_disjoint_and_cover_the_catalogue():
    catalogue = {f"map{i}.hdr": ("indoor" if i % 3 else "outdoor_sun") for i in range(30)}
    parts = lighting.split_hdris(catalogue)
    sets = [set(parts[s]) for s in lighting.SPLITS]
    assert sum(len(s) for s in sets) == len(catalogue)
    assert set().union(*sets) == set(catalogue)


def test_hdri_split_is_stratified_by_category():
    catalogue = {f"map{i}.hdr": ("indoor" if i % 3 else "outdoor_sun") for i in range(30)}
    test = lighting.split_hdris(catalogue)["test"]
    assert {catalogue[n] for n in test} == {"indoor", "outdoor_sun"}


def test_shared_hdri_split_is_disjoint():
    if not (lighting.hdri_dir() / "index.csv").is_file():
        pytest.skip("shared HDRIs not found")
    parts = lighting.hdri_splits()
    assert not set(parts["train"]) & (set(parts["val"]) | set(parts["test"]))
    assert not set(parts["val"]) & set(parts["test"])
    assert len(parts["test"]) >= 3


# --- procedural sky ----------------------------------------------------------------------------

def test_procedural_sky_sun_radiance_is_the_requested_multiple_of_the_sky_median():
    env = lighting.procedural_sky(64, sun_elevation_deg=45, sun_azimuth_deg=0, sun_to_sky=1e6,
                                  sun_radius_deg=10.0, haze=0.0)
    lum = env @ np.array([0.2126, 0.7152, 0.0722])
    assert lum.max() == pytest.approx(1e6, rel=0.01)


def test_procedural_sun_energy_does_not_depend_on_resolution():
    kwargs = dict(sun_elevation_deg=30, sun_azimuth_deg=40, sun_to_sky=1e6, sun_radius_deg=0.5)
    energies = []
    for height in (64, 256):
        env = lighting.procedural_sky(height, **kwargs).astype(np.float64)
        sun = env[..., 1] > 1e3  # the disc only: the sky and ground follow the map
        energies.append((env[..., 1] * sun * texel_solid_angles(height, 2 * height)).sum())
    assert energies[0] == pytest.approx(energies[1], rel=0.02)


def test_procedural_sun_sits_at_its_azimuth_and_elevation():
    env = lighting.procedural_sky(128, sun_elevation_deg=20, sun_azimuth_deg=93, sun_to_sky=1e6,
                                  sun_radius_deg=0.5)
    row, col = np.unravel_index(np.argmax(env[..., 1]), env.shape[:2])
    e, a = math.radians(20), math.radians(93)
    u, v = direction_to_uv(np.array([math.cos(e) * math.sin(a), math.sin(e), -math.cos(e) * math.cos(a)]))
    assert (col, row) == (int(u * 256), int(v * 128))


# --- camera frame ---------------------------------------------------------------------------------

def test_pitch_moves_the_zenith_toward_the_viewer():
    env = np.zeros((64, 128, 3), np.float32)
    env[0] = 1.0  # the top row: straight up
    turned = lighting.pitch_environment(env, 30.0)
    row, col = np.unravel_index(np.argmax(turned[..., 0]), turned.shape[:2])
    # (0, cos 30, sin 30): theta = 30 deg, toward +Z (u = 0 or 1)
    assert row == pytest.approx(30 / 180 * 64 - 0.5, abs=1.0)
    assert min(col, 128 - col) <= 1


def test_camera_rotation_turns_plus_x_toward_minus_z():
    assert lighting.camera_rotation(0.0, 90.0) @ np.array([1.0, 0, 0]) == pytest.approx([0, 0, -1])


def test_camera_settings_of_a_group_are_distinct_grid_points():
    settings = [scenes.camera_setting(0, "train", i, 6) for i in range(6)]
    assert len(set(settings)) == 6
    assert all(s in scenes.CAMERA_SETTINGS for s in settings)


def test_sample_scene_is_deterministic():
    hdris = ("a.hdr", "b.hdr", "c.hdr")
    assert scenes.sample_scene(3, "val", 17, hdris) == scenes.sample_scene(3, "val", 17, hdris)


def test_a_yaw_offset_turns_the_camera_and_changes_nothing_else():
    from dataclasses import replace

    hdris = ("a.hdr", "b.hdr", "c.hdr")
    front = scenes.sample_scene(3, "test", 5, hdris)
    back = scenes.sample_scene(3, "test", 5, hdris, yaw_offset_deg=180.0)
    assert back.yaw_deg == front.yaw_deg + 180.0
    assert replace(back, yaw_deg=front.yaw_deg) == front


def test_frame_rect_centres_the_person_with_the_fill():
    points = np.array([[0.0, 0.0], [0.5, 2.0]])
    x0, x1, y0, y1 = scenes.frame_rect(points, scale=1.0)
    assert ((x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0) == pytest.approx(
        (0.25, 1.0, 2.0 / scenes.FRAME_FILL, 2.0 / scenes.FRAME_FILL))


# --- camera model ----------------------------------------------------------------------------------

def test_auto_exposure_maps_the_metering_percentile_to_the_key():
    image = np.linspace(0.01, 4.0, 300, dtype=np.float32).reshape(10, 10, 3)
    mask = np.ones((10, 10), bool)
    k = camera_model.auto_exposure(image, mask, 0.9)
    brightest = (image * k).max(axis=-1)
    assert np.percentile(brightest, camera_model.METERING_PERCENTILE) == pytest.approx(0.9, rel=1e-5)


def test_auto_exposure_clips_at_most_the_metered_share():
    image = np.random.default_rng(1).uniform(0, 3, (40, 40, 3)).astype(np.float32)
    k = camera_model.auto_exposure(image, np.ones((40, 40), bool), 1.0)
    clipped = (image * k > 1.0).any(axis=-1).mean()
    assert clipped <= 1 - camera_model.METERING_PERCENTILE / 100 + 1e-3


def test_photograph_is_the_quantised_srgb_of_the_clipped_exposed_image():
    radiance = np.linspace(0.0, 3.0, 3 * 64, dtype=np.float32).reshape(8, 8, 3)
    photo = camera_model.photograph(radiance, 0.7)
    expected = np.round(linear_to_srgb(np.clip(radiance * np.float32(0.7), 0, 1)) * 255)
    assert photo.dtype == np.uint8 and np.array_equal(photo, expected.astype(np.uint8))


# --- rendering (a sphere) ---------------------------------------------------------------------------

def test_image_is_albedo_times_shading_exactly(sphere_sample):
    arrays, _ = sphere_sample
    assert np.array_equal(arrays["image_a"], arrays["albedo"] * arrays["shading_a"])


def test_relit_is_albedo_times_shading_b_exactly(sphere_sample):
    arrays, _ = sphere_sample
    assert np.array_equal(arrays["relit_b"], arrays["albedo"] * arrays["shading_b"])


def test_ao_is_in_unit_interval(sphere_sample):
    ao = sphere_sample[0]["ao"]
    assert ao.min() >= 0.0 and ao.max() <= 1.0


def test_unoccluded_sphere_has_ao_one(sphere_sample):
    arrays, _ = sphere_sample
    # a few cosine rays of an interpolated normal dip below a facet and count as blocked
    ao = arrays["ao"][arrays["mask"] > 0]
    assert np.median(ao) == 1.0 and ao.mean() > 0.99


def test_normals_are_unit_in_the_mask_and_zero_outside(sphere_sample):
    arrays, _ = sphere_sample
    inside = arrays["mask"] > 0
    for name in ("normal", "back_normal"):
        length = np.linalg.norm(arrays[name], axis=-1)
        assert length[inside] == pytest.approx(1.0, abs=1e-4)
        assert np.all(length[~inside] == 0)


def test_front_and_back_depth_match_the_sphere(sphere_sample):
    arrays, _ = sphere_sample
    x0, x1, y0, y1 = arrays["rect"]
    n = arrays["mask"].shape[0]
    x = x0 + (np.arange(n) + 0.5) * (x1 - x0) / n
    y = y1 - (np.arange(n) + 0.5) * (y1 - y0) / n
    xx, yy = np.meshgrid(x, y)
    inside = arrays["mask"] > 0
    # with pitch 0 and yaw 0 the camera frame is the world frame: the sphere is at CENTRE
    half = np.sqrt(np.maximum(RADIUS ** 2 - xx ** 2 - (yy - CENTRE[1]) ** 2, 0.0))
    # the icosphere's flat facets sit inside the true sphere by up to ~1 % of the radius
    assert arrays["front_depth"][inside] == pytest.approx(half[inside], abs=0.02)
    assert arrays["back_depth"][inside] == pytest.approx(-half[inside], abs=0.02)


def test_back_normals_face_away_from_the_camera(sphere_sample):
    arrays, _ = sphere_sample
    inside = arrays["mask"] > 0
    assert np.all(arrays["back_normal"][inside][:, 2] <= 1e-6)
    assert np.all(arrays["normal"][inside][:, 2] >= -1e-6)


def test_input_clean_is_the_quantised_photo_of_image_a(sphere_sample):
    arrays, _ = sphere_sample
    covered = arrays["coverage"] == 1.0  # edge pixels blend with black
    expected = np.round(linear_to_srgb(np.clip(arrays["image_a"], 0, 1)) * 255).astype(np.uint8)
    assert np.array_equal(arrays["input_clean"][covered], expected[covered])


def test_input_clean_is_black_off_the_silhouette(sphere_sample):
    arrays, _ = sphere_sample
    assert np.all(arrays["input_clean"][arrays["coverage"] == 0] == 0)


def test_input_without_augmentation_equals_the_clean_photo_on_the_person(sphere_sample):
    arrays, _ = sphere_sample
    covered = arrays["coverage"] == 1.0
    assert np.array_equal(arrays["input"][covered], arrays["input_clean"][covered])


def test_coverage_integrates_to_the_disc_area(sphere_sample):
    arrays, _ = sphere_sample
    x0, x1, _, _ = arrays["rect"]
    pixel = (x1 - x0) / arrays["mask"].shape[0]
    # an icosphere's outline is a polygon slightly inside the circle
    assert arrays["coverage"].sum() * pixel ** 2 == pytest.approx(math.pi * RADIUS ** 2, rel=0.03)


def test_fill_edges_extends_colour_outside_the_mask():
    image = np.zeros((5, 5, 3), np.float32)
    mask = np.zeros((5, 5), bool)
    image[2, 2], mask[2, 2] = 0.7, True
    filled = camera_model.fill_edges(image, mask, passes=1)
    assert filled[1:4, 1:4] == pytest.approx(0.7) and np.all(filled[0] == 0)


def test_sun_from_plus_x_lights_the_right_half(sphere_sample):
    shading = sphere_sample[0]["shading_a"].mean(axis=2)
    n = shading.shape[1]
    assert shading[:, n // 2:].sum() > 5 * shading[:, :n // 2].sum()


def test_yaw_turns_person_and_light_together():
    # sun behind (-Z); a 90 degree yaw turns it to -X: the image's left half is lit
    spec = sphere_spec(yaw=90.0, light=sky(azimuth=0.0))
    shading = render.render_sample(spec, sphere_person(), SETTINGS)[0]["shading_a"].mean(axis=2)
    n = shading.shape[1]
    assert shading[:, :n // 2].sum() > 5 * shading[:, n // 2:].sum()


def test_light_map_is_the_lighting_times_the_exposure(sphere_sample):
    arrays, meta = sphere_sample
    env = lighting.camera_environment(sky(), 0.0, 0.0)
    from relightcli.io.envmap import gaussian_pyramid_downsample
    expected = gaussian_pyramid_downsample(env, 16) * arrays["exposure"]
    assert arrays["light_a"] == pytest.approx(expected, rel=1e-5)


def test_face_box_bounds_the_projected_face_vertices(sphere_sample):
    arrays, _ = sphere_sample
    person = sphere_person()
    pixels = render.world_to_pixel(person.vertices[person.face_vertex_ids].astype(np.float64),
                                   arrays["rect"], arrays["mask"].shape[0])
    expected = [*pixels.min(axis=0), *pixels.max(axis=0)]
    assert arrays["face_box"] == pytest.approx(expected, abs=1e-3)


def test_face_box_is_minus_one_when_the_face_looks_away():
    person = sphere_person()
    person.face_vertex_ids = np.flatnonzero(person.vertices[:, 2] < -0.8 * RADIUS)
    box = render.render_sample(sphere_spec(), person, SETTINGS)[0]["face_box"]
    assert np.all(box == -1)


def test_second_bounce_keeps_image_equal_to_albedo_times_shading():
    settings = render.RenderSettings(resolution=32, spp=8, target_error=None, ao_spp=4, bounces=2)
    arrays, _ = render.render_sample(sphere_spec(), sphere_person(), settings)
    assert np.array_equal(arrays["image_a"], arrays["albedo"] * arrays["shading_a"])
