"""The working data sets the benchmarks and learning curves read, rebuilt by name from the
factory's own commands (every one resumable: a set half made is finished, a whole one is left
as it is).

    python bench/sets.py list
    python bench/sets.py make val60 factory256 [--workers 2] [--dry-run]

Each set is a factory dataset under data/ and, for the eval sets, its scene folders
(`export.factory.eval_scenes`); the 60-person sets are one scene per person (docs/RESULTS.md,
"Four people are not a validation set"). Times on two cores.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RENDER = ["--spp", "128", "--target-error", "0.03", "--bounces", "2"]


def generate(out: str, count: int, splits: str, resolution: int, seed: int, *extra: str) -> list[str]:
    return ["-m", "export.factory.generate", "--out", out, "--count", str(count), "--splits", splits,
            "--resolution", str(resolution), "--seed", str(seed), *RENDER, *extra]


def scenes(factory: str, out: str, split: str) -> list[str]:
    return ["-m", "export.factory.eval_scenes", factory, out, "--split", split]


ONE_EACH = ("--samples-per-person", "1")
MIXED = ("--pose-variety", "0.5")
# name -> (what it is, its commands: python arguments, each run with --workers after `generate`)
SETS = {
    "val60": ("60 validation people at 512, one scene each (choose on it; ~3 min)",
              [generate("data/factory512val60", 60, "val=1", 512, 21, *ONE_EACH),
               scenes("data/factory512val60", "data/evalval512p60", "val")]),
    "val60m": ("the same 60 validation people, cameras and lights, poses mixed (~5 min)",
               [generate("data/factory512val60m", 60, "val=1", 512, 21, *ONE_EACH, *MIXED),
                scenes("data/factory512val60m", "data/evalval512p60m", "val")]),
    "test60": ("60 test people at 512 (the README's table; never to choose on; ~3 min)",
               [generate("data/factory512test60", 60, "test=1", 512, 21, *ONE_EACH),
                scenes("data/factory512test60", "data/eval512p60", "test")]),
    "factory256": ("the nets' training set: 2,400 training and 300 validation samples at 256, "
                   "catalogue poses (~70 min at ~40 a minute; the models' card's set, without its test split)",
                   [generate("data/factory256", 2700, "train=0.8,val=0.1", 256, 0)]),
    "factory256-normals": ("factory256's geometry-net normals, the de-lighting net's input (~15 min)",
                           [["-m", "export.factory.coarse", "data/factory256", "--normals-only",
                             "--splits", "train,val"]]),
    "factory256-priors": ("factory256's fitted bodies' maps, the geometry prior net's input (~70 min)",
                          [["-m", "export.factory.coarse", "data/factory256", "--priors", "--splits", "train,val"]]),
    "factory256v": ("7,600 more training samples at 256, poses mixed (~3 hours)",
                    [generate("data/factory256v", 7600, "train=1", 256, 1, *MIXED)]),
}


def commands(name: str, workers: int) -> list[list[str]]:
    out = []
    for args in SETS[name][1]:
        extra = ["--workers", str(workers)] if "export.factory.generate" in args else []
        out.append([sys.executable, *args, *extra])
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("list", help="the sets and what each is")
    make = sub.add_parser("make", help="make (or finish) the named sets, in order")
    make.add_argument("names", nargs="+", choices=sorted(SETS))
    make.add_argument("--workers", type=int, default=2)
    make.add_argument("--dry-run", action="store_true", help="print the commands only")
    args = parser.parse_args()
    if args.command == "list":
        for name, (what, _) in SETS.items():
            print(f"{name:<20} {what}")
        return 0
    for name in args.names:
        for command in commands(name, args.workers):
            print(" ".join(command[1:]), flush=True)
            if not args.dry_run:
                subprocess.run(command, cwd=ROOT, check=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
