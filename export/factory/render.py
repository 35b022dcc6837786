"""Render every map of one sample with the project's integrator (relightcli.render).

The person is turned into the camera frame (camera_rotation(pitch, yaw)), framed by
scenes.frame_rect, and traced by the orthographic camera of DESIGN.md along -Z; the lightings
are turned the same way (lighting.camera_environment), so image, maps and lighting agree.

Outputs (`render_sample`): float32 linear maps, HDR ones multiplied by the photo's exposure
factor k (the dataset contract, DATASET_CONTRACT.md):
  image_a = albedo * shading_a exactly (shading_a includes the second bounce when enabled),
  relit_b = albedo * shading_b, light_a / light_b = 16x32 Gaussian-pyramid lightings x k,
  input (uint8 sRGB photo over a background), input_clean (uint8, over black), mask, albedo,
  normal, back_normal, front_depth, back_depth, ao, rect, face_box, exposure, and (beyond
  the contract) coverage: the share of each pixel the person covers (2x2 rays), used to
  composite the photo with anti-aliased edges; "mask" is the pixel-centre hit, like every map.
Lighting B is scaled to the luminous energy of lighting A before anything (its gain is in
the metadata), so relit_b is exposed like the photo.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from relightcli.io.envmap import envmap_energy, gaussian_pyramid_downsample
from relightcli.io.images import LUMINANCE
from relightcli.render.camera import pixel_centres, render_pixel_geometry
from relightcli.render.environment import EnvironmentLight
from relightcli.render.integrator import ambient_occlusion, shade_environment
from relightcli.render.scene import Scene, orient_normals

from . import camera_model, lighting
from .albedo import sample_texture
from .scenes import SceneSpec, frame_rect

LIGHT_HEIGHT = 16
# A face vertex is visible when it lies within this many metres of the front surface
FACE_DEPTH_TOLERANCE = 0.015
# ... and a face box is given when at least this share of the face vertices is visible
FACE_VISIBLE_SHARE = 0.3


@dataclass(frozen=True)
class RenderSettings:
    """resolution: square side in pixels. spp: cap of shading passes per pixel, sampled until
    the relative standard error reaches target_error (None: always spp); min_spp: first
    adaptive round. ao_spp: AO passes. bounces: 1 (direct) or 2 (plus one interreflection).
    hdri_folder: None for lighting.hdri_dir()."""

    resolution: int = 512
    spp: int = 64
    target_error: float | None = 0.03
    min_spp: int = 16
    ao_spp: int = 32
    bounces: int = 2
    hdri_folder: str | None = None

    def as_dict(self) -> dict:
        return asdict(self)


def camera_vertices(vertices, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """World vertices (V, 3) -> camera frame (V, 3) float64 (lighting.camera_rotation)."""
    return np.asarray(vertices, dtype=np.float64) @ lighting.camera_rotation(pitch_deg, yaw_deg).T


def trace_pixels(scene: Scene, rect, resolution: int, towards_viewer: bool = False):
    """One orthographic ray per pixel, along -Z (front) or +Z (`towards_viewer`, from behind:
    its first hit is the last surface along the -Z ray). Returns (hits, directions (N, 3),
    world points (N, 3) float64), N = resolution ** 2 in row-major pixel order."""
    centres = pixel_centres(rect, (resolution, resolution)).reshape(-1, 2)
    lo, hi = scene.bounds_local
    z_start = (lo[2] - 0.01 * scene.diagonal) if towards_viewer else (hi[2] + 0.01 * scene.diagonal)
    origins = np.empty((centres.shape[0], 3))
    origins[:, :2] = centres - scene.centre[:2]
    origins[:, 2] = z_start
    directions = np.tile([0.0, 0.0, 1.0 if towards_viewer else -1.0], (origins.shape[0], 1))
    hits = scene.intersect(origins, directions)
    points = scene.to_world(origins + hits.t[:, None].astype(np.float64) * directions)
    return hits, directions, points


def surface_albedo(face_uv, texture, hits) -> np.ndarray:
    """Albedo (N, 3) float32 linear at hits: corner UVs interpolated with the barycentrics,
    then the atlas sampled bilinearly; zero for misses."""
    prim = np.where(hits.hit, hits.prim, 0)
    corners = face_uv[prim]  # (N, 3, 2)
    b1, b2 = hits.bary[:, 0:1], hits.bary[:, 1:2]
    uv = (1.0 - b1 - b2) * corners[:, 0] + b1 * corners[:, 1] + b2 * corners[:, 2]
    return np.where(hits.hit[:, None], sample_texture(texture, uv), 0.0).astype(np.float32)


def back_surface(scene: Scene, rect, resolution: int):
    """Last surface along each pixel's -Z ray: (back_depth (H, W) float32 world z,
    back_normal (H, W, 3) float32 unit, facing away from the camera (toward -Z rays'
    exit side), mask (H, W) bool). Zero where nothing is hit."""
    hits, directions, points = trace_pixels(scene, rect, resolution, towards_viewer=True)
    normal, _ = orient_normals(hits.geometric_normal, scene.shading_normals(hits), directions)
    shape = (resolution, resolution)
    miss = ~hits.hit
    depth = np.where(miss, 0.0, points[:, 2]).astype(np.float32).reshape(shape)
    normal = np.where(miss[:, None], 0.0, normal).astype(np.float32).reshape(shape + (3,))
    return depth, normal, hits.hit.reshape(shape)


def silhouette_coverage(scene: Scene, rect, resolution: int, subpixels: int = 2) -> np.ndarray:
    """(H, W) float32 share of each pixel covered by the person: subpixels x subpixels rays
    per pixel (the pixel grid of a subpixels-times finer image of the same rectangle)."""
    hits, _, _ = trace_pixels(scene, rect, resolution * subpixels)
    fine = hits.hit.reshape(resolution, subpixels, resolution, subpixels)
    return fine.mean(axis=(1, 3)).astype(np.float32)


def world_to_pixel(points, rect, resolution: int) -> np.ndarray:
    """Camera-frame points (N, >= 2) -> continuous pixel coordinates (N, 2) (col, row); pixel
    (i, j) covers [j, j + 1) x [i, i + 1), its centre at (j + 0.5, i + 0.5)."""
    x0, x1, y0, y1 = rect
    col = (points[:, 0] - x0) / (x1 - x0) * resolution
    row = (y1 - points[:, 1]) / (y1 - y0) * resolution
    return np.stack([col, row], axis=1)


def face_box(face_points, rect, resolution: int, front_depth, mask) -> np.ndarray:
    """(4,) float32 x0, y0, x1, y1 in pixels of the visible face vertices (camera frame
    (K, 3)), all -1 when fewer than FACE_VISIBLE_SHARE of them are visible (depth test
    against front_depth (H, W))."""
    pixels = world_to_pixel(face_points, rect, resolution)
    cols = np.clip(pixels[:, 0].astype(np.int64), 0, resolution - 1)
    rows = np.clip(pixels[:, 1].astype(np.int64), 0, resolution - 1)
    inside = (pixels >= 0).all(axis=1) & (pixels < resolution).all(axis=1)
    seen = inside & mask[rows, cols] & (face_points[:, 2] >= front_depth[rows, cols]
                                        - FACE_DEPTH_TOLERANCE)
    if face_points.shape[0] == 0 or seen.mean() < FACE_VISIBLE_SHARE:
        return np.full(4, -1.0, np.float32)
    lo, hi = pixels[seen].min(axis=0), pixels[seen].max(axis=0)
    return np.clip(np.array([lo[0], lo[1], hi[0], hi[1]]), 0, resolution).astype(np.float32)


def _energy_luminance(env) -> float:
    return float(envmap_energy(env) @ LUMINANCE)


def sample_environments(spec: SceneSpec, settings: RenderSettings):
    """(env_a, env_b, b_gain, background env): camera-frame (H, 2H, 3) float32 maps; env_b
    already multiplied by b_gain = energy(A) / energy(B) (luminance)."""
    folder = settings.hdri_folder
    env_a = lighting.camera_environment(spec.lighting_a, spec.pitch_deg, spec.yaw_deg, folder)
    env_b = lighting.camera_environment(spec.lighting_b, spec.pitch_deg, spec.yaw_deg, folder)
    energy_b = _energy_luminance(env_b)
    gain = _energy_luminance(env_a) / energy_b if energy_b > 0 else 1.0
    if spec.background == spec.lighting_a:
        background = env_a
    else:
        background = lighting.camera_environment(spec.background, spec.pitch_deg, spec.yaw_deg,
                                                 folder)
    return env_a, (env_b * np.float32(gain)).astype(np.float32), gain, background


def background_plate_for(spec, env_a, background_env, size):
    """The background plate (size, size, 3) linear radiance; a borrowed HDRI is scaled so
    its median luminance matches that of lighting A's own view."""
    plate = camera_model.background_plate(background_env, size, size, spec.background_fov_deg)
    if background_env is env_a:
        return plate
    own = camera_model.background_plate(env_a, size, size, spec.background_fov_deg)
    level = np.median(camera_model.luminance(plate))
    return plate * np.float32(np.median(camera_model.luminance(own)) / max(level, 1e-12))


