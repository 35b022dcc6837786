"""Camera and lighting settings of the synthetic dataset, drawn deterministically per sample.

As in the paper: an orthographic camera pitched {0, 10, 20, 30} degrees down, the person
turned by a yaw in {-32, ..., 32} step 8 degrees, scale {0.8, 1, 1.1}, and two lightings per
setting (A: the photo's, B: the relighting target). Samples come in groups of
`samples_per_person` that share one person (building a body costs ~1.5 s); a group takes
distinct camera settings (a random permutation of the 108 combinations).

Every random choice of sample `index` in `split` comes from SeedSequence([seed, split index,
index]) (the group's from SeedSequence([seed, split index, group, 1])), so a sample is the
same whatever the order or the worker that renders it.

Framing: the person is centred (bounding box of the projected mesh) in a square crop whose
side is the box's larger extent / (FRAME_FILL x scale): at scale 1 the person spans 80 % of
the crop, 64 % at 0.8, 88 % at 1.1.
"""

from __future__ import annotations

import itertools
from dataclasses import asdict, dataclass, field

import numpy as np

from relightcli.errors import UsageError

from . import camera_model, lighting

SPLITS = ("train", "val", "test")
PITCHES_DEG = (0.0, 10.0, 20.0, 30.0)
YAWS_DEG = tuple(float(y) for y in range(-32, 33, 8))
SCALES = (0.8, 1.0, 1.1)
CAMERA_SETTINGS = tuple(itertools.product(PITCHES_DEG, YAWS_DEG, SCALES))
FRAME_FILL = 0.8
SAMPLES_PER_PERSON = 6
# Background field of view (degrees) of the pinhole view of the environment
BACKGROUND_FOV_DEG = (45.0, 90.0)


@dataclass(frozen=True)
class SceneSpec:
    """Everything that decides one sample (JSON-serialisable through `as_dict`).

    person_seed: the build_person seed (in `split`). pitch_deg, yaw_deg, scale: camera.
    lighting_a, lighting_b: LightingSpec (world frame). background: the HDRI the background
    is viewed from (LightingSpec; lighting A itself when A is an HDRI) and fov_deg.
    exposure_key: auto-exposure target; augmentation: camera_model.Augmentation.
    """

    split: str
    index: int
    person_seed: int
    pitch_deg: float
    yaw_deg: float
    scale: float
    lighting_a: lighting.LightingSpec
    lighting_b: lighting.LightingSpec
    background: lighting.LightingSpec
    background_fov_deg: float
    exposure_key: float
    augmentation: camera_model.Augmentation = field(default=camera_model.NO_AUGMENTATION)

    @property
    def sample_id(self) -> str:
        return sample_id(self.index)

    def as_dict(self) -> dict:
        out = asdict(self)
        out["sample_id"] = self.sample_id
        return out


def spec_from_dict(values: dict) -> SceneSpec:
    """The SceneSpec of `SceneSpec.as_dict()` (e.g. a stored sample's meta["spec"])."""
    fields = {k: v for k, v in values.items() if k != "sample_id"}
    for key in ("lighting_a", "lighting_b", "background"):
        fields[key] = lighting.LightingSpec(**fields[key])
    augmentation = dict(fields.get("augmentation", {}))
    if "gains" in augmentation:
        augmentation["gains"] = tuple(augmentation["gains"])
    fields["augmentation"] = camera_model.Augmentation(**augmentation)
    return SceneSpec(**fields)


def sample_id(index: int) -> str:
    """File stem of sample `index`: zero-padded to 6 digits."""
    return f"{int(index):06d}"


def person_seed(seed: int, split: str, group: int) -> int:
    """build_person seed of a group: a 31-bit hash of (seed, split, group)."""
    state = np.random.SeedSequence([int(seed), SPLITS.index(split), int(group), 0])
    return int(state.generate_state(1)[0] % (2 ** 31))


def _check(seed, split, index, samples_per_person):
    if split not in SPLITS:
        raise UsageError(f"unknown split {split!r}", fix=f"use one of {', '.join(SPLITS)}")
    if int(seed) < 0 or int(index) < 0:
        raise UsageError(f"seed and index must be >= 0, got {seed} and {index}")
    if not 1 <= samples_per_person <= len(CAMERA_SETTINGS):
        raise UsageError(f"samples per person must be in 1..{len(CAMERA_SETTINGS)}, "
                         f"got {samples_per_person}")


def camera_setting(seed: int, split: str, index: int,
                   samples_per_person: int = SAMPLES_PER_PERSON) -> tuple[float, float, float]:
    """(pitch_deg, yaw_deg, scale) of a sample: entry index % k of its group's permutation."""
    group, slot = divmod(int(index), samples_per_person)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), SPLITS.index(split), group, 1]))
    return CAMERA_SETTINGS[int(rng.permutation(len(CAMERA_SETTINGS))[slot])]


def sample_scene(seed: int, split: str, index: int, hdris: tuple[str, ...], *,
                 samples_per_person: int = SAMPLES_PER_PERSON,
                 sky_probability: float = lighting.SKY_PROBABILITY,
                 augment: bool = True, yaw_offset_deg: float = 0.0) -> SceneSpec:
    """The settings of sample `index` of `split`, drawn from `hdris` (that split's maps).
    yaw_offset_deg turns every camera by that much more (180: the people seen from behind);
    everything else is the sample's as without it."""
    _check(seed, split, index, samples_per_person)
    state = np.random.SeedSequence([int(seed), SPLITS.index(split), int(index)])
    rng = np.random.default_rng(state)
    pitch, yaw, scale = camera_setting(seed, split, index, samples_per_person)
    yaw += float(yaw_offset_deg)
    light_a = lighting.sample_lighting(rng, hdris, sky_probability)
    light_b = lighting.sample_lighting(rng, hdris, sky_probability)
    # a photo's background is what lit it; a procedural sky borrows a split HDRI
    background = light_a if light_a.kind == "hdri" else lighting.sample_lighting(rng, hdris, 0.0)
    fov = float(rng.uniform(*BACKGROUND_FOV_DEG))
    key = float(rng.uniform(*camera_model.KEY_RANGE))
    aug = camera_model.sample_augmentation(rng) if augment else camera_model.NO_AUGMENTATION
    return SceneSpec(split=split, index=int(index),
                     person_seed=person_seed(seed, split, int(index) // samples_per_person),
                     pitch_deg=pitch, yaw_deg=yaw, scale=scale, lighting_a=light_a,
                     lighting_b=light_b, background=background, background_fov_deg=fov,
                     exposure_key=key, augmentation=aug)


def frame_rect(points_xy, scale: float, fill: float = FRAME_FILL) -> tuple:
    """Square world rectangle (x0, x1, y0, y1) centred on the bounding box of points (N, 2)
    (camera-frame x, y), side = larger extent / (fill x scale)."""
    points_xy = np.asarray(points_xy, dtype=np.float64)
    lo, hi = points_xy.min(axis=0), points_xy.max(axis=0)
    centre, extent = (lo + hi) / 2.0, float(np.max(hi - lo))
    if not extent > 0 or not 0 < fill * scale < 1.0 + 1e-9:
        raise UsageError(f"cannot frame: extent {extent}, fill x scale {fill * scale}")
    half = extent / (fill * scale) / 2.0
    return (centre[0] - half, centre[0] + half, centre[1] - half, centre[1] + half)
