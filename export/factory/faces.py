"""Synthetic face crops with exact 68-point landmarks (issue 6), on which
`python -m export.face_correspondence` measures the face mesh -> iBUG table.

One sample = the shipped ICT face model (`models/face_model.npz`) with random identity,
expression, head pose and look (`face_look.py`), lit by an environment map, framed in a
128x128 crop the way the runtime frames a detected face, photographed (exposure, white
balance, blur, noise, sRGB 8-bit, sometimes JPEG). Ground truth: the 68 landmark vertices
projected into the crop, (col, row) with pixel (i, j)'s centre at (j, i) (DESIGN.md).

Shape and pose
- identity ~ N(0, 1) per mode (the fit's prior), clipped at +-2.5 sigma;
- expressions: none (30 %) or 1-4 random blendshapes with weights U(0, 1) (the fit bounds
  them to [0, 1] with prior sigma 0.5: sparse and rare);
- pose: yaw U(-40, 40), pitch U(-25, 25), roll U(-20, 20) degrees (`rotation_matrix`).
Framing: the crop's side is `crop_scale` x the larger side of the landmarks' bounding box,
its centre shifted by `crop_shift` x the side; both ranges cover what the former OpenCV
cascade + `face_crop_rect` produced (measured, see FRAMING).

Lighting: the split's HDRIs (`lighting.hdri_splits`: test lighting never seen in training)
or a procedural sun + sky (25 %), area-resampled to 128 x 256, turned about +Y by any angle
and tilted by up to +-20 degrees. Shading: the project's integrator (`shade_environment`:
MIS with the sun sampled on its own and the unoccluded-shading control variate) at 4 samples
per pixel on a 2x supersampled grid (16 per output pixel), blurred by one fine pixel inside
the head (a cheap denoiser). The ray tracer rather than SH-9 irradiance because SH has no
visibility: under a hard sun a photo shows the nose's cast shadow, dark eye sockets and a
shadowed neck, which a landmark net must not mistake for features. Cost: ~0.15 s of the
~0.35 s a sample takes on one core (the rest: Embree scene, primary rays, painting).
Background: a view of the same environment, smooth noise, or a flat colour, with a hair blob
behind the head and a garment-coloured torso below, so the silhouette is not always clean.
Photo: auto-exposure metered on the face, white-balance jitter, blur, noise (each p = 0.5,
`camera_model.sample_augmentation`), half the faces shrunk to 28-110 px and enlarged back
(a face in a full-body crop is that small before `face_crop_rect` enlarges it), sRGB 8-bit,
JPEG (quality 40-95) with p = 0.3.
"""

from __future__ import annotations

import functools
import time
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from export.factory import albedo as body_albedo
from export.factory import camera_model, lighting
from export.factory.face_look import FaceLook, paint, sample_look
from relightcli.geometry.face_model import FaceModel, rotation_matrix, transform, world_to_pixel
from relightcli.io.envmap import environment_view, load_envmap, resample_envmap, rotate_envmap
from relightcli.render import EnvironmentLight, PixelGeometry, Scene, pixel_centres, shade_environment
from relightcli.render.scene import orient_normals

CROP = 128
SUPERSAMPLE = 2
SPP = 4
SHADING_BLUR_PX = 1.0          # fine pixels
ENV_HEIGHT = 128
POSE_LIMITS_DEG = (40.0, 25.0, 20.0)      # |yaw|, |pitch|, |roll|
IDENTITY_CLIP = 2.5
EXPRESSION_FREE = 0.3                     # share of samples with no expression at all
LIGHT_TILT_DEG = 20.0
# Framing of the crop around the landmarks' bounding box: side = scale x its larger side,
# centre moved by (shift x, shift y) x side (x right, y up). Covers the former cascade +
# face_crop_rect framing measured on renders (40 renders: scale
# 1.73-2.39, median 2.11; shift x -0.12..0.11, y 0.04..0.12: the box includes the forehead).
FRAMING = {"scale": (1.6, 2.6), "shift_x": (-0.13, 0.13), "shift_y": (-0.03, 0.16)}
# The framing of the runtime's face crop around landmarks (the measured median;
# relightcli.geometry.face.face_box_around)
CANONICAL_FRAMING = {"scale": 2.1, "shift": (0.0, 0.08)}
# Faces in a full-body crop span only 25-60 px before face_crop_rect enlarges them to 128
LOW_RES_PROBABILITY = 0.5
LOW_RES_SIDE = (28, 110)
JPEG_PROBABILITY = 0.3


