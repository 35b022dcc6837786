"""The landmark lifter (issue 49): BlazePose's world landmarks corrected by a net learnt on the
factory's people, for the body fit (whose 3D error is mostly BlazePose's depths: docs/RESULTS.md,
"What limits the fit"). Not shipped: "The fit's landmarks lifted" there.

    python -m export.lift pairs data/factory256 data/factory256v --splits val train --out data/lift
    python -m export.lift train data/lift --out data/runs_lift/w1024 --width 1024 --epochs 40 --dropout 0.3
    python -m export.lift export data/runs_lift/w1024 --to DIR     # DIR: a copy of models/

`pairs`: per sample, the runtime's people stage on the sample as the photo (its true mask, the
whole sample as the crop: export.factory.coarse.working_frame) and the first person's pose, beside
the true body's landmarks as BlazePose gives its world ones (export.body_model.true_world_landmarks);
one file per dataset and split, DATASET_SPLIT.npz in --out, written every 250 samples so that the
command resumes. `train`: an MLP from the pose's features (relightcli.nets.lift.features) to the
world landmarks' correction, the mirror image of each pose as augmentation, chosen by its mean
landmark error on the val pairs. `export`: the chosen epoch's net to ONNX (DIR/lift.onnx) with
its manifest entry.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from export.factory import dataset

CHUNK = 250


def pose_pair(data, split: str, sample_id: str, models) -> dict:
    """One sample's BlazePose pose (landmarks (33, 5), world (33, 3); NaN where nobody was
    found) and the true body's world landmarks (33, 3)."""
    from export.body_model import true_world_landmarks
    from export.factory.coarse import working_frame
    from export.factory.person import naked_body
    from relightcli.stages.people import stage_people

    sample, meta = data.load(split, sample_id, ["input", "mask"]), data.meta(split, sample_id)
    frame, options = working_frame(sample, None)
    stage_people(frame, options, models)
    pose = frame.people[0].pose if frame.people else None
    person = meta["person"]
    body = naked_body(person["seed"], person["split"], person.get("pose_variety", 0.0), placed=False)
    nan = np.full((33, 3), np.nan)
    return {"landmarks": np.c_[nan, nan[:, :2]] if pose is None else pose.landmarks,
            "world": nan if pose is None else pose.world,
            "true": true_world_landmarks(body, meta),
            "pose": person["pose"]}


def pairs(roots: list[str], splits: list[str], out: Path, threads: int = 1) -> None:
    """pose_pair of every sample of the datasets' splits not yet in out/DATASET_SPLIT.npz."""
    from relightcli.stages.frame import Models

    models = Models(threads=threads)
    out.mkdir(parents=True, exist_ok=True)
    for root in roots:
        data = dataset.open_dataset(root)
        for split in splits:
            path = out / f"{Path(root).name}_{split}.npz"
            kept = dict(np.load(path)) if path.exists() else {"ids": np.array([], str)}
            done = set(kept["ids"].tolist())
            todo = [i for i in data.ids(split) if i not in done]
            rows, start = [], time.time()
            for n, sample_id in enumerate(todo, 1):
                rows.append({"ids": sample_id, **pose_pair(data, split, sample_id, models)})
                if n % CHUNK == 0 or n == len(todo):
                    kept = _appended(kept, rows)
                    np.savez(path.with_suffix(".tmp.npz"), **kept)
                    path.with_suffix(".tmp.npz").replace(path)
                    rows = []
                    print(f"{path.name}: {len(kept['ids'])} pairs ({n / (time.time() - start):.1f} a second)",
                          flush=True)


def _appended(kept: dict, rows: list[dict]) -> dict:
    new = {key: np.stack([np.asarray(row[key]) for row in rows]) for key in rows[0]}
    return {key: np.concatenate([kept[key], new[key]]) if key in kept and len(kept[key]) else new[key]
            for key in new}


# --- training ---------------------------------------------------------------------------------

def load_pairs(folder: Path, split: str) -> dict:
    """The pairs of every dataset's `split` in `folder`, where BlazePose found the person."""
    files = sorted(folder.glob(f"*_{split}.npz"))
    if not files:
        raise SystemExit(f"no *_{split}.npz pairs in {folder}: make them with python -m export.lift pairs")
    parts = [dict(np.load(path)) for path in files]
    joined = {key: np.concatenate([part[key] for part in parts]) for key in parts[0]}
    found = np.isfinite(joined["world"]).all(axis=(1, 2))
    return {key: value[found] for key, value in joined.items()}


