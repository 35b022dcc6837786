"""On-disk format of the synthetic dataset (DATASET_CONTRACT.md) and its card.

Layout:
    root/dataset.json              the card (format version, counts, splits, seeds, sources...)
    root/<split>/<sample_id>.npz   one compressed numpy archive per sample

Inside a sample file each array is stored in the encoding of `ENCODINGS` (the loader undoes
it; names not listed are stored and returned as float32):
    srgb8   uint8, the 8-bit sRGB photo exactly as quantised; loaded as linear [0, 1]
            (relightcli.io.images.srgb_to_linear): "input", "input_clean"
    unit8   uint8 round(255 x), x in [0, 1]: "mask", "coverage" (beyond the contract: the
            share of each pixel the person covers, with which the photo was composited),
            "face_pixels" (export/factory/face_closeups.py), "prior_mask"
    unit16  uint16 round(65535 x), x in [0, 1]: "albedo", "ao", "ao_pred", "prior_ao"
    normal  float16 unit vectors, renormalised on load (zero rows stay zero): "normal",
            "back_normal", "normal_pred", "prior_normal", "prior_back_normal"
    hdr16   float16 of x / s with s = max |x| kept as "<name>__scale" (float64), so relative
            precision ~5e-4 down to 6e-5 s: "shading_a", "shading_b", "image_a", "relit_b",
            "coarse_shading_b", "coarse_face_b", "body_shading_b"
    float32 as is: depths, "rect", "face_box", "exposure", "light_a", "light_b"
plus "__meta__" (a JSON string: the sample's settings, integrator statistics) and
"__format__" (FORMAT_VERSION). Files are written to a temporary name and renamed into place,
so a sample file is complete or absent (this is what makes generation resumable).

`add_arrays` adds arrays to a written sample (export/factory/coarse.py adds what the runtime's
own stages make of the sample: "coarse_shading_b", "ao_pred", "normal_pred", and the fitted bodies'
prior maps and ray-traced AO "prior_*"); the stored bytes of the others are kept as they are.
"""

from __future__ import annotations

import json
import os
import secrets
from pathlib import Path

import numpy as np

from relightcli.errors import InputError, OutputError, UsageError
from relightcli.io.images import srgb_to_linear

FORMAT_VERSION = 1
SPLITS = ("train", "val", "test")
CARD_NAME = "dataset.json"
ENCODINGS = {
    "input": "srgb8", "input_clean": "srgb8", "mask": "unit8", "coverage": "unit8", "albedo": "unit16",
    "ao": "unit16", "normal": "normal", "back_normal": "normal", "shading_a": "hdr16",
    "shading_b": "hdr16", "image_a": "hdr16", "relit_b": "hdr16", "front_depth": "float32",
    "back_depth": "float32", "rect": "float32", "face_box": "float32", "exposure": "float32",
    "light_a": "float32", "light_b": "float32", "coarse_shading_b": "hdr16", "ao_pred": "unit16", "prior_ao": "unit16",
    "coarse_face_b": "hdr16", "body_shading_b": "hdr16", "face_pixels": "unit8",
    "normal_pred": "normal", "prior_mask": "unit8", "prior_normal": "normal", "prior_back_normal": "normal",
}
# What open_dataset(...).load returns: name -> (shape with H, W symbolic, dtype)
CONTRACT = {
    "input": ("H", "W", 3), "input_clean": ("H", "W", 3), "mask": ("H", "W"),
    "albedo": ("H", "W", 3), "ao": ("H", "W"), "normal": ("H", "W", 3),
    "back_normal": ("H", "W", 3), "front_depth": ("H", "W"), "back_depth": ("H", "W"),
    "rect": (4,), "shading_a": ("H", "W", 3), "shading_b": ("H", "W", 3),
    "image_a": ("H", "W", 3), "relit_b": ("H", "W", 3), "light_a": (16, 32, 3),
    "light_b": (16, 32, 3), "exposure": (), "face_box": (4,),
    "coverage": ("H", "W"),  # beyond DATASET_CONTRACT.md; trainers may ignore it
}


def sample_path(root, split: str, sample_id: str) -> Path:
    """root/<split>/<sample_id>.npz"""
    if split not in SPLITS:
        raise UsageError(f"unknown split {split!r}", fix=f"use one of {', '.join(SPLITS)}")
    return Path(root) / split / f"{sample_id}.npz"


