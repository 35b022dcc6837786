"""The landmark dataset: one compressed NPZ shard of synthetic face crops (faces.py) per
split, and a JSON card.

    python -m export.factory.face_dataset --out data/faces128 --train 4000 --val 400 \\
        --test 400 --workers 2 --seed 0

Layout: `root/faces.json` (card: counts, seed, command, settings, HDRI splits, sources and
licences, timing) and `root/<split>.npz` with, for N samples,
- image (N, 128, 128, 3) uint8 sRGB: the photo as the net sees it (decode to linear);
- landmarks (N, 68, 2) float32: (col, row) pixels, pixel (i, j)'s centre at (j, i);
- angles_deg (N, 3) float32 yaw, pitch, roll (face_model.rotation_matrix);
- identity (N, K) and expression (N, E) float32: the model coefficients;
- rect (N, 4) float32: the crop's (x0, x1, y0, y1) in cm of the camera frame (scale 1);
- index (N,) int64.
Deterministic: sample `index` of `split` comes from SeedSequence([seed, split number, index])
alone, whatever the worker count (tested). A shard is written to a temporary name and
renamed; a split whose shard exists with the asked count is skipped.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import sys
import time
from pathlib import Path

import numpy as np

from export.factory import camera_model, faces, lighting
from export.factory.dataset import read_card
from relightcli.geometry.face_model import FaceModel

FORMAT_VERSION = 1
CARD_NAME = "faces.json"
SPLITS = ("train", "val", "test")
ARRAYS = ("image", "landmarks", "angles_deg", "identity", "expression", "rect", "index")
LICENSES = {
    "face_model": "ICT FaceKit: MIT License, Copyright (c) 2020 USC Institute for Creative Technologies",
    "hdri": "Poly Haven HDRIs: CC0 1.0",
}

_worker: dict = {}


def _init_worker(model_path: str | None) -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    _worker["model"] = FaceModel.load(model_path)
    _worker["hdris"] = lighting.hdri_splits()


def render_sample(seed: int, split: str, index: int) -> dict:
    """Sample `index` of `split` (run in a worker after `_init_worker`)."""
    model = _worker["model"]
    rng = np.random.default_rng([seed, SPLITS.index(split), index])
    spec = faces.sample_spec(rng, model, _worker["hdris"][split])
    out = faces.render_face(model, spec)
    return {"image": out["image"], "landmarks": out["landmarks"],
            "angles_deg": np.asarray(spec.angles_deg, np.float32),
            "identity": np.asarray(spec.identity, np.float32),
            "expression": np.asarray(spec.expression, np.float32), "rect": out["rect"],
            "index": np.int64(index), "lighting": spec.light.kind if spec.light.kind == "sky"
            else spec.light.name, "seconds": out["seconds"]}


def _render_task(task):
    return render_sample(*task)


def render_split(seed: int, split: str, count: int, workers: int, model_path=None) -> tuple[dict, dict]:
    """All samples of one split, in index order. Returns (arrays, facts for the card)."""
    start = time.perf_counter()
    tasks = [(seed, split, index) for index in range(count)]
    if workers > 1:
        context = multiprocessing.get_context("fork")
        with context.Pool(workers, _init_worker, (model_path,)) as pool:
            samples = list(pool.imap(_render_task, tasks, chunksize=8))
    else:
        _init_worker(model_path)
        samples = [_render_task(task) for task in tasks]
    arrays = {name: np.stack([s[name] for s in samples]) for name in ARRAYS}
    seconds = time.perf_counter() - start
    lightings: dict[str, int] = {}
    for s in samples:
        lightings[s["lighting"]] = lightings.get(s["lighting"], 0) + 1
    facts = {"count": count, "seconds": round(seconds, 1),
             "samples_per_minute": round(60.0 * count / max(seconds, 1e-9), 1),
             "worker_seconds_per_sample": round(float(np.mean([s["seconds"] for s in samples])), 3),
             "lightings": dict(sorted(lightings.items()))}
    return arrays, facts


def write_shard(root: Path, split: str, arrays: dict) -> Path:
    path = root / f"{split}.npz"
    tmp = root / f".{split}.tmp.npz"
    np.savez_compressed(tmp, **arrays)
    tmp.replace(path)
    return path


def settings_card() -> dict:
    """What the renders are made of (for the card)."""
    return {"crop": faces.CROP, "supersample": faces.SUPERSAMPLE, "spp": faces.SPP,
            "shading": "relightcli.render.shade_environment (MIS, control variate, sun sampled "
                       "apart), 2x2 supersampled, blurred 1 fine px inside the face",
            "environment_height": faces.ENV_HEIGHT, "pose_limits_deg": faces.POSE_LIMITS_DEG,
            "identity": f"N(0, 1) clipped at +-{faces.IDENTITY_CLIP}",
            "expression": f"none with p={faces.EXPRESSION_FREE}, else 1-4 blendshapes U(0, 1)",
            "framing": faces.FRAMING, "canonical_framing": faces.CANONICAL_FRAMING,
            "low_res": {"probability": faces.LOW_RES_PROBABILITY, "side": faces.LOW_RES_SIDE},
            "jpeg_probability": faces.JPEG_PROBABILITY, "sky_probability": lighting.SKY_PROBABILITY,
            "light_tilt_deg": faces.LIGHT_TILT_DEG}


def generate(root, counts: dict, seed: int, workers: int, command: str = "") -> dict:
    """Render the splits into `root` and write the card; returns the card."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    model = FaceModel.load()
    card_path = root / CARD_NAME
    card = json.loads(card_path.read_text()) if card_path.is_file() else {}
    card.update({"name": "relightcli synthetic face landmarks", "format_version": FORMAT_VERSION,
                 "seed": seed, "settings": settings_card(),
                 "sources": {"face_model": {"file": "models/face_model.npz", "sha256": model.sha256},
                             "hdri": {"folder": str(lighting.hdri_dir()),
                                      "splits": {k: list(v) for k, v in lighting.hdri_splits().items()}},
                             "licenses": LICENSES}})
    card.setdefault("splits", {})
    for split in SPLITS:
        count = counts.get(split, 0)
        done = card["splits"].get(split, {}).get("count")
        if count <= 0 or (done == count and (root / f"{split}.npz").is_file()):
            continue
        arrays, facts = render_split(seed, split, count, workers)
        write_shard(root, split, arrays)
        card["splits"][split] = {**facts, "workers": workers, "command": command}
        _write_json(card_path, card)
    _write_json(card_path, card)
    return card


