"""The model manifest, `models/manifest.json`: the one source of truth for which ONNX files
ship, their sha256 and their I/O contract.

Format (version 1)::

    {"version": 1,
     "models": {name: {"file": "geometry.onnx", "sha256": "<64 hex>",
                       "inputs":  [{"name": "image", "shape": ["N", 3, "H", "W"], "dtype": "float32"}],
                       "outputs": [...],
                       "multiple": 32, "colour_space": "...", "normalisation": "...",
                       "config": {...}, "training_data": {...}, "metrics": {...}}}}

`file` is relative to the models directory. Shapes use "N" for batch and "H"/"W" for dynamic
spatial sizes; integers are fixed. Non-network files the runtime needs (the face morphable model)
are entries with "kind": "data" and only "file", "sha256", "description" and "license".
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import relightcli
from relightcli.errors import MissingDependencyError

MANIFEST_VERSION = 1
MANIFEST_NAME = "manifest.json"
MODELS_DIR_ENV = "RELIGHT_MODELS_DIR"
REQUIRED_KEYS = {"onnx": ("file", "sha256", "inputs", "outputs", "multiple"), "data": ("file", "sha256")}
MODELS_FIX = ("reinstall relightcli (pip install --force-reinstall relightcli: the package carries its models; "
              f"in a source checkout, git checkout models/), or set {MODELS_DIR_ENV} to a folder holding "
              "manifest.json and the model files")


@dataclass(frozen=True)
class TensorContract:
    name: str
    shape: tuple  # ints for fixed dims, strings ("N", "H", "W") for dynamic ones
    dtype: str = "float32"

    @property
    def rank(self) -> int:
        return len(self.shape)


@dataclass(frozen=True)
class ModelEntry:
    """One model of the manifest; `path` is absolute."""

    name: str
    path: Path
    sha256: str
    inputs: tuple[TensorContract, ...]
    outputs: tuple[TensorContract, ...]
    multiple: int
    colour_space: str = ""
    normalisation: str = ""
    config: dict = field(default_factory=dict)
    training_data: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)
    kind: str = "onnx"  # "onnx" for networks, "data" for other files the runtime reads
    description: str = ""
    calibration: dict = field(default_factory=dict)  # constants applied to the outputs (DelightNet: albedo_gain)

    @property
    def trained_resolution(self) -> int | None:
        """The side of the square crops it learned on (training_data), None if unknown."""
        trained = self.training_data.get("resolution")
        return int(trained) if trained else None


@dataclass(frozen=True)
class ModelStatus:
    """What `relight info` shows per manifest model."""

    name: str
    path: Path
    present: bool
    sha256_ok: bool | None  # None when not checked (or the file is absent)


def models_dir() -> Path:
    """Where the models are: $RELIGHT_MODELS_DIR when set; else the installed package's own
    `relightcli/models/` (a wheel carries them as package data); else `models/` beside the
    relightcli folder (a source checkout, or an editable install of one)."""
    override = os.environ.get(MODELS_DIR_ENV)
    if override:
        return Path(override).expanduser()
    package = Path(relightcli.__file__).resolve().parent
    installed = package / "models"
    if (installed / MANIFEST_NAME).is_file():
        return installed
    return package.parent / "models"


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file's bytes, read in 1 MiB chunks."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            digest.update(block)
    return digest.hexdigest()


def load_manifest(directory: str | Path | None = None) -> dict[str, ModelEntry]:
    """Parse `<directory>/manifest.json` into entries by model name.

    Raises MissingDependencyError naming the manifest when it is missing, not JSON, of another
    version, or an entry lacks a required key.
    """
    directory = Path(directory) if directory is not None else models_dir()
    path = directory / MANIFEST_NAME
    if not path.is_file():
        raise MissingDependencyError("model manifest not found", path=path, fix=MODELS_FIX)
    try:
        raw = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MissingDependencyError(f"model manifest unreadable: {exc}", path=path, fix=MODELS_FIX) from exc
    if not isinstance(raw, dict) or raw.get("version") != MANIFEST_VERSION or not isinstance(raw.get("models"), dict):
        raise MissingDependencyError(f"model manifest is not version {MANIFEST_VERSION} with a 'models' table",
                                     path=path, fix=MODELS_FIX)
    return {name: _parse_entry(name, spec, directory, path) for name, spec in raw["models"].items()}


def _parse_entry(name: str, spec: dict, directory: Path, manifest_path: Path) -> ModelEntry:
    kind = spec.get("kind", "onnx") if isinstance(spec, dict) else "onnx"
    if kind not in REQUIRED_KEYS:
        raise MissingDependencyError(f"model {name!r} has unknown kind {kind!r}", path=manifest_path, fix=MODELS_FIX)
    missing = [k for k in REQUIRED_KEYS[kind] if not isinstance(spec, dict) or k not in spec]
    if missing:
        raise MissingDependencyError(f"model {name!r} lacks {', '.join(missing)}", path=manifest_path, fix=MODELS_FIX)
    try:
        inputs = tuple(_parse_tensor(t) for t in spec.get("inputs", ()))
        outputs = tuple(_parse_tensor(t) for t in spec.get("outputs", ()))
        multiple = int(spec.get("multiple", 1))
    except (KeyError, TypeError, ValueError) as exc:
        raise MissingDependencyError(f"model {name!r} has a malformed I/O contract: {exc}",
                                     path=manifest_path, fix=MODELS_FIX) from exc
    calibration = spec.get("calibration", {})
    gain = calibration.get("albedo_gain", 1.0) if isinstance(calibration, dict) else None
    if not (isinstance(gain, (int, float)) and not isinstance(gain, bool) and math.isfinite(gain) and gain > 0):
        raise MissingDependencyError(f"model {name!r} has a calibration whose albedo_gain is not a positive "
                                     f"number: {calibration!r}", path=manifest_path, fix=MODELS_FIX)
    return ModelEntry(
        name=name,
        path=directory / spec["file"],
        sha256=str(spec["sha256"]).lower(),
        inputs=inputs,
        outputs=outputs,
        multiple=multiple,
        colour_space=spec.get("colour_space", ""),
        normalisation=spec.get("normalisation", ""),
        config=spec.get("config", {}),
        training_data=spec.get("training_data", {}),
        metrics=spec.get("metrics", {}),
        calibration=calibration,
        kind=kind,
        description=spec.get("description", ""),
    )


def _parse_tensor(spec: dict) -> TensorContract:
    return TensorContract(name=spec["name"], shape=tuple(spec["shape"]), dtype=spec.get("dtype", "float32"))


def model_entry(name: str, directory: str | Path | None = None) -> ModelEntry:
    """The manifest entry of model `name`; MissingDependencyError when the manifest lacks it."""
    directory = Path(directory) if directory is not None else models_dir()
    entries = load_manifest(directory)
    if name not in entries:
        raise MissingDependencyError(f"model {name!r} is not in the manifest (has: {', '.join(sorted(entries)) or 'none'})",
                                     path=directory / MANIFEST_NAME, fix=MODELS_FIX)
    return entries[name]


def verified_file(name: str, directory: str | Path | None = None) -> Path:
    """The path of manifest entry `name` after checking it exists and matches its sha256;
    MissingDependencyError naming the file and the fix otherwise."""
    entry = model_entry(name, directory)
    if not entry.path.is_file():
        raise MissingDependencyError(f"{name} file not found", path=entry.path, fix=MODELS_FIX)
    if sha256_file(entry.path) != entry.sha256:
        raise MissingDependencyError(f"{name} file does not match its sha256 in the manifest (corrupt or replaced)",
                                     path=entry.path, fix=MODELS_FIX)
    return entry.path


def read_data_arrays(path: str | Path, required: tuple[str, ...], what: str, fix: str) -> dict:
    """Every array of a data asset's .npz (no pickles) by name; MissingDependencyError naming
    the file and `fix` when it is unreadable or lacks one of `required`. `what` names the
    asset in the message ("face model")."""
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [name for name in required if name not in data.files]
            if missing:
                raise MissingDependencyError(f"{what} lacks {', '.join(missing)}", path=path, fix=fix)
            return {name: data[name] for name in data.files}
    except (OSError, ValueError, zipfile.BadZipFile) as error:
        raise MissingDependencyError(f"{what} file is unreadable ({error})", path=path, fix=fix) from error


def list_models(directory: str | Path | None = None, verify: bool = False) -> list[ModelStatus]:
    """Every manifest model with whether its file is present and, with `verify`, whether its
    sha256 matches (hashing reads every file: about 1 s per GB)."""
    statuses = []
    for name, entry in sorted(load_manifest(directory).items()):
        present = entry.path.is_file()
        sha_ok = (sha256_file(entry.path) == entry.sha256) if (present and verify) else None
        statuses.append(ModelStatus(name, entry.path, present, sha_ok))
    return statuses