@dataclass(frozen=True)
class FaceSpec:
    """Everything random about one sample (reproducible from its seed)."""

    identity: tuple
    expression: tuple
    angles_deg: tuple          # yaw, pitch, roll
    crop_scale: float
    crop_shift: tuple
    look: FaceLook
    light: lighting.LightingSpec
    light_turn_deg: float      # about +Y, any angle
    light_tilt_deg: float
    background: str            # "environment", "noise" or "flat"
    background_fov_deg: float
    hair_blob: float           # 0: none, else its size relative to the head
    torso: bool
    exposure_key: float
    augmentation: camera_model.Augmentation
    jpeg_quality: int          # 0: no JPEG
    source_side: int           # 0: none, else the photo is shrunk to this side and enlarged back
    seed: int

    def as_dict(self) -> dict:
        out = asdict(self)
        out["look"], out["light"] = self.look.as_dict(), self.light.as_dict()
        out["augmentation"] = self.augmentation.as_dict()
        return out


def sample_spec(rng: np.random.Generator, model: FaceModel, hdris: tuple[str, ...]) -> FaceSpec:
    """A random sample of the distribution in the module docstring."""
    identity = np.clip(rng.normal(size=model.n_identity), -IDENTITY_CLIP, IDENTITY_CLIP)
    expression = np.zeros(model.n_expression)
    if rng.random() >= EXPRESSION_FREE:
        chosen = rng.choice(model.n_expression, size=int(rng.integers(1, 5)), replace=False)
        expression[chosen] = rng.uniform(0.0, 1.0, chosen.size)
    angles = tuple(float(rng.uniform(-a, a)) for a in POSE_LIMITS_DEG)
    background = str(rng.choice(["environment", "noise", "flat"], p=[0.5, 0.3, 0.2]))
    return FaceSpec(
        identity=tuple(float(v) for v in identity), expression=tuple(float(v) for v in expression),
        angles_deg=angles, crop_scale=float(rng.uniform(*FRAMING["scale"])),
        crop_shift=(float(rng.uniform(*FRAMING["shift_x"])), float(rng.uniform(*FRAMING["shift_y"]))),
        look=sample_look(rng), light=lighting.sample_lighting(rng, hdris),
        light_turn_deg=float(rng.uniform(0.0, 360.0)),
        light_tilt_deg=float(rng.uniform(-LIGHT_TILT_DEG, LIGHT_TILT_DEG)),
        background=background, background_fov_deg=float(rng.uniform(30.0, 80.0)),
        hair_blob=float(rng.uniform(1.0, 1.5)) if rng.random() < 0.6 else 0.0,
        torso=bool(rng.random() < 0.7), exposure_key=float(rng.uniform(0.5, 0.95)),
        augmentation=camera_model.sample_augmentation(rng),
        jpeg_quality=int(rng.integers(40, 96)) if rng.random() < JPEG_PROBABILITY else 0,
        source_side=int(rng.integers(*LOW_RES_SIDE)) if rng.random() < LOW_RES_PROBABILITY else 0,
        seed=int(rng.integers(2 ** 31)))


# --- geometry ------------------------------------------------------------------------------

def posed_face(model: FaceModel, spec: FaceSpec):
    """(vertices (V, 3), landmarks (68, 3)) float64 in the camera frame, cm: the model turned
    by the spec's angles about its origin (scale 1, no translation)."""
    rotation = rotation_matrix(*spec.angles_deg)
    identity, expression = np.asarray(spec.identity), np.asarray(spec.expression)
    vertices = transform(model.vertices(identity, expression), 1.0, rotation, np.zeros(3))
    landmarks = transform(model.landmarks(identity, expression), 1.0, rotation, np.zeros(3))
    return vertices, landmarks


def crop_rect(landmarks, scale: float, shift=(0.0, 0.0)) -> tuple:
    """(x0, x1, y0, y1) square around the landmarks' x-y bounding box: side = scale x its
    larger side, centre moved by shift x side (x right, y up)."""
    lo, hi = landmarks[:, :2].min(axis=0), landmarks[:, :2].max(axis=0)
    side = scale * float(np.max(hi - lo))
    cx, cy = (lo + hi) / 2.0 + np.asarray(shift) * side
    return (cx - side / 2, cx + side / 2, cy - side / 2, cy + side / 2)


