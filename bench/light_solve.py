"""The input light and the albedo of each `--albedo` source against the truth (issue 20).

    python bench/light_solve.py data/evalval512 data/factory512val --split val [--use-gt-mask]
    python bench/light_solve.py data/eval512 data/factory512test --split test [--use-gt-mask]

Runs the pipeline (`--method raytrace-norefine`) on every scene folder with `--albedo ratio`
(the de-lighting net's light) and `--albedo solve` (the light by inverse rendering on the
mesh), and compares with the factory's true input light (`light_a`, in the photo's exposure
units): solid-angle weighted RMS of log luminance (the truth's mean radiance / 100 added to
both, so black texels stay finite), the level ratio (mean luminance over the sphere, estimate /
truth) and the luminance correlation over the texels. Albedo and relit PSNR by the eval
protocol (relightcli.evaluate), as is and with an oracle per-channel gain on the albedo (the
gain that gives it the true albedo's mean over the person), so level and shape errors are seen
apart; the seconds of the de-lighting stage. Writes --out (JSON) and prints a table.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from export.factory import dataset  # noqa: E402
from relightcli import compose  # noqa: E402
from relightcli.batch import ItemReport  # noqa: E402
from relightcli.evaluate import find_scenes, layer_metrics, load_scene  # noqa: E402
from relightcli.io.envmap import load_envmap, texel_solid_angles  # noqa: E402
from relightcli.io.images import read_image  # noqa: E402
from relightcli.pipeline import RelightOptions, run_stages  # noqa: E402
from relightcli.stages.frame import Models  # noqa: E402

SOURCES = ("ratio", "solve")


def light_errors(estimate: np.ndarray, truth: np.ndarray) -> dict:
    """log-L2, level ratio and correlation of two (16, 32, 3) lights (see the docstring)."""
    omega = texel_solid_angles(*truth.shape[:2])
    a, b = estimate @ compose.LUMINANCE, truth @ compose.LUMINANCE
    floor = 0.01 * float((b * omega).sum() / omega.sum())
    log_l2 = np.sqrt((omega * (np.log(a + floor) - np.log(b + floor)) ** 2).sum() / omega.sum())
    level = float((a * omega).sum() / max((b * omega).sum(), 1e-30))
    spread = a.std() * b.std()
    correlation = float(((a - a.mean()) * (b - b.mean())).mean() / spread) if spread > 0 else 0.0
    return {"log_l2": float(log_l2), "level": level, "correlation": correlation}


def albedo_metrics(frame, scene) -> dict:
    """Albedo and relit PSNR as is, with the oracle per-channel albedo gain (level and colour)
    and with the oracle level alone (one gain for the three channels)."""
    height, width = frame.image.shape[:2]
    albedo = compose.paste_back(frame.albedo, frame.box, height, width)
    relit = frame.relit
    inside = scene.mask > 0.5
    gain = scene.albedo[inside].mean(axis=0) / np.maximum(albedo[inside].mean(axis=0), 1e-6)
    level = scene.albedo[inside].mean() / max(float(albedo[inside].mean()), 1e-6)
    psnr = lambda pred, gt: layer_metrics(pred, gt, scene.mask)["psnr"]  # noqa: E731
    return {"albedo": psnr(albedo, scene.albedo), "relit": psnr(relit, scene.relit),
            "albedo_oracle_gain": psnr(albedo * gain, scene.albedo),
            "relit_oracle_gain": psnr(relit * gain, scene.relit),
            "albedo_oracle_level": psnr(albedo * level, scene.albedo),
            "relit_oracle_level": psnr(relit * level, scene.relit)}


def measure(folder: Path, truth, source: str, use_gt_mask: bool, models) -> dict:
    scene = load_scene(folder)
    options = RelightOptions(outputs=("relit", "albedo", "light"), method="raytrace-norefine",
                             albedo=source, threads=2)
    image = read_image(scene.input_path)
    report = ItemReport(str(folder))
    frame, _ = run_stages(image.rgb, scene.mask if use_gt_mask else None, load_envmap(scene.target_path),
                          options, report, models)
    return {**light_errors(frame.light, truth), **albedo_metrics(frame, scene),
            "delight_seconds": report.seconds.get("delight"), "note": frame.notes.get("delight")}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", help="eval scene folders (python -m export.factory.eval_scenes)")
    parser.add_argument("factory", help="the factory dataset they came from (its light_a)")
    parser.add_argument("--split", default="test")
    parser.add_argument("--use-gt-mask", action="store_true")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    data, models = dataset.open_dataset(args.factory), Models(2)
    rows = {source: [] for source in SOURCES}
    for folder in find_scenes(args.scenes):
        truth = data.load(args.split, folder.name.split("_", 1)[1])["light_a"]
        for source in SOURCES:
            try:
                rows[source].append({"scene": folder.name, **measure(folder, truth, source, args.use_gt_mask, models)})
            except Exception as error:  # noqa: BLE001 - a failed scene is reported, the others count
                rows[source].append({"scene": folder.name, "error": str(error)})
        print(folder.name, {s: {k: round(v, 3) for k, v in rows[s][-1].items() if isinstance(v, float)}
                            for s in SOURCES}, flush=True)
    keys = ("log_l2", "level", "correlation", "albedo", "relit", "albedo_oracle_gain", "relit_oracle_gain",
            "albedo_oracle_level", "relit_oracle_level",
            "delight_seconds")
    summary = {source: {k: float(np.mean([r[k] for r in rs if "error" not in r])) for k in keys}
               for source, rs in rows.items()}
    print(f"{'source':<8}" + "".join(f"{k:>20}" for k in keys))
    for source, means in summary.items():
        print(f"{source:<8}" + "".join(f"{means[k]:>20.3f}" for k in keys))
    if args.out:
        args.out.write_text(json.dumps({"summary": summary, "scenes": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
