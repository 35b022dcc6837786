"""Ambient occlusion against the factory's truth: the AO net, the fitted bodies' ray-traced AO,
their mean, and the AO prior net (the AO stage, relightcli.stages.geometry.stage_ao).

    python bench/bench_ao.py data/factory512val --split val [--weights 0,0.5,1] [--prior]

Runs the runtime's stages up to the AO on every sample of the split (its photo, its true mask)
once per weight of the bodies' AO in the blend (stages.geometry.BODY_AO_WEIGHT: 0 is the net alone), and
with --prior once with the AO prior net of the models folder (RELIGHT_MODELS_DIR to try one not
shipped), and prints the AO MAE over the person (the factory's "ao": the cosine-weighted
unoccluded fraction on the true mesh, as relightcli.render.integrator.ambient_occlusion), on all
samples and on those where a body fit converged, and the AO stage's seconds.
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
from relightcli.pipeline import RelightOptions, run_stages  # noqa: E402
from relightcli.stages import geometry as geometry_stages  # noqa: E402
from relightcli.stages.frame import Models  # noqa: E402

WHITE = np.ones((8, 16, 3), np.float32)


class BlendOnly(Models):
    """The shipped models without the AO prior net: the AO layer is the blend."""

    def has(self, name: str) -> bool:
        return name != "ao_prior" and super().has(name)


def measure(sample: dict, variant, models: Models) -> dict:
    """variant: a weight of the bodies' AO in the blend, or "prior" (the AO prior net)."""
    if variant != "prior":
        geometry_stages.BODY_AO_WEIGHT = variant
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
    parser.add_argument("--prior", action="store_true", help="also the AO prior net (the models folder's)")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    data, blend, prior = dataset.open_dataset(args.factory), BlendOnly(2), Models(2)
    variants = [float(w) for w in args.weights.split(",") if w] + (["prior"] if args.prior else [])
    rows = {v: [] for v in variants}
    for sample_id in data.ids(args.split):
        sample = data.load(args.split, sample_id)
        for variant in variants:
            models = prior if variant == "prior" else blend
            rows[variant].append({"sample": sample_id, **measure(sample, variant, models)})
        print(sample_id, {w: round(r[-1]["mae"], 4) for w, r in rows.items()}, flush=True)
    summary = {}
    for variant, found in rows.items():
        fitted = [r["mae"] for r in found if r["fitted"]]
        summary[variant] = {"mae": float(np.mean([r["mae"] for r in found])),
                           "mae_fitted": float(np.mean(fitted)) if fitted else None, "fitted": len(fitted),
                           "seconds": float(np.median([r["seconds"] for r in found]))}
        label = "AO prior net" if variant == "prior" else f"body weight {variant}"
        print(f"{label}: " + ", ".join(f"{k} {v:.4f}" if isinstance(v, float) else f"{k} {v}"
                                       for k, v in summary[variant].items()))
    if args.out:
        args.out.write_text(json.dumps({"summary": summary, "samples": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