def trace_surface(scene: Scene, rect, resolution: int):
    """One -Z ray per pixel: (PixelGeometry for the integrator, triangle ids (N,), corner
    weights (N, 3)); N = resolution ** 2 in row-major order, triangle -1 for a miss."""
    centres = pixel_centres(rect, (resolution, resolution)).reshape(-1, 2)
    origins = np.empty((centres.shape[0], 3))
    origins[:, :2] = centres - scene.centre[:2]
    origins[:, 2] = scene.bounds_local[1, 2] + 0.01 * scene.diagonal
    directions = np.tile([0.0, 0.0, -1.0], (origins.shape[0], 1))
    hits = scene.intersect(origins, directions)
    shading_normal, geometric = orient_normals(hits.geometric_normal, scene.shading_normals(hits),
                                               directions)
    miss = ~hits.hit[:, None]
    shape = (resolution, resolution)
    position = origins + hits.t[:, None].astype(np.float64) * directions
    geometry = PixelGeometry(
        mask=hits.hit.reshape(shape),
        position=np.where(miss, 0.0, position).astype(np.float32).reshape(shape + (3,)),
        normal=np.where(miss, 0.0, shading_normal).astype(np.float32).reshape(shape + (3,)),
        geometric_normal=np.where(miss, 0.0, geometric).astype(np.float32).reshape(shape + (3,)),
        rect=tuple(float(c) for c in rect))
    b1, b2 = hits.bary[:, 0].astype(np.float64), hits.bary[:, 1].astype(np.float64)
    weights = np.stack([1.0 - b1 - b2, b1, b2], axis=1)
    return geometry, hits.prim, weights


# --- lighting and background -------------------------------------------------------------

@functools.lru_cache(maxsize=64)
def _small_hdri(name: str) -> np.ndarray:
    env = resample_envmap(load_envmap(lighting.hdri_dir() / name), ENV_HEIGHT)
    env.setflags(write=False)
    return env


def camera_environment(spec: FaceSpec) -> np.ndarray:
    """(128, 256, 3) float32 linear radiance of the sample's lighting in the camera frame."""
    if spec.light.kind == "hdri":
        env = _small_hdri(spec.light.name)
    else:
        env = lighting.procedural_sky(ENV_HEIGHT, **spec.light.params)
    env = rotate_envmap(env, spec.light_turn_deg)
    return lighting.pitch_environment(env, spec.light_tilt_deg)


def background_plate(spec: FaceSpec, env, rng: np.random.Generator, level: float) -> np.ndarray:
    """(CROP, CROP, 3) linear radiance behind the head; `level` is the face's mean radiance,
    which the synthetic plates are scaled to (the environment view keeps its own)."""
    if spec.background == "environment":
        yaw = float(rng.uniform(-180, 180))
        return environment_view(env, width=CROP, height=CROP, fov_deg=spec.background_fov_deg,
                                yaw_deg=yaw).astype(np.float32)
    colour = body_albedo.random_cloth_colour(rng) * np.float32(level * rng.uniform(0.3, 2.0))
    if spec.background == "flat":
        ramp = np.linspace(rng.uniform(0.6, 1.0), rng.uniform(0.6, 1.0), CROP, dtype=np.float32)
        return colour[None, None, :] * ramp[:, None, None] * np.ones((1, CROP, 1), np.float32)
    noise = body_albedo.smooth_noise(rng, CROP)[..., None]
    other = body_albedo.random_cloth_colour(rng) * np.float32(level * rng.uniform(0.3, 2.0))
    return (colour * noise + other * (1.0 - noise)).astype(np.float32)


def _ellipse_alpha(rect, centre_cm, radii_cm, size: int) -> np.ndarray:
    """(size, size) float32 soft ellipse of the crop (centre and radii in camera cm)."""
    centres = pixel_centres(rect, (size, size))
    d = ((centres[..., 0] - centre_cm[0]) / radii_cm[0]) ** 2 + ((centres[..., 1] - centre_cm[1]) / radii_cm[1]) ** 2
    return np.clip((1.15 - d) / 0.3, 0.0, 1.0).astype(np.float32)


def add_hair_and_torso(plate, spec: FaceSpec, rect, level: float, rng) -> np.ndarray:
    """Paint a dark hair blob behind the head top and a garment-coloured torso below the
    neck into the background plate (both in camera cm, so they follow the framing)."""
    rotation = rotation_matrix(*spec.angles_deg)
    out = plate
    if spec.torso:
        centre = np.array([0.0, -27.0, -4.0]) @ rotation_matrix(spec.angles_deg[0] * 0.3, 0, 0).T
        alpha = _ellipse_alpha(rect, centre, (22.0, 13.0), CROP)
        cloth = body_albedo.random_cloth_colour(rng) * np.float32(level * rng.uniform(0.4, 1.2))
        out = out * (1 - alpha[..., None]) + cloth * alpha[..., None]
    if spec.hair_blob:
        centre = rotation @ np.array([0.0, 5.0 - 6.0 * (spec.hair_blob - 1.0), -3.0])
        radii = (11.0 * spec.hair_blob, 12.0 * spec.hair_blob)
        alpha = _ellipse_alpha(rect, centre, radii, CROP) * np.float32(rng.uniform(0.7, 1.0))
        hair = np.asarray(spec.look.hair, np.float32) * np.float32(level * rng.uniform(0.5, 1.0))
        texture = 0.8 + 0.4 * body_albedo.smooth_noise(rng, CROP, (8, 16, 32, 64))[..., None]
        out = out * (1 - alpha[..., None]) + hair * texture * alpha[..., None]
    return out.astype(np.float32)