def _encode(name: str, value) -> dict:
    """Stored arrays of one named array (see the module docstring)."""
    kind = ENCODINGS.get(name, "float32")
    value = np.asarray(value)
    if kind == "srgb8":
        if value.dtype != np.uint8:
            raise UsageError(f"{name} must be the uint8 sRGB photo, got {value.dtype}")
        return {name: value}
    if kind == "unit8":
        return {name: np.round(np.clip(value, 0, 1) * 255).astype(np.uint8)}
    if kind == "unit16":
        return {name: np.round(np.clip(value, 0, 1) * 65535).astype(np.uint16)}
    if kind == "normal":
        return {name: value.astype(np.float16)}
    if kind == "hdr16":
        scale = float(np.max(np.abs(value))) if value.size else 0.0
        scale = scale if scale > 0 and np.isfinite(scale) else 1.0
        return {name: (value / scale).astype(np.float16), f"{name}__scale": np.float64(scale)}
    return {name: value.astype(np.float32)}


def _decode(name: str, stored) -> np.ndarray:
    """float32 array of a name from the opened archive `stored`."""
    kind = ENCODINGS.get(name, "float32")
    value = stored[name]
    if kind == "srgb8":
        return srgb_to_linear(value.astype(np.float32) / np.float32(255.0))
    if kind == "unit8":
        return value.astype(np.float32) / np.float32(255.0)
    if kind == "unit16":
        return value.astype(np.float32) / np.float32(65535.0)
    if kind == "normal":
        n = value.astype(np.float32)
        length = np.linalg.norm(n, axis=-1, keepdims=True)
        return np.where(length > 0, n / np.where(length > 0, length, 1.0), 0.0).astype(np.float32)
    if kind == "hdr16":
        return (value.astype(np.float32) * np.float32(stored[f"{name}__scale"])).astype(np.float32)
    return value.astype(np.float32)


def _atomic_write(path: Path, write) -> None:
    """Call write(handle) on a temporary file next to `path`, then rename it into place."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
    try:
        with open(temporary, "wb") as handle:
            write(handle)
        os.replace(temporary, path)
    except OSError as error:
        temporary.unlink(missing_ok=True)
        raise OutputError(f"cannot write: {error.strerror}", path=path,
                          fix="check free disk space and permissions") from error


def write_sample(root, split: str, sample_id: str, arrays: dict, meta: dict) -> Path:
    """Write one sample atomically to root/<split>/<sample_id>.npz; returns the path."""
    path = sample_path(root, split, sample_id)
    stored = {"__format__": np.int64(FORMAT_VERSION),
              "__meta__": np.array(json.dumps(meta, sort_keys=True))}
    for name, value in arrays.items():
        if name.startswith("__") or "__" in name:
            raise UsageError(f"array name {name!r} is reserved (contains '__')")
        stored.update(_encode(name, value))
    _atomic_write(path, lambda handle: np.savez_compressed(handle, **stored))
    return path


def add_arrays(root, split: str, sample_id: str, arrays: dict, meta_update: dict) -> Path:
    """Add (or replace) arrays of a written sample and merge `meta_update` into its metadata;
    atomic like write_sample. The other arrays' stored bytes are copied, not re-encoded."""
    path = sample_path(root, split, sample_id)
    if not path.is_file():
        raise InputError("sample not found", path=path, fix="list samples with open_dataset(root).ids(split)")
    with np.load(path, allow_pickle=False) as old:
        stored = {name: old[name] for name in old.files}
    meta = dict(json.loads(str(stored["__meta__"])), **meta_update)
    stored["__meta__"] = np.array(json.dumps(meta, sort_keys=True))
    for name, value in arrays.items():
        if "__" in name:
            raise UsageError(f"array name {name!r} is reserved (contains '__')")
        stored.update(_encode(name, value))
    _atomic_write(path, lambda handle: np.savez_compressed(handle, **stored))
    return path


def write_card(root, card: dict) -> Path:
    """Write root/dataset.json atomically (format_version added); returns the path."""
    card = dict(card, format_version=FORMAT_VERSION)
    path = Path(root) / CARD_NAME
    text = json.dumps(card, indent=2, sort_keys=True).encode()
    _atomic_write(path, lambda handle: handle.write(text))
    return path


