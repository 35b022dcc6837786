"""From dataset samples (export/factory/DATASET_CONTRACT.md) to what the nets train on:
augmentations, translation-invariant depth, the stand-in coarse shadings, face crops.

Everything here is numpy on one sample, (H, W, C) float32 as the dataset returns it; the
random choices come from an explicit `np.random.Generator` so a run is reproducible and a
resumed run continues bit-exactly.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter, map_coordinates

# Keys that are not images of the sample's (H, W) and so are never flipped or cropped.
NON_SPATIAL = {"light_a", "light_b", "exposure", "face_box", "rect"}
NORMAL_KEYS = ("normal", "back_normal", "normal_pred", "prior_normal", "prior_back_normal")
LIGHT_KEYS = ("light_a", "light_b")


def spatial_keys(sample: dict) -> list[str]:
    height, width = sample["mask"].shape
    return [k for k, v in sample.items()
            if k not in NON_SPATIAL and np.ndim(v) >= 2 and v.shape[:2] == (height, width)]


def flip_horizontal(sample: dict) -> dict:
    """Mirror a sample left-right, consistently: images flip along W; normals' x changes sign;
    the light maps mirror too (x -> -x is u -> 1 - u in the lat-long convention, i.e. a flip of
    the columns); the face box mirrors; `rect` keeps its extent (the mirror is about the crop's
    centre, so the crop covers the same world rectangle)."""
    out = dict(sample)
    width = sample["mask"].shape[1]
    for key in spatial_keys(sample):
        out[key] = np.ascontiguousarray(sample[key][:, ::-1])
    for key in NORMAL_KEYS:
        if key in out:
            out[key] = out[key] * np.array([-1, 1, 1], dtype=np.float32)
    for key in LIGHT_KEYS:
        if key in out:
            out[key] = np.ascontiguousarray(sample[key][:, ::-1])
    if "face_box" in out and np.all(out["face_box"] >= 0):
        x0, y0, x1, y1 = out["face_box"]
        out["face_box"] = np.array([width - x1, y0, width - x0, y1], dtype=np.float32)
    return out


def crop_sample(sample: dict, top: int, left: int, size: int) -> dict:
    """The `size` x `size` window at (top, left): images cropped, `rect` narrowed to the
    window's world rectangle, the face box moved (all -1 when it leaves the window)."""
    height, width = sample["mask"].shape
    if not (0 <= top <= height - size and 0 <= left <= width - size):
        raise ValueError(f"crop {size} at ({top}, {left}) does not fit a {height}x{width} sample")
    out = dict(sample)
    for key in spatial_keys(sample):
        out[key] = np.ascontiguousarray(sample[key][top:top + size, left:left + size])
    if "rect" in out:
        x0, x1, y0, y1 = (float(v) for v in sample["rect"])
        px, py = (x1 - x0) / width, (y1 - y0) / height
        out["rect"] = np.array([x0 + left * px, x0 + (left + size) * px,
                                y1 - (top + size) * py, y1 - top * py], dtype=np.float32)
    if "face_box" in out and np.all(out["face_box"] >= 0):
        box = out["face_box"] - np.array([left, top, left, top], dtype=np.float32)
        inside = box[0] >= 0 and box[1] >= 0 and box[2] <= size and box[3] <= size
        out["face_box"] = box if inside else np.full(4, -1, dtype=np.float32)
    return out


def augment(sample: dict, rng: np.random.Generator, flip: bool, crop: int | None) -> dict:
    """The paper's cheap augmentations: a random horizontal flip and a random square crop
    (scale and view changes are already in the data factory's renders)."""
    if flip and rng.random() < 0.5:
        sample = flip_horizontal(sample)
    if crop is not None:
        height, width = sample["mask"].shape
        if crop > min(height, width):
            raise ValueError(f"crop {crop} is larger than the {height}x{width} samples; lower `crop`")
        sample = crop_sample(sample, int(rng.integers(0, height - crop + 1)),
                             int(rng.integers(0, width - crop + 1)), crop)
    return sample


def relative_depths(sample: dict) -> tuple[np.ndarray, np.ndarray]:
    """Front and back depth in the geometry net's units, made translation-invariant:
    (z - mean front z over the mask) * 2 / crop width, so the crop spans [-1, 1] in X and the
    person's mean front depth is 0. Both (H, W) float32, 0 outside the mask."""
    mask = sample["mask"] > 0.5
    x0, x1 = float(sample["rect"][0]), float(sample["rect"][1])
    if not x1 > x0:
        raise ValueError(f"sample rect {sample['rect']} has no width")
    scale = 2.0 / (x1 - x0)
    mean = float(sample["front_depth"][mask].mean()) if mask.any() else 0.0
    front = np.where(mask, (sample["front_depth"] - mean) * scale, 0.0).astype(np.float32)
    back = np.where(mask, (sample["back_depth"] - mean) * scale, 0.0).astype(np.float32)
    return front, back


