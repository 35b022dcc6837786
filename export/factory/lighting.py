"""Lightings of the synthetic dataset: HDRI selection and splits, procedural sun + sky maps,
and the environment as the camera sees it.

Environment maps follow relightcli.io.envmap (DESIGN.md): (H, 2H, 3) float32 linear radiance,
row 0 straight up, the centre column -Z (what the camera looks at).

HDRI split (deterministic, disjoint, stratified): the maps listed in `index.csv` are grouped
by category; inside a category they are ordered by SHA-256("relightcli-split:hdri:<file>"),
the first round(0.15 n) go to test and the next round(0.1 n) to val (none for categories of
fewer than 3 maps), the rest to train. Test lighting is never seen in training.

A lighting is a `LightingSpec`: an HDRI turned about +Y by a multiple of 36 degrees (the
paper's 10 rotations per map), or a procedural sky with a sun disc whose radiance is 1e3 to
1e6 times the sky's median (`procedural_sky`).
"""

from __future__ import annotations

import csv
import functools
import hashlib
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from relightcli.errors import InputError, UsageError
from relightcli.io.images import LUMINANCE
from relightcli.io.envmap import (
    direction_to_uv,
    load_envmap,
    lookup_bilinear,
    rotate_envmap,
    texel_directions,
    texel_solid_angles,
)

SPLITS = ("train", "val", "test")
ROTATION_STEP_DEG = 36.0
ROTATIONS = 10
TEST_FRACTION, VAL_FRACTION = 0.15, 0.10
# Share of lightings that are procedural sun + sky maps rather than HDRIs
SKY_PROBABILITY = 0.25
SKY_HEIGHT = 256
# Sun: radiance / median sky radiance (log-uniform), angular radius (the real sun: 0.27 deg)
SUN_TO_SKY = (1e3, 1e6)
SUN_RADIUS_DEG = (0.27, 1.5)
SUN_ELEVATION_DEG = (5.0, 80.0)


def hdri_dir() -> Path:
    """Folder of the shared HDRIs: $RELIGHT_HDRI_DATA or ../shared/data/hdri."""
    default = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "hdri"
    return Path(os.environ.get("RELIGHT_HDRI_DATA", default)).resolve()


@functools.lru_cache(maxsize=4)
def hdri_catalogue(folder: str | None = None) -> dict[str, str]:
    """file name -> category, read from `index.csv` in the HDRI folder (only files present)."""
    folder = Path(folder) if folder else hdri_dir()
    index = folder / "index.csv"
    if not index.is_file():
        raise InputError("HDRI index not found", path=index,
                         fix="point RELIGHT_HDRI_DATA at the shared hdri folder")
    with open(index, newline="") as handle:
        rows = list(csv.DictReader(handle))
    return {r["file"]: r["category"] for r in rows if (folder / r["file"]).is_file()}


def _split_key(name: str) -> str:
    return hashlib.sha256(f"relightcli-split:hdri:{name}".encode()).hexdigest()


def split_hdris(catalogue: dict[str, str]) -> dict[str, tuple[str, ...]]:
    """split -> sorted HDRI file names; stratified by category (see the module docstring)."""
    out = {split: [] for split in SPLITS}
    for category in sorted(set(catalogue.values())):
        names = sorted((n for n, c in catalogue.items() if c == category), key=_split_key)
        n = len(names)
        n_test = int(math.floor(TEST_FRACTION * n + 0.5)) if n >= 3 else 0
        n_val = int(math.floor(VAL_FRACTION * n + 0.5)) if n >= 3 else 0
        out["test"] += names[:n_test]
        out["val"] += names[n_test:n_test + n_val]
        out["train"] += names[n_test + n_val:]
    return {split: tuple(sorted(names)) for split, names in out.items()}


def hdri_splits(folder: str | None = None) -> dict[str, tuple[str, ...]]:
    """The HDRI split of the shared folder: split -> sorted file names."""
    return split_hdris(hdri_catalogue(None if folder is None else str(folder)))


@dataclass(frozen=True)
class LightingSpec:
    """One lighting, in the world frame (before the camera turns it).

    kind: "hdri" (name = file, rotation_deg a multiple of 36) or "sky" (name = "sky",
    params = procedural_sky keyword arguments). gain: a linear factor on the radiance.
    """

    kind: str
    name: str
    rotation_deg: float = 0.0
    params: dict = field(default_factory=dict)
    gain: float = 1.0

    def as_dict(self) -> dict:
        return asdict(self)


