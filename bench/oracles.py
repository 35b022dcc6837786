"""Where the dB go (issue 49): the truth in place of one quantity at a time, through the product's
own pipeline (`relight eval`'s: the default method and albedo, 512 crops), on eval scenes.

    python bench/oracles.py data/evalval512 data/factory512val --split val --out FILE.json
    python bench/oracles.py data/eval512 data/factory512test --split test --out FILE.json

Rows (every row after `ours` keeps the true mask, and is scored against `true mask`):
  ours             the product as users run it (its own mask)
  true mask        the scene's mask (gt_mask.png) as the input's
  true body        the factory's naked body under the clothes, posed as rendered, in place of
                   the fitted body (export.factory.person.naked_body): a perfect body fit
  true 3D landmarks  BlazePose's world landmarks (and its image landmarks' depths) replaced by
                   the naked body's, its 2D keypoints kept, the body then fitted as usual: a
                   BlazePose without depth noise
  true normals     the geometry stage's front normals replaced by the true ones
  true depth       front and back depth replaced by the factory's (as in `true geometry`),
                   the net's normals kept
  true AO          the AO net's map (the refinement's input and the AO layer) replaced by the
                   factory's AO over the true mask, the net's outside it
  true geometry    front and back normals and depth replaced by the factory's (the depth
                   moved to our front depth's median over the person, so the fitted bodies and
                   the reconstruction stay where they were; the silhouette's rim pixels blend
                   with that median when the maps are cropped)
  true light       the factory's input light (in the photo's units) for the solved one, the
                   albedo at that light's own level (bench/light_solve.py's oracle)
  true light, net level  the same light, the albedo levelled to the net's as the product does
  true albedo      relit = the true albedo x our shading (no rerun)
  true shading     relit = our albedo x the true shading (no rerun)
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

from export.body_model import true_world_landmarks  # noqa: E402
from export.factory import dataset  # noqa: E402
from export.factory.person import naked_body  # noqa: E402
from export.factory.render import camera_vertices, world_to_pixel  # noqa: E402
from relightcli import compose, stages  # noqa: E402
from relightcli.evaluate import find_scenes, load_scene, scene_metrics  # noqa: E402
from relightcli.pipeline import RelightOptions, predict_scene  # noqa: E402
from relightcli.stages.frame import Models, unit  # noqa: E402

ROWS = ("ours", "true mask", "true body", "true 3D landmarks", "true normals", "true depth", "true AO", "true geometry",
        "true light", "true light, net level", "true albedo", "true shading")
KEYS = ("relit", "albedo", "shading", "normal_deg")


def with_true_geometry(geometry_stage, truth: dict, normals: bool = True):
    """The geometry stage, then the factory's depth and (`normals`) normals (full frame) in its
    maps."""
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
        g = replace(g, front_depth=front + shift, back_depth=np.minimum(back + shift, front + shift))
        if normals:
            normal = unit(compose.crop_square(truth["normal"], box))
            g = replace(g, front_normal=normal, back_normal=unit(compose.crop_square(truth["back_normal"], box)))
            frame.normal = normal * (frame.crop_mask[..., None] > 0.5)
        frame.geometry = g
    return stage


def with_true_ao(ao_stage, truth: dict):
    """The AO stage, then the factory's AO (full frame) in the net's map over the true mask."""
    def stage(frame, options, models):
        ao_stage(frame, options, models)
        inside = compose.crop_square(truth["mask"].astype(np.float32), frame.box)
        true_ao = compose.crop_square(truth["ao"].astype(np.float32), frame.box)
        frame.ao_net = (inside * true_ao + (1.0 - inside) * frame.ao_net).astype(np.float32)
        frame.ao = frame.ao_net
    return stage


def true_body_in_crop(body, meta: dict, rect, box, photo_width: int) -> np.ndarray:
    """(V, 3) float64: a scene's naked body's vertices (export.factory.person.naked_body) in the
    crop's world frame (body_fit.BodyFit's: x and y span [-1, 1] over the crop, z in the same
    unit, +Z toward the viewer)."""
    camera = camera_vertices(body.vertices, meta["spec"]["pitch_deg"], meta["spec"]["yaw_deg"])
    resolution = int(meta["settings"]["resolution"])
    pixels = world_to_pixel(camera, rect, resolution) * (photo_width / resolution)
    units_per_pixel = 2.0 / box.size
    crop = np.empty_like(camera)
    crop[:, 0] = (pixels[:, 0] - box.x0) * units_per_pixel - 1.0
    crop[:, 1] = 1.0 - (pixels[:, 1] - box.y0) * units_per_pixel
    crop[:, 2] = camera[:, 2] * (photo_width / (rect[1] - rect[0])) * units_per_pixel
    return crop


def with_true_body(body_stage, meta: dict, rect):
    """The body stage (its notes), then the first person's fit replaced by the true body; and
    a body_maps stage tracing it with its own triangles. Eval scenes hold one person."""
    from relightcli.geometry.body_fit import BodyFit
    from relightcli.geometry.body_maps import bodies_scene, render_body_maps

    body = naked_body(meta["person"]["seed"], meta["person"]["split"], meta["person"].get("pose_variety", 0.0))
    body_vertices = int(body.faces.max()) + 1  # the helpers' vertices after them: no face uses them

    def stage_body(frame, options, models):
        body_stage(frame, options, models)
        vertices = true_body_in_crop(body, meta, rect, frame.box, frame.image.shape[1])[:body_vertices]
        frame.bodies = [BodyFit(shape=None, rotations=None, translation=None, scale=float("nan"),
                                vertices=vertices, residual_px=0.0, converged=True, reason="true body")]

    def stage_body_maps(frame, options, models):
        frame.body_scene = bodies_scene([frame.bodies[0].vertices], body.faces)
        frame.body_maps = render_body_maps(frame.body_scene, options.resolution, where=frame.crop_mask > 0)
        frame.body_hits = frame.body_maps.front
    return stage_body, stage_body_maps


def with_true_world(body_stage, meta: dict):
    """The body stage fitted to the first person's BlazePose keypoints and the true body's world
    landmarks (true_world_landmarks) in place of BlazePose's, its image landmarks' depths made
    the true ones too."""
    world = true_world_landmarks(naked_body(meta["person"]["seed"], meta["person"]["split"], meta["person"].get("pose_variety", 0.0)), meta)

    def stage(frame, options, models):
        person = frame.people[0]
        # the image landmarks' depths too (the fit's witness of the turn, body_fit.depth_side),
        # in their pixels: the world's metres scaled by the landmarks' own spread over the world's
        landmarks = person.pose.landmarks.copy()
        spread = np.ptp(landmarks[:, :2], axis=0).max() / max(np.ptp(world[:, :2], axis=0).max(), 1e-9)
        landmarks[:, 2] = world[:, 2] * spread
        pose = replace(person.pose, world=world.astype(person.pose.world.dtype), landmarks=landmarks)
        frame.people[0] = replace(person, pose=pose)
        body_stage(frame, options, models)
    return stage


def scored(scene, pred: dict) -> dict:
    metrics = scene_metrics(scene, pred)
    row = {layer: metrics[layer]["psnr"] for layer in ("relit", "albedo", "shading")}
    row["normal_deg"] = metrics.get("normal", {}).get("deg")
    return row


def measure(folder: Path, truth: dict, rows: tuple, models: Models) -> dict:
    scene = load_scene(folder)
    options = RelightOptions(outputs=("relit", "albedo", "shading", "normal"), threads=2)
    meta = json.loads((folder / "scene.json").read_text())
    gains = np.asarray(meta["spec"]["augmentation"]["gains"], np.float32)
    out, kept = {}, dict(stages.STAGES)
    for row in rows:
        if row in ("true albedo", "true shading"):
            continue
        try:
            if row == "true body":
                stages.STAGES["body"], stages.STAGES["body_maps"] = with_true_body(kept["body"], meta, truth["rect"])
            if row == "true 3D landmarks":
                stages.STAGES["body"] = with_true_world(kept["body"], meta)
            if row == "true normals":
                stages.STAGES["geometry"] = with_true_normals(kept["geometry"], scene.normal)
            if row == "true AO":
                stages.STAGES["ao"] = with_true_ao(kept["ao"], truth)
            if row in ("true depth", "true geometry"):
                stages.STAGES["geometry"] = with_true_geometry(kept["geometry"], truth, normals=row == "true geometry")
            source = {"true light": "true-light-own-level", "true light, net level": "true-light"}.get(row, "")
            with substituted(source, truth["light_a"] * gains):
                pred = predict_scene(scene, options, use_gt_mask=row != "ours", models=models)
        except Exception as error:  # noqa: BLE001 - a failed scene is reported, the others count
            out[row] = {"error": str(error)}
            continue
        finally:
            stages.STAGES.update(kept)
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
