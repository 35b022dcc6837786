"""A `relight eval --json` report split by the people's poses (the factory's scenes).

    python bench/by_pose.py bench/results/eval512p60/raytrace.json data/eval512p60
    python bench/by_pose.py bench/results/oracles_test60.json data/eval512p60   # bench/oracles.py's rows

The 60-person sets hold a few poses each (validation: the high kick `fight04` and `tpose`; test:
`fly02`, a body flying level, and `standing02`, `standing04`), so a set's mean is a mix of
poses: this prints, per pose, the scenes, those scored (a scene where nobody is found fails)
and the mean normals (degrees), shading, relit and albedo (dB); for a `bench/oracles.py` report,
each of its rows (the truth in place of one quantity) so.
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
import warnings
from pathlib import Path

import numpy as np


def scores(entry: dict) -> list:
    """[normals, shading, relit, albedo] of one scene: `relight eval`'s entry (layers as dicts
    with "psnr", normals as {"deg"}) or an oracle row's (plain numbers, "normal_deg")."""
    if entry.get("error"):
        return [np.nan] * 4
    normal = entry["normal"].get("deg") if isinstance(entry.get("normal"), dict) else entry.get("normal_deg")
    layers = [entry[layer]["psnr"] if isinstance(entry[layer], dict) else entry[layer]
              for layer in ("shading", "relit", "albedo")]
    return [np.nan if normal is None else normal, *layers]


def by_pose(report: dict, scenes: Path, row: str | None = None) -> dict:
    """pose -> (scenes, scored, [normals, shading, relit, albedo] means over the scored); `row`:
    which of an oracle report's rows."""
    rows = collections.defaultdict(list)
    entries = report["per_scene"] if row is None else [{**entry[row], "scene": entry["scene"]} for entry in report["scenes"]]
    for entry in entries:
        pose = json.loads((scenes / entry["scene"] / "scene.json").read_text())["person"]["pose"]
        rows[pose].append(scores(entry))
    out = {}
    for pose, values in sorted(rows.items()):
        values = np.array(values, float)
        scored = ~np.isnan(values[:, 2])
        with warnings.catch_warnings():  # a layer an oracle row does not score is all NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            means = np.nanmean(values[scored], axis=0) if scored.any() else [np.nan] * 4
        out[pose] = (len(values), int(scored.sum()), [float(v) for v in means])
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("report", type=Path, help="relight eval --json output")
    parser.add_argument("scenes", type=Path, help="the scene folders it was run on")
    args = parser.parse_args()
    report = json.loads(args.report.read_text())
    rows = [None] if "per_scene" in report else [key for key in report["scenes"][0] if key != "scene"]
    print("row             pose           scenes scored  normals  shading   relit  albedo")
    for row in rows:
        for pose, (count, scored, (normal, shading, relit, albedo)) in by_pose(report, args.scenes, row).items():
            print(f"{row or '-':<15} {pose:<14} {count:6d} {scored:6d} {normal:8.1f} {shading:8.2f} {relit:7.2f} {albedo:7.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
