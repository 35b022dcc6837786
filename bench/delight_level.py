"""The de-lighting net's albedo level on a factory set's validation samples, without the rest
of the pipeline: each models folder's net run as the stage runs it (stages.delight.net_estimate),
its level error per sample (log2 of the true albedo's mean over the person's core over the
net's: the mean compose.albedo_gain brings the ratio albedo to) and the albedo's PSNR (the
protocol's encoding) with the net's albedo made lighter or darker by a grid of stops. Where that
PSNR peaks against where the level is unbiased says which level the metric prefers; two nets'
levels side by side say how far apart their conventions are.

    python bench/delight_level.py data/factory256 models data/models_d2x2400 --skip 100 --count 200 \
        --out bench/results/delight_level_factory256.json

`calibration` (what `net_curves.py export/ship --calibrate-to` writes into a new net's manifest
entry) is the albedo gain that brings a net's median level to a reference net's on the same
samples: a photo cannot tell its albedo's level, and nets trained alike land up to ~0.2 stops
apart (docs/RESULTS.md, "The wider net at full length, and the level each net keeps").
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from export.factory import dataset  # noqa: E402
from export.train.tasks import protocol_encode  # noqa: E402
from relightcli import compose, metrics  # noqa: E402

SHIFTS = tuple(round(s, 2) for s in np.arange(-0.6, 0.61, 0.1))  # stops


def sample_row(sample: dict, albedo: np.ndarray, shifts=SHIFTS) -> dict:
    """One sample's level error (stops, > 0: the net's albedo darker than the truth) and its
    albedo PSNR at each shift (the net's albedo times 2 ** shift)."""
    mask = sample["mask"][..., 0] if sample["mask"].ndim == 3 else sample["mask"]
    true = protocol_encode(sample["albedo"])
    return {"level": float(np.log2(compose.albedo_gain(albedo, sample["albedo"], mask))),
            "psnr": [metrics.psnr(protocol_encode(albedo * np.float32(2.0 ** s)), true, mask) for s in shifts]}


def summarise(rows: list, shifts=SHIFTS) -> dict:
    levels, psnr = np.array([r["level"] for r in rows]), np.array([r["psnr"] for r in rows]).mean(axis=0)
    return {"samples": len(rows), "level_median": float(np.median(levels)), "level_mean": float(levels.mean()),
            "level_rms": float(np.sqrt(np.mean(levels ** 2))), "shifts": list(shifts), "psnr": psnr.tolist(),
            "best_shift": float(shifts[int(np.argmax(psnr))]), "psnr_unshifted": float(psnr[list(shifts).index(0.0)])}


def net_albedo(net, sample: dict) -> np.ndarray:
    """The net's albedo as the de-lighting stage makes it, at the sample's side."""
    from relightcli.stages.delight import net_estimate
    from relightcli.stages.frame import unit

    side = sample["input"].shape[0]
    frame = SimpleNamespace(crop=sample["input"].astype(np.float32), normal=unit(sample["normal_pred"].astype(np.float32)))
    return net_estimate(frame, net, SimpleNamespace(resolution=side)).albedo


def measure(models: Path, data, split: str, ids: list) -> dict:
    """summarise() of one models folder's de-lighting net (its manifest's calibration applied) on
    the samples `ids` of `data`'s `split`, with its rows."""
    from relightcli.nets.delight import DelightNet

    net = DelightNet(models_dir=models, threads=2)
    rows = []
    for sample_id in ids:
        sample = data.load(split, sample_id, ("input", "normal_pred", "albedo", "mask"))
        rows.append({"id": sample_id, **sample_row(sample, net_albedo(net, sample))})
    return {**summarise(rows), "rows": rows}


def calibration(net: dict, reference: dict, where: str) -> dict:
    """The manifest's `calibration` for a net whose level (measure()'s summary, measured without
    a calibration) is to be the reference's: its albedo times 2 ** (net's median level - the
    reference's), with what it was measured on."""
    stops = net["level_median"] - reference["level_median"]
    return {"albedo_gain": round(float(2.0 ** stops), 4),
            "why": "the reference net's level convention: a photo cannot tell its albedo's level "
                   "(bench/delight_level.py)",
            "measured": {"on": where, "samples": net["samples"], "level_median_stops": round(net["level_median"], 4),
                         "reference_level_median_stops": round(reference["level_median"], 4)}}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", help="a factory set with the geometry net's normals (normal_pred)")
    parser.add_argument("models", nargs="+", type=Path, help="models folders whose de-lighting nets to measure")
    parser.add_argument("--split", default="val")
    parser.add_argument("--skip", type=int, default=0, help="leave out the split's first N samples")
    parser.add_argument("--count", type=int, default=200)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    data = dataset.open_dataset(args.data)
    ids = list(data.ids(args.split))[args.skip:args.skip + args.count]
    results = {}
    for folder in args.models:
        results[str(folder)] = summary = measure(folder, data, args.split, ids)
        print(f"{folder}: {summary['samples']} samples, level median {summary['level_median']:+.3f} / mean "
              f"{summary['level_mean']:+.3f} / RMS {summary['level_rms']:.3f} stops; albedo PSNR "
              + " ".join(f"{s:+.1f}:{p:.3f}" for s, p in zip(summary["shifts"], summary["psnr"]))
              + f"; best at {summary['best_shift']:+.1f}", flush=True)
    if args.out:
        args.out.write_text(json.dumps({"data": args.data, "split": args.split, "skip": args.skip, "nets": results},
                                       indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