def arrays(pairs: dict, mirror: bool, depth_only: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(inputs (N, FEATURES), targets (N, 99): the truth minus BlazePose's world landmarks (in
    depth alone with `depth_only`: x and y as BlazePose gave them), world (N, 33, 3)); with
    `mirror` the mirror image of each pair after them."""
    from relightcli.nets.lift import features, mirrored

    rows = list(zip(pairs["landmarks"], pairs["world"], pairs["true"]))
    if mirror:
        rows += [(*mirrored(landmarks, world), mirrored(landmarks, true)[1]) for landmarks, world, true in rows]
    inputs = np.stack([features(landmarks, world) for landmarks, world, _ in rows])
    world = np.stack([world for _, world, _ in rows])
    targets = np.stack([true - world for _, world, true in rows])
    if depth_only:
        targets[:, :, :2] = 0.0
    targets = targets.reshape(len(rows), -1)
    return inputs, targets.astype(np.float32), world


def make_net(width: int, blocks: int = 2, dropout: float = 0.1):
    """An MLP: a linear layer to `width`, `blocks` residual blocks of two linear layers with ReLU
    and dropout, a linear layer to the 99 corrections (its weights zero: it starts from BlazePose)."""
    import torch
    from torch import nn

    from relightcli.nets.lift import FEATURES

    class Block(nn.Module):
        def __init__(self):
            super().__init__()
            self.layers = nn.Sequential(nn.Linear(width, width), nn.ReLU(), nn.Dropout(dropout),
                                        nn.Linear(width, width), nn.ReLU(), nn.Dropout(dropout))

        def forward(self, x):
            return x + self.layers(x)

    head = nn.Linear(width, 99)
    nn.init.zeros_(head.weight)
    nn.init.zeros_(head.bias)
    torch.manual_seed(0)
    return nn.Sequential(nn.Linear(FEATURES, width), nn.ReLU(), *[Block() for _ in range(blocks)], head)


def landmark_errors(correction: np.ndarray, targets: np.ndarray) -> dict:
    """Mean landmark error (cm) with the correction and without it, and the depth's alone."""
    left = (targets - correction).reshape(len(targets), 33, 3)
    before = targets.reshape(len(targets), 33, 3)
    return {"cm": 100 * float(np.linalg.norm(left, axis=2).mean()),
            "cm_blazepose": 100 * float(np.linalg.norm(before, axis=2).mean()),
            "depth_cm": 100 * float(np.abs(left[:, :, 2]).mean()),
            "depth_cm_blazepose": 100 * float(np.abs(before[:, :, 2]).mean())}


def train(folder: Path, out: Path, width: int = 256, epochs: int = 200, batch: int = 256, lr: float = 1e-3,
          samples: int | None = None, threads: int = 1, dropout: float = 0.1, weight_decay: float = 0.0,
          depth_only: bool = False) -> dict:
    """Trains the lifter on `folder`'s train pairs (the first `samples`), keeps the epoch with
    the lowest mean landmark error on its val pairs (against the truth: with `depth_only` the
    net corrects the depths alone); out/ gets lift.pt, log.jsonl, metrics.json."""
    import torch

    torch.set_num_threads(threads)
    train_pairs, val_pairs = load_pairs(folder, "train"), load_pairs(folder, "val")
    if samples is not None:
        train_pairs = {key: value[:samples] for key, value in train_pairs.items()}
    x, y, _ = arrays(train_pairs, mirror=True, depth_only=depth_only)
    vx, vy, _ = arrays(val_pairs, mirror=False)
    x, y, vx = torch.from_numpy(x), torch.from_numpy(y), torch.from_numpy(vx)
    net = make_net(width, dropout=dropout)
    optimiser = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=weight_decay)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, epochs)
    generator = torch.Generator().manual_seed(0)
    out.mkdir(parents=True, exist_ok=True)
    best, start = None, time.time()
    with open(out / "log.jsonl", "w") as log:
        for epoch in range(1, epochs + 1):
            net.train()
            for index in torch.randperm(len(x), generator=generator).split(batch):
                error = (net(x[index]) - y[index]).view(-1, 33, 3).norm(dim=2).mean()
                optimiser.zero_grad()
                error.backward()
                optimiser.step()
            schedule.step()
            net.eval()
            with torch.no_grad():
                record = {"epoch": epoch, "train_cm": 100 * float(error),
                          **landmark_errors(net(vx).numpy(), vy), "elapsed_s": round(time.time() - start, 1)}
            log.write(json.dumps(record) + "\n")
            if best is None or record["cm"] < best["cm"]:
                best = record
                torch.save(net.state_dict(), out / "lift.pt")
    metrics = {"best": best, "width": width, "epochs": epochs, "lr": lr, "batch": batch, "dropout": dropout,
               "weight_decay": weight_decay, "depth_only": depth_only,
               "train_pairs": int(len(train_pairs["ids"])), "val_pairs": int(len(val_pairs["ids"])),
               "parameters": sum(p.numel() for p in net.parameters()), "folder": str(folder)}
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    return metrics


