"""A `relight eval --json` report split by the people's poses (the factory's scenes).

    python bench/by_pose.py bench/results/eval512p60/raytrace.json data/eval512p60

The 60-person sets hold a few poses each (validation: the high kick `fight04` and `tpose`; test:
`fly02`, a body flying level, and `standing02`, `standing04`), so a set's mean is a mix of
poses: this prints, per pose, the scenes, those scored (a scene where nobody is found fails)
and the mean normals (degrees), shading, relit and albedo (dB).
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
from pathlib import Path

import numpy as np


def by_pose(report: dict, scenes: Path) -> dict:
    """pose -> (scenes, scored, [normals, shading, relit, albedo] means over the scored)."""
    rows = collections.defaultdict(list)
    for entry in report["per_scene"]:
        pose = json.loads((scenes / entry["scene"] / "scene.json").read_text())["person"]["pose"]
        if entry.get("error"):
            rows[pose].append([np.nan] * 4)
            continue
        normal = (entry.get("normal") or {}).get("deg")
        rows[pose].append([np.nan if normal is None else normal,
                           *(entry[layer]["psnr"] for layer in ("shading", "relit", "albedo"))])
    out = {}
    for pose, values in sorted(rows.items()):
        values = np.array(values, float)
        scored = ~np.isnan(values[:, 1])
        means = np.nanmean(values[scored], axis=0) if scored.any() else [np.nan] * 4
        out[pose] = (len(values), int(scored.sum()), [float(v) for v in means])
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("report", type=Path, help="relight eval --json output")
    parser.add_argument("scenes", type=Path, help="the scene folders it was run on")
    args = parser.parse_args()
    print("pose           scenes scored  normals  shading   relit  albedo")
    for pose, (count, scored, (normal, shading, relit, albedo)) in by_pose(json.loads(args.report.read_text()),
                                                                          args.scenes).items():
        print(f"{pose:<14} {count:6d} {scored:6d} {normal:8.1f} {shading:8.2f} {relit:7.2f} {albedo:7.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
