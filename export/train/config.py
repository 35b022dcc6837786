"""Training configuration: one JSON file per net and size under export/train/configs/.

A config is a flat set of known keys (unknown keys are refused, so a typo cannot silently
fall back to a default) plus two nested dicts: `loss` (term weights) and `standin` (how the
stand-in coarse shadings are degraded from the ground truth).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from export.nets import FAMILIES

CONFIG_DIR = Path(__file__).resolve().parent / "configs"
ALL_NETS = ("geometry", "ao", "delight", "body_refine", "face_refine")
# Nets trained on their own command only (not in `all`): they need arrays the factory adds later
EXTRA_NETS = ("geometry_prior", "ao_prior")

# The paper's loss weights (DESIGN.md); the configs repeat them so a run records what it used.
PAPER_LOSS = {
    "geometry": {"l1": 5.0, "perceptual": 1.0, "angular": 1.0},
    "geometry_prior": {"l1": 5.0, "perceptual": 1.0, "angular": 1.0},
    "ao": {"l1": 5.0, "perceptual": 1.0},
    "ao_prior": {"l1": 5.0, "perceptual": 1.0},
    "delight": {"l1": 500.0, "perceptual": 100.0, "light": 0.025},
    "body_refine": {"l1": 10.0, "adversarial": 1.0, "fft": 0.001},
    "face_refine": {"l1": 5.0, "adversarial": 1.0},
}
# Terms of our own, off unless a config weights them: the delight net's SH-9 irradiance of its
# light against the true input shading, its albedo's level over the person, and its albedo at
# the true level (export.train.tasks.DelightTask)
EXTRA_LOSS = {"delight": ("irradiance", "level", "shape")}
DEFAULT_STANDIN = {
    "blur_sigma": 2.0,       # px: the smoothed reconstructed mesh loses fine shading detail
    "noise": 0.05,           # relative Monte Carlo noise of the ray tracer
    "ao_power": 1.0,         # shading / ao**p: the reconstruction misses contact shadows
    "body_blur_sigma": 0.75,  # px: the face net's "refined body shading" input is nearly right
    "face_blur_sigma": 1.0,
    "face_noise": 0.05,
    "face_gain": 0.15,       # smooth multiplicative error of the fitted face model's shading
}


class ConfigError(ValueError):
    """A training config (file or override) is wrong; the message names the key and the fix."""


@dataclass(frozen=True)
class TrainConfig:
    net: str
    size: str = "small"
    seed: int = 0
    steps: int = 1000
    max_minutes: float | None = None
    batch_size: int = 4
    lr: float = 1e-5
    lr_disc: float = 1e-6
    betas: tuple = (0.9, 0.999)
    crop: int | None = None           # random square crop (pixels) for the full-image nets
    flip: bool = True                 # random horizontal flips (normals' x and the light mirrored)
    threads: int | None = None        # torch intra-op threads (None: torch's default)
    log_every: int = 10
    val_every: int = 500
    checkpoint_every: int = 500
    val_max_samples: int = 32
    train_samples: int | None = None  # train on the first N training samples (curves over data size)
    coarse_shading: str = "standin"   # "standin" (degraded shading_b) or a dataset key
    shading_key: str = "shading_b"    # the target shading of the refinement nets
    ao_key: str = "ao"                # the body refinement's AO input: "ao" (truth) or "ao_pred" (the AO net's)
    normal_key: str = "normal"        # the de-lighting net's normal input: "normal" (truth) or "normal_pred"
    face_crop_size: int = 128         # the face net trains on crops resampled to this size
    face_margin: float = 1.2          # square face crop side = margin * max(face box side)
    export_size: int = 256            # trace size for the ONNX export (axes stay dynamic)
    loss: dict = field(default_factory=dict)
    standin: dict = field(default_factory=dict)
    note: str = ""
    lr_schedule: str = "constant"     # "constant", or "cosine": lr * (1 + cos(pi step / steps)) / 2
    init: str | None = None           # an ONNX file of this net whose weights start the run (fine-tuning)
    # input lights (each sample's spec.lighting_a.name: an HDRI's file name, "sky") whose samples
    # are left out of training: scenes lit by them then validate on maps the run never saw
    exclude_lights: tuple = ()

    def __post_init__(self):
        if self.net not in FAMILIES:
            raise ConfigError(f"unknown net {self.net!r}; known: {sorted(FAMILIES)}")
        if self.size not in FAMILIES[self.net][1]:
            raise ConfigError(f"unknown size {self.size!r} for {self.net}; known: {sorted(FAMILIES[self.net][1])}")
        for name in ("steps", "batch_size", "log_every", "val_every", "checkpoint_every", "val_max_samples"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < (0 if name == "steps" else 1):
                raise ConfigError(f"{name} must be a positive integer, got {value!r}")
        if isinstance(self.exclude_lights, str) or not all(isinstance(n, str) for n in self.exclude_lights):
            raise ConfigError(f"exclude_lights must be a list of light names, got {self.exclude_lights!r}")
        object.__setattr__(self, "exclude_lights", tuple(self.exclude_lights))
        if not (self.lr > 0 and self.lr_disc > 0):
            raise ConfigError(f"learning rates must be positive, got lr={self.lr}, lr_disc={self.lr_disc}")
        if self.train_samples is not None and not (isinstance(self.train_samples, int) and self.train_samples > 0):
            raise ConfigError(f"train_samples must be a positive integer or null, got {self.train_samples!r}")
        if self.max_minutes is not None and not self.max_minutes > 0:
            raise ConfigError(f"max_minutes must be positive or null, got {self.max_minutes}")
        if self.lr_schedule not in ("constant", "cosine"):
            raise ConfigError(f"lr_schedule must be 'constant' or 'cosine', got {self.lr_schedule!r}")
        known = set(PAPER_LOSS[self.net]) | set(EXTRA_LOSS.get(self.net, ()))
        unknown = set(self.loss) - known
        if unknown:
            raise ConfigError(f"unknown loss terms {sorted(unknown)} for {self.net}; known: {sorted(known)}")
        unknown = set(self.standin) - set(DEFAULT_STANDIN)
        if unknown:
            raise ConfigError(f"unknown standin keys {sorted(unknown)}; known: {sorted(DEFAULT_STANDIN)}")
        # Fill in the paper's weights and the default stand-in for whatever the file leaves out.
        object.__setattr__(self, "loss", {**PAPER_LOSS[self.net], **self.loss})
        object.__setattr__(self, "standin", {**DEFAULT_STANDIN, **self.standin})
        object.__setattr__(self, "betas", tuple(self.betas))

    @classmethod
    def from_dict(cls, data: dict, source: str = "config") -> "TrainConfig":
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ConfigError(f"{source}: unknown keys {sorted(unknown)}; known: {sorted(known)}")
        if "net" not in data:
            raise ConfigError(f"{source}: missing key 'net'")
        return cls(**data)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["betas"] = list(self.betas)
        d["exclude_lights"] = list(self.exclude_lights)
        return d

    def with_overrides(self, overrides: dict) -> "TrainConfig":
        """A copy with `overrides` applied (nested `loss` / `standin` dicts are merged)."""
        data = self.to_dict()
        for key, value in overrides.items():
            if key in ("loss", "standin") and isinstance(value, dict):
                data[key] = {**data[key], **value}
            else:
                data[key] = value
        return TrainConfig.from_dict(data, "overrides")


def load_config(path: str | Path, overrides: dict | None = None) -> TrainConfig:
    """Read a JSON config file and apply `overrides`."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {path} not found; the shipped ones are in {CONFIG_DIR}")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path} is not valid JSON: {exc}") from exc
    config = TrainConfig.from_dict(data, str(path))
    return config.with_overrides(overrides) if overrides else config


def default_config_path(net: str, size: str) -> Path:
    return CONFIG_DIR / f"{net}_{size}.json"


def parse_override(text: str) -> tuple[str, object]:
    """`key=value` with a JSON value (`lr=1e-4`, `crop=null`, `loss.l1=2`); bare words are strings."""
    if "=" not in text:
        raise ConfigError(f"override {text!r} must look like key=value")
    key, raw = text.split("=", 1)
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    if "." in key:
        outer, inner = key.split(".", 1)
        return outer, {inner: value}
    return key, value


def merge_overrides(items: list[str]) -> dict:
    merged: dict = {}
    for item in items:
        key, value = parse_override(item)
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key].update(value)
        else:
            merged[key] = value
    return merged