def sample_sky_params(rng: np.random.Generator) -> dict:
    """Random procedural_sky keyword arguments (sun elevation, azimuth, strength, size, tint)."""
    return {
        "sun_elevation_deg": float(rng.uniform(*SUN_ELEVATION_DEG)),
        "sun_azimuth_deg": float(rng.uniform(-180.0, 180.0)),
        "sun_to_sky": float(np.exp(rng.uniform(*np.log(SUN_TO_SKY)))),
        "sun_radius_deg": float(rng.uniform(*SUN_RADIUS_DEG)),
        "haze": float(rng.uniform(0.0, 1.0)),
        "ground_albedo": float(rng.uniform(0.05, 0.35)),
    }


def sample_lighting(rng: np.random.Generator, hdris: tuple[str, ...],
                    sky_probability: float = SKY_PROBABILITY) -> LightingSpec:
    """A random lighting: with `sky_probability` a procedural sky, otherwise one of `hdris`
    turned by a random multiple of 36 degrees."""
    if not hdris and sky_probability < 1.0:
        raise UsageError("no HDRIs to choose from", fix="check the HDRI folder and its split")
    if rng.random() < sky_probability:
        return LightingSpec("sky", "sky", 0.0, sample_sky_params(rng))
    name = str(hdris[int(rng.integers(len(hdris)))])
    return LightingSpec("hdri", name, ROTATION_STEP_DEG * int(rng.integers(ROTATIONS)))


# --- procedural sun + sky -------------------------------------------------------------------

def _sun_colour(elevation_deg: float) -> np.ndarray:
    """Linear RGB of the sun, unit luminance: reddish near the horizon, white high up."""
    t = np.clip(elevation_deg / 30.0, 0.0, 1.0)
    rgb = (1 - t) * np.array([1.0, 0.62, 0.35]) + t * np.array([1.0, 0.96, 0.9])
    return rgb / (rgb @ LUMINANCE)


def _sky_radiance(directions, sun_dir, haze):
    """Sky radiance (..., 3), unnormalised: blue zenith, paler horizon, a glow around the sun."""
    y = np.clip(directions[..., 1], 0.0, 1.0)[..., None]
    zenith = (1 - haze) * np.array([0.25, 0.45, 1.0]) + haze * np.array([0.7, 0.75, 0.85])
    horizon = np.array([0.85, 0.9, 1.0])
    sky = zenith + (horizon - zenith) * (1.0 - y) ** 3
    cos_sun = np.clip(directions @ sun_dir, -1.0, 1.0)[..., None]
    glow = (0.5 + 2.0 * haze) * np.exp((cos_sun - 1.0) / 0.03) + 0.3 * (1.0 + cos_sun) ** 2 / 4
    return sky * (1.0 + glow)


def _sun_coverage(height, sun_dir, radius_rad, samples=8):
    """(H, 2H) float64 fraction of each texel's solid angle inside the sun disc: sub-texel
    supersampling in (u, t = cos theta), where solid angle is uniform, then rescaled so the
    disc's total is exactly its solid angle 2 pi (1 - cos r)."""
    width = 2 * height
    samples = max(samples, int(math.ceil(4 * math.pi / height / radius_rad)))
    cover = np.zeros((height, width))
    u_sun, v_sun = direction_to_uv(sun_dir)
    reach = 2 + int(math.ceil(math.degrees(radius_rad) / (180.0 / height)))
    centre_row = int(v_sun * height)
    rows = np.arange(max(0, centre_row - reach), min(height, centre_row + reach + 1))
    cols = np.arange(int(u_sun * width) - 2 * reach - 4, int(u_sun * width) + 2 * reach + 5) % width
    if abs(sun_dir[1]) > 0.95:  # near a pole the disc spans every column
        cols = np.arange(width)
    sub = (np.arange(samples) + 0.5) / samples
    for i in rows:
        c_top, c_bottom = math.cos(math.pi * i / height), math.cos(math.pi * (i + 1) / height)
        cos_t = c_top + (c_bottom - c_top) * sub  # uniform in cos theta
        sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t ** 2))
        phi = 2 * np.pi * ((cols[:, None] + sub[None, :]) / width - 0.5)  # (C, S)
        d = np.stack([sin_t[None, None, :] * np.sin(phi)[..., None],
                      np.broadcast_to(cos_t, (len(cols), samples, samples)),
                      -sin_t[None, None, :] * np.cos(phi)[..., None]], axis=-1)
        inside = (d @ sun_dir) >= math.cos(radius_rad)
        cover[i, cols] = inside.mean(axis=(1, 2))
    total = (cover * texel_solid_angles(height, width)).sum()
    if total <= 0:  # a disc far below a texel that no sub-sample found: its nearest texel
        row, col = min(int(v_sun * height), height - 1), int(u_sun * width) % width
        cover[row, col], total = 1.0, texel_solid_angles(height, width)[row, col]
    return cover * (2.0 * math.pi * (1.0 - math.cos(radius_rad)) / total)


