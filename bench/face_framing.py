"""How the runtime frames a face: the OpenCV cascade's box (`detect_face`) and the crop
`face_crop_rect` makes of it, against the 68 landmarks, measured on synthetic renders.

Usage: PYTHONPATH=. python bench/face_framing.py [--count N] [--seed S]

Each sample is a synthetic face (export/factory/faces.py) framed loosely (crop scale 3, so the
face spans ~40 px as in a full-body crop at 256-512 px). Prints one JSON line: the detection
rate overall and by |yaw|, and over the detections the crop's framing in the units of
faces.FRAMING: scale = crop side / larger side of the landmarks' bounding box, shift =
(crop centre - box centre) / crop side (x right, y up). The landmark data's FRAMING ranges
must cover these.
"""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=60)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    from export.factory import camera_model, faces, lighting
    from relightcli.geometry.face_detect import detect_face, face_crop_rect
    from relightcli.geometry.face_model import FaceModel

    model = FaceModel.load()
    hdris = lighting.hdri_splits()["train"]
    scales, shifts, found, yaws = [], [], [], []
    for index in range(args.count):
        spec = faces.sample_spec(np.random.default_rng([args.seed, 99, index]), model, hdris)
        spec = dataclasses.replace(spec, crop_scale=3.0, crop_shift=(0.0, 0.0),
                                   augmentation=camera_model.NO_AUGMENTATION, jpeg_quality=0,
                                   source_side=0)
        sample = faces.render_face(model, spec)
        box, _ = detect_face(camera_model.decode_photo(sample["image"]), model=model)
        yaws.append(abs(spec.angles_deg[0]))
        found.append(box is not None)
        if box is None:
            continue
        crop = face_crop_rect(box)
        points = sample["landmarks"]
        lo, hi = points.min(axis=0), points.max(axis=0)
        centre = np.array([crop.left + crop.size / 2.0, crop.top + crop.size / 2.0]) - 0.5
        scales.append(crop.size / float(np.max(hi - lo)))
        offset = (centre - (lo + hi) / 2.0) / crop.size
        shifts.append([offset[0], -offset[1]])   # rows grow downward, y upward
    found, yaws = np.array(found), np.array(yaws)
    scales, shifts = np.array(scales), np.array(shifts).reshape(-1, 2)
    report = {
        "count": args.count,
        "detected": float(found.mean()),
        "detected_by_abs_yaw": {f"{lo}-{lo + 10}": float(found[(yaws >= lo) & (yaws < lo + 10)].mean())
                                for lo in range(0, 40, 10) if np.any((yaws >= lo) & (yaws < lo + 10))},
    }
    if scales.size:
        report["scale"] = {"min": float(scales.min()), "median": float(np.median(scales)),
                           "max": float(scales.max())}
        report["shift_x"] = [float(shifts[:, 0].min()), float(shifts[:, 0].max())]
        report["shift_y"] = [float(shifts[:, 1].min()), float(shifts[:, 1].max())]
    print(json.dumps(report))


if __name__ == "__main__":
    main()
