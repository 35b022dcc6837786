"""The relit person composited over each background, against its ground truth: the true relit
person over the same background by the true mask.

    python bench/composite_matte.py data/evalval256 --resolution 256 [--out FILE]
    python bench/composite_matte.py data/evalval512

The paper's protocol scores the layers over the true mask only, so it cannot see what a
predicted mask does to a composite: where it is unsure inside the person the background shows
through, where it spills outside the background is painted with relit colour. This scores the
composites the product writes (relightcli.compose.composite_crop, at the relit output's display
exposure) in sRGB, clipped, around the people (the true and the predicted person, grown by 3
px) and on the true person alone, over the kept photo (`--background keep`, the default), the
environment view (`env`), black and grey, for the mask as alpha and for sharpened mattes (the
mask stretched from low..high to 0..1, compose.PREDICTED_MATTE, used over
stages.compose.SHARPENED_OVER). The people and the mask are the pipeline's own (no --mask). Choose
the matte here, on validation folders.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from relightcli.batch import ItemReport  # noqa: E402
from relightcli.compose import PREDICTED_MATTE, composite, composite_crop  # noqa: E402
from relightcli.evaluate import find_scenes, load_scene  # noqa: E402
from relightcli.io.envmap import load_envmap  # noqa: E402
from relightcli.io.images import linear_to_srgb, read_image  # noqa: E402
from relightcli.pipeline import RelightOptions, run_stages  # noqa: E402
from relightcli.stages.compose import SHARPENED_OVER, background_view, scene_exposure  # noqa: E402
from relightcli.stages.frame import Models  # noqa: E402

BACKGROUNDS = ("keep", "env", "#000000", "#808080")

MATTES = {"mask as alpha": None, "0.1..0.9": (0.1, 0.9), "0.2..0.8": (0.2, 0.8),
          "0.35..0.65": (0.35, 0.65), "0..0.8 (inside only)": (0.0, 0.8), "0.5 threshold": (0.4999, 0.5001)}


def psnr(a, b, where) -> float:
    return float(10.0 * np.log10(1.0 / max(float(np.mean(np.square(a - b)[where])), 1e-12)))


def score(folder: Path, options, models) -> dict:
    """{background: {matte name: {"around": dB, "person": dB}}} for one scene."""
    scene = load_scene(folder)
    image = read_image(scene.input_path).rgb
    env = load_envmap(scene.target_path)
    frame, _ = run_stages(image, None, env, options, ItemReport(str(folder)), models)
    scale = np.float32(scene_exposure(env))
    view = background_view(frame, options)
    display = lambda rgb: linear_to_srgb(np.clip(rgb, 0.0, 1.0))  # noqa: E731
    person = scene.mask > 0.5
    around = cv2.dilate(((frame.mask > 0.02) | person).astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    out = {}
    for background in BACKGROUNDS:
        truth = display(composite(scene.relit * scale, scene.mask, background, photo=image,
                                  env_view=view * scale)[0])
        out[background] = {}
        for name, matte in MATTES.items():
            ours = display(composite_crop(frame.relit_crop, frame.box, frame.mask, background, photo=image,
                                          env_view=view, scale=scale, matte=matte)[0])
            out[background][name] = {"around": psnr(ours, truth, around), "person": psnr(ours, truth, person)}
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scenes")
    parser.add_argument("--resolution", type=int, default=512)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    options, models = RelightOptions(resolution=args.resolution), Models(2)
    rows = {}
    for folder in find_scenes(args.scenes):
        try:
            rows[folder.name] = score(folder, options, models)
        except Exception as error:  # noqa: BLE001 - a scene without a person found is left out
            print(f"{folder.name}: {error}")
    summary = {}
    for background in BACKGROUNDS:
        base = np.array([r[background]["mask as alpha"]["around"] for r in rows.values()])
        print(f"over {background}: {len(rows)} scenes; sRGB PSNR around the people / on the true person (dB)")
        summary[background] = {}
        for name, matte in MATTES.items():
            around = np.array([r[background][name]["around"] for r in rows.values()])
            person = np.array([r[background][name]["person"] for r in rows.values()])
            summary[background][name] = {"around": float(around.mean()), "person": float(person.mean()),
                                         "better_around": int((around > base).sum())}
            shipped = " (shipped)" if matte == PREDICTED_MATTE and background in SHARPENED_OVER else ""
            print(f"  {name:22s} {around.mean():7.3f} ({around.mean() - base.mean():+.3f}, better in "
                  f"{(around > base).sum():3d})  {person.mean():7.3f}{shipped}")
    if args.out:
        args.out.write_text(json.dumps({"summary": summary, "scenes": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
