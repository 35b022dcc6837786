"""Learning curves of the de-lighting net over width and data size (issue 47): is it at its
limit, or short of capacity or of data?

    python bench/delight_curves.py train --data data/factory256 --runs data/curves \
        [--sizes small_half small small_double] [--samples 1200 2400] [--steps 1500] [--crop 128]
    python bench/delight_curves.py score --data data/factory256 --runs data/curves \
        [--eval data/evalval512] [--out bench/results/delight_curves.json]

`train` trains one run per (width, training samples) in turn with the runtime's inputs (the
geometry net's normals: `python -m export.factory.coarse DATA --normals-only` first), both
cores, checkpoints every 250 steps: rerun the same command to resume where it stopped.
`score` reads each run's validation metrics (the factory's val split, the net alone) and its
training CPU-hours; with --eval it also exports each finished run's net into a copy of models/ and runs
the product's own `relight eval` on those scenes with it (albedo and relit through the whole
pipeline, which divides the photo by the light solved against this net's albedo). Choose by
validation only.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "export/train/configs/delight_small_runtime.json"
THREADS = 2


def run_dir(runs: Path, size: str, samples: int) -> Path:
    return runs / f"{size}_{samples}"


def train_command(data: str, out: Path, size: str, samples: int, steps: int, crop: int) -> list[str]:
    return [sys.executable, "-m", "export.train", "delight", "--config", str(CONFIG), "--data", data,
            "--out", str(out), "--steps", str(steps), "--threads", str(THREADS),
            "--set", f'size="{size}"', "--set", f"train_samples={samples}", "--set", f"crop={crop}"]


def train(args) -> None:
    for samples in args.samples:
        for size in args.sizes:
            out = run_dir(Path(args.runs), size, samples)
            print(f"{out.name}: training to step {args.steps}", flush=True)
            subprocess.run(train_command(args.data, out, size, samples, args.steps, args.crop), cwd=ROOT, check=True)


def last_record(path: Path) -> dict:
    lines = path.read_text().splitlines() if path.is_file() else []
    return json.loads(lines[-1]) if lines else {}


def pipeline_scores(run: Path, data: str, scenes: str, size: str, samples: int) -> dict:
    """The product's eval on `scenes` with this run's delight net in place of the shipped one."""
    with tempfile.TemporaryDirectory() as tmp:
        models = Path(tmp) / "models"
        shutil.copytree(ROOT / "models", models)
        step = last_record(run / "log.jsonl").get("step", 0)
        command = train_command(data, run, size, samples, step, 128) + ["--export-to", str(models)]
        subprocess.run(command, cwd=ROOT, check=True, capture_output=True)
        env = {**os.environ, "RELIGHT_MODELS_DIR": str(models)}
        # (exit status 1 when a scene fails, e.g. nobody found without the mask: the others count)
        done = subprocess.run([sys.executable, "-m", "relightcli", "eval", scenes, "--json"], cwd=ROOT,
                              env=env, capture_output=True, text=True)
    if not done.stdout.strip():
        raise RuntimeError(f"relight eval failed: {done.stderr[-2000:]}")
    report = json.loads(done.stdout)
    return {key: round(report[key]["psnr"], 3) for key in ("relit", "albedo", "shading") if key in report}


def score(args) -> None:
    rows = []
    for run in sorted(Path(args.runs).iterdir()):
        config_path = run / "config.json"
        if not config_path.is_file():
            continue
        config = json.loads(config_path.read_text())
        log = last_record(run / "log.jsonl")
        row = {"run": run.name, "size": config["size"], "train_samples": config["train_samples"],
               "step": log.get("step"), "cpu_hours": round(log.get("elapsed_s", 0) * THREADS / 3600, 2)}
        finished = row["step"] is not None and row["step"] >= config["steps"]
        if args.eval and finished:  # (exporting validates the net again: on the val split as it is now)
            row["pipeline"] = pipeline_scores(run, args.data, args.eval, config["size"], config["train_samples"])
        row["val"] = last_record(run / "val.jsonl")
        rows.append(row)
        print(json.dumps(row), flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(rows, indent=2) + "\n")
    print("| run | step | CPU-hours | val albedo dB (net) | val ratio-albedo dB | light log-L2 | pipeline relit / albedo |")
    print("|---|---|---|---|---|---|---|")
    for row in rows:
        val, pipe = row["val"], row.get("pipeline", {})
        print(f"| {row['run']} | {row['step']} | {row['cpu_hours']} | {val.get('albedo_psnr', float('nan')):.2f} | "
              f"{val.get('ratio_albedo_psnr', float('nan')):.2f} | {val.get('light_log_l2', float('nan')):.3f} | "
              f"{pipe.get('relit', '-')} / {pipe.get('albedo', '-')} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name in ("train", "score"):
        command = sub.add_parser(name)
        command.add_argument("--data", required=True)
        command.add_argument("--runs", required=True)
    sub.choices["train"].add_argument("--sizes", nargs="+", default=["small_half", "small", "small_double"])
    sub.choices["train"].add_argument("--samples", nargs="+", type=int, default=[1200, 2400])
    sub.choices["train"].add_argument("--steps", type=int, default=1500)
    sub.choices["train"].add_argument("--crop", type=int, default=128)
    sub.choices["score"].add_argument("--eval", help="eval scenes to run the product on with each net")
    sub.choices["score"].add_argument("--out")
    args = parser.parse_args()
    train(args) if args.command == "train" else score(args)


if __name__ == "__main__":
    main()
