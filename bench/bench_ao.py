"""Ambient occlusion against the factory's truth: the AO net, the fitted bodies' ray-traced AO
and their mean (the AO stage, relightcli.stages.stage_ao).

    python bench/bench_ao.py data/factory512val --split val [--weights 0,0.5,1]

Runs the runtime's stages up to the AO on every sample of the split (its photo, its true mask)
once per weight of the bodies' AO (stages.BODY_AO_WEIGHT: 0 is the net alone) and prints the AO
MAE over the person (the factory's "ao": the cosine-weighted unoccluded fraction on the true
mesh, as relightcli.render.integrator.ambient_occlusion), on all samples and on those where a
body fit converged, and the AO stage's seconds.
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
from relightcli import compose, stages  # noqa: E402
from relightcli.batch import ItemReport  # noqa: E402
from relightcli.pipeline import RelightOptions, run_stages  # noqa: E402
from relightcli.stages import Models  # noqa: E402

WHITE = np.ones((8, 16, 3), np.float32)


def measure(sample: dict, weight: float, models: Models) -> dict:
    stages.BODY_AO_WEIGHT = weight
    report = ItemReport("sample")
    frame, _ = run_stages(sample["input"], sample["mask"], WHITE, RelightOptions(outputs=("ao",), threads=2),
                          report, models)
    height, width = sample["mask"].shape
    ao = compose.paste_back(frame.ao, frame.box, height, width)
    inside = sample["mask"] > 0.5
    return {"mae": float(np.abs(ao[inside] - sample["ao"][inside]).mean()),
            "fitted": frame.body_scene is not None, "seconds": report.seconds["ao"]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("factory", help="a factory dataset (python -m export.factory.generate)")
    parser.add_argument("--split", default="val")
    parser.add_argument("--weights", default="0,0.5,1")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    data, models = dataset.open_dataset(args.factory), Models(2)
    weights = [float(w) for w in args.weights.split(",")]
    rows = {w: [] for w in weights}
    for sample_id in data.ids(args.split):
        sample = data.load(args.split, sample_id)
        for weight in weights:
            rows[weight].append({"sample": sample_id, **measure(sample, weight, models)})
        print(sample_id, {w: round(r[-1]["mae"], 4) for w, r in rows.items()}, flush=True)
    summary = {}
    for weight, found in rows.items():
        fitted = [r["mae"] for r in found if r["fitted"]]
        summary[weight] = {"mae": float(np.mean([r["mae"] for r in found])),
                           "mae_fitted": float(np.mean(fitted)) if fitted else None, "fitted": len(fitted),
                           "seconds": float(np.median([r["seconds"] for r in found]))}
        print(f"body weight {weight}: " + ", ".join(f"{k} {v:.4f}" if isinstance(v, float) else f"{k} {v}"
                                                  for k, v in summary[weight].items()))
    if args.out:
        args.out.write_text(json.dumps({"summary": summary, "samples": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