def procedural_sky(height: int = SKY_HEIGHT, *, sun_elevation_deg: float, sun_azimuth_deg: float,
                   sun_to_sky: float, sun_radius_deg: float, haze: float = 0.3,
                   ground_albedo: float = 0.2) -> np.ndarray:
    """A clear sky with a sun disc over a grey-brown ground. Returns (height, 2 height, 3)
    float32 linear radiance with the sky's median luminance (upper hemisphere) = 1.

    sun_to_sky: sun radiance / median sky luminance. sun_azimuth_deg: 0 puts the sun toward
    -Z (behind the person, seen by the camera), 90 toward +X, 180 behind the camera.
    The disc is anti-aliased by its exact share of each texel, so its energy does not depend
    on the map's resolution. The ground reflects sun and sky diffusely (albedo / pi x its
    irradiance), so the lower hemisphere is consistent with the upper one.
    """
    elevation, azimuth = math.radians(sun_elevation_deg), math.radians(sun_azimuth_deg)
    sun_dir = np.array([math.cos(elevation) * math.sin(azimuth), math.sin(elevation),
                        -math.cos(elevation) * math.cos(azimuth)])
    directions = texel_directions(height, 2 * height)
    sky = _sky_radiance(directions, sun_dir, haze)
    upper = directions[..., 1] > 0
    sky /= np.median(sky[upper] @ LUMINANCE)
    omega = texel_solid_angles(height, 2 * height)
    cover = _sun_coverage(height, sun_dir, math.radians(sun_radius_deg))
    sun = sun_to_sky * cover[..., None] * _sun_colour(sun_elevation_deg)
    # ground: Lambertian, lit by the upper hemisphere (sky and sun) with cos to +Y
    cos_up = np.maximum(directions[..., 1], 0.0)[..., None]
    irradiance = ((sky * upper[..., None] + sun) * cos_up * omega[..., None]).sum(axis=(0, 1))
    ground = np.broadcast_to(ground_albedo / math.pi * irradiance * np.array([1.0, 0.9, 0.8]),
                             sky.shape)
    env = np.where(upper[..., None], sky, ground) + sun
    return env.astype(np.float32)


# --- the environment in the camera frame ----------------------------------------------------

@functools.lru_cache(maxsize=8)
def _load_hdri(path: str) -> np.ndarray:
    env = load_envmap(path)
    env.setflags(write=False)
    return env


def world_environment(spec: LightingSpec, folder: str | None = None) -> np.ndarray:
    """(H, 2H, 3) float32 linear radiance of a lighting in the world frame (rotation and
    gain applied)."""
    if spec.kind == "hdri":
        env = _load_hdri(str((Path(folder) if folder else hdri_dir()) / spec.name))
        env = rotate_envmap(env, spec.rotation_deg) if spec.rotation_deg else env
    elif spec.kind == "sky":
        env = procedural_sky(**spec.params)
    else:
        raise UsageError(f"unknown lighting kind {spec.kind!r}", fix="use 'hdri' or 'sky'")
    return (env * np.float32(spec.gain)).astype(np.float32)


def pitch_environment(env: np.ndarray, pitch_deg: float) -> np.ndarray:
    """The environment seen from a camera pitched down by `pitch_deg`: L'(d) = L(Rx^T d), with
    Rx the turn about +X that takes world +Y to (0, cos p, sin p) (up leans toward the
    viewer). Bilinear resampling. (H, 2H, 3) float32 -> same."""
    if not pitch_deg:
        return env
    p = math.radians(pitch_deg)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(p), -math.sin(p)],
                   [0.0, math.sin(p), math.cos(p)]])
    d = texel_directions(*env.shape[:2]) @ rx  # row vectors: d @ R = (R^T d^T)^T
    return lookup_bilinear(env, *direction_to_uv(d))


def camera_rotation(pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """(3, 3) float64 world -> camera rotation Rx(pitch) Ry(yaw); Ry turns +X toward -Z
    (counter-clockwise seen from above, the sense of rotate_envmap)."""
    p, y = math.radians(pitch_deg), math.radians(yaw_deg)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(p), -math.sin(p)],
                   [0.0, math.sin(p), math.cos(p)]])
    ry = np.array([[math.cos(y), 0.0, math.sin(y)], [0.0, 1.0, 0.0],
                   [-math.sin(y), 0.0, math.cos(y)]])
    return rx @ ry


def camera_environment(spec: LightingSpec, pitch_deg: float, yaw_deg: float,
                       folder: str | None = None) -> np.ndarray:
    """The lighting in the camera frame of a person turned by `camera_rotation(pitch, yaw)`:
    the world map turned by yaw about +Y (exact for whole texels) then pitched. (H, 2H, 3)
    float32 linear radiance: what `target.hdr` / the light loss use."""
    env = world_environment(spec, folder)
    if yaw_deg:
        env = rotate_envmap(env, yaw_deg)
    return pitch_environment(env, pitch_deg)
