"""Every face in real photos, relit: its detail and its artifacts (issue 48).

    python bench/face_check.py ../shared/data/photos examples --pair examples/skier.jpg \
        [--out bench/results/face_check.json] [--pictures DIR]

Relights every photo (`.jpg`, `.png`, not a `*_mask.png`) in the folders under
examples/noon_grass.hdr as bench/photo_detail.py does (--pair PHOTO adds PHOTO beside its
mirror image: two people), then measures each face the report's face stage found (its
detection box; the face mesh's 468 points found again there outline the face, cut to the
person mask, 2 px inside). In the face, the log ratio relit / photo per channel is, for a
relight, a smooth shading field (sharp only at cast-shadow edges); r is its mean over the
channels, its colour each channel's minus r (per channel, so that the photo's own colour edges
do not count as the relight's); local medians are taken over a window a sixth of the face's
side:

- detail: correlation of the high-pass log luminance (sigma 2 px) of photo and relit
- jumps: share of pixels where |r - its local median| > 0.35 (blotches, a composite's seam)
- colour: share where a channel's log ratio minus r departs from its local median by > 0.15
  (colour fringes)
- bright: share where r exceeds its local median by log 1.65 (hot spots)
- spread: r's standard deviation over the face (>= 0.05: the face is visibly relit)

Goals per face (issue 48): detail >= 0.85, jumps <= 5%, colour <= 6%, bright <= 0.3%,
spread >= 0.05; per photo: person detail (bench/photo_detail.py) >= 0.85. --pictures writes
each face side by side (photo | relit, the relit at the photo's median level over the face).

    python bench/face_check.py --synthetic data/evalval512 data/eval512

scores, on eval scenes (`relight eval`'s folders, relit with their true mask under their own
target), the true relight (the factory's path-traced gt_relit.exr) beside ours: what the goals
make of a physical relight, hard shadows and all.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from photo_detail import detail, high_pass, photos  # noqa: E402

from relightcli.io.images import LUMINANCE, linear_to_srgb, read_image, write_image  # noqa: E402

JUMP, COLOUR, BRIGHT = 0.35, 0.15, np.log(1.65)
GOALS = {"detail": (">=", 0.85), "jumps": ("<=", 0.05), "colour": ("<=", 0.06), "bright": ("<=", 0.003),
         "spread": (">=", 0.05)}
EPS = 1e-4
# A photo pixel darker than one 8-bit sRGB step above black (linear 1 / 255 / 12.92): its ratio
# relit / photo is 0 / 0, and EPS made it 1 whatever the relight's level (the nostrils of a
# portrait relit to a fifth of its level "brightened" by 5x while they stayed black). Such a
# pixel is neutral (its local median) when the relit is as black (at the relight's level); a
# relit above that keeps its ratio, and counts.
BLACK = 1.0 / 255.0 / 12.92


def face_region(photo: np.ndarray, box, mask: np.ndarray, models) -> np.ndarray | None:
    """(H, W) bool: the face mesh's outline around the face detected in `box` (x0, y0, x1, y1
    photo pixels), inside the person mask, 2 px in; None when the mesh finds no face there."""
    from relightcli.nets.blaze import RotatedRect
    from relightcli.nets.face_mesh import find_face
    from relightcli.stages.frame import PerceptionView

    view = PerceptionView.of(photo)
    scale = np.asarray(view.scale)
    x0, y0, x1, y1 = box
    for grow in (2.0, 1.5, 3.0):  # the first square around the box where the face is found again
        side = grow * max(x1 - x0, y1 - y0)
        head = RotatedRect(((x0 + x1) / 2 * scale[0], (y0 + y1) / 2 * scale[1]), side * scale[0], side * scale[1], 0.0)
        face, _ = find_face(view.image, head, models.get("face_detector"), models.get("face_mesh"))
        if face is not None:
            break
    else:
        return None
    points = face.mesh.points[:, :2] / scale
    hull = cv2.convexHull(np.round(points).astype(np.int32))
    region = np.zeros(mask.shape, np.uint8)
    cv2.fillConvexPoly(region, hull, 1)
    region &= (mask > 0.5).astype(np.uint8)
    return cv2.erode(region, np.ones((5, 5), np.uint8), borderValue=0) > 0


def local_median(values: np.ndarray, region: np.ndarray, window: int) -> np.ndarray:
    """The median of `values` over a window x window square, the pixels outside `region`
    standing in as the region's median."""
    filled = np.where(region, values, np.median(values[region]))
    return ndimage.median_filter(filled, size=window, mode="nearest")


