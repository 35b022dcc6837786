"""The face stage on the real sample photos (no ground truth: a look, not a metric).

Usage: PYTHONPATH=. python bench/face_landmarks_photos.py [--out bench/results/face_landmarks_photos.png]

`fit_face_in_crop` runs on each whole photo (the cascade finds more faces at full resolution
than in a 512 px person crop, and this looks at the landmarks, not at the detector). Prints one
JSON line per photo (the info dict, run time) and writes a sheet: each face crop (128 px, shown
2x) with the net's landmarks (red) and the fitted model's landmarks (green), or the skip reason.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

PHOTOS = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "photos"
NAMES = ("pexels_portrait_woman.png", "pexels_portrait_face_paint.png", "pexels_woman_with_dog.jpg",
         "nasa_apollo11_aldrin_fullbody.png", "coco_000000000785_skier.jpg", "pexels_jockey.jpg")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench/results/face_landmarks_photos.png")
    args = parser.parse_args(argv)

    from relightcli.geometry.face import cut_crop, face_landmarks, fit_face_in_crop
    from relightcli.geometry.face_detect import CropRect
    from relightcli.geometry.face_model import FaceModel
    from relightcli.io.images import linear_to_srgb, read_image
    from relightcli.nets.landmarks import LandmarkNet

    model, net = FaceModel.load(), LandmarkNet(threads=1)
    tiles = []
    for name in NAMES:
        if not (PHOTOS / name).is_file():
            continue
        crop = read_image(PHOTOS / name).rgb
        start = time.perf_counter()
        fit, info = fit_face_in_crop(crop, None, net, model=model)
        info["ms"] = round(1e3 * (time.perf_counter() - start), 1)
        print(json.dumps({"photo": name, **info}))
        tile = np.zeros((256, 256, 3), np.uint8)
        if "crop" in info:
            rect = CropRect(*info["crop"])
            face = cut_crop(crop, rect)
            tile = cv2.resize(np.round(linear_to_srgb(np.clip(face, 0, 1)) * 255).astype(np.uint8),
                              (256, 256), interpolation=cv2.INTER_NEAREST)
            points = [(face_landmarks(crop, rect, net), (255, 40, 40))]
            if fit is not None:
                points.append((fit.landmarks_px(), (40, 255, 40)))
            for landmarks, colour in points:
                for col, row in (landmarks + 0.5) * 2 * 16:
                    cv2.circle(tile, (int(col), int(row)), 24, colour, -1, cv2.LINE_AA, shift=4)
        if fit is None:
            cv2.putText(tile, "skipped", (8, 248), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 0), 1)
        tiles.append(tile)
    sheet = np.concatenate(tiles, axis=1)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(args.out, sheet[..., ::-1])


if __name__ == "__main__":
    main()
