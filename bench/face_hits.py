"""How often the face stage fits a face: the stages up to "face" on every scene folder (true
mask fed, as `relight eval` does), and the face stage's note per scene.

    python bench/face_hits.py data/evalval512 [--out bench/results/face_hits_evalval512.json]

Prints one JSON line per scene, then the hit rate (faces fitted / scenes) and the face stage's
median time per scene.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

STAGES_TO_FACE = ("people", "mask", "crop", "geometry", "face")


def face_note(scene, options, models) -> tuple[dict, float]:
    """The face stage's note on one scene and the stage's wall time (seconds)."""
    from relightcli.io.images import read_image
    from relightcli.stages import STAGES
    from relightcli.stages.frame import Frame

    image = read_image(scene.input_path, max_pixels=options.max_pixels)
    frame = Frame(image=image.rgb, mask=scene.mask, env=np.zeros((4, 8, 3), np.float32))
    seconds = 0.0
    for stage in STAGES_TO_FACE:
        start = time.perf_counter()
        STAGES[stage](frame, options, models)
        seconds = time.perf_counter() - start
    return frame.notes.get("face", {}), seconds


def main() -> int:
    from relightcli.evaluate import find_scenes, load_scene
    from relightcli.pipeline import RelightOptions
    from relightcli.stages.frame import Models

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("--out", default=None)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    options = RelightOptions(threads=args.threads)
    models = Models(options.threads)
    rows = []
    for path in find_scenes(args.dataset):
        note, seconds = face_note(load_scene(path), options, models)
        row = {"scene": path.name, "fitted": "skipped" not in note, "face_s": round(seconds, 3), "note": note}
        rows.append(row)
        print(json.dumps(row), flush=True)
    summary = {"dataset": args.dataset, "scenes": len(rows), "fitted": sum(r["fitted"] for r in rows),
               "median_face_s": float(np.median([r["face_s"] for r in rows])) if rows else None,
               "per_scene": rows}
    if args.out:
        Path(args.out).write_text(json.dumps(summary, indent=2) + "\n")
    print(json.dumps({k: summary[k] for k in ("dataset", "scenes", "fitted", "median_face_s")}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