def export(run: Path, models: Path) -> Path:
    """The run's chosen net to models/lift.onnx (features (N, FEATURES) -> correction (N, 99)),
    checked against torch, with its manifest entry."""
    import onnxruntime
    import torch

    from export.manifest import update_manifest
    from relightcli.nets.lift import FEATURES
    from relightcli.nets.manifest import sha256_file

    metrics = json.loads((run / "metrics.json").read_text())
    net = make_net(metrics["width"])
    net.load_state_dict(torch.load(run / "lift.pt"))
    net.eval()
    path = Path(models) / "lift.onnx"
    probe = torch.from_numpy(np.random.default_rng(0).normal(size=(2, FEATURES)).astype(np.float32))
    torch.onnx.export(net, (probe,), str(path), input_names=["features"], output_names=["correction"],
                      dynamic_axes={"features": {0: "N"}, "correction": {0: "N"}}, opset_version=17, dynamo=False)
    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    with torch.no_grad():
        parity = float(np.abs(session.run(None, {"features": probe.numpy()})[0] - net(probe).numpy()).max())
    update_manifest(models, "lift", {
        "file": "lift.onnx", "sha256": sha256_file(path), "multiple": 1, "parity_max_abs": parity,
        "inputs": [{"name": "features", "shape": ["N", FEATURES], "dtype": "float32"}],
        "outputs": [{"name": "correction", "shape": ["N", 99], "dtype": "float32"}],
        "config": {"family": "lift", "width": metrics["width"], "blocks": 2},
        "normalisation": "relightcli.nets.lift.features: image landmarks about the hips over the body's extent, "
                         "visibility, presence, world landmarks in metres; the output is added to the world landmarks",
        "colour_space": "none (landmarks)",
        "source": "trained here: python -m export.lift (BlazePose's poses of factory samples against their true bodies)",
        "metrics": {"val": metrics["best"]}, "training": metrics})
    return path


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m export.lift", description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    make = commands.add_parser("pairs", help="BlazePose's pose and the true landmarks, per sample")
    make.add_argument("data", nargs="+", help="factory datasets")
    make.add_argument("--splits", nargs="+", default=["train", "val"])
    make.add_argument("--out", type=Path, required=True)
    make.add_argument("--threads", type=int, default=1)
    learn = commands.add_parser("train", help="the lifter on the pairs")
    learn.add_argument("pairs", type=Path, help="the folder `pairs` wrote")
    learn.add_argument("--out", type=Path, required=True)
    learn.add_argument("--width", type=int, default=256)
    learn.add_argument("--epochs", type=int, default=200)
    learn.add_argument("--lr", type=float, default=1e-3)
    learn.add_argument("--samples", type=int, default=None, help="the first N training pairs")
    learn.add_argument("--threads", type=int, default=1)
    learn.add_argument("--dropout", type=float, default=0.1)
    learn.add_argument("--weight-decay", type=float, default=0.0)
    learn.add_argument("--depth-only", action="store_true", help="correct the depths alone")
    ship = commands.add_parser("export", help="a trained run's net to ONNX with its manifest entry")
    ship.add_argument("run", type=Path)
    ship.add_argument("--to", type=Path, required=True, help="the models folder")
    args = parser.parse_args(argv)
    if args.command == "export":
        print(export(args.run, args.to))
    elif args.command == "pairs":
        pairs(args.data, args.splits, args.out, args.threads)
    elif args.command == "train":
        print(json.dumps(train(args.pairs, args.out, args.width, args.epochs, lr=args.lr, samples=args.samples,
                               threads=args.threads, dropout=args.dropout, weight_decay=args.weight_decay,
                               depth_only=args.depth_only)["best"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