def face_scores(photo: np.ndarray, relit: np.ndarray, region: np.ndarray) -> dict:
    rows, cols = np.nonzero(region)
    window = (slice(max(rows.min() - 8, 0), rows.max() + 9), slice(max(cols.min() - 8, 0), cols.max() + 9))
    a, b, inside = photo[window].astype(np.float64), relit[window].astype(np.float64), region[window]
    side = max(np.ptp(rows), np.ptp(cols)) + 1
    size = max(5, int(side / 6) | 1)
    # EPS at each image's own level over the face: a relight to a fifth of the photo's level
    # otherwise met EPS at a fifth of the pixel's value, and its darkest pixels (nostril rims,
    # pupils) looked up to 2x brighter than their neighbours
    gain = np.median(b[inside] @ LUMINANCE) / max(np.median(a[inside] @ LUMINANCE), EPS)
    ratio = np.log(np.maximum(b, 0) + EPS * gain) - np.log(np.maximum(a, 0) + EPS)  # per channel
    both_black = (a @ LUMINANCE < BLACK) & (b @ LUMINANCE < BLACK * gain)
    inside = inside & ~both_black  # undefined ratios stand in as the face's median (local_median)
    r = ratio.mean(axis=-1)
    jump = np.abs(r - local_median(r, inside, size))
    colour = np.zeros_like(r)
    for k in range(3):
        c = ratio[..., k] - r
        colour = np.maximum(colour, np.abs(c - local_median(c, inside, size)))
    bright = r - local_median(r, inside, size)
    hp_a, hp_b = high_pass(a.astype(np.float32))[inside], high_pass(b.astype(np.float32))[inside]
    return {"pixels": int(inside.sum()), "side_px": int(side), "black_px": int((both_black & region[window]).sum()),
            "detail": round(float(np.corrcoef(hp_a, hp_b)[0, 1]), 3),
            "jumps": round(float(np.mean(jump[inside] > JUMP)), 4),
            "colour": round(float(np.mean(colour[inside] > COLOUR)), 4),
            "bright": round(float(np.mean(bright[inside] > BRIGHT)), 4),
            "spread": round(float(np.std(r[inside])), 3)}


def passes(scores: dict) -> list:
    """The goals a face misses."""
    return [name for name, (op, goal) in GOALS.items()
            if not (scores[name] >= goal if op == ">=" else scores[name] <= goal)]