def read_card(card_path: Path, format_version: int, generate_fix: str) -> dict:
    """A dataset card (JSON), checked to exist and to have the format this reader reads."""
    if not card_path.is_file():
        raise InputError("no dataset card", path=card_path, fix=generate_fix)
    card = json.loads(card_path.read_text())
    if card.get("format_version") != format_version:
        raise InputError(f"format version {card.get('format_version')}, this reader reads "
                         f"{format_version}", path=card_path, fix="regenerate the dataset")
    return card


class Dataset:
    """A dataset folder opened for reading: `.card`, `.ids(split)`, `.load(split, id)`."""

    split_names = SPLITS

    def __init__(self, root):
        self.root = Path(root)
        self.card = read_card(self.root / CARD_NAME, FORMAT_VERSION,
                              "generate the dataset with python -m export.factory.generate")

    def ids(self, split: str) -> list[str]:
        """Sorted ids of the complete samples of a split."""
        folder = sample_path(self.root, split, "x").parent
        return sorted(p.stem for p in folder.glob("*.npz")) if folder.is_dir() else []

    def _open(self, split, sample_id):
        path = sample_path(self.root, split, sample_id)
        if not path.is_file():
            raise InputError("sample not found", path=path, fix="list samples with .ids(split)")
        return np.load(path, allow_pickle=False)

    def load(self, split: str, sample_id: str, names=None) -> dict:
        """name -> float32 array of one sample (decoded, see the module docstring); names: only
        those of them the sample has (each array is decompressed on its own), None: all."""
        with self._open(split, sample_id) as stored:
            found = [n for n in stored.files if "__" not in n and (names is None or n in names)]
            return {name: _decode(name, stored) for name in found}

    def load_raw(self, split: str, sample_id: str, name: str) -> np.ndarray:
        """One array exactly as stored (e.g. the uint8 sRGB "input")."""
        with self._open(split, sample_id) as stored:
            return stored[name]

    def meta(self, split: str, sample_id: str) -> dict:
        """The sample's metadata (settings, integrator statistics)."""
        with self._open(split, sample_id) as stored:
            return json.loads(str(stored["__meta__"]))


def open_dataset(root) -> Dataset:
    """Open a dataset folder written by write_sample / write_card."""
    return Dataset(root)


# --- a contact sheet for a human eye ------------------------------------------------------------

SHEET_COLUMNS = ("input", "albedo", "normal", "ao", "shading_a", "light_a", "relit_b", "light_b")


def _display(name: str, value, size: int) -> np.ndarray:
    """One map as a (size, size, 3) float32 sRGB-encoded tile in [0, 1]."""
    import cv2

    from relightcli.io.images import linear_to_srgb

    if name.startswith("light_"):
        value = cv2.resize(value, (size, size // 2), interpolation=cv2.INTER_NEAREST)
        value = np.concatenate([value, np.zeros_like(value)], axis=0)
    if value.ndim == 2:
        value = np.repeat(value[..., None], 3, axis=2)
    if name in ("normal", "back_normal"):
        return np.where(np.any(value != 0, axis=-1, keepdims=True), (value + 1) / 2, 0.0)
    if name.startswith(("shading", "light")):
        scale = np.percentile(value[value > 0], 95) / 0.8 if np.any(value > 0) else 1.0
        value = value / scale
    return linear_to_srgb(np.clip(value, 0.0, 1.0))


def contact_sheet(root, count: int = 6, seed: int = 0, size: int = 160) -> np.ndarray:
    """(count x size, 8 x size, 3) uint8 sRGB: random samples of a dataset, one per row, with
    the columns of SHEET_COLUMNS (HDR maps divided by their 95th percentile / 0.8; normals as
    (n + 1) / 2; the 16x32 lightings as equirectangular strips)."""
    import cv2

    data = open_dataset(root)
    pool = [(s, i) for s in SPLITS for i in data.ids(s)]
    if not pool:
        raise InputError("dataset has no samples", path=root, fix="generate some first")
    rng = np.random.default_rng(seed)
    picks = [pool[k] for k in rng.choice(len(pool), min(count, len(pool)), replace=False)]
    rows = []
    for split, sample_id in picks:
        sample = data.load(split, sample_id)
        tiles = [cv2.resize(_display(n, sample[n], size), (size, size),
                            interpolation=cv2.INTER_AREA) for n in SHEET_COLUMNS]
        rows.append(np.concatenate(tiles, axis=1))
    return np.round(np.concatenate(rows, axis=0) * 255).astype(np.uint8)
