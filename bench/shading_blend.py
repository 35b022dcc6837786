"""The fitted bodies' share of the traced shading, per pixel (issue 49): where the fit is good,
trust it.

    python bench/shading_blend.py capture data/evalval512 --cache data/blendcache/val
    python bench/shading_blend.py weights data/blendcache/val [--fit data/blendcache/train]

`capture` runs the product's pipeline (`relight eval`'s default method, the true mask) on each
eval scene and keeps, in the crop, the two renders the target shading blends (the
reconstruction's and the fitted bodies'), the true shading and normals, and what a per-pixel
weight could be computed from: the geometry net's and the bodies' normals and depths, the
crop mask, the pixels whose fit converged. `weights` scores blends of the two renders against
the true shading over the person (the coarse shading, before the refinement net, at the
evaluation's normaliser; sRGB PSNR as `relight eval`): today's one share, other shares, a
per-pixel oracle (the best weight per pixel, an upper bound), and weights from the bodies'
agreement with the nets' normals, their depth gap and the distance to the outline. With
`--fit` a weight's parameters are fitted on those scenes (never on the scored ones).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from relightcli import compose, pipeline  # noqa: E402
from relightcli.evaluate import find_scenes, load_scene, shading_normaliser  # noqa: E402
from relightcli.pipeline import RelightOptions, predict_scene  # noqa: E402
from relightcli.stages import shading as shading_stage  # noqa: E402
from relightcli.stages.body import body_shading_pixels  # noqa: E402
from relightcli.stages.frame import Models  # noqa: E402


def capture(scenes: Path, cache: Path) -> None:
    """One npz per scene in `cache` (see the module docstring)."""
    cache.mkdir(parents=True, exist_ok=True)
    models, record = Models(2), {"on": False, "renders": [], "frame": None}
    original_traced, original_trace, original_run = shading_stage.traced, shading_stage.trace_shading, pipeline.run_stages

    def traced(*args, **kwargs):
        values, result = original_traced(*args, **kwargs)
        if record["on"]:
            record["renders"].append(values[..., :3].copy())
        return values, result

    def trace_shading(*args, **kwargs):  # stage_raytrace's: the target light's
        record["on"], record["renders"] = True, []
        try:
            return original_trace(*args, **kwargs)
        finally:
            record["on"] = False

    def run_stages(*args, **kwargs):
        frame, report = original_run(*args, **kwargs)
        record["frame"] = frame
        return frame, report

    shading_stage.traced, shading_stage.trace_shading, pipeline.run_stages = traced, trace_shading, run_stages
    try:
        for folder in find_scenes(scenes):
            scene = load_scene(folder)
            options = RelightOptions(outputs=("relit", "albedo", "shading", "normal"), threads=2)
            try:
                predict_scene(scene, options, use_gt_mask=True, models=models)
            except Exception as error:  # noqa: BLE001 - a failed scene is reported, the others kept
                print(folder.name, "failed:", error, flush=True)
                continue
            frame = record["frame"]
            if frame.body_maps is None or len(record["renders"]) != 2:
                print(folder.name, "no converged body fit: skipped", flush=True)
                continue
            own, body = record["renders"]
            maps, g = frame.body_maps, frame.geometry
            np.savez_compressed(
                cache / f"{folder.name}.npz", own=own, body=body, usable=body_shading_pixels(frame),
                crop_mask=frame.crop_mask, net_normal=g.front_normal, net_depth=g.front_depth,
                body_mask=maps.mask, body_normal=maps.front_normal, body_depth=maps.front_depth,
                true_shading=compose.crop_square(scene.shading, frame.box),
                true_normal=compose.crop_square(scene.normal, frame.box),
                scale=np.float32(shading_normaliser(scene.shading, scene.mask)))
            print(folder.name, "kept", flush=True)
    finally:
        shading_stage.traced, shading_stage.trace_shading, pipeline.run_stages = original_traced, original_trace, original_run


def srgb_psnr(pred: np.ndarray, truth: np.ndarray, where: np.ndarray) -> float:
    from relightcli.evaluate import layer_metrics
    return layer_metrics(pred, truth, where.astype(np.float32))["psnr"]


def features(s) -> dict:
    """Per-pixel quantities a weight may use."""
    person = s["crop_mask"] > 0.5
    both = person & s["body_mask"]
    cosine = np.clip(np.sum(s["net_normal"] * s["body_normal"], -1), -1.0, 1.0)
    agreement = np.where(both, cosine, 0.0)
    side = person.shape[0]
    outline = cv2.distanceTransform(person.astype(np.uint8), cv2.DIST_L2, 5) / side
    gap = np.where(both, np.abs(s["net_depth"] - s["body_depth"]), 1.0)
    return {"agreement": agreement, "outline": outline, "gap": gap, "both": both}


def oracle_weight(s, sigma: float) -> np.ndarray:
    """The weight per pixel that brings the blend's luminance nearest the truth's, smoothed."""
    own, body, truth = (s[k].mean(-1) for k in ("own", "body", "true_shading"))
    difference = body - own
    w = np.clip((truth - own) * difference / np.maximum(difference ** 2, 1e-8), 0.0, 1.0)
    w = np.where(np.abs(difference) > 1e-4, w, 0.2)
    return cv2.GaussianBlur(w.astype(np.float32), (0, 0), sigma) if sigma else w


def blended(s, weight: np.ndarray) -> np.ndarray:
    w = (weight * s["usable"])[..., None]
    return (1.0 - w) * s["own"] + w * s["body"]


def score(scenes: list, weight_of) -> float:
    values = []
    for s in scenes:
        person = s["crop_mask"] > 0.5
        values.append(srgb_psnr(blended(s, weight_of(s)) / s["scale"], s["true_shading"] / s["scale"], person))
    return float(np.mean(values))


def load(cache: Path) -> list:
    return [dict(np.load(p)) for p in sorted(cache.glob("*.npz"))]


def variants() -> dict:
    out = {f"share {w}": (lambda w: lambda s: np.full(s["own"].shape[:2], w, np.float32))(w)
           for w in (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 1.0)}
    out.update({f"oracle, blur {sigma}": (lambda sigma: lambda s: oracle_weight(s, sigma))(sigma)
                for sigma in (0, 4, 16)})
    def agreeing(s, high):  # more body where its normals agree with the net's
        f = features(s)
        return np.where(f["both"], 0.2 + (high - 0.2) * np.clip((f["agreement"] - 0.8) / 0.2, 0, 1), 0.2)

    for high in (0.3, 0.5, 0.7):
        out[f"agreement -> {high}"] = lambda s, high=high: agreeing(s, high)
    for near in (0.0, 0.4, 0.6):  # the outline's ring (3% of the crop) takes `near`
        out[f"outline ring -> {near}"] = (lambda near: lambda s: np.where(
            features(s)["outline"] < 0.03, near, 0.2).astype(np.float32))(near)
    for width in (0.02, 0.05, 0.1):  # less body where its depth departs from the net's
        out[f"depth gap {width}"] = (lambda width: lambda s: np.float32(0.4) * np.exp(
            -features(s)["gap"] / width).astype(np.float32))(width)
    return out


# Weights fitted on other scenes: one share per bin of a feature (or of two), the share of each
# bin the one of GRID with the least squared sRGB error over the fitting scenes' pixels
GRID = np.linspace(0.0, 1.0, 21)
BINNED = {"outline": (("outline", (0.01, 0.02, 0.04, 0.08)),),
          "agreement": (("agreement", (0.5, 0.9, 0.97, 0.99)),),
          "outline x agreement": (("outline", (0.01, 0.02, 0.04, 0.08)), ("agreement", (0.5, 0.9, 0.97, 0.99))),
          "depth gap": (("gap", (0.05, 0.1, 0.2)),)}


def bins(s, spec) -> tuple[np.ndarray, int]:
    """(R, R) bin index of each pixel under `spec` ((feature, edges), ...), and the bin count."""
    f, index, count = features(s), 0, 1
    for name, edges in spec:
        index = index + np.digitize(f[name], edges) * count
        count *= len(edges) + 1
    return index, count


def fit_bins(scenes: list, spec) -> np.ndarray:
    from relightcli.io.images import linear_to_srgb

    errors = np.zeros((bins(scenes[0], spec)[1], len(GRID)))
    for s in scenes:
        index = bins(s, spec)[0]
        pixels = (s["crop_mask"] > 0.5) & s["usable"]
        truth = linear_to_srgb(np.clip(s["true_shading"][pixels] / s["scale"], 0.0, 1.0))
        for j, w in enumerate(GRID):
            pred = linear_to_srgb(np.clip(((1 - w) * s["own"][pixels] + w * s["body"][pixels]) / s["scale"], 0.0, 1.0))
            np.add.at(errors[:, j], index[pixels], ((pred - truth) ** 2).sum(-1))
    return GRID[errors.argmin(axis=1)]


def per_scene_best(scenes: list) -> float:
    """The mean over the scenes of each one's best single share: what a weight per person could
    reach at most."""
    shares = np.linspace(0.0, 1.0, 11)
    return float(np.mean([max(score([s], lambda s, w=w: np.full(s["own"].shape[:2], w, np.float32))
                               for w in shares) for s in scenes]))


def weights(cache: Path, fit: Path | None) -> None:
    scenes = load(cache)
    print(f"{len(scenes)} scenes; coarse shading dB over the person")
    results = {}
    for name, weight_of in variants().items():
        results[name] = score(scenes, weight_of)
        print(f"{name:<32}{results[name]:8.3f}", flush=True)
    results["best share per scene"] = per_scene_best(scenes)
    print(f"{'best share per scene':<32}{results['best share per scene']:8.3f}")
    if fit is not None:
        fitting = load(fit)
        for name, spec in BINNED.items():
            table = fit_bins(fitting, spec)
            results[f"bins of {name}"] = score(scenes, lambda s, t=table, spec=spec: t[bins(s, spec)[0]].astype(np.float32))
            print(f"{'bins of ' + name:<32}{results['bins of ' + name]:8.3f}  shares {np.round(table, 2).tolist()}")
    (cache / "weights.json").write_text(json.dumps(results, indent=1))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    c = commands.add_parser("capture")
    c.add_argument("scenes")
    c.add_argument("--cache", type=Path, required=True)
    w = commands.add_parser("weights")
    w.add_argument("cache", type=Path)
    w.add_argument("--fit", type=Path, help="a cache of other scenes to fit the binned weights on")
    args = parser.parse_args()
    if args.command == "capture":
        capture(Path(args.scenes), args.cache)
    else:
        weights(args.cache, args.fit)
    return 0


if __name__ == "__main__":
    sys.exit(main())
