"""How the face path's shading should join the body's: blends scored against the true shading
over the faces of the synthetic eval scenes (issue 48).

    python bench/face_blend.py data/eval512 data/evalval512 [--out bench/results/face_blend.json]

Runs the default pipeline (true mask fed, as `relight eval --use-gt-mask`) on every scene
folder, and for each fitted face keeps the body's shading B before the face path, the face
net's shading F and the blend weight w (geometry.face.face_blend_weight), in the face crop.
Each blend is scored over the pixels it may change (w > 0.01, inside the person) by the RMS of
log(shading / truth), the truth levelled to the body's shading over the whole person (the eval
normalises shading per scene): the body alone (B), today's linear blend, the blend in log
shading, and the face net's detail on the body's low frequencies (F x blur(B) / blur(F),
sigma DETAIL_SIGMA of the 128 px face crop) blended in log shading. Lower is better.
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
sys.path.insert(0, str(ROOT / "bench"))

EPS = 1e-4
DETAIL_SIGMAS = (8.0, 16.0)
CLAMPS = (0.35, 0.7)


def blends(body: np.ndarray, face: np.ndarray, weight: np.ndarray, inside: np.ndarray) -> dict:
    """The blends of a face crop: (128, 128, 3) body and face shading, weight and person
    pixels (128, 128)."""
    w = weight[..., None]
    log_b, log_f = np.log(body + EPS), np.log(face + EPS)
    out = {"body": body, "linear": w * face + (1 - w) * body, "log": np.exp(log_b + w * (log_f - log_b))}
    for bound in CLAMPS:  # the face's departure from the body held within +-bound (log)
        out[f"clamp_{bound:g}"] = np.exp(log_b + w * np.clip(log_f - log_b, -bound, bound))
    support = inside.astype(np.float32)
    for sigma in DETAIL_SIGMAS:
        norm = np.maximum(cv2.GaussianBlur(support, (0, 0), sigma), 1e-6)[..., None]
        low_b = cv2.GaussianBlur(log_b * support[..., None], (0, 0), sigma) / norm
        low_f = cv2.GaussianBlur(log_f * support[..., None], (0, 0), sigma) / norm
        out[f"detail_{sigma:g}"] = np.exp(log_b + w * (log_f - low_f - log_b + low_b))
    return out


def scene_rows(folder: Path, options, models) -> list:
    from scene_run import replaced, run_scene

    from relightcli.compose import crop_square
    from relightcli.evaluate import load_scene
    from relightcli.geometry.face import cut_crop, face_blend_weight
    from relightcli.stages import face as face_stage

    captured = []
    original = face_stage.face_shading

    def spy(frame, face, options, models):
        patch, pixels, scale = original(frame, face, options, models)
        captured.append((face.crop, cut_crop(frame.shading, face.crop), patch, face_blend_weight(pixels),
                         cut_crop(frame.crop_mask, face.crop)))
        return patch, pixels, scale

    scene = load_scene(folder)
    with replaced(face_stage, "face_shading", spy):
        frame = run_scene(folder, options, models, scene=scene)
    truth = crop_square(scene.shading, frame.box)
    person = frame.crop_mask > 0.5
    rows = []
    for crop, body, face, weight, mask in captured:
        # the truth levelled to the body's shading over the person (before the face path)
        true = cut_crop(truth, crop)
        changed = (weight > 0.01) & (mask > 0.5)
        if changed.sum() < 20:
            continue
        level = np.median(np.log(frame.shading[person] + EPS) - np.log(truth[person] + EPS))
        departure = (np.log(face + EPS) - np.log(body + EPS)).mean(axis=-1)[changed]
        row = {"scene": folder.name, "pixels": int(changed.sum()),
               "departure_median": round(float(np.median(departure)), 3),
               "departure_p90": round(float(np.percentile(np.abs(departure), 90)), 3)}
        for name, shading in blends(body, face, weight, mask > 0.5).items():
            error = np.log(shading[changed] + EPS) - np.log(true[changed] + EPS) - level
            row[name] = round(float(np.sqrt(np.mean(error ** 2))), 4)
        rows.append(row)
    return rows


def main() -> int:
    from relightcli.evaluate import find_scenes
    from relightcli.pipeline import RelightOptions
    from relightcli.stages.frame import Models

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("datasets", nargs="+")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    options = RelightOptions(outputs=("relit",), threads=2)
    models = Models(options.threads)
    summary = {}
    for dataset in args.datasets:
        rows = [row for folder in find_scenes(dataset) for row in scene_rows(folder, options, models)]
        for row in rows:
            print(json.dumps(row), flush=True)
        names = [key for key in rows[0] if key not in ("scene", "pixels") and not key.startswith("departure")] if rows else []
        summary[dataset] = {"faces": len(rows), **{name: round(float(np.mean([r[name] for r in rows])), 4)
                                                    for name in names}, "rows": rows}
        print(dataset, {k: v for k, v in summary[dataset].items() if k != "rows"}, flush=True)
    if args.out:
        args.out.write_text(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
