"""Person-mask quality: IoU with the true mask (mean and worst) of each way of making the mask,
on eval scene folders (input.png + gt_mask.png) and on the COCO skier's annotation.

    python bench/mask_iou.py data/eval512 data/evalval512 [--out bench/results/mask_iou.json]

Methods: `pose` (the union of BlazePose's person segmentations, raw) and `stage` (what the
pipeline's people and mask stages make: that union with its edges snapped). A scene where no
person is found scores 0.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from relightcli.io.images import linear_to_srgb, read_image  # noqa: E402

SKIER = (REPO / "examples" / "skier.jpg", REPO / "examples" / "skier_mask.png")


def iou(mask: np.ndarray, truth: np.ndarray) -> float:
    a, b = mask > 0.5, truth > 0.5
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0


def scenes(folders: list[str]) -> list[tuple[str, Path, Path]]:
    out = [("coco_skier", *SKIER)]
    for folder in folders:
        for scene in sorted(Path(folder).iterdir()):
            if (scene / "input.png").is_file():
                out.append((f"{Path(folder).name}/{scene.name}", scene / "input.png", scene / "gt_mask.png"))
    return out


class Masks:
    def __init__(self, resolution: int = 512):
        from relightcli.nets.pose import PersonDetector, PoseLandmarker
        from relightcli.stages.frame import Models

        self.models = Models(threads=2)
        self.detector, self.landmarker = PersonDetector(threads=2), PoseLandmarker(threads=2)
        self.resolution = resolution

    def people(self, linear: np.ndarray):
        from relightcli.nets.pose import find_people

        srgb = np.clip(linear_to_srgb(linear), 0.0, 1.0).astype(np.float32)
        return [p for p in find_people(srgb, self.detector, self.landmarker) if p.found]

    def pose(self, linear: np.ndarray) -> tuple[np.ndarray, int]:
        people = self.people(linear)
        if not people:
            return np.zeros(linear.shape[:2], np.float32), 0
        return np.max([p.pose.mask for p in people], axis=0), len(people)

    def stage(self, linear: np.ndarray) -> tuple[np.ndarray, int]:
        from relightcli.errors import RelightError
        from relightcli.pipeline import RelightOptions
        from relightcli.stages.frame import Frame
        from relightcli.stages.people import stage_mask, stage_people

        frame = Frame(image=linear, mask=None, env=np.ones((4, 8, 3), np.float32))
        options = RelightOptions(resolution=self.resolution)
        stage_people(frame, options, self.models)
        try:
            stage_mask(frame, options, self.models)
        except RelightError:  # no person found
            return np.zeros(linear.shape[:2], np.float32), 0
        return frame.mask, len(frame.people)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="*")
    parser.add_argument("--methods", default="pose,stage")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    masks = Masks()
    results = {}
    for method in args.methods.split(","):
        rows, seconds = {}, []
        for name, image_path, truth_path in scenes(args.folders):
            linear = read_image(image_path).rgb
            truth = cv2.imread(str(truth_path), cv2.IMREAD_GRAYSCALE).astype(np.float32) / 255.0
            start = time.perf_counter()
            mask, people = getattr(masks, method)(linear)
            seconds.append(time.perf_counter() - start)
            rows[name] = {"iou": round(iou(mask, truth), 4), "people": people}
        scores = [r["iou"] for k, r in rows.items() if k != "coco_skier"]
        results[method] = {
            "mean_iou": round(float(np.mean(scores)), 4) if scores else None,
            "worst_iou": round(float(np.min(scores)), 4) if scores else None,
            "coco_skier_iou": rows["coco_skier"]["iou"],
            "median_seconds": round(float(np.median(seconds)), 4),
            "scenes": rows,
        }
        print(f"{method}: mean {results[method]['mean_iou']} worst {results[method]['worst_iou']} "
              f"skier {results[method]['coco_skier_iou']} ({len(scores)} scenes, "
              f"{results[method]['median_seconds'] * 1000:.0f} ms median)", flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
