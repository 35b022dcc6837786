"""How sure the landmark net is of the people BlazePose's detector finds (nets.pose.
WEAK_DETECTION_SCORE, WEAK_DETECTION_PRESENCE): every detection's score and the landmark
net's presence, against the true mask (the share of the person's mask inside it), on eval
scene folders; on views of the HDRIs in ../shared/data/hdri (no person in them) with `hdri`;
on the photos of a folder with `photos=DIR` (no truth: listed for a look).

    python bench/people_presence.py data/evalval512 data/evaltrain512 data/evalval256v7 hdri \
        photos=../shared/data/photos

Choose the thresholds here, on validation folders, never on the test scenes.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from relightcli.nets.pose import (  # noqa: E402
    MIN_PRESENCE,
    WEAK_DETECTION_PRESENCE,
    WEAK_DETECTION_SCORE,
    PersonDetector,
    PoseLandmarker,
    find_people,
)
from whole_photo_presence import empty_views  # noqa: E402

REAL = 0.5  # a detection is a real person when this share of its mask lies in the true mask


def read_srgb(path: Path) -> np.ndarray:
    return cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0


def detections(image, nets, truth=None):
    """(detection score, presence, share of the person's mask in `truth` or None) of each
    detection whose crop the landmark net looked at."""
    for person in find_people(image, *nets):
        if person.pose is None:
            continue
        share = None
        if truth is not None:
            mask = person.pose.mask > 0.5
            share = float((mask & truth).sum() / max(mask.sum(), 1))
        yield person.detection.score, person.pose.presence, share


def rows(source: str, nets):
    if source == "hdri":
        for name, view in empty_views():
            for score, presence, _ in detections(view, nets):
                yield "hdri", name, score, presence, 0.0
    elif source.startswith("photos="):
        folder = Path(source.split("=", 1)[1])
        for path in sorted(p for p in folder.iterdir() if p.suffix in (".jpg", ".png") and "mask" not in p.stem):
            for score, presence, _ in detections(read_srgb(path), nets):
                yield "photos", path.name, score, presence, None
    else:
        for scene in sorted(p for p in Path(source).iterdir() if p.is_dir()):
            truth = cv2.imread(str(scene / "gt_mask.png"), cv2.IMREAD_GRAYSCALE) > 127
            for score, presence, share in detections(read_srgb(scene / "input.png"), nets, truth):
                yield Path(source).name, scene.name, score, presence, share


def main() -> int:
    nets = PersonDetector(), PoseLandmarker()
    print("set           item                          score  presence  in true mask")
    by_set: dict[str, list] = {}
    for row in (r for source in sys.argv[1:] for r in rows(source, nets)):
        name, item, score, presence, share = row
        by_set.setdefault(name, []).append(row)
        shown = "-" if share is None else f"{share:.2f}"
        print(f"{name:13s} {item[:29]:29s} {score:5.3f}  {presence:8.3f}  {shown}")
    print(f"\nper set: real people (share >= {REAL}): how many, how many under MediaPipe's {MIN_PRESENCE}, the "
          f"lowest presence of the others; the presences of the weak detections (score < {WEAK_DETECTION_SCORE}, "
          f"taken at >= {WEAK_DETECTION_PRESENCE}), of real people and of the rest")
    for name, found in by_set.items():
        real = [r for r in found if r[4] is not None and r[4] >= REAL]
        other = [r for r in found if r[4] is not None and r[4] < REAL]
        kept = [r[3] for r in real if r[3] >= MIN_PRESENCE]
        low = f"{min(kept):.3f}" if kept else "-"
        weak = lambda rows: " ".join(f"{r[3]:.2f}" for r in rows if r[2] < WEAK_DETECTION_SCORE) or "-"  # noqa: E731
        print(f"{name:13s} real {len(real):4d} ({len(real) - len(kept)} under, lowest above {low}; weak: {weak(real)}); "
              f"others {len(other)} (weak: {weak(other)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
