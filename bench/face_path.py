"""What the face path changes: shading PSNR with and without the face refinement, on the
pixels it changes and over the whole person, for every scene folder where it changes anything.

    python bench/face_path.py data/eval512faces [--out bench/results/face_path.json]

Scene folders as `relight eval` reads them (true mask fed); the models are the shipped ones,
and "without" is the same models with face_refine left out of the manifest (the pipeline then
plans no face stage). Scenes: `python -m export.factory.generate --out data/factory512faces
--count 60 --splits test=1 --resolution 512 --workers 1 --seed 1 --spp 128 --target-error 0.03
--bounces 2`, then `python -m export.factory.eval_scenes data/factory512faces data/eval512faces`.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def shading_with(models_dir: Path, scene, options) -> np.ndarray:
    from relightcli.pipeline import predict_scene
    from relightcli.stages.frame import Models

    os.environ["RELIGHT_MODELS_DIR"] = str(models_dir)
    return predict_scene(scene, options, use_gt_mask=True, models=Models(options.threads))["shading"]


def main() -> int:
    from relightcli import metrics
    from relightcli.evaluate import find_scenes, load_scene, shading_normaliser
    from relightcli.io.images import linear_to_srgb
    from relightcli.pipeline import RelightOptions

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("--out", default="bench/results/face_path.json")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    options = RelightOptions(threads=args.threads)
    with tempfile.TemporaryDirectory() as folder:
        without = Path(folder)
        shutil.copytree(REPO / "models", without, dirs_exist_ok=True)
        manifest = json.loads((without / "manifest.json").read_text())
        del manifest["models"]["face_refine"]
        (without / "manifest.json").write_text(json.dumps(manifest))
        rows = []
        for path in find_scenes(args.dataset):
            scene = load_scene(path)
            body, face = shading_with(without, scene, options), shading_with(REPO / "models", scene, options)
            changed = np.abs(body - face).max(axis=-1) > 1e-4
            if not changed.any():
                continue
            scale = shading_normaliser(scene.shading, scene.mask)
            encode = lambda x: linear_to_srgb(np.clip(x / scale, 0.0, 1.0))  # noqa: E731
            row = {"scene": path.name, "changed_pixels": int(changed.sum())}
            for name, shading in (("body", body), ("face", face)):
                row[f"{name}_changed_psnr"] = metrics.psnr(encode(shading), encode(scene.shading), scene.mask * changed)
                row[f"{name}_person_psnr"] = metrics.psnr(encode(shading), encode(scene.shading), scene.mask)
            rows.append(row)
            print(json.dumps(row), flush=True)
    keys = ("body_changed_psnr", "face_changed_psnr", "body_person_psnr", "face_person_psnr")
    summary = {"scenes": len(rows), **{k: float(np.mean([r[k] for r in rows])) if rows else None for k in keys},
               "per_scene": rows}
    Path(args.out).write_text(json.dumps(summary, indent=2) + "\n")
    print({k: summary[k] for k in ("scenes",) + keys})
    return 0


if __name__ == "__main__":
    sys.exit(main())
