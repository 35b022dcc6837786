"""One photo as a whole process, as a user runs it (issue 50): `relight` started, models loaded,
the shipped example relit with its mask, outputs written, the process ended.

    python bench/whole_process.py [--resolutions 256 512 1024] [--runs 5] [--out FILE.json]
    python bench/whole_process.py --own-mask   # the README's first command: the person found
    python bench/whole_process.py --resolutions 512 --runs 8 --against /tmp/before  # A/B

`--against DIR`: another checkout (`git worktree add /tmp/before COMMIT`) timed in turn with
this one, run for run alternating, so that both see the same machine: this VM's speed drifts
by up to 2.5x over hours, which only a side-by-side comparison sees past.

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
OWN_MASK = ["examples/skier.jpg", "--hdr", "examples/noon_grass.hdr"]


# As an installed package runs: with its modules' bytecode (pip compiles it when it installs; a
# development shell with PYTHONDONTWRITEBYTECODE set would compile our modules at every start,
# ~0.2 s here), written by a first run that is not timed
CHILD_ENV = {key: value for key, value in os.environ.items() if key != "PYTHONDONTWRITEBYTECODE"}


def one_run(resolution: int, out: Path, tree: Path = ROOT, example=EXAMPLE) -> dict:
    command = [sys.executable, "-m", "relightcli", *example, "-o", str(out / "skier.png"),
               "--resolution", str(resolution), "--overwrite", "--json"]
    start = time.perf_counter()
    child = subprocess.Popen(command, cwd=tree, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
                             env={**CHILD_ENV, "PYTHONPATH": str(tree)})
    stdout = child.stdout.read()
    _, status, usage = os.wait4(child.pid, 0)  # the child's own peak memory, not the largest so far
    wall = time.perf_counter() - start
    child.returncode = os.waitstatus_to_exitcode(status)
    if child.returncode != 0:
        raise RuntimeError(f"relight exited {child.returncode}")
    item = json.loads(stdout)["items"][0]
    return {"wall_s": wall, "item_s": item["seconds"].get("total"), "stages": item["seconds"],
            "peak_rss_gb": usage.ru_maxrss / 2**20}


def measure(resolution: int, runs: int, trees: list[Path], example=EXAMPLE) -> list[dict]:
    """One row per tree; with two, their runs alternate (A B B A A B ...)."""
    records = {tree: [] for tree in trees}
    with tempfile.TemporaryDirectory() as tmp:
        for index in range(runs):
            for tree in trees if index % 2 == 0 else trees[::-1]:
                records[tree].append(one_run(resolution, Path(tmp), tree, example))
    return [{"tree": str(tree), **summarise(resolution, records[tree])} for tree in trees]


def summarise(resolution: int, records: list[dict]) -> dict:
    runs = len(records)
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
    parser.add_argument("--against", type=Path, help="another checkout, timed in turn with this one")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--own-mask", action="store_true", help="no --mask: the product finds the person")
    args = parser.parse_args()
    example = OWN_MASK if args.own_mask else EXAMPLE
    trees = [ROOT] + ([args.against.resolve()] if args.against else [])
    with tempfile.TemporaryDirectory() as tmp:
        for tree in trees:
            one_run(args.resolutions[0], Path(tmp), tree, example)  # writes the bytecode; not timed
    rows = [row for resolution in args.resolutions for row in measure(resolution, args.runs, trees, example)]
    for row in rows:
        stages = ", ".join(f"{k} {v:.2f}" for k, v in sorted(row["stages_median_s"].items(), key=lambda kv: -kv[1])
                           if k != "total")
        print(f"{row['tree']} {row['resolution']}: whole process {row['wall_median_s']:.2f} s "
              f"({row['wall_range_s'][0]:.2f}-{row['wall_range_s'][1]:.2f}), the item {row['item_median_s']:.2f} s, "
              f"peak {row['peak_rss_gb']:.2f} GB; "
              f"{stages}", flush=True)
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
