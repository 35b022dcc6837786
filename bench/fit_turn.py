"""The fit's turn and its mirror (issue 49): every eval person fitted to BlazePose's world
landmarks as given and with their depths mirrored (z -> -z: the torso's turn -> minus the turn,
the 2D keypoints unchanged), against the true torso yaw; whether a cue at hand picks the better
of the two; and the product's fit (`shipped`: refitted to the mirrored turn where BlazePose's
image landmarks' depths firmly say the other way, body_fit.depth_side).

    python bench/fit_turn.py data/evalval512p60 data/factory512val60 --split val --out FILE.json

True mask. Per person: the true torso yaw, BlazePose's own (its world landmarks' hips and
shoulders), each fit's yaw, RMS keypoint residual and 3D joint error, the nose's side of the
shoulders' midpoint in 2D (in shoulder widths) and the image landmarks' depth_side (body_fit).
Printed: the torso yaw error (mean, median) and the 3D joints of each fit, of the better one
(an oracle), of the one each cue picks (the lower keypoint residual, the nose's side,
BlazePose's own sign), of the product's, and of the product's rule with the witness's
threshold at WITNESS_THRESHOLDS (torso lengths); and how often each sign agrees with the
truth's over the people turned more than 10 degrees.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import bench_fit_renders as fit_bench  # noqa: E402
from scene_run import replaced, run_scene  # noqa: E402

from export.factory import dataset  # noqa: E402
from relightcli.geometry.body_fit import TURN_WITNESS_MIN, blazepose_world_to_model  # noqa: E402
from relightcli.pipeline import RelightOptions  # noqa: E402
from relightcli.stages import body as body_stage  # noqa: E402
from relightcli.stages.frame import Models  # noqa: E402

NOSE, LEFT_SHOULDER, RIGHT_SHOULDER, LEFT_HIP, RIGHT_HIP = 0, 11, 12, 23, 24
WITNESS_THRESHOLDS = (0.0, 0.25, 0.5, 1.0, 1.5, 2.0)


def turn_error(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def hip_centred(joints: dict) -> dict:
    hips = (joints[fit_bench.HIPS[0]] + joints[fit_bench.HIPS[1]]) / 2
    return {name: point - hips for name, point in joints.items()}


def measure(folder: Path, data, split: str, models) -> dict:
    """Both fits of the scene's person against the truth (the body stage's fit run twice)."""
    truth = hip_centred(fit_bench.true_joints(data, split, folder.name.split("_", 1)[1])[0])
    seen = {}
    fit_once = body_stage._fit_on_one_opencv_thread

    def fit_all(model, keypoints, visibility, world, silhouette, models=None, turn_witness=None):
        mirrored = None if world is None else np.asarray(world) * np.array([1.0, 1.0, -1.0])
        fits = [fit_once(model, keypoints, visibility, w, silhouette, models) for w in (world, mirrored)]
        fits.append(fit_once(model, keypoints, visibility, world, silhouette, models, turn_witness))
        # the witness at any strength: refitted wherever its sign contradicts the fit's
        firm = None if turn_witness is None or not np.isfinite(turn_witness) else \
            float(np.sign(turn_witness)) * max(abs(turn_witness), TURN_WITNESS_MIN)
        fits.append(fit_once(model, keypoints, visibility, world, silhouette, models, firm))
        seen.update(inputs=(keypoints, world), fits=fits, witness=turn_witness)
        return fits[2]

    with replaced(body_stage, "_fit_on_one_opencv_thread", fit_all):
        # the body_normal layer needs the stages up to the body maps, no more
        frame = run_scene(folder, RelightOptions(outputs=("body_normal",), threads=2), models)
    if "fits" not in seen:
        return {"scene": folder.name, "skipped": "nobody fitted"}
    row = {"scene": folder.name, "true_yaw": fit_bench.yaw_deg(fit_bench.facing(truth)), "depth_side": seen["witness"]}
    for tag, fit in zip(("given", "mirrored", "shipped", "any_witness"), seen["fits"]):
        if not fit.converged:
            return {"scene": folder.name, "skipped": f"the {tag} fit did not converge"}
        frame.bodies = [fit]
        joints = hip_centred(fit_bench.fitted_joints(frame, models)[0])
        row[f"{tag}_yaw"] = fit_bench.yaw_deg(fit_bench.facing(joints))
        row[f"{tag}_residual_px"] = float(fit.residual_px)
        row[f"{tag}_3d_cm"] = float(np.mean([np.linalg.norm(joints[n] - truth[n]) for n in fit_bench.MAIN]) * 100)
    keypoints, world = (np.asarray(a, np.float64) for a in seen["inputs"])
    model_world = blazepose_world_to_model(world)
    row["blazepose_yaw"] = fit_bench.yaw_deg(fit_bench.facing(dict(zip(
        fit_bench.HIPS + fit_bench.SHOULDERS, model_world[[LEFT_HIP, RIGHT_HIP, LEFT_SHOULDER, RIGHT_SHOULDER]]))))
    middle = (keypoints[LEFT_SHOULDER] + keypoints[RIGHT_SHOULDER]) / 2
    row["nose_side"] = float((keypoints[NOSE, 0] - middle[0]) / (abs(keypoints[LEFT_SHOULDER, 0] - keypoints[RIGHT_SHOULDER, 0]) + 1e-6))
    return row


def summary(rows: list) -> dict:
    """Yaw error (mean, median) and 3D cm of each choice; sign agreement over the turned."""
    rows = [r for r in rows if "skipped" not in r]
    pick = {
        "given": lambda r: "given",
        "the product (body_fit.depth_side)": lambda r: "shipped",
        "mirrored": lambda r: "mirrored",
        "the better (oracle)": lambda r: min(("given", "mirrored"), key=lambda t: turn_error(r[f"{t}_yaw"], r["true_yaw"])),
        "lower residual": lambda r: min(("given", "mirrored"), key=lambda t: r[f"{t}_residual_px"]),
        "the nose's side": lambda r: "given" if np.sign(r["given_yaw"]) == np.sign(r["nose_side"]) else "mirrored",
        "BlazePose's sign": lambda r: "given" if np.sign(r["given_yaw"]) == np.sign(r["blazepose_yaw"]) else "mirrored",
    }
    for threshold in WITNESS_THRESHOLDS:  # the product's rule at other strengths
        pick[f"the witness from {threshold} torso lengths"] = (
            lambda r, t=threshold: "any_witness" if abs(r["depth_side"]) >= t else "given")
    out = {"people": len(rows)}
    for name, choose in pick.items():
        errors = [turn_error(r[f"{choose(r)}_yaw"], r["true_yaw"]) for r in rows]
        out[name] = {"yaw_mean": float(np.mean(errors)), "yaw_median": float(np.median(errors)),
                     "3d_cm": float(np.mean([r[f"{choose(r)}_3d_cm"] for r in rows]))}
    turned = [r for r in rows if abs(r["true_yaw"]) > 10]
    out["sign_agrees_over_turned"] = {key: float(np.mean([np.sign(r[key]) == np.sign(r["true_yaw"]) for r in turned]))
                                      for key in ("given_yaw", "blazepose_yaw", "nose_side", "depth_side")}
    out["turned"] = len(turned)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", help="eval scene folders (python -m export.factory.eval_scenes)")
    parser.add_argument("factory", help="the factory dataset they came from")
    parser.add_argument("--split", default="val")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    data, models = dataset.open_dataset(args.factory), Models(2)
    rows = fit_bench.each_scene(args.scenes, lambda folder: measure(folder, data, args.split, models))
    result = summary(rows)
    print(json.dumps(result, indent=1))
    if args.out:
        args.out.write_text(json.dumps({"summary": result, "scenes": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
