"""Batch throughput (issue "Batch at scale"): images per minute sequential, with the process
pool and on Ray, and memory per worker / growth over a long batch.

    python bench/bench_batch.py --images 12                 # sequential vs pool (2 workers)
    python bench/bench_batch.py --images 12 --ray           # also --engine ray
    python bench/bench_batch.py --images 200 --growth       # RSS of one worker over 200 images

Inputs are copies of the shipped example (different seeds would not change the cost). Prints a
table and writes bench/results/batch_<modes>.json. Target (issue): >= 30 images/min with the pool on
2 cores for 512x512 crops.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
EXAMPLES = REPO / "examples"


def make_inputs(folder: Path, count: int) -> Path:
    """`count` RGBA copies of the example (the mask as alpha, so every image is a full item)."""
    sys.path.insert(0, str(REPO))
    from relightcli.io.images import read_image, write_image

    photo = read_image(EXAMPLES / "skier.jpg").rgb
    mask = read_image(EXAMPLES / "skier_mask.png", srgb=False).rgb[..., 0]
    first = folder / "in" / "p000.png"
    first.parent.mkdir(parents=True)
    write_image(first, photo, mask)
    for index in range(1, count):
        shutil.copy(first, folder / "in" / f"p{index:03d}.png")
    return folder / "in"


def run_batch(inputs: Path, out: Path, extra: list[str]) -> dict:
    command = [sys.executable, "-m", "relightcli", str(inputs), "--hdr", str(EXAMPLES / "noon_grass.hdr"),
               "-o", str(out), "--json", *extra]
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, cwd=REPO,
                          env=os.environ | {"PYTHONPATH": str(REPO)})
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"batch failed ({done.returncode}):\n{done.stderr[-2000:]}")
    report = json.loads(done.stdout)
    count = report["ok"]
    rss = [item.get("worker_rss_mb") for item in report["items"] if item.get("worker_rss_mb")]
    result = {"images": count, "seconds": seconds, "images_per_min": 60.0 * count / seconds,
              "peak_rss_mb_any_process": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0,
              "worker_rss_mb_first_last": [rss[0], rss[-1]] if rss else None}
    if len(rss) >= 10:  # growth: slope of RSS over the second half of the batch (after warm-up)
        import numpy as np

        half = np.asarray(rss[len(rss) // 2:])
        (slope, _), cov = np.polyfit(np.arange(half.size), half, 1, cov=True)
        result["rss_growth_mb_per_100_images"] = float(slope * 100)
        result["rss_growth_stderr_mb_per_100_images"] = float(np.sqrt(cov[0, 0]) * 100)
        quarters = np.array_split(np.asarray(rss), 4)
        result["worker_rss_mb_quarter_means"] = [round(float(q.mean()), 1) for q in quarters]
        result["worker_rss_mb_quarter_max"] = [round(float(q.max()), 1) for q in quarters]
        result["worker_rss_mb_every_10th"] = rss[::10]
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=12)
    parser.add_argument("--resolution", type=int, default=None)
    parser.add_argument("--spp", type=int, default=None)
    parser.add_argument("--ray", action="store_true")
    parser.add_argument("--growth", action="store_true", help="one worker, RSS logged per image")
    args = parser.parse_args()
    extra = (["--resolution", str(args.resolution)] if args.resolution else []) + \
            (["--spp", str(args.spp)] if args.spp else [])
    results = {}
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        inputs = make_inputs(folder, args.images)
        runs = {"sequential": ["--workers", "1", "--threads", "2"], "pool": ["--workers", "2", "--threads", "2"]}
        if args.ray:
            runs["ray"] = ["--engine", "ray", "--workers", "2", "--threads", "2"]
        if args.growth:
            runs = {"growth": ["--workers", "1", "--threads", "2"]}
        for name, flags in runs.items():
            results[name] = run_batch(inputs, folder / name, extra + flags)
            print(f"{name:<11} {results[name]['images']:4d} images  {results[name]['seconds']:7.1f} s  "
                  f"{results[name]['images_per_min']:6.2f} images/min  peak RSS {results[name]['peak_rss_mb_any_process']:.0f} MB")
    out = REPO / "bench" / "results" / f"batch_{'_'.join(results)}.json"  # one file per set of modes
    out.write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
