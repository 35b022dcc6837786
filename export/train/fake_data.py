"""A tiny synthetic dataset with the factory's interface (export/factory/DATASET_CONTRACT.md),
for smoke tests of the trainer: one ellipsoid "person" (body + head) per sample, with
consistent normals, depths, AO, albedo, two directional-plus-ambient lightings, their shadings,
the photo (8-bit sRGB round trip, over a background) and a face box on the head.

Not a substitute for the real renders: it only has to be learnable and self-consistent.
"""

from __future__ import annotations

import numpy as np

from relightcli.io.images import linear_to_srgb, srgb_to_linear
from relightcli.io.envmap import texel_directions

SPLIT_NAMES = ("train", "val", "test")
LIGHT_SHAPE = (16, 32)


def _light(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(16, 32, 3) map: a sky-like ambient plus one bright blob; returns the map, the blob's
    unit direction, its RGB strength (shading units) and the ambient RGB."""
    dirs = texel_directions(*LIGHT_SHAPE)
    ambient = rng.uniform(0.1, 0.4, 3).astype(np.float32)
    sun = rng.normal(size=3)
    sun[2] = abs(sun[2]) + 0.5  # toward the viewer, so the person's front is lit
    sun /= np.linalg.norm(sun)
    strength = rng.uniform(1.0, 3.0, 3).astype(np.float32)
    lobe = np.exp(20.0 * (dirs @ sun - 1.0))[..., None]
    env = (ambient + 8.0 * strength * lobe).astype(np.float32)
    return env, sun.astype(np.float32), strength, ambient


def fake_sample(rng: np.random.Generator, size: int = 32) -> dict[str, np.ndarray]:
    """One sample at size x size, every array of the contract, float32."""
    y, x = np.meshgrid(np.linspace(-1, 1, size, dtype=np.float32) + 1.0 / size,
                       np.linspace(-1, 1, size, dtype=np.float32) + 1.0 / size, indexing="ij")
    cx, sx, sy = rng.uniform(-0.15, 0.15), rng.uniform(0.3, 0.45), rng.uniform(0.55, 0.7)
    body = ((x - cx) / sx) ** 2 + ((y - 0.2) / sy) ** 2
    head = ((x - cx) / 0.2) ** 2 + ((y + 0.62) / 0.22) ** 2
    r2 = np.minimum(body, head)
    mask = (r2 < 1).astype(np.float32)
    nz = np.sqrt(np.clip(1 - r2, 0, 1))
    in_body = body < head
    gx = np.where(in_body, (x - cx) / sx, (x - cx) / 0.2)
    gy = np.where(in_body, -(y - 0.2) / sy, -(y + 0.62) / 0.22)
    norm = np.sqrt(gx**2 + gy**2 + nz**2) + 1e-8
    normal = np.stack([gx, gy, nz], -1) / norm[..., None] * mask[..., None]
    back_normal = normal * np.array([1, 1, -1], dtype=np.float32)
    thickness = np.where(in_body, 0.3, 0.2) * nz
    z0 = rng.uniform(-0.5, 0.5)
    front_depth = (z0 + thickness) * mask
    back_depth = (z0 - thickness) * mask
    ao = np.where(mask > 0, np.clip(0.35 + 0.65 * nz, 0, 1), 1.0).astype(np.float32)
    colour = rng.uniform(0.2, 0.8, 3).astype(np.float32)
    albedo = np.clip(colour + 0.1 * np.sin(9 * x + 5 * y)[..., None], 0, 1) * mask[..., None]

    def shade(sun, strength, ambient):
        cosine = np.clip(normal @ sun, 0, None)[..., None]
        return ((ambient + strength * cosine) * ao[..., None] * mask[..., None]).astype(np.float32)

    light_a, sun_a, strength_a, ambient_a = _light(rng)
    light_b, sun_b, strength_b, ambient_b = _light(rng)
    shading_a, shading_b = shade(sun_a, strength_a, ambient_a), shade(sun_b, strength_b, ambient_b)
    image_a = albedo * shading_a
    exposure = np.float32(1.0)
    clean = srgb_to_linear(np.round(linear_to_srgb(np.clip(image_a, 0, 1)) * 255) / 255) * mask[..., None]
    background = np.stack([0.3 + 0.2 * y, 0.4 + 0.1 * x, 0.5 - 0.1 * x * y], -1)
    photo = image_a * mask[..., None] + background * (1 - mask[..., None])
    photo = srgb_to_linear(np.round(linear_to_srgb(np.clip(photo, 0, 1)) * 255) / 255)
    prior_mask = (mask > 0) & np.roll(mask > 0, 1, 0) & np.roll(mask > 0, -1, 0) & np.roll(mask > 0, 1, 1)
    prior_mask = (prior_mask & np.roll(mask > 0, -1, 1)).astype(np.float32)
    tilted = normal + np.array([0, 0, 0.3], np.float32) * mask[..., None]
    prior_normal = tilted / np.maximum(np.linalg.norm(tilted, axis=-1, keepdims=True), 1e-8) * prior_mask[..., None]
    prior_back_normal = prior_normal * np.array([1, 1, -1], dtype=np.float32)
    rows, cols = np.nonzero(~in_body & (mask > 0))
    face_box = (np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1], dtype=np.float32)
                if rows.size else np.full(4, -1, dtype=np.float32))
    arrays = {
        "input": photo, "input_clean": clean, "mask": mask, "albedo": albedo, "ao": ao,
        "normal": normal, "back_normal": back_normal, "front_depth": front_depth, "back_depth": back_depth,
        "rect": np.array([-1.2, 1.2, -1.2, 1.2]), "shading_a": shading_a, "shading_b": shading_b,
        "image_a": image_a, "relit_b": albedo * shading_b, "light_a": light_a, "light_b": light_b,
        "exposure": exposure, "face_box": face_box,
        # a fitted naked body's prior maps (export.factory.coarse --priors): the person minus a
        # 1-pixel rim of clothes, normals tilted toward +z, the surface a little behind
        "prior_mask": prior_mask, "prior_normal": prior_normal, "prior_back_normal": prior_back_normal,
        "prior_front_depth": (front_depth - 0.02) * prior_mask, "prior_back_depth": (back_depth + 0.02) * prior_mask,
        # and its ray-traced AO (--prior-ao): a little more open than the clothed person's
        "prior_ao": np.clip(ao + 0.05, 0.0, 1.0) * prior_mask,
    }
    return {k: np.asarray(v, dtype=np.float32) for k, v in arrays.items()}


class FakeDataset:
    """In-memory dataset with `export.factory.dataset.Dataset`'s interface."""

    split_names = SPLIT_NAMES

    def __init__(self, counts: dict[str, int] | None = None, size: int = 32, seed: int = 0):
        counts = counts or {"train": 6, "val": 2, "test": 2}
        self.samples = {}
        for k, split in enumerate(SPLIT_NAMES):
            rng = np.random.default_rng([seed, k])
            self.samples[split] = {f"{split}_{i:04d}": fake_sample(rng, size) for i in range(counts.get(split, 0))}
        self.card = {"format_version": 1, "counts": {s: len(v) for s, v in self.samples.items()},
                     "resolution": size, "seeds": {"fake": seed}, "generation_command": "export.train.fake_data"}

    def ids(self, split: str) -> list[str]:
        if split not in self.samples:
            raise KeyError(f"unknown split {split!r}; known: {self.split_names}")
        return sorted(self.samples[split])

    def load(self, split: str, sample_id: str, names=None) -> dict[str, np.ndarray]:
        return {k: v.copy() for k, v in self.samples[split][sample_id].items() if names is None or k in names}


def write_fake_dataset(root, counts: dict[str, int] | None = None, size: int = 32, seed: int = 0):
    """Write a `FakeDataset` to `root` with the factory's writer (export.factory.dataset)."""
    from export.factory.dataset import write_card, write_sample

    fake = FakeDataset(counts, size, seed)
    for split in SPLIT_NAMES:
        for sample_id in fake.ids(split):
            arrays = fake.load(split, sample_id)
            # the writer stores the photos as the 8-bit sRGB they were quantised to
            for key in ("input", "input_clean"):
                arrays[key] = np.round(linear_to_srgb(arrays[key]) * 255).astype(np.uint8)
            write_sample(root, split, sample_id, arrays, {"fake": True})
    write_card(root, fake.card)
    return root
