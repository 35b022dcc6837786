"""Measure the shipped landmark net and the face fit on held-out synthetic faces.

    PYTHONPATH=. python -m export.landmark_eval --data data/faces128 --split test \\
        [--models models] [--pipeline 60] [--update-manifest]

1. The split's crops (export/factory/face_dataset.py): the ONNX model through the runtime
   class (`relightcli.nets.landmarks.LandmarkNet`), then `fit_face` in the crop's frame.
   Landmark error (mean point-to-point, pixels of the 128 crop), NME (/ inter-ocular
   distance, 300-W), failures (NME > 0.1); fit: head rotation error (angle of R_fit^T R_true)
   and per-angle errors, the fitted landmarks' reprojection error against the truth, the
   fit residual, the identity error on the first modes; run time per face.
2. `--pipeline N`: N new faces of the split rendered small in a loose square (as in a
   full-body crop) through `fit_face_in_crop` (detector, crop, two landmark passes, fit):
   detection rate, skips, and the pose error of the accepted fits, with 1 and 2 passes.
`--update-manifest` writes the numbers into the model's manifest entry ("metrics").
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from export.factory import camera_model, faces
from export.factory.face_dataset import SPLITS, FaceLandmarkDataset
from relightcli.geometry.face import LANDMARK_SIGMA_PX, fit_face_in_crop
from relightcli.geometry.face_fit import fit_face
from relightcli.geometry.face_model import (FaceModel, rotation_angle_deg, rotation_angles_deg,
                                           rotation_matrix)
from relightcli.nets.landmarks import LandmarkNet

NME_FAILURE = 0.1
IDENTITY_MODES = 3


def summary(values) -> dict:
    values = np.asarray(values, np.float64)
    return {"mean": round(float(values.mean()), 3), "median": round(float(np.median(values)), 3),
            "p90": round(float(np.percentile(values, 90)), 3), "max": round(float(values.max()), 3)}


def evaluate_crops(net: LandmarkNet, model: FaceModel, arrays: dict,
                   landmark_sigma_px: float = LANDMARK_SIGMA_PX) -> dict:
    """Landmark and fit errors over every crop of a split (see the module docstring)."""
    rows = {k: [] for k in ("error_px", "nme", "rotation_deg", "yaw", "pitch", "roll",
                            "reprojection_px", "residual_px", "identity", "identity0", "net_ms", "fit_ms")}
    for k in range(arrays["index"].size):
        image = camera_model.decode_photo(arrays["image"][k])
        truth = arrays["landmarks"][k].astype(np.float64)
        start = time.perf_counter()
        predicted = net.predict(image)
        middle = time.perf_counter()
        fit = fit_face(predicted, model, tuple(arrays["rect"][k]), (faces.CROP, faces.CROP),
                       landmark_sigma_px=landmark_sigma_px)
        rows["fit_ms"].append(1e3 * (time.perf_counter() - middle))
        rows["net_ms"].append(1e3 * (middle - start))
        error = np.linalg.norm(predicted - truth, axis=1).mean()
        rows["error_px"].append(error)
        rows["nme"].append(error / faces.interocular_px(truth))
        angles = arrays["angles_deg"][k]
        rows["rotation_deg"].append(rotation_angle_deg(fit.rotation, rotation_matrix(*angles)))
        for name, fitted, true in zip(("yaw", "pitch", "roll"), rotation_angles_deg(fit.rotation), angles):
            rows[name].append(abs(fitted - true))
        rows["reprojection_px"].append(np.linalg.norm(fit.landmarks_px() - truth, axis=1).mean())
        rows["residual_px"].append(fit.residual_px)
        rows["identity"].append(np.abs(fit.identity[:IDENTITY_MODES]
                                       - arrays["identity"][k][:IDENTITY_MODES]).mean())
        rows["identity0"].append(abs(fit.identity[0] - arrays["identity"][k][0]))
    nme = np.asarray(rows["nme"])
    return {
        "count": int(nme.size),
        "landmark_error_px": summary(rows["error_px"]),
        "nme": summary(nme),
        "failure_rate_nme_0.1": round(float(np.mean(nme > NME_FAILURE)), 4),
        "fit_rotation_error_deg": summary(rows["rotation_deg"]),
        "fit_abs_error_deg": {k: summary(rows[k]) for k in ("yaw", "pitch", "roll")},
        "fit_reprojection_error_px": summary(rows["reprojection_px"]),
        "fit_residual_px": {**summary(rows["residual_px"]),
                            "p99": round(float(np.percentile(rows["residual_px"], 99)), 3)},
        f"identity_abs_error_first_{IDENTITY_MODES}_modes": summary(rows["identity"]),
        "identity_abs_error_if_zero": round(float(np.abs(arrays["identity"][:, :IDENTITY_MODES]).mean()), 3),
        "identity_mode_0_abs_error": summary(rows["identity0"]),
        "identity_mode_0_abs_error_if_zero": round(float(np.abs(arrays["identity"][:, 0]).mean()), 3),
        "runtime_ms": {"landmarks": summary(rows["net_ms"]), "fit": summary(rows["fit_ms"])},
    }


def evaluate_pipeline(net: LandmarkNet, model: FaceModel, split: str, count: int, seed: int,
                      landmark_sigma_px: float = LANDMARK_SIGMA_PX) -> dict:
    """`count` faces rendered small in a loose square, through fit_face_in_crop."""
    from export.factory import lighting

    hdris = lighting.hdri_splits()[split]
    results = {1: [], 2: []}
    detected, skipped = 0, {}
    for index in range(count):
        spec = faces.sample_spec(np.random.default_rng([seed, 77, SPLITS.index(split), index]), model, hdris)
        spec = dataclasses.replace(spec, crop_scale=3.0, crop_shift=(0.0, 0.0), source_side=0)
        image = camera_model.decode_photo(faces.render_face(model, spec)["image"])
        truth = rotation_matrix(*spec.angles_deg)
        for passes in (1, 2):
            fit, info = fit_face_in_crop(image, None, net, model=model, passes=passes,
                                         landmark_sigma_px=landmark_sigma_px)
            if passes == 2 and "box" in info:
                detected += 1
            if fit is None:
                if passes == 2 and "box" in info:
                    reason = info["skipped"].split(" (")[0].split(":")[0]
                    skipped[reason] = skipped.get(reason, 0) + 1
                continue
            results[passes].append(rotation_angle_deg(fit.rotation, truth))
    out = {"count": count, "detected": detected, "skipped_after_detection": skipped}
    for passes, errors in results.items():
        if errors:
            out[f"rotation_error_deg_{passes}_pass"] = {**summary(errors), "fits": len(errors)}
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--split", default="test")
    parser.add_argument("--models", default=None, help="models directory (default: the shipped one)")
    parser.add_argument("--pipeline", type=int, default=0, help="faces for the detector-to-fit check")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--landmark-sigma", type=float, default=LANDMARK_SIGMA_PX,
                        help="the fit's landmark noise in pixels (choose it on val, not test)")
    parser.add_argument("--update-manifest", action="store_true")
    args = parser.parse_args(argv)

    model = FaceModel.load()
    net = LandmarkNet(models_dir=args.models, threads=args.threads)
    report = {"split": args.split,
              "landmark_sigma_px": args.landmark_sigma,
              "crops": evaluate_crops(net, model, FaceLandmarkDataset(args.data).arrays(args.split),
                                      args.landmark_sigma)}
    if args.pipeline:
        report["pipeline"] = evaluate_pipeline(net, model, args.split, args.pipeline, args.seed,
                                               args.landmark_sigma)
    print(json.dumps(report, indent=2))
    if args.update_manifest:
        _update_manifest(Path(args.models) if args.models else None, args.split, report)
    return 0


def _update_manifest(models_dir, split: str, report: dict) -> None:
    from export.manifest import update_manifest
    from relightcli.nets.manifest import MANIFEST_NAME, models_dir as default_models_dir

    models_dir = models_dir or default_models_dir()
    manifest = json.loads((models_dir / MANIFEST_NAME).read_text())
    entry = manifest["models"]["landmarks"]
    entry["metrics"] = {**entry.get("metrics", {}), split: report}
    update_manifest(models_dir, "landmarks", entry)


if __name__ == "__main__":
    raise SystemExit(main())