# --- one sample ----------------------------------------------------------------------------

def render_face(model: FaceModel, spec: FaceSpec) -> dict:
    """The photo and its ground truth. Returns image (128, 128, 3) uint8 sRGB; landmarks
    (68, 2) float32 (col, row) pixels; rect (4,) float32 cm of the crop; seconds."""
    start = time.perf_counter()
    rng = np.random.default_rng(spec.seed)
    vertices, landmarks = posed_face(model, spec)
    rect = crop_rect(landmarks, spec.crop_scale, spec.crop_shift)
    fine = CROP * SUPERSAMPLE
    scene = Scene(vertices, model.triangles)
    geometry, triangles, weights = trace_surface(scene, rect, fine)
    hit = triangles >= 0
    albedo = np.zeros((fine * fine, 3), np.float32)
    albedo[hit] = paint(model, spec.look, triangles[hit], weights[hit])
    env = camera_environment(spec)
    shading = shade_environment(scene, geometry, EnvironmentLight(env), spp=SPP, min_spp=2,
                                sampler="independent", seed=spec.seed).mean
    radiance = albedo.reshape(fine, fine, 3) * smooth_inside(shading, geometry.mask)
    # 2x2 box filter: premultiplied colour and coverage of each output pixel
    subject = radiance.reshape(CROP, SUPERSAMPLE, CROP, SUPERSAMPLE, 3).mean(axis=(1, 3))
    coverage = _box_filter(hit)
    # Meter on the face proper (a photographer exposes for the face, not a lit ear or neck)
    face = _box_filter(hit & np.all(model.face_region[model.triangles[triangles]], axis=1)) > 0.5
    if not face.any():
        face = np.ones_like(face)
    level = float(subject[face].mean())
    plate = add_hair_and_torso(background_plate(spec, env, rng, level), spec, rect, level, rng)
    image = subject + plate * (1.0 - coverage[..., None])
    photo = photograph(image, camera_model.auto_exposure(image, face, spec.exposure_key), spec)
    pixels = world_to_pixel(landmarks, rect, (CROP, CROP))
    scene.close()
    return {"image": photo, "landmarks": pixels.astype(np.float32),
            "rect": np.asarray(rect, np.float32), "seconds": time.perf_counter() - start}


def photograph(image, exposure: float, spec: FaceSpec) -> np.ndarray:
    """(CROP, CROP, 3) linear radiance -> the uint8 sRGB photo: maybe shrunk and enlarged back
    (a small face, enlarged as compose.crop_square does it: area down, bilinear up), exposed,
    augmented, encoded, maybe JPEG-compressed."""
    if spec.source_side:
        small = cv2.resize(image, (spec.source_side, spec.source_side), interpolation=cv2.INTER_AREA)
        image = cv2.resize(small, (CROP, CROP), interpolation=cv2.INTER_LINEAR)
    photo = camera_model.photograph(image, exposure, spec.augmentation)
    if spec.jpeg_quality:
        _, encoded = cv2.imencode(".jpg", photo[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, spec.jpeg_quality])
        photo = cv2.imdecode(encoded, cv2.IMREAD_COLOR)[..., ::-1]
    return np.ascontiguousarray(photo)


def smooth_inside(shading, mask, sigma: float = SHADING_BLUR_PX) -> np.ndarray:
    """Gaussian blur of (H, W, 3) shading that mixes only pixels inside `mask` (H, W)
    (normalised convolution): a cheap denoiser for the low sample count; shading varies
    slowly except at shadow edges, which move by less than a fine pixel."""
    weight = mask.astype(np.float32)
    num = cv2.GaussianBlur(shading * weight[..., None], (0, 0), sigma)
    den = cv2.GaussianBlur(weight, (0, 0), sigma)[..., None]
    return np.where(den > 1e-6, num / np.maximum(den, 1e-6), 0.0).astype(np.float32)


def _box_filter(values) -> np.ndarray:
    """(CROP, CROP) float32 mean of each SUPERSAMPLE x SUPERSAMPLE block of the fine
    (row-major, flattened) per-ray values."""
    blocks = np.asarray(values, np.float32).reshape(CROP, SUPERSAMPLE, CROP, SUPERSAMPLE)
    return blocks.mean(axis=(1, 3))
