"""One photo as a whole process, as a user runs it (issue 50): `relight` started, models loaded,
the shipped example relit with its mask, outputs written, the process ended.

    python bench/whole_process.py [--resolutions 256 512 1024] [--runs 5] [--out FILE.json]

Times each run from outside (wall clock around the child process) and reads its peak resident
memory (the child's ru_maxrss) and the report's stage seconds (`--json`). Prints, per working
crop, the median and range of the whole process, the median of the item's own seconds (the
relighting inside the process) and the median of each stage. Run it on an otherwise idle
machine: the README's speed table is its output.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ["examples/skier.jpg", "--mask", "examples/skier_mask.png", "--hdr", "examples/noon_grass.hdr"]


def one_run(resolution: int, out: Path) -> dict:
    command = [sys.executable, "-m", "relightcli", *EXAMPLE, "-o", str(out / "skier.png"),
               "--resolution", str(resolution), "--overwrite", "--json"]
    start = time.perf_counter()
    child = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    stdout = child.stdout.read()
    _, status, usage = os.wait4(child.pid, 0)  # the child's own peak memory, not the largest so far
    wall = time.perf_counter() - start
    child.returncode = os.waitstatus_to_exitcode(status)
    if child.returncode != 0:
        raise RuntimeError(f"relight exited {child.returncode}")
    item = json.loads(stdout)["items"][0]
    return {"wall_s": wall, "item_s": item["seconds"].get("total"), "stages": item["seconds"],
            "peak_rss_gb": usage.ru_maxrss / 2**20}


def measure(resolution: int, runs: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        records = [one_run(resolution, Path(tmp)) for _ in range(runs)]
    walls = [r["wall_s"] for r in records]
    stages = {key: float(np.median([r["stages"][key] for r in records if key in r["stages"]]))
              for key in records[0]["stages"]}
    return {"resolution": resolution, "runs": runs, "wall_median_s": float(np.median(walls)),
            "wall_range_s": [min(walls), max(walls)], "item_median_s": float(np.median([r["item_s"] for r in records])),
            "peak_rss_gb": max(r["peak_rss_gb"] for r in records), "stages_median_s": stages}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolutions", nargs="+", type=int, default=[256, 512, 1024])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    rows = [measure(resolution, args.runs) for resolution in args.resolutions]
    for row in rows:
        stages = ", ".join(f"{k} {v:.2f}" for k, v in sorted(row["stages_median_s"].items(), key=lambda kv: -kv[1])
                           if k != "total")
        print(f"{row['resolution']}: whole process {row['wall_median_s']:.2f} s "
              f"({row['wall_range_s'][0]:.2f}-{row['wall_range_s'][1]:.2f}), the item {row['item_median_s']:.2f} s, "
              f"peak {row['peak_rss_gb']:.2f} GB; "
              f"{stages}", flush=True)
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
