"""What a camera makes of the rendered radiance: auto-exposure, clipping, sRGB 8-bit
quantisation, the paper's photometric augmentation, and photographic backgrounds.

Order of operations (a sensor's): composite person over background (linear radiance) ->
exposure factor -> white-balance gains (colour jitter) -> optical blur -> sensor noise ->
clip to [0, 1] -> sRGB encode -> 8-bit quantise. The linear ground truth is only scaled by
the exposure factor, never clipped.

All images are float32 linear light (H, W, 3) unless said otherwise; masks (H, W) in [0, 1].
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np

from relightcli.errors import UsageError
from relightcli.io.envmap import environment_view
from relightcli.io.images import LUMINANCE, linear_to_srgb, srgb_to_linear

# Auto-exposure: this percentile of the person's brightest channel is mapped to the key
METERING_PERCENTILE = 95.0
KEY_RANGE = (0.55, 1.0)


@dataclass(frozen=True)
class Augmentation:
    """The paper's photometric augmentation of the input photo.

    gains: (3,) white-balance factors (colour jitter); blur_sigma: Gaussian blur in pixels
    (0 = none); noise_sigma: std of additive Gaussian noise on the exposed linear image
    (0 = none); noise_seed: seed of the noise.
    """

    gains: tuple = (1.0, 1.0, 1.0)
    blur_sigma: float = 0.0
    noise_sigma: float = 0.0
    noise_seed: int = 0

    def as_dict(self) -> dict:
        return asdict(self)


NO_AUGMENTATION = Augmentation()


def sample_augmentation(rng: np.random.Generator, probability: float = 0.5) -> Augmentation:
    """Each of colour jitter (gains 0.9-1.1), blur (sigma 0.3-1.0 px) and noise (sigma
    0.002-0.02) is on with `probability`."""
    gains = tuple(float(g) for g in rng.uniform(0.9, 1.1, 3)) if rng.random() < probability \
        else (1.0, 1.0, 1.0)
    blur = float(rng.uniform(0.3, 1.0)) if rng.random() < probability else 0.0
    noise = float(np.exp(rng.uniform(np.log(0.002), np.log(0.02)))) if rng.random() < probability \
        else 0.0
    return Augmentation(gains, blur, noise, int(rng.integers(2 ** 31)))


def luminance(rgb) -> np.ndarray:
    """(..., 3) linear RGB -> (...) float32 Rec. 709 luminance."""
    return np.asarray(rgb, dtype=np.float32) @ LUMINANCE


def auto_exposure(image, mask, key: float) -> float:
    """Exposure factor that maps the METERING_PERCENTILE of the brightest channel over the
    mask to `key`: with key near 1 the brightest few % of the person clip (metering on
    luminance would clip far more of a saturated or evenly lit garment). image (H, W, 3)
    linear radiance, mask (H, W) bool. Returns a float > 0 (1.0 for an empty or black
    person)."""
    values = np.asarray(image, np.float32).max(axis=-1)[np.asarray(mask, dtype=bool)]
    level = float(np.percentile(values, METERING_PERCENTILE)) if values.size else 0.0
    return key / level if level > 0 else 1.0


def composite(foreground, mask, background) -> np.ndarray:
    """foreground * mask + background * (1 - mask). (H, W, 3) float32."""
    alpha = np.asarray(mask, dtype=np.float32)[..., None]
    return (foreground * alpha + background * (1.0 - alpha)).astype(np.float32)


def fill_edges(image, mask, passes: int = 2) -> np.ndarray:
    """Extend an image (H, W, 3) beyond its mask (H, W) bool by `passes` pixels: each outside
    pixel takes the mean of its inside 3x3 neighbours (where a partly covered edge pixel gets
    its colour). Inside pixels are unchanged. Returns (H, W, 3) float32."""
    image = np.asarray(image, np.float32).copy()
    inside = np.asarray(mask, bool).copy()
    for _ in range(passes):
        weight = cv2.blur(inside.astype(np.float32), (3, 3), borderType=cv2.BORDER_CONSTANT)
        total = cv2.blur(image * inside[..., None], (3, 3), borderType=cv2.BORDER_CONSTANT)
        grow = ~inside & (weight > 0)
        image[grow] = total[grow] / weight[grow][:, None]
        inside |= grow
    return image


def background_plate(env, width: int, height: int, fov_deg: float) -> np.ndarray:
    """A pinhole view of the (camera-frame) environment toward -Z: the photo's background,
    (height, width, 3) float32 linear radiance."""
    return environment_view(env, width=width, height=height, fov_deg=fov_deg)


def _apply_augmentation(linear, aug: Augmentation) -> np.ndarray:
    out = linear * np.asarray(aug.gains, dtype=np.float32)
    if aug.blur_sigma > 0:
        out = cv2.GaussianBlur(out, (0, 0), aug.blur_sigma, borderType=cv2.BORDER_REFLECT)
    if aug.noise_sigma > 0:
        rng = np.random.default_rng(aug.noise_seed)
        # shot-like noise: grows with the signal, never below a read-noise floor
        sigma = aug.noise_sigma * np.sqrt(np.maximum(out, 0.0) + 0.05)
        out = out + sigma * rng.standard_normal(out.shape).astype(np.float32)
    return out.astype(np.float32)


def photograph(radiance, exposure: float, aug: Augmentation = NO_AUGMENTATION) -> np.ndarray:
    """The 8-bit sRGB photo of linear radiance (H, W, 3): expose, augment, clip to [0, 1],
    encode, quantise (round to nearest). Returns (H, W, 3) uint8."""
    if not exposure > 0:
        raise UsageError(f"exposure must be > 0, got {exposure}")
    exposed = _apply_augmentation(np.asarray(radiance, np.float32) * np.float32(exposure), aug)
    encoded = linear_to_srgb(np.clip(exposed, 0.0, 1.0))
    return np.round(encoded * 255.0).astype(np.uint8)


def decode_photo(photo) -> np.ndarray:
    """(H, W, 3) uint8 sRGB -> (H, W, 3) float32 linear in [0, 1] (what the nets see)."""
    return srgb_to_linear(np.asarray(photo, dtype=np.float32) / np.float32(255.0))
