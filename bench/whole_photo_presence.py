"""How far to trust the landmark net on a whole photo (nets.pose.find_person_in_photo, run when
BlazePose's detector finds nobody): its presence on views of the HDRIs in ../shared/data/hdri
(no person in them: every "person" is a false one) and, on eval scene folders, on the photos
where the detector finds nobody (a person in each), with the IoU of its mask against the truth.

    python bench/whole_photo_presence.py data/evalval512 data/evalval256 [--out FILE]

Choose WHOLE_PHOTO_PRESENCE here, on validation folders, never on the test scenes.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from relightcli.io.envmap import environment_view, load_envmap  # noqa: E402
from relightcli.io.images import LUMINANCE, linear_to_srgb, read_image  # noqa: E402
from relightcli.nets.pose import (  # noqa: E402
    WHOLE_PHOTO_PRESENCE,
    PersonDetector,
    PoseLandmarker,
    find_people,
    find_person_in_photo,
)
from relightcli.stages.frame import PerceptionView  # noqa: E402

HDRI = REPO.parent / "shared" / "data" / "hdri"
VIEWS = ((0.0, 512, 384), (120.0, 384, 512), (240.0, 512, 512))  # yaw (degrees), width, height


def empty_views():
    """Three 60-degree views of each HDRI, exposed to a mid-grey median, as sRGB photos."""
    for path in sorted(HDRI.glob("*.hdr")):
        env = load_envmap(path)
        for yaw, width, height in VIEWS:
            view = environment_view(env, width=width, height=height, fov_deg=60.0, yaw_deg=yaw)
            exposure = 0.18 / max(float(np.median(view @ LUMINANCE)), 1e-6)
            yield f"{path.stem}@{yaw:.0f}", linear_to_srgb(np.clip(view * exposure, 0.0, 1.0)).astype(np.float32)


def missed_people(folders, detector, landmarker):
    """(name, sRGB view, true mask at the view's size) of each scene the detector finds nobody in."""
    for folder in folders:
        for scene in sorted(Path(folder).iterdir()):
            if not (scene / "input.png").is_file():
                continue
            view = PerceptionView.of(read_image(scene / "input.png").rgb).image
            if any(p.found for p in find_people(view, detector, landmarker)):
                continue
            truth = cv2.imread(str(scene / "gt_mask.png"), cv2.IMREAD_GRAYSCALE) > 127
            truth = cv2.resize(truth.astype(np.uint8), view.shape[1::-1], interpolation=cv2.INTER_NEAREST) > 0
            yield f"{Path(folder).name}/{scene.name}", view, truth


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="*")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    detector, landmarker = PersonDetector(threads=2), PoseLandmarker(threads=2)
    empty = {name: find_person_in_photo(view, landmarker).pose.presence for name, view in empty_views()}
    missed = {}
    for name, view, truth in missed_people(args.folders, detector, landmarker):
        pose = find_person_in_photo(view, landmarker).pose
        found = pose.mask > 0.5
        missed[name] = {"presence": pose.presence,
                        "iou": float((found & truth).sum() / max((found | truth).sum(), 1))}
    false = sorted(empty.values())
    taken = [m for m in missed.values() if m["presence"] >= WHOLE_PHOTO_PRESENCE]
    print(f"{len(empty)} views without a person: presence max {false[-1]:.4f}, "
          f"{sum(p >= 0.5 for p in false)} at >= 0.5, {sum(p >= WHOLE_PHOTO_PRESENCE for p in false)} "
          f"at >= {WHOLE_PHOTO_PRESENCE}")
    if missed:
        print(f"{len(missed)} people the detector missed: {len(taken)} at >= {WHOLE_PHOTO_PRESENCE}, "
              f"mask IoU of those mean {np.mean([m['iou'] for m in taken]):.3f}, "
              f"min {min(m['iou'] for m in taken):.3f}; presences below: "
              f"{sorted(round(m['presence'], 4) for m in missed.values() if m not in taken)}")
    if args.out:
        Path(args.out).write_text(json.dumps({"empty_views": empty, "missed_people": missed}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