def shade(scene, geometry, env, settings, albedo, seed):
    """The integrator's result for one lighting at the settings' effort (the albedo feeds the
    second bounce when settings.bounces == 2)."""
    return shade_environment(scene, geometry, EnvironmentLight(env), spp=settings.spp,
                             target_error=settings.target_error, min_spp=settings.min_spp,
                             bounces=settings.bounces,
                             albedo=albedo if settings.bounces == 2 else 1.0, seed=seed)


def _stats(result) -> dict:
    passes = result.passes[result.mask]
    return {"median_relative_error": round(result.median_relative_error(), 5),
            "mean_spp": round(float(passes.mean()) if passes.size else 0.0, 2),
            "seconds": round(result.seconds, 3), "strategy": result.strategy}


def render_geometry(person, spec: SceneSpec, resolution: int, rect=None):
    """Scene, pixel geometry and the geometric maps of a person in the sample's camera; rect:
    the world square (x0, x1, y0, y1) seen, by default the sample's framing of the person.
    Returns (scene, geometry, maps dict, camera-frame vertices)."""
    vertices = camera_vertices(person.vertices, spec.pitch_deg, spec.yaw_deg)
    rect = frame_rect(vertices[:, :2], spec.scale) if rect is None else tuple(float(v) for v in rect)
    scene = Scene(vertices, person.faces)
    geometry = render_pixel_geometry(scene, rect, (resolution, resolution))
    hits, _, points = trace_pixels(scene, rect, resolution)
    shape = (resolution, resolution)
    mask = geometry.mask & hits.hit.reshape(shape)
    albedo = surface_albedo(person.face_uv, person.texture, hits).reshape(shape + (3,))
    front = np.where(mask, points[:, 2].reshape(shape), 0.0).astype(np.float32)
    back_depth, back_normal, _ = back_surface(scene, rect, resolution)
    maps = {"mask": mask.astype(np.float32), "albedo": albedo * mask[..., None],
            "normal": geometry.normal * mask[..., None], "front_depth": front,
            "back_depth": back_depth * mask, "back_normal": back_normal * mask[..., None],
            "rect": np.asarray(rect, np.float32)}
    maps["face_box"] = face_box(vertices[person.face_vertex_ids], rect, resolution, front, mask)
    maps["coverage"] = silhouette_coverage(scene, rect, resolution)
    return scene, geometry, maps, vertices


