"""The geometry from the image alone against the fitted body's prior and the prior net (issue 19).

    python bench/bench_geometry_prior.py data/evalval512 --use-gt-mask --out bench/results/geometry_prior_val_gt.json

Runs `relight eval`'s pipeline (`--method raytrace-norefine`, ratio albedo) on every scene
folder once per variant of the geometry stage and scores it by the eval protocol
(relightcli.evaluate: relit / albedo / shading PSNR, normals' mean angle over the mask), plus
the normals' angle on the person's pixels the fitted body covers:

  net        the geometry net from the image alone (the prior-free path)
  body       the fitted body's normals where it covers the person, the net's elsewhere (the
             body prior alone: no learning on top of it); depths the net's
  blend      unit(net + body) where the body covers: the two averaged, the net's elsewhere
  prior_net  the prior net (models/geometry_prior.onnx, or $RELIGHT_MODELS_DIR's), when the
             manifest has one
  true_normals  the prior net's maps with the scene's true normals (gt_normal.exr) in place
             of the predicted ones: the ceiling of what better normals alone can bring

A scene without a converged fit runs the net alone in every variant (the runtime's fallback).
`--body-weight W` sets the fitted bodies' share of the traced shading (stages.shading.BODY_SHADING_WEIGHT,
shipped 0.5) for every variant.
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

from scene_run import replaced_stage  # noqa: E402

from relightcli import compose  # noqa: E402
from relightcli.stages import shading as shading_stages  # noqa: E402
from relightcli.batch import ItemReport  # noqa: E402
from relightcli.errors import RelightError  # noqa: E402
from relightcli.evaluate import find_scenes, load_scene, normal_metrics, scene_metrics  # noqa: E402
from relightcli.io.envmap import load_envmap  # noqa: E402
from relightcli.io.images import read_image  # noqa: E402
from relightcli.nets.geometry import GeometryNet  # noqa: E402
from relightcli.pipeline import RelightOptions, run_stages  # noqa: E402
from relightcli.stages.compose import layer_image  # noqa: E402
from relightcli.stages.frame import Models, resample, unit  # noqa: E402


class BodyNormals:
    """A stand-in prior net: the image-alone net's maps with the body's normals where it covers
    (`blend`: the normalised sum of both)."""

    def __init__(self, net: GeometryNet, blend: bool):
        self.net, self.blend = net, blend
        self.trained_resolution = net.trained_resolution

    def predict(self, image: np.ndarray, prior: np.ndarray):
        maps = self.net.predict(image)
        covered = prior[..., 8:9] > 0.5
        body = prior[..., 0:3]
        normal = unit(maps.front_normal + body) if self.blend else body
        return replace(maps, front_normal=np.where(covered, normal, maps.front_normal).astype(np.float32))


class VariantModels(Models):
    def __init__(self, threads: int, variant: str):
        super().__init__(threads)
        self.variant = variant

    def has(self, name: str) -> bool:
        if name == "geometry_prior":
            return self.variant in ("body", "blend") or (self.variant != "net" and super().has(name))
        return super().has(name)

    def get(self, family: str):
        if family == "geometry_prior" and self.variant in ("body", "blend"):
            return BodyNormals(super().get("geometry"), self.variant == "blend")
        return super().get(family)


def with_true_normals(geometry_stage, truth: np.ndarray):
    """The geometry stage, then the true normals (full frame) cropped into its maps."""
    def stage(frame, options, models):
        geometry_stage(frame, options, models)
        normal = unit(compose.crop_square(truth, frame.box))
        frame.geometry = replace(frame.geometry, front_normal=normal)
        frame.normal = normal * (frame.crop_mask[..., None] > 0.5)
    return stage


def measure(folder: Path, variant: str, models: Models, use_gt_mask: bool) -> dict:
    scene = load_scene(folder)
    options = RelightOptions(outputs=("relit", "albedo", "shading"), method="raytrace-norefine", threads=2)
    image = read_image(scene.input_path)
    wrap = (lambda stage: with_true_normals(stage, scene.normal)) if variant == "true_normals" else None
    with replaced_stage("geometry", wrap):
        frame, _ = run_stages(image.rgb, scene.mask if use_gt_mask else None, load_envmap(scene.target_path),
                              options, ItemReport(str(folder)), models)
    height, width = image.rgb.shape[:2]
    normal = compose.paste_back(frame.normal, frame.box, height, width)
    pred = {"relit": frame.relit, "albedo": compose.paste_back(frame.albedo, frame.box, height, width),
            "shading": layer_image("shading", frame, options)[0], "normal": normal}
    row = {layer: values["psnr"] if isinstance(values, dict) and "psnr" in values else values
           for layer, values in scene_metrics(scene, pred).items()}
    row["normal_deg"] = row.pop("normal")["deg"]
    if frame.body_maps is not None:
        covered = resample(frame.body_maps.mask.astype(np.float32), frame.crop_mask.shape[0])
        covered = compose.paste_back(covered, frame.box, height, width) > 0.5
        row["normal_deg_covered"] = normal_metrics(normal, scene.normal, scene.mask * covered)["deg"]
    row["geometry"] = frame.notes.get("geometry", {}).get("net")
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", help="eval scene folders (python -m export.factory.eval_scenes)")
    parser.add_argument("--use-gt-mask", action="store_true")
    parser.add_argument("--variants", default="net,body,blend,prior_net")
    parser.add_argument("--body-weight", type=float, default=None)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    if args.body_weight is not None:
        shading_stages.BODY_SHADING_WEIGHT = args.body_weight
    variants = args.variants.split(",")
    models = {v: VariantModels(2, v) for v in variants}
    rows = {v: [] for v in variants}
    for folder in find_scenes(args.scenes):
        for variant in variants:
            try:
                rows[variant].append({"scene": folder.name, **measure(folder, variant, models[variant], args.use_gt_mask)})
            except RelightError as error:  # no person found: reported, left out of the means
                rows[variant].append({"scene": folder.name, "error": str(error)})
        print(folder.name, {v: {k: round(x, 2) for k, x in rows[v][-1].items() if isinstance(x, float)}
                            for v in variants}, flush=True)
    keys = ("relit", "albedo", "shading", "normal_deg", "normal_deg_covered")
    summary = {v: {k: float(np.mean([r[k] for r in rs if r.get(k) is not None])) for k in keys}
               | {"scenes": sum("error" not in r for r in rs)} for v, rs in rows.items()}
    print(f"{'variant':<10}" + "".join(f"{k:>20}" for k in keys))
    for variant, means in summary.items():
        print(f"{variant:<10}" + "".join(f"{means[k]:>20.3f}" for k in keys))
    if args.out:
        args.out.write_text(json.dumps({"summary": summary, "scenes": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
