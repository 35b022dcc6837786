"""Should a net ship as int8? Quantise the shipped fp32 ONNX models (QDQ static, calibrated on
training samples) and compare both on the factory's validation split: quality and run time.

    PYTHONPATH=. python -m export.int8_eval --data data/factory256 [--models models] \\
        [--families geometry ao delight body_refine] [--calibration 16] [--count 32] \\
        [--out bench/results/int8.json]

Per net, the quality is one PSNR in dB against the ground truth over the person (the issue's
rule: int8 ships only where it loses less than 0.3 dB): geometry: the front normals encoded
(n + 1) / 2; ao: the AO map; delight: the albedo (sRGB, as the trainer's validation); body
refinement: the refined shading (the trainer's protocol). The trainer's own validation metrics
are reported for both too, and the median single-thread run time of one 256 x 256 inference.
Inputs are built exactly as the trainer builds them (export.train.tasks), from the same
dataset, with the validation rng.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort

from export.onnx_export import quantize_int8
from export.train.cli import open_dataset
from export.train.config import load_config
from export.train.data import sample_rng
from export.train.tasks import hwc, make_task
from relightcli import metrics

CONFIGS = Path(__file__).resolve().parent / "train" / "configs"
FAMILIES = ("geometry", "ao", "delight", "body_refine")
SHIP_BELOW_DB = 0.3


def quality_psnr(family: str, out: dict, example: dict, task_metrics: dict) -> float:
    """The one dB number per net that decides int8 (see the module docstring)."""
    mask = example["mask"][0]
    if family == "geometry":
        pred = np.clip((hwc(out["front_normal"]) + 1) / 2, 0, 1)
        return metrics.psnr(pred, (hwc(example["front_normal"]) + 1) / 2, mask)
    if family == "ao":
        return metrics.psnr(np.clip(hwc(out["ao"]), 0, 1), hwc(example["ao"]), mask)
    if family == "delight":
        return task_metrics["albedo_psnr"]
    return task_metrics["shading_psnr_refined"]


def session(path: Path) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def feeds_and_examples(task, dataset, split: str, count: int, input_names: list[str]):
    for sample_id in dataset.ids(split)[:count]:
        example = task.example(dataset.load(split, sample_id), sample_rng(task.config.seed, split, sample_id))
        if example is None:
            continue
        feed = {name: example[key][None].astype(np.float32) for name, key in zip(input_names, task.input_keys)}
        yield feed, example


def evaluate(family: str, models: Path, dataset, calibration: int, count: int, workdir: Path) -> dict:
    task = make_task(load_config(CONFIGS / f"{family}_small.json"))
    fp32_path = models / f"{family}.onnx"
    fp32 = session(fp32_path)
    input_names = [i.name for i in fp32.get_inputs()]
    output_names = [o.name for o in fp32.get_outputs()]
    int8_path = workdir / f"{family}.int8.onnx"
    start = time.perf_counter()
    quantize_int8(fp32_path, int8_path,
                  (feed for feed, _ in feeds_and_examples(task, dataset, "train", calibration, input_names)))
    quantize_seconds = time.perf_counter() - start
    int8 = session(int8_path)
    rows = {"fp32": [], "int8": []}
    quality = {"fp32": [], "int8": []}
    times = {"fp32": [], "int8": []}
    non_finite = {"fp32": 0, "int8": 0}
    for feed, example in feeds_and_examples(task, dataset, "val", count, input_names):
        for name, sess in (("fp32", fp32), ("int8", int8)):
            tick = time.perf_counter()
            values = sess.run(output_names, feed)
            times[name].append(time.perf_counter() - tick)
            out = {k: v[0] for k, v in zip(output_names, values)}
            if not all(np.isfinite(v).all() for v in values):
                non_finite[name] += 1  # a quantised net can divide by a quantised zero
                continue
            task_metrics = task.metrics(out, example)
            rows[name].append(task_metrics)
            quality[name].append(quality_psnr(family, out, example, task_metrics))
    result = {"samples": len(times["fp32"]), "calibration_samples": calibration,
              "quantize_seconds": round(quantize_seconds, 1),
              "size_mb": {"fp32": round(fp32_path.stat().st_size / 2**20, 2),
                          "int8": round(int8_path.stat().st_size / 2**20, 2)}}
    for name in ("fp32", "int8"):
        if not quality[name]:
            result[name] = {"non_finite_samples": non_finite[name], "quality_psnr_db": None,
                            "median_ms": round(1e3 * float(np.median(times[name])), 1)}
            continue
        result[name] = {"non_finite_samples": non_finite[name],
                        "quality_psnr_db": round(float(np.mean(quality[name])), 3),
                        "median_ms": round(1e3 * float(np.median(times[name])), 1),
                        "metrics": {k: round(float(np.mean([r[k] for r in rows[name]])), 4)
                                    for k in rows[name][0]}}
    faster = result["int8"]["median_ms"] < result["fp32"]["median_ms"]
    if non_finite["int8"] or result["int8"]["quality_psnr_db"] is None:
        result["drop_db"], result["ship_int8"] = None, False
        result["why"] = f"int8 gives non-finite outputs on {non_finite['int8']} of {result['samples']} samples"
        return result
    drop = result["fp32"]["quality_psnr_db"] - result["int8"]["quality_psnr_db"]
    result["drop_db"] = round(drop, 3)
    result["ship_int8"] = bool(drop < SHIP_BELOW_DB and faster)
    result["why"] = (f"drop {drop:.2f} dB {'<' if drop < SHIP_BELOW_DB else '>='} {SHIP_BELOW_DB} dB; "
                     f"int8 {result['int8']['median_ms']} ms vs fp32 {result['fp32']['median_ms']} ms")
    return result


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="factory dataset (export/factory)")
    parser.add_argument("--models", default="models")
    parser.add_argument("--families", nargs="*", default=list(FAMILIES))
    parser.add_argument("--calibration", type=int, default=16, help="training samples to calibrate on")
    parser.add_argument("--count", type=int, default=32, help="validation samples")
    parser.add_argument("--out", default=None, help="write the results here (JSON)")
    args = parser.parse_args(argv)
    dataset = open_dataset(args.data)
    results = {}
    with tempfile.TemporaryDirectory() as workdir:
        for family in args.families:
            results[family] = evaluate(family, Path(args.models), dataset, args.calibration, args.count,
                                       Path(workdir))
            r = results[family]
            print(f"{family:12s} fp32 {r['fp32']['quality_psnr_db']} dB {r['fp32']['median_ms']} ms | "
                  f"int8 {r['int8']['quality_psnr_db']} dB {r['int8']['median_ms']} ms | "
                  f"{'ship int8' if r['ship_int8'] else 'keep fp32'}: {r['why']}", flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(results, indent=2) + "\n")
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
