"""After training: the ONNX export of a trained net into a models directory, with a manifest
entry that records the training config, a summary of the data card and the validation metrics."""

from __future__ import annotations

import math
from pathlib import Path

from export.manifest import update_manifest
from export.onnx_export import export_onnx, parity, person_like_inputs

PARITY_TOLERANCE = 1e-3  # max |ORT - torch|; the nets' own tests see ~1e-6
MAX_LIST = 8  # longer lists in the data card are summarised by their length


def _json_safe(value):
    """Non-finite floats (an infinite PSNR of a perfect prediction) become None: strict JSON."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


def card_summary(card: dict) -> dict:
    """The data card with long lists replaced by {"count": n} (HDRI names, pose files...)."""
    def shorten(value):
        if isinstance(value, dict):
            return {k: shorten(v) for k, v in value.items()}
        if isinstance(value, (list, tuple)) and len(value) > MAX_LIST:
            return {"count": len(value)}
        return value
    return shorten(dict(card))


def _samples_used(trainer) -> dict:
    """Samples per split the trainer actually saw (the card's counts describe the generation
    run that wrote it, which may have been stopped or resumed since): its training samples
    (config train_samples of them), each other split's count."""
    dataset = trainer.dataset
    return {split: len(trainer.train_ids) if split == "train" else len(dataset.ids(split))
            for split in dataset.split_names}


def _started_from(config, models_dir: Path, run_dir: Path) -> dict | None:
    """A fine-tuned net's origin: the record of the file it started from (config.init), taken
    from `models_dir`'s manifest entry when that entry describes the same file (its sha256).
    When that file is this run's own earlier export (exported into the folder it started from,
    then again), its entry's origin stands."""
    import json

    from relightcli.nets.manifest import sha256_file

    path = models_dir / "manifest.json"
    if not config.init or not Path(config.init).is_file() or not path.is_file():
        return None
    entry = json.loads(path.read_text())["models"].get(config.net, {})
    sha256 = sha256_file(config.init)
    if entry.get("sha256") != sha256:
        return {"sha256": sha256, "file": str(config.init)}
    exported_by = entry.get("training", {}).get("run_dir")
    if "fine_tuned_from" in entry and exported_by and Path(exported_by).resolve() == Path(run_dir).resolve():
        return entry["fine_tuned_from"]
    return {key: entry[key] for key in ("sha256", "training", "training_data", "metrics") if key in entry}


def export_trained(trainer, models_dir: str | Path, card: dict, run: dict) -> dict:
    """Export `trainer.net` to `<models_dir>/<family>.onnx`, check ONNX Runtime against torch,
    and insert its entry in `<models_dir>/manifest.json`. `run` is `Trainer.run`'s result.
    A net fine-tuned from a shipped file (config.init) keeps that file's record
    (`fine_tuned_from`). Returns the entry."""
    config = trainer.config
    net = trainer.net.eval()
    multiple = net.io_contract().multiple
    size = max(multiple, int(math.ceil(config.export_size / multiple)) * multiple)
    path = Path(models_dir) / f"{config.net}.onnx"
    origin = _started_from(config, Path(models_dir), trainer.out)  # read before the export replaces the file
    extra = _json_safe({
        "training": {"config": config.to_dict(), "step": run["step"], "elapsed_s": round(run["elapsed_s"], 1),
                     "stopped_by": run["stopped_by"], "run_dir": str(trainer.out)},
        "training_data": {**card_summary(card), "samples_used": _samples_used(trainer)},
        "metrics": {"split": "val", **run["metrics"]},
        **({"fine_tuned_from": origin} if origin else {}),
    })
    entry = export_onnx(net, path, height=size, width=size, extra=extra)
    feeds = person_like_inputs(net.io_contract(), size, size, seed=1)
    worst = max(parity(net, path, feeds).values())
    if not worst <= PARITY_TOLERANCE:
        raise RuntimeError(f"{path}: ONNX Runtime differs from torch by {worst:.3g} (> {PARITY_TOLERANCE})")
    entry["parity_max_abs"] = worst
    update_manifest(models_dir, config.net, entry)
    return entry