def render_sample(spec: SceneSpec, person, settings: RenderSettings = RenderSettings()):
    """All maps of one sample. Returns (arrays: dict name -> np.ndarray, meta: dict)."""
    start = time.perf_counter()
    res = settings.resolution
    scene, geometry, maps, _ = render_geometry(person, spec, res)
    env_a, env_b, gain_b, background_env = sample_environments(spec, settings)
    seed = 4 * spec.index
    ao = ambient_occlusion(scene, geometry, spp=settings.ao_spp, seed=seed + 1)
    shading_a = shade(scene, geometry, env_a, settings, maps["albedo"], seed + 2)
    shading_b = shade(scene, geometry, env_b, settings, maps["albedo"], seed + 3)
    k = camera_model.auto_exposure(maps["albedo"] * shading_a.mean, maps["mask"] > 0,
                                   spec.exposure_key)
    kf = np.float32(k)
    # everything in exposed units from here: image_a is exactly albedo * shading_a
    arrays = dict(maps)
    arrays.update({"shading_a": shading_a.mean * kf, "shading_b": shading_b.mean * kf,
                   "ao": np.clip(ao.mean[..., 0], 0.0, 1.0).astype(np.float32),
                   "light_a": gaussian_pyramid_downsample(env_a, LIGHT_HEIGHT) * kf,
                   "light_b": gaussian_pyramid_downsample(env_b, LIGHT_HEIGHT) * kf,
                   "exposure": np.float32(k)})
    arrays["image_a"] = maps["albedo"] * arrays["shading_a"]
    arrays["relit_b"] = maps["albedo"] * arrays["shading_b"]
    # the photo: anti-aliased silhouette (coverage), edge pixels coloured by their neighbours
    plate = background_plate_for(spec, env_a, background_env, res) * kf
    subject = camera_model.fill_edges(arrays["image_a"], maps["mask"] > 0)
    coverage = maps["coverage"]
    arrays["input"] = camera_model.photograph(camera_model.composite(subject, coverage, plate),
                                              1.0, spec.augmentation)
    arrays["input_clean"] = camera_model.photograph(subject * coverage[..., None], 1.0)
    meta = {"spec": spec.as_dict(), "settings": settings.as_dict(), "lighting_b_gain": gain_b,
            "exposure": k, "person": _person_meta(person),
            "integrator": {"ao": _stats(ao), "shading_a": _stats(shading_a),
                           "shading_b": _stats(shading_b)},
            "seconds": round(time.perf_counter() - start, 3)}
    return arrays, meta


def _person_meta(person) -> dict:
    keep = ("seed", "split", "pose", "pose_variety", "pose_mix", "outfit", "skin_tone", "hair_colour", "stature_m")
    return {k: person.metadata[k] for k in keep if k in person.metadata}
