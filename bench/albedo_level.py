"""How far off the albedo's level is, and whether the photo's background tells the light's (issue 20).

    python bench/albedo_level.py data/evalval512 data/factory512val --split val
    python bench/albedo_level.py data/evalval256v7 data/factory256v7 --split val --resolution 256
    python bench/albedo_level.py data/evaltrainpose256 data/factory256t11 --split train --resolution 256

Runs the default pipeline with the true mask on every scene folder and measures, per scene:

- the albedo's level error: log2 of the median albedo luminance over the person (2 px inside
  the outline), ours over the truth's;
- the light on the person's front: the unoccluded irradiance of a normal facing the camera,
  (1/pi) sum_j L_j max(0, w_j.z) omega_j, of the solved input light and of the factory's true
  one (`light_a`, in the photo's exposure units): log2 of ours over the truth's;
- the photo's background: the median luminance of the photo more than 7 px from the person
  (the light behind the person at the photo's exposure, where the camera sees it), and its
  share of clipped pixels.

Then prints the RMS and mean of the level errors, the spread of log2(true front / background)
(how well the background alone would predict the front light) against that of our light, and
a least-squares fit on the set itself of log2(true front) on [log2(our front), log2(background),
1] with and without the background term: if the background carried what our light misses, the
fit's residual would fall with it. Writes --out (JSON) with every scene's numbers.
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

from export.factory import dataset  # noqa: E402
from relightcli import compose  # noqa: E402
from relightcli.batch import ItemReport  # noqa: E402
from relightcli.evaluate import find_scenes, load_scene  # noqa: E402
from relightcli.io.envmap import load_envmap  # noqa: E402
from relightcli.io.images import read_image  # noqa: E402
from relightcli.pipeline import RelightOptions, run_stages  # noqa: E402
from relightcli.render.inverse import unoccluded_transport  # noqa: E402
from relightcli.stages.frame import Models  # noqa: E402

# Background pixels: this far from the person's mask (px), so the outline's blend is left out
BACKGROUND_GAP = 7
CLIPPED = 0.99


def front_irradiance(light: np.ndarray) -> float:
    """The unoccluded irradiance (luminance, DESIGN.md units) of a normal facing the camera (+Z)
    under an (H, 2H, 3) light: the inverse-rendering solve's own transport of that normal."""
    transport = unoccluded_transport(np.array([[0.0, 0.0, 1.0]]), light.shape[0])
    return float((transport @ light.reshape(-1, 3))[0] @ compose.LUMINANCE)


def albedo_level(albedo: np.ndarray, inside: np.ndarray) -> float:
    """The median luminance of an (R, R, 3) albedo over `inside` (R, R) bool."""
    return float(np.median(albedo[inside] @ compose.LUMINANCE))


def measure(folder: Path, truth_light: np.ndarray, options, models) -> dict:
    scene = load_scene(folder)
    image = read_image(scene.input_path)
    frame, _ = run_stages(image.rgb, scene.mask, load_envmap(scene.target_path), options,
                          ItemReport(str(folder)), models)
    inside = cv2.erode((frame.crop_mask > 0.5).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    truth_albedo = compose.crop_square(scene.albedo, frame.box)
    person = (scene.mask > 0.5).astype(np.uint8)
    size = 2 * BACKGROUND_GAP + 1
    background = image.rgb[cv2.dilate(person, np.ones((size, size), np.uint8)) == 0]
    return {
        "albedo_level_error": float(np.log2(albedo_level(frame.albedo, inside) / albedo_level(truth_albedo, inside))),
        "front_ours": front_irradiance(frame.light), "front_true": front_irradiance(truth_light),
        "background": float(np.median(background @ compose.LUMINANCE)) if background.size else float("nan"),
        "background_clipped": float((background.max(axis=1) >= CLIPPED).mean()) if background.size else float("nan"),
    }


def summarise(rows: list[dict]) -> dict:
    level = np.array([r["albedo_level_error"] for r in rows])
    ours, true, background = (np.log2([r[k] for r in rows]) for k in ("front_ours", "front_true", "background"))
    design = np.stack([ours, background, np.ones_like(ours)], axis=1)

    def residual(columns):
        coefficients, *_ = np.linalg.lstsq(design[:, columns], true, rcond=None)
        return float(np.sqrt(np.mean((true - design[:, columns] @ coefficients) ** 2))), coefficients.tolist()

    without, _ = residual([0, 2])
    with_background, coefficients = residual([0, 1, 2])
    return {"scenes": len(rows),
            "albedo_level_rms_stops": float(np.sqrt(np.mean(level ** 2))), "albedo_level_mean_stops": float(level.mean()),
            "front_ours_error_rms_stops": float(np.sqrt(np.mean((ours - true) ** 2))),
            "front_true_over_background_mean_stops": float((true - background).mean()),
            "front_true_over_background_sd_stops": float((true - background).std()),
            "fit_residual_without_background": without, "fit_residual_with_background": with_background,
            "fit_coefficients_ours_background_offset": coefficients}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes", help="eval scene folders (python -m export.factory.eval_scenes)")
    parser.add_argument("factory", help="the factory dataset they came from (its light_a)")
    parser.add_argument("--split", default="test")
    parser.add_argument("--resolution", type=int, default=512)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    data, models = dataset.open_dataset(args.factory), Models(2)
    options = RelightOptions(resolution=args.resolution, threads=2)
    rows = []
    for folder in find_scenes(args.scenes):
        truth = data.load(args.split, folder.name.split("_", 1)[1])["light_a"]
        rows.append({"scene": folder.name, **measure(folder, truth, options, models)})
        print(folder.name, {k: round(v, 3) for k, v in rows[-1].items() if isinstance(v, float)}, flush=True)
    summary = summarise(rows)
    print(json.dumps(summary, indent=1))
    if args.out:
        args.out.write_text(json.dumps({"summary": summary, "scenes": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
