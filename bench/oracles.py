"""Where the dB go (issue 49): the truth in place of one quantity at a time, through the product's
own pipeline (`relight eval`'s: the default method and albedo, 512 crops), on eval scenes.

    python bench/oracles.py data/evalval512 data/factory512val --split val --out FILE.json
    python bench/oracles.py data/eval512 data/factory512test --split test --out FILE.json

Rows (every row after `ours` keeps the true mask, and is scored against `true mask`):
  ours             the product as users run it (its own mask)
  true mask        the scene's mask (gt_mask.png) as the input's
  true normals     the geometry stage's front normals replaced by the true ones
  true geometry    front and back normals and depth replaced by the factory's (the depth
                   moved to our front depth's median over the person, so the fitted bodies and
                   the reconstruction stay where they were; the silhouette's rim pixels blend
                   with that median when the maps are cropped)
  true light       the factory's input light (in the photo's units) for the solved one, the
                   albedo at that light's own level (bench/light_solve.py's oracle)
  true light, net level  the same light, the albedo levelled to the net's as the product does
  true albedo      relit = the true albedo x our shading (no rerun)
  true shading     relit = our albedo x the true shading (no rerun)
There is no row for the fitted body: the eval scenes keep no body parameters.
Relit / albedo / shading PSNR by `relight eval`'s protocol, the normals' mean angle; the means
over the scenes every row scored; prints the table with each row's gain over `true mask`.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from bench_geometry_prior import with_true_normals  # noqa: E402
from light_solve import substituted  # noqa: E402

from export.factory import dataset  # noqa: E402
from relightcli import compose, stages  # noqa: E402
from relightcli.evaluate import find_scenes, load_scene, scene_metrics  # noqa: E402
from relightcli.pipeline import RelightOptions, predict_scene  # noqa: E402
from relightcli.stages.frame import Models, unit  # noqa: E402

ROWS = ("ours", "true mask", "true normals", "true geometry", "true light", "true light, net level",
        "true albedo", "true shading")
KEYS = ("relit", "albedo", "shading", "normal_deg")


def with_true_geometry(geometry_stage, truth: dict):
    """The geometry stage, then the factory's normals and depth (full frame) in its maps."""
    inside = truth["mask"] > 0.5

    def filled(depth):  # outside the person: the person's median, so cropping blends no zeros in
        return np.where(inside, depth, np.median(depth[inside])).astype(np.float32)

    def stage(frame, options, models):
        geometry_stage(frame, options, models)
        g, box = frame.geometry, frame.box
        # factory world units -> crop units: the crop spans 2 units over box.size photo pixels
        x0, x1 = truth["rect"][:2]
        scale = (2.0 / box.size) / ((x1 - x0) / truth["mask"].shape[1])
        front = compose.crop_square(filled(truth["front_depth"]), box) * scale
        back = compose.crop_square(filled(truth["back_depth"]), box) * scale
        person = frame.crop_mask > 0.5
        shift = np.median(g.front_depth[person]) - np.median(front[person])
        normal = unit(compose.crop_square(truth["normal"], box))
        frame.geometry = replace(g, front_normal=normal, back_normal=unit(compose.crop_square(truth["back_normal"], box)),
                                 front_depth=front + shift, back_depth=np.minimum(back + shift, front + shift))
        frame.normal = normal * (frame.crop_mask[..., None] > 0.5)
    return stage


def scored(scene, pred: dict) -> dict:
    metrics = scene_metrics(scene, pred)
    row = {layer: metrics[layer]["psnr"] for layer in ("relit", "albedo", "shading")}
    row["normal_deg"] = metrics.get("normal", {}).get("deg")
    return row


def measure(folder: Path, truth: dict, rows: tuple, models: Models) -> dict:
    scene = load_scene(folder)
    options = RelightOptions(outputs=("relit", "albedo", "shading", "normal"), threads=2)
    gains = np.asarray(json.loads((folder / "scene.json").read_text())["spec"]["augmentation"]["gains"], np.float32)
    out, geometry_stage = {}, stages.STAGES["geometry"]
    for row in rows:
        if row in ("true albedo", "true shading"):
            continue
        try:
            if row == "true normals":
                stages.STAGES["geometry"] = with_true_normals(geometry_stage, scene.normal)
            if row == "true geometry":
                stages.STAGES["geometry"] = with_true_geometry(geometry_stage, truth)
            source = {"true light": "true-light-own-level", "true light, net level": "true-light"}.get(row, "")
            with substituted(source, truth["light_a"] * gains):
                pred = predict_scene(scene, options, use_gt_mask=row != "ours", models=models)
        except Exception as error:  # noqa: BLE001 - a failed scene is reported, the others count
            out[row] = {"error": str(error)}
            continue
        finally:
            stages.STAGES["geometry"] = geometry_stage
        out[row] = scored(scene, pred)
        if row == "true mask":
            out["true albedo"] = {**scored(scene, {**pred, "relit": scene.albedo * pred["shading"]}), "albedo": None}
            out["true shading"] = {**scored(scene, {**pred, "relit": pred["albedo"] * scene.shading}), "shading": None}
    return out


def summarise(scenes: list, rows: tuple) -> dict:
    """Means over the scenes every row scored, and each row's gain over `true mask`."""
    done = [s for s in scenes if all("error" not in s[r] for r in rows)]
    summary = {}
    for row in rows:
        summary[row] = {k: float(np.mean([s[row][k] for s in done])) for k in KEYS
                        if done and all(s[row][k] is not None for s in done)}
    if "true mask" in summary:
        for row, means in summary.items():
            means.update({f"{k}_gain": means[k] - summary["true mask"][k] for k in ("relit", "albedo", "shading")
                          if k in means and k in summary["true mask"]})
    return {"scenes": len(done), "rows": summary}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", help="eval scene folders (python -m export.factory.eval_scenes)")
    parser.add_argument("factory", help="the factory dataset they came from (light, depth, back normals)")
    parser.add_argument("--split", default="val")
    parser.add_argument("--rows", nargs="+", default=list(ROWS), choices=ROWS)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    rows = tuple(r for r in ROWS if r in args.rows or (r == "true mask" and {"true albedo", "true shading"} & set(args.rows)))
    data, models, scenes = dataset.open_dataset(args.factory), Models(2), []
    for folder in find_scenes(args.scenes):
        truth = data.load(args.split, folder.name.split("_", 1)[1])
        scenes.append({"scene": folder.name, **measure(folder, truth, rows, models)})
        print(folder.name, {r: {k: round(v, 2) for k, v in scenes[-1][r].items() if isinstance(v, float)}
                            for r in rows}, flush=True)
    summary = summarise(scenes, rows)
    print(f"{summary['scenes']} scenes scored by every row")
    print(f"{'row':<16}" + "".join(f"{k:>12}" for k in KEYS) + "".join(f"{k + ' gain':>14}" for k in KEYS[:3]))
    for row, means in summary["rows"].items():
        print(f"{row:<16}" + "".join(f"{means.get(k, float('nan')):>12.2f}" for k in KEYS)
              + "".join(f"{means.get(k + '_gain', float('nan')):>14.2f}" for k in KEYS[:3]))
    if args.out:
        args.out.write_text(json.dumps({"summary": summary, "scenes": scenes}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
