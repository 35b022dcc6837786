"""Do the geometry nets' normals tell a torso's turn (issue 49)? Before a fit term that matches
the fitted body's normals to the nets': the mean front normal over the true torso (the
quadrilateral of the true shoulders and hips, inside the true mask) of the image-only net
("geometry") and of the final normals (the prior net on the fitted bodies, smoothed), turned
into a yaw and compared with the true torso's, beside the fit's own yaw and the same measure
on the true normals (what a mean normal can tell).

    python bench/normals_yaw.py data/evalval512 data/factory512val --split val
    python bench/normals_yaw.py data/eval512 data/factory512test --split test

Per source: the yaw error's mean and median (degrees) and the slope of its yaw on the true
one (1: it follows the turn; 0: it always faces the camera).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import bench_fit_renders as fit_bench  # noqa: E402
from scene_run import run_scene  # noqa: E402

from export.factory import dataset  # noqa: E402
from relightcli import compose  # noqa: E402
from relightcli.evaluate import find_scenes, load_scene  # noqa: E402
from relightcli.pipeline import RelightOptions  # noqa: E402
from relightcli.stages.frame import Models, net_side, resample  # noqa: E402

TORSO = ("upperarm01.L", "upperarm01.R", "upperleg01.R", "upperleg01.L")


def mean_yaw(normals: np.ndarray, region: np.ndarray) -> float:
    n = normals[region]
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-6)
    return fit_bench.yaw_deg(n.mean(axis=0))


def hip_centred(joints: dict) -> dict:
    hips = (joints[fit_bench.HIPS[0]] + joints[fit_bench.HIPS[1]]) / 2
    return {name: value - hips for name, value in joints.items()}


def measure(folder: Path, data, split: str, models) -> dict:
    scene = load_scene(folder)
    truth_m, truth_px, _ = fit_bench.true_joints(data, split, folder.name.split("_", 1)[1])
    options = RelightOptions(outputs=("normal",), method="sh9", threads=2)
    frame = run_scene(folder, options, models, scene=scene)
    side, box = frame.crop_mask.shape[0], frame.box
    quad = np.array([(truth_px[n] - [box.x0, box.y0]) * side / box.size for n in TORSO])
    region = np.zeros((side, side), np.uint8)
    cv2.fillConvexPoly(region, np.round(quad).astype(np.int32), 1)
    region = (region > 0) & (frame.crop_mask > 0.5)
    net = models.get("geometry")
    plain = resample(net.predict(resample(frame.crop, net_side(net, side))).front_normal, side)
    row = {"scene": folder.name, "true": fit_bench.yaw_deg(fit_bench.facing(hip_centred(truth_m))),
           "image net": mean_yaw(plain, region), "final normals": mean_yaw(frame.normal, region)}
    if scene.normal is not None:  # the measure itself: the true normals' mean over the region
        row["true normals"] = mean_yaw(compose.crop_square(scene.normal, box), region)
    fitted = fit_bench.fitted_joints(frame, models)
    if fitted is not None:
        row["fit"] = fit_bench.yaw_deg(fit_bench.facing(hip_centred(fitted[0])))
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes")
    parser.add_argument("factory")
    parser.add_argument("--split", default="test")
    args = parser.parse_args()
    data, models = dataset.open_dataset(args.factory), Models(2, 512)
    rows = [measure(folder, data, args.split, models) for folder in find_scenes(args.scenes)]
    for source in ("true normals", "image net", "final normals", "fit"):
        have = [r for r in rows if source in r]
        truth, yaw = np.array([r["true"] for r in have]), np.array([r[source] for r in have])
        error = np.abs((yaw - truth + 180.0) % 360.0 - 180.0)
        print(f"{source}: {len(have)} scenes, yaw error mean {error.mean():.1f} median {np.median(error):.1f} deg, "
              f"slope on the true yaw {np.polyfit(truth, yaw, 1)[0]:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