def _write_json(path: Path, data: dict) -> None:
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")
    tmp.replace(path)


class FaceLandmarkDataset:
    """A generated landmark dataset, read for training: `.card`, `.ids(split)`,
    `.load(split, id)` (the interface export/train's Trainer uses), and `.arrays(split)`."""

    split_names = SPLITS

    def __init__(self, root):
        self.root = Path(root)
        self.card = read_card(self.root / CARD_NAME, FORMAT_VERSION,
                              "generate it with python -m export.factory.face_dataset")
        self._shards: dict[str, dict] = {}

    def arrays(self, split: str) -> dict:
        """The split's arrays as stored (empty arrays for a split not generated)."""
        if split not in self._shards:
            path = self.root / f"{split}.npz"
            if path.is_file():
                with np.load(path, allow_pickle=False) as stored:
                    self._shards[split] = {name: stored[name] for name in stored.files}
            else:
                self._shards[split] = {"index": np.zeros(0, np.int64)}
        return self._shards[split]

    def ids(self, split: str) -> list[str]:
        return [f"{int(i):06d}" for i in self.arrays(split)["index"]]

    def load(self, split: str, sample_id: str) -> dict:
        """One sample: image (128, 128, 3) float32 linear, landmarks (68, 2) float32, ..."""
        arrays = self.arrays(split)
        row = int(np.searchsorted(arrays["index"], int(sample_id)))
        sample = {name: arrays[name][row] for name in ARRAYS if name != "image"}
        sample["image"] = camera_model.decode_photo(arrays["image"][row])
        return sample


def open_face_dataset(root) -> FaceLandmarkDataset:
    return FaceLandmarkDataset(root)


def contact_sheet(root, split: str = "val", count: int = 12, columns: int = 6, zoom: int = 2,
                  predicted=None) -> np.ndarray:
    """(rows * 128 zoom, columns * 128 zoom, 3) uint8 sRGB sheet of the first `count` photos
    of a split with their landmarks (green; `predicted` (count, 68, 2) in red)."""
    import cv2

    arrays = FaceLandmarkDataset(root).arrays(split)
    tiles = []
    for k in range(count):
        tile = cv2.resize(arrays["image"][k], None, fx=zoom, fy=zoom, interpolation=cv2.INTER_NEAREST)
        sets = [(arrays["landmarks"][k], (0, 255, 0))]
        if predicted is not None:
            sets.append((predicted[k], (255, 40, 40)))
        for points, colour in sets:
            for col, row in (np.asarray(points) + 0.5) * zoom * 16:  # 4 fractional bits
                cv2.circle(tile, (int(col), int(row)), 16, colour, -1, cv2.LINE_AA, shift=4)
        tiles.append(tile)
    tiles += [np.zeros_like(tiles[0])] * (-len(tiles) % columns)
    rows = [np.concatenate(tiles[r:r + columns], axis=1) for r in range(0, len(tiles), columns)]
    return np.concatenate(rows, axis=0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m export.factory.face_dataset",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True)
    parser.add_argument("--train", type=int, default=4000)
    parser.add_argument("--val", type=int, default=400)
    parser.add_argument("--test", type=int, default=400)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    command = "python -m export.factory.face_dataset " + " ".join(argv if argv is not None else sys.argv[1:])
    card = generate(args.out, {"train": args.train, "val": args.val, "test": args.test},
                    args.seed, args.workers, command)
    print(json.dumps(card["splits"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
