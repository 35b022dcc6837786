"""A `relight eval --json` report split by the people's poses (the factory's scenes).

    python bench/by_pose.py bench/results/eval512p60/raytrace.json data/eval512p60
    python bench/by_pose.py bench/results/oracles_test60.json data/eval512p60   # bench/oracles.py's rows
    python bench/by_pose.py bench/results/fit_renders_test60_gt_witness.json data/eval512p60   # the fit's

The 60-person sets hold a few poses each (validation: the high kick `fight04` and `tpose`; test:
`fly02`, a body flying level, and `standing02`, `standing04`), so a set's mean is a mix of
poses: this prints, per pose, the scenes, those scored (a scene where nobody is found fails)
and the mean normals (degrees), shading, relit and albedo (dB); for a `bench/oracles.py` report,
each of its rows (the truth in place of one quantity) so; for a `bench/bench_fit_renders.py`
report, the fit's errors (3D joints, their depth, 2D, cm; the torso's yaw, degrees) over the
people fitted.
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


FIT_COLUMNS = ("3d_cm", "depth_cm", "2d_cm", "yaw_deg")


def fit_by_pose(report: dict, scenes: Path) -> dict:
    """pose -> (scenes, fitted, [3D, depth, 2D cm, yaw degrees] means over the fitted) of a
    bench_fit_renders report (a scene skipped, nobody fitted, has no errors)."""
    rows = collections.defaultdict(list)
    for entry in report["scenes"]:
        pose = json.loads((scenes / entry["scene"] / "scene.json").read_text())["person"]["pose"]
        rows[pose].append([entry.get(column, np.nan) for column in FIT_COLUMNS])
    out = {}
    for pose, values in sorted(rows.items()):
        values = np.array(values, float)
        fitted = ~np.isnan(values[:, 0])
        means = values[fitted].mean(axis=0) if fitted.any() else [np.nan] * len(FIT_COLUMNS)
        out[pose] = (len(values), int(fitted.sum()), [float(v) for v in means])
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("report", type=Path, help="relight eval --json, oracles.py or bench_fit_renders.py output")
    parser.add_argument("scenes", type=Path, help="the scene folders it was run on")
    args = parser.parse_args()
    report = json.loads(args.report.read_text())
    if "summary" in report and any("3d_cm" in entry for entry in report["scenes"]):
        print("pose           scenes fitted  3D cm  depth cm  2D cm  yaw deg")
        for pose, (count, fitted, (joints, depth, flat, yaw)) in fit_by_pose(report, args.scenes).items():
            print(f"{pose:<14} {count:6d} {fitted:6d} {joints:6.1f} {depth:9.1f} {flat:6.1f} {yaw:8.1f}")
        return 0
    rows = [None] if "per_scene" in report else [key for key in report["scenes"][0] if key != "scene"]
    print("row             pose           scenes scored  normals  shading   relit  albedo")
    for row in rows:
        for pose, (count, scored, (normal, shading, relit, albedo)) in by_pose(report, args.scenes, row).items():
            print(f"{row or '-':<15} {pose:<14} {count:6d} {scored:6d} {normal:8.1f} {shading:8.2f} {relit:7.2f} {albedo:7.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