def picture(photo: np.ndarray, relit: np.ndarray, mask: np.ndarray, region: np.ndarray, path: Path) -> None:
    rows, cols = np.nonzero(region)
    pad = int(0.25 * max(np.ptp(rows), np.ptp(cols)))
    window = (slice(max(rows.min() - pad, 0), rows.max() + pad), slice(max(cols.min() - pad, 0), cols.max() + pad))
    gain = np.median(photo[region] @ LUMINANCE) / max(np.median(relit[region] @ LUMINANCE), EPS)
    side = np.concatenate([photo[window], relit[window] * gain * mask[window][..., None]], axis=1)
    height = side.shape[0]
    side = cv2.resize(side, (side.shape[1] * 256 // height, 256), interpolation=cv2.INTER_AREA)
    write_image(path, linear_to_srgb(np.clip(side, 0, None)))


def relight(photo: Path, hdr: str, out: Path, mask: Path | None = None):
    """(the item's report, None) or (None, the error's last line); the mask: `mask`, else a
    `<stem>_mask.png` beside the photo when there is one."""
    command = [sys.executable, "-m", "relightcli", str(photo), "--hdr", hdr, "-o", str(out / "relit.exr"),
               "--outputs", "relit,mask", "--background", "transparent", "--overwrite", "--json"]
    mask = mask or photo.with_name(photo.stem + "_mask.png")
    command += ["--mask", str(mask)] if mask.is_file() else []
    result = subprocess.run(command, capture_output=True, text=True)
    if result.returncode != 0:
        return None, result.stderr.strip().splitlines()[-1:]
    return json.loads(result.stdout)["items"][0], None


def measure(photo: Path, hdr: str, work: Path, models, pictures: Path | None) -> dict:
    out = work / photo.stem
    report, error = relight(photo, hdr, out)
    if report is None:
        return {"photo": photo.name, "error": error}
    image = read_image(photo).rgb
    relit = read_image(out / "relit.exr").rgb
    mask = read_image(report["outputs"]["mask"], srgb=False).rgb[..., 0]
    row = {"photo": photo.name, "size": list(image.shape[:2]), "person_detail": round(detail(image, relit, mask), 3),
           "faces": []}
    note = report["stages"].get("face", {})
    # (a report from before every face took the face path holds one face, the note itself)
    for entry in note.get("faces", [note] if "detection_box_photo" in note else []):
        face = {"head": entry["head"], "path": entry.get("path") if "skipped" not in entry else None,
                "skipped": entry.get("skipped")}
        row["faces"].append(face)
        if "detection_box_photo" not in entry:
            continue
        region = face_region(image, entry["detection_box_photo"], mask, models)
        if region is None or region.sum() < 50:
            face["skipped"] = (face["skipped"] or "") + " (checker: no face mesh outline)"
            continue
        face.update(face_scores(image, relit, region))
        face["misses"] = passes(face)
        if pictures:
            picture(image, relit, mask, region, pictures / f"{photo.stem}_{entry['head'].replace(' ', '')}.png")
    return row


def mirrored_pair(photo: Path, work: Path) -> Path:
    image = read_image(photo).rgb
    path = work / f"{photo.stem}_pair.png"
    write_image(path, linear_to_srgb(np.concatenate([image, image[:, ::-1]], axis=1)))
    return path


def synthetic(roots: list, models) -> list:
    """Each face of the eval scenes under `roots`: the checker's scores of the true relight and
    of ours, against the scene's input."""
    rows = []
    with tempfile.TemporaryDirectory() as work:
        for scene in (folder for root in roots for folder in sorted(Path(root).iterdir()) if folder.is_dir()):
            out = Path(work) / scene.name
            report, _ = relight(scene / "input.png", str(scene / "target.hdr"), out, mask=scene / "gt_mask.png")
            if report is None:
                continue
            image, mask = read_image(scene / "input.png").rgb, read_image(scene / "gt_mask.png", srgb=False).rgb[..., 0]
            for entry in report["stages"].get("face", {}).get("faces", []):
                region = face_region(image, entry["detection_box_photo"], mask, models) \
                    if "detection_box_photo" in entry else None
                if region is None or region.sum() < 50:
                    continue
                rows.append({"scene": scene.name, "head": entry["head"],
                             "truth": face_scores(image, read_image(scene / "gt_relit.exr").rgb, region),
                             "ours": face_scores(image, read_image(out / "relit.exr").rgb, region)})
                print(json.dumps(rows[-1]), flush=True)
    for name, (op, goal) in GOALS.items():
        line = [f"  {name}:"]
        for who in ("truth", "ours"):
            values = [row[who][name] for row in rows]
            missed = sum(not (v >= goal if op == ">=" else v <= goal) for v in values)
            line.append(f"{who} median {np.median(values):.4f}, goal missed by {missed} of {len(values)};")
        print(" ".join(line))
    return rows


def main() -> int:
    from relightcli.stages.frame import Models

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="*")
    parser.add_argument("--pair", action="append", default=[], type=Path)
    parser.add_argument("--hdr", default=str(ROOT / "examples" / "noon_grass.hdr"))
    parser.add_argument("--out", type=Path)
    parser.add_argument("--pictures", type=Path)
    parser.add_argument("--synthetic", action="store_true",
                        help="the folders hold eval scenes: score the true relight beside ours")
    args = parser.parse_args()
    if args.pictures:
        args.pictures.mkdir(parents=True, exist_ok=True)
    models = Models(2)
    if args.synthetic:
        rows = synthetic(args.folders, models)
        if args.out:
            args.out.write_text(json.dumps(rows, indent=1))
        return 0
    rows = []
    with tempfile.TemporaryDirectory() as work:
        inputs = photos(args.folders) + [mirrored_pair(path, Path(work)) for path in args.pair]
        for photo in inputs:
            rows.append(measure(photo, args.hdr, Path(work), models, args.pictures))
            print(json.dumps(rows[-1]), flush=True)
    faces = [face for row in rows for face in row.get("faces", []) if "detail" in face]
    print(f"{len(faces)} faces measured, {sum(face['path'] == 'face mesh' for face in faces)} on the face path, "
          f"{sum(not face['misses'] for face in faces)} meet every goal")
    for name in GOALS:
        print(f"  {name}: median {np.median([face[name] for face in faces]):.4f}, "
              f"goal missed by {sum(name in face['misses'] for face in faces)}")
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
