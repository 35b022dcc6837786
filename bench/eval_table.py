"""The README's relighting-quality table: `relight eval` for every method, with the predicted
and with the true person mask, as markdown rows (and the JSON of each run under --out); the
normals column is their mean angle to the true normals in degrees.

    python bench/eval_table.py data/eval512p60 [--out bench/results/eval512p60] [--resolution 512]

Eval scenes, 60 people (one scene each): `python -m export.factory.generate --out
data/factory512test60 --count 60 --splits test=1 --resolution 512 --workers 2 --seed 21 --spp 128
--target-error 0.03 --bounces 2 --samples-per-person 1` then `python -m
export.factory.eval_scenes data/factory512test60 data/eval512p60 --split test`; their
validation twin, to choose on: the same with `--out data/factory512val60 --splits val=1`, then
`eval_scenes data/factory512val60 data/evalval512p60 --split val`. The older sets of 20 scenes
hold only 4 people (the factory's default renders each person 6 times), too few to choose by
(docs/RESULTS.md, "Four people are not a validation set"): `python -m export.factory.generate
--out data/factory512test --count 20 --splits test=1 --resolution 512 --workers 2 --seed 0
--spp 128 --target-error 0.03 --bounces 2` then `python -m export.factory.eval_scenes
data/factory512test data/eval512`.
Validation scenes, to choose settings on (used for the mask's edge snapping):
`python -m export.factory.generate --out data/factory512val --count 20 --splits val=1
--resolution 512 --workers 1 --seed 2 --spp 128 --target-error 0.03 --bounces 2` then
`python -m export.factory.eval_scenes data/factory512val data/evalval512 --split val`.
A larger validation set, 150 scenes at 256 with many more people and outfits:
`python -m export.factory.generate --out data/factory256p --count 1500 --splits
train=0.9,val=0.1 --resolution 256 --workers 2 --seed 0 --spp 128 --target-error 0.03
--bounces 2` (the nets' training set), then `python -m export.factory.eval_scenes
data/factory256p data/evalval256 --split val`, then
`relight eval data/evalval256 --resolution 256 --use-gt-mask` (the albedo's single gain was
chosen on it).
Two more validation sets at 256 (the outline's normals were chosen on them,
relightcli.geometry.silhouette): `python -m export.factory.generate --out data/factory256v7
--count 150 --splits val=1 --resolution 256 --workers 2 --seed 7 --spp 128 --target-error 0.03
--bounces 2` then `python -m export.factory.eval_scenes data/factory256v7 data/evalval256v7
--split val` (T-posed and fighting figures), and the same with `--out data/factory256t11
--count 120 --splits train=1 --seed 11` then `eval_scenes data/factory256t11
data/evaltrainpose256 --split train`: new people in the training split's poses (standing,
resting, sitting...), which the validation poses lack.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

RUNS = [  # (method, true mask, albedo source; None: the default)
    ("raytrace", False, None), ("raytrace-norefine", False, None), ("sh9", False, None),
    ("sh25", False, None), ("raytrace", False, "ratio"), ("raytrace", False, "net"),
    ("raytrace", True, None), ("raytrace-norefine", True, None), ("sh9", True, None),
    ("raytrace", True, "ratio"), ("raytrace", True, "net"),
]


def cell(layer: dict) -> str:
    return f"{layer['mse']:.2f} / {layer['ssim']:.4f} / {layer['psnr']:.2f}"


def run_name(method: str, true_mask: bool, albedo: str | None) -> str:
    return f"{method}{'_gtmask' if true_mask else ''}{f'_{albedo}albedo' if albedo else ''}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("--out", default="bench/results/eval")
    parser.add_argument("--resolution", type=int, default=None)
    parser.add_argument("--methods", default=None,
                        help="comma-separated methods to (re)run; the table uses every run in --out")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    wanted = set(args.methods.split(",")) if args.methods else {method for method, _, _ in RUNS}
    for method, true_mask, albedo in RUNS:
        if method not in wanted:
            continue
        command = [sys.executable, "-m", "relightcli", "eval", args.dataset, "--method", method, "--json"]
        command += ["--albedo", albedo] if albedo else []
        command += ["--use-gt-mask"] if true_mask else []
        command += ["--resolution", str(args.resolution)] if args.resolution else []
        # exit status 1 when a scene fails (nobody found without the mask): the JSON counts it
        done = subprocess.run(command, capture_output=True, text=True)
        if done.returncode not in (0, 1) or not done.stdout.strip():
            raise RuntimeError(f"{' '.join(command)} failed: {done.stderr[-2000:]}")
        name = run_name(method, true_mask, albedo)
        (out / f"{name}.json").write_text(done.stdout)
        print(f"{name} done", file=sys.stderr, flush=True)
    rows = []
    for method, true_mask, albedo in RUNS:
        path = out / f"{run_name(method, true_mask, albedo)}.json"
        if path.is_file():
            result = json.loads(path.read_text())
            label = (f"ours `{method}`" + (", true mask" if true_mask else "")
                     + (f", {albedo} albedo (`--albedo {albedo}`)" if albedo else ""))
            normal = f"{result['normal']['deg']:.1f}" if "normal" in result else "n/a"
            rows.append(f"| {label} | {cell(result['relit'])} | {cell(result['albedo'])} | "
                        f"{cell(result['shading'])} | {normal} | {result['seconds_per_image']:.1f} |")
            if result.get("failed"):
                rows[-1] += f" ({result['failed']} of {result['scenes'] + result['failed']} scenes failed)"
    (out / "table.md").write_text("\n".join(rows) + "\n")
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