def _blur_inside(image: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur of (H, W, C) `image` that only mixes pixels inside `mask` (normalised
    convolution), so the black background does not bleed into the person's rim."""
    if sigma <= 0:
        return image
    m = mask.astype(np.float32)
    spatial = (sigma, sigma, 0)
    num = gaussian_filter(image * m[..., None], spatial)
    den = gaussian_filter(m, sigma)[..., None]
    return np.where(den > 1e-6, num / np.maximum(den, 1e-6), 0.0).astype(np.float32)


def standin_coarse_shading(shading: np.ndarray, ao: np.ndarray, mask: np.ndarray,
                           rng: np.random.Generator, params: dict) -> np.ndarray:
    """Stand-in for the integrator's ray-traced shading of the reconstructed mesh, until the
    pipeline produces it: the true shading with the contact shadows removed (/ ao**p), blurred
    inside the person (the smoothed mesh), times Monte Carlo-like noise, 0 off the person.
    shading: (H, W, 3) linear; ao, mask: (H, W). Returns (H, W, 3) float32 >= 0."""
    inside = mask > 0.5
    s = shading / np.maximum(ao, 0.2)[..., None] ** params["ao_power"]
    s = _blur_inside(s, inside, params["blur_sigma"])
    s = s * (1.0 + params["noise"] * rng.standard_normal(s.shape).astype(np.float32))
    return np.where(inside[..., None], np.maximum(s, 0.0), 0.0).astype(np.float32)


def standin_face_shadings(shading: np.ndarray, mask: np.ndarray, rng: np.random.Generator,
                          params: dict) -> tuple[np.ndarray, np.ndarray]:
    """Stand-ins for the face net's two inputs (full-frame, cropped later): the refined body
    shading (the truth, lightly blurred) and the coarse face-model shading (the truth blurred,
    with a smooth left-right gain error, as a misfitted face model would give, and noise)."""
    inside = mask > 0.5
    body = _blur_inside(shading, inside, params["body_blur_sigma"])
    face = _blur_inside(shading, inside, params["face_blur_sigma"])
    width = shading.shape[1]
    ramp = np.linspace(-1.0, 1.0, width, dtype=np.float32)[None, :, None]
    gain = 1.0 + params["face_gain"] * float(rng.uniform(-1, 1)) * ramp
    face = face * gain * (1.0 + params["face_noise"] * rng.standard_normal(face.shape).astype(np.float32))
    zero = np.float32(0)
    return (np.where(inside[..., None], body, zero).astype(np.float32),
            np.where(inside[..., None], np.maximum(face, 0), zero).astype(np.float32))


def has_face(sample: dict) -> bool:
    box = sample.get("face_box")
    return box is not None and bool(np.all(np.asarray(box) >= 0)) and box[2] > box[0] and box[3] > box[1]


def face_square(face_box: np.ndarray, margin: float) -> tuple[float, float, float]:
    """(centre x, centre y, side) in pixels of the square face crop around `face_box`
    (x0, y0, x1, y1): side = margin * the box's longer side."""
    x0, y0, x1, y1 = (float(v) for v in face_box)
    return (x0 + x1) / 2, (y0 + y1) / 2, margin * max(x1 - x0, y1 - y0)


def crop_resample(image: np.ndarray, centre_x: float, centre_y: float, side: float, size: int) -> np.ndarray:
    """The square window (pixel coordinates; pixel centres at j + 0.5) resampled bilinearly to
    (size, size[, C]); outside the image reads 0."""
    t = (np.arange(size, dtype=np.float64) + 0.5) / size - 0.5
    cols = centre_x + t * side - 0.5
    rows = centre_y + t * side - 0.5
    rr, cc = np.meshgrid(rows, cols, indexing="ij")
    if image.ndim == 2:
        return map_coordinates(image, [rr, cc], order=1, mode="constant").astype(np.float32)
    return np.stack([map_coordinates(image[..., c], [rr, cc], order=1, mode="constant")
                     for c in range(image.shape[-1])], axis=-1).astype(np.float32)


def sample_rng(seed: int, split: str, sample_id: str) -> np.random.Generator:
    """A generator fixed per (seed, split, sample): validation stand-ins are the same every time."""
    key = [seed] + list(f"{split}/{sample_id}".encode())
    return np.random.default_rng(key)
