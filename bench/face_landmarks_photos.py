"""The face stage on the real sample photos (no ground truth: a look, not a metric).

Usage: PYTHONPATH=. python bench/face_landmarks_photos.py [--out bench/results/face_landmarks_photos.png]

The runtime's face chain runs on each whole photo: `find_face` (face detector + face mesh) on
the whole picture, the 468 points -> 68 landmarks (geometry.face_correspondence), then
`fit_face_to_landmarks` in the 128 face crop framed around them (the whole photo rather than
a pose's head square: this looks at the landmarks and the fit, not at the framing). Prints
one JSON line per photo (the fit's info dict, run time) and writes a sheet: each face crop
(128 px, shown 2x) with the table's landmarks (red) and the fitted model's landmarks
(green), or the skip reason.
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


def photo_landmarks(srgb, nets):
    """((68, 2) landmarks in pixel indices of the photo, or None; the info dict)."""
    from relightcli.geometry.face_correspondence import load_correspondence
    from relightcli.nets.face_mesh import find_face

    face, why = find_face(srgb, None, *nets)
    if face is None:
        return None, {"skipped": why}
    return load_correspondence().landmarks(face.mesh.points[:, :2]) - 0.5, face.summary()


def face_tile(image, landmarks, fit, info) -> np.ndarray:
    """(256, 256, 3) uint8: the face crop shown 2x with the landmarks (red) and the fit's (green)."""
    from relightcli.geometry.face import CropRect, cut_crop, image_to_crop
    from relightcli.io.images import linear_to_srgb

    tile = np.zeros((256, 256, 3), np.uint8)
    if "crop" in info:
        rect = CropRect(*info["crop"])
        face = cut_crop(image, rect)
        tile = cv2.resize(np.round(linear_to_srgb(np.clip(face, 0, 1)) * 255).astype(np.uint8),
                          (256, 256), interpolation=cv2.INTER_NEAREST)
        points = [(image_to_crop(landmarks, rect), (255, 40, 40))]
        if fit is not None:
            points.append((fit.landmarks_px(), (40, 255, 40)))
        for crop_points, colour in points:
            for col, row in (crop_points + 0.5) * 2 * 16:
                cv2.circle(tile, (int(col), int(row)), 24, colour, -1, cv2.LINE_AA, shift=4)
    if fit is None:
        cv2.putText(tile, "skipped", (8, 248), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 0), 1)
    return tile


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench/results/face_landmarks_photos.png")
    args = parser.parse_args(argv)

    from relightcli.geometry.face import fit_face_to_landmarks
    from relightcli.geometry.face_model import FaceModel
    from relightcli.io.images import linear_to_srgb, read_image
    from relightcli.nets.face_mesh import FaceDetector, FaceMesh

    model, nets = FaceModel.load(), (FaceDetector(threads=1), FaceMesh(threads=1))
    tiles = []
    for name in NAMES:
        if not (PHOTOS / name).is_file():
            continue
        image = read_image(PHOTOS / name).rgb
        start = time.perf_counter()
        srgb = np.clip(linear_to_srgb(np.nan_to_num(image)), 0.0, 1.0).astype(np.float32)
        landmarks, info = photo_landmarks(srgb, nets)
        fit = None
        if landmarks is not None:
            fit, fit_info = fit_face_to_landmarks(landmarks, image.shape, model=model)
            info.update(fit_info)
        info["ms"] = round(1e3 * (time.perf_counter() - start), 1)
        print(json.dumps({"photo": name, **info}))
        tiles.append(face_tile(image, landmarks, fit, info))
    sheet = np.concatenate(tiles, axis=1)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(args.out, sheet[..., ::-1])


if __name__ == "__main__":
    main()
