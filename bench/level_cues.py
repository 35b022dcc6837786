"""What the albedo's relative structure tells of its level (issue 47).

    python bench/level_cues.py bound data/factory256
    python bench/level_cues.py capture data/evalval512p60 data/factory512val60 --split val --out data/levelcues/val60
    python bench/level_cues.py capture SCENES256 data/factory256 --split train --out data/levelcues/train256 --resolution 256
    python bench/level_cues.py fit data/levelcues/train256 data/levelcues/val60 data/levelcues/test60

The level (log2 of the true albedo's median luminance over the person) is what a photo metered
on the person cannot show directly; what is left are its relative cues: the spread of the
albedo's luminance about its median (albedos lie between ~0.01 and ~0.9, so a wide spread means
a dark median), the face's skin against the rest, the colours. Each is a function of the albedo
divided by its median, so a regressor on them asks how much of the level the *shape* carries.

`bound` fits on the factory's first 2400 training samples and scores its validation split: a
constant, and a quadratic ridge on the relative features of (a) the true albedo (a perfect
de-lighting up to one gain) and (b) the photo over the true input shading (a perfect light,
with the photo's noise, clipping and white balance). `capture` runs the product's pipeline
(`raytrace-norefine`, the true mask) on scene folders and keeps, at 256, the ratio albedo before
its level is set (photo over the solved light's shading), the net's albedo, the mask, the face's
BlazePose landmarks and the truth cropped alike. `fit` trains the same regressor on the first
folder's captures (the correction to the product's level) and scores the others: level RMS and
the albedo's PSNR at the true mask's pixels, the product's level against the regressor's.
SCENES256: scene folders of every third of data/factory256's first 2400 training samples
(`export.factory.eval_scenes.write_scene(dataset.open_dataset("data/factory256"), "train", id,
"data/levelcues/scenes256train")`). Numbers: docs/RESULTS.md, "The level's cues".
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from relightcli.io.images import LUMINANCE  # noqa: E402

QUANTILES = (1, 5, 10, 25, 75, 90, 95, 99)
FACE_POINTS = [0, 2, 5, 9, 10]  # BlazePose: nose, eyes, mouth corners
SIDE = 256


def relative_features(albedo: np.ndarray, mask: np.ndarray, face_points: np.ndarray | None = None) -> np.ndarray:
    """Features of albedo / its median over mask > 0.5 (so one gain changes none of them): the
    quantiles of log2 luminance, the mean chromaticity (r, g) in five luminance bands, and the
    face's skin (a disc about the eyes, nose and mouth): found, log2 luminance, chromaticity."""
    inside = mask > 0.5
    rgb = np.maximum(albedo[inside].astype(np.float64), 0.0)
    luminance = np.maximum(rgb @ LUMINANCE, 1e-4)
    median = np.median(luminance)
    relative = np.log2(luminance / median)
    chroma = rgb / np.maximum(rgb.sum(axis=1, keepdims=True), 1e-6)
    bands = np.array_split(np.argsort(relative), 5)
    face = np.array([0.0, 0.0, 1 / 3, 1 / 3])
    if face_points is not None and np.any(face_points):
        centre = face_points[FACE_POINTS].mean(axis=0)
        radius = max(1.5, 0.9 * np.linalg.norm(face_points[[2, 5]].mean(axis=0) - face_points[[9, 10]].mean(axis=0)))
        rows, cols = np.nonzero(inside)
        disc = (cols - centre[0]) ** 2 + (rows - centre[1]) ** 2 <= radius ** 2
        if disc.sum() >= 3:
            face = np.array([1.0, np.median(relative[disc]), *np.median(chroma[disc], axis=0)[:2]])
    return np.concatenate([np.percentile(relative, QUANTILES),
                           np.concatenate([chroma[band].mean(axis=0)[:2] for band in bands]), face])


def true_level(albedo: np.ndarray, scored: np.ndarray) -> float:
    return float(np.log2(np.median(albedo[scored] @ LUMINANCE)))


class QuadraticRidge:
    """Ridge regression on standardised features and their pairwise products."""

    def __init__(self, weight: float = 10.0):
        self.weight = weight

    def design(self, x: np.ndarray) -> np.ndarray:
        z = (x - self.mean) / self.scale
        i, j = np.triu_indices(z.shape[1])
        return np.column_stack([z, z[:, i] * z[:, j], np.ones(len(z))])

    def fit(self, x: np.ndarray, y: np.ndarray) -> QuadraticRidge:
        self.mean, self.scale = x.mean(axis=0), x.std(axis=0) + 1e-9
        a = self.design(x)
        penalty = self.weight * np.eye(a.shape[1])
        penalty[-1, -1] = 0.0
        self.w = np.linalg.solve(a.T @ a + penalty, a.T @ y)
        return self

    def predict(self, x: np.ndarray) -> np.ndarray:
        return self.design(x) @ self.w


def rms(errors) -> float:
    return float(np.sqrt(np.mean(np.square(errors))))


def bound(factory: str, train: int) -> None:
    from export.factory import dataset

    data = dataset.open_dataset(factory)

    def rows(split: str, limit: int | None):
        truth, photo, levels = [], [], []
        for sample_id in data.ids(split)[:limit]:
            z = data.load(split, sample_id, names=["input", "shading_a", "mask", "albedo"])
            scored = z["mask"] > 0.99
            levels.append(true_level(z["albedo"], scored))
            truth.append(relative_features(z["albedo"], scored.astype(np.float32)))
            usable = scored & (z["input"].max(axis=-1) < 0.98) & (z["shading_a"].mean(axis=-1) > 1e-4)
            photo.append(relative_features(z["input"] / np.maximum(z["shading_a"], 1e-6), usable.astype(np.float32)))
        return np.array(truth)[:, :18], np.array(photo)[:, :18], np.array(levels)

    truth_tr, photo_tr, y_tr = rows("train", train)
    truth_va, photo_va, y_va = rows("val", None)
    print(f"{len(y_tr)} training, {len(y_va)} validation samples; true level {y_va.mean():+.2f} +- {y_va.std():.2f} "
          f"stops; RMS on validation:")
    print(f"  a constant (the training mean)            {rms(y_va - y_tr.mean()):.3f}")
    for label, x_tr, x_va in (("the true albedo's relative features", truth_tr, truth_va),
                              ("  its luminance quantiles alone", truth_tr[:, :8], truth_va[:, :8]),
                              ("the photo over the true input shading", photo_tr, photo_va)):
        print(f"  {label:<42}{rms(QuadraticRidge().fit(x_tr, y_tr).predict(x_va) - y_va):.3f}")


def capture(scenes: str, factory: str, split: str, out: Path, resolution: int) -> None:
    from scene_run import replaced, run_scene

    from export.factory import dataset
    from relightcli import compose
    from relightcli.evaluate import find_scenes
    from relightcli.pipeline import RelightOptions
    from relightcli.stages import delight
    from relightcli.stages.frame import Models

    out.mkdir(parents=True, exist_ok=True)
    data, models, kept = dataset.open_dataset(factory), Models(2), {}
    anchor = compose.anchor_albedo

    def keeping(ratio, net_albedo, mask, *args, **kwargs):
        kept.update(ratio=ratio.copy(), net=net_albedo.copy(), mask=mask.copy())
        return anchor(ratio, net_albedo, mask, *args, **kwargs)

    small = lambda image: cv2.resize(np.asarray(image, np.float32), (SIDE, SIDE), interpolation=cv2.INTER_AREA)  # noqa: E731
    options = RelightOptions(outputs=("relit",), method="raytrace-norefine", threads=2, resolution=resolution)
    with replaced(delight.compose, "anchor_albedo", keeping):
        for folder in find_scenes(scenes):
            if (out / f"{folder.name}.npz").exists():
                continue
            truth = data.load(split, folder.name.split("_", 1)[1])
            kept.clear()
            frame = run_scene(folder, options, models)
            if not kept:
                print(folder.name, "no albedo", flush=True)
                continue
            face = np.zeros((11, 2), np.float32)
            found = [person for person in frame.people if person.found]
            if found and frame.view is not None:
                points = found[0].pose.landmarks[:11, :2] / np.asarray(frame.view.scale)
                face = ((points - [frame.box.x0, frame.box.y0]) / frame.box.scale * (SIDE / resolution)).astype(np.float32)
            box = frame.box
            at = lambda image, box=box: small(compose.crop_square(np.asarray(image, np.float32), box))  # noqa: E731
            person = json.loads((folder / "scene.json").read_text())["spec"]["person_seed"]
            np.savez_compressed(out / f"{folder.name}.npz", ratio=small(kept["ratio"]), net=small(kept["net"]),
                                mask=small(kept["mask"]), face_points=face, true_albedo=at(truth["albedo"]),
                                true_mask=at(truth["mask"]), person=person)
            print(folder.name, flush=True)


def captured(folder: Path):
    """Per scene: [true level, the product's level, features of its ratio albedo] and the
    arrays the albedo's PSNR needs (the product's albedo unclipped, the truth, scored pixels)."""
    rows, arrays = [], []
    for path in sorted(folder.glob("*.npz")):
        z = np.load(path)
        inside = z["mask"] > 0.5
        scored = inside & (z["true_mask"] > 0.99) & (z["true_albedo"] @ LUMINANCE > 0.02)
        if scored.sum() < 50:
            continue
        ours = z["ratio"] * (z["net"][inside].mean() / max(z["ratio"][inside].mean(), 1e-6))
        level = float(np.log2(np.median(np.clip(ours, 0, 1)[scored] @ LUMINANCE)))
        rows.append([true_level(z["true_albedo"], scored), level,
                     *relative_features(np.clip(ours, 0, 4), z["mask"], z["face_points"])])
        arrays.append((ours[scored], z["true_albedo"][scored]))
    return np.array(rows), arrays


def albedo_db(arrays, stops) -> float:
    return float(np.mean([-10 * np.log10(np.mean(np.square(np.clip(ours * 2.0 ** k, 0, 1) - truth)))
                          for (ours, truth), k in zip(arrays, stops)]))


def fit(folders: list[Path]) -> None:
    sets = [(folder.name, *captured(folder)) for folder in folders]
    train = sets[0][1]
    groups = {"quantiles": list(range(2, 10)), "+ colours": list(range(2, 20)), "+ face": list(range(2, 24)),
              "face alone": list(range(20, 24))}
    print("level RMS (stops) / albedo dB at the true mask's pixels; the regressor learns the product's "
          f"error on {sets[0][0]} ({len(train)} scenes, the product's mean error there "
          f"{np.mean(train[:, 1] - train[:, 0]):+.2f} stops)")
    for name, rows, arrays in sets[1:]:
        print(f"{name} ({len(rows)} scenes, mean error {np.mean(rows[:, 1] - rows[:, 0]):+.2f}): "
              f"the product {rms(rows[:, 1] - rows[:, 0]):.3f} / "
              f"{albedo_db(arrays, np.zeros(len(rows))):.2f}, the oracle level {albedo_db(arrays, rows[:, 0] - rows[:, 1]):.2f}, "
              f"0.15 stops darker {albedo_db(arrays, np.full(len(rows), -0.15)):.2f}")
        for label, columns in groups.items():
            columns = [1] + columns  # the product's own level is a feature too
            model = QuadraticRidge(100.0).fit(train[:, columns], train[:, 0] - train[:, 1])
            correction = model.predict(rows[:, columns])
            centred = correction - np.mean(model.predict(train[:, columns]))  # the training set's bias left out
            print(f"  + {label:<12} {rms(rows[:, 1] + correction - rows[:, 0]):.3f} / {albedo_db(arrays, correction):.2f}; "
                  f"its bias left out {rms(rows[:, 1] + centred - rows[:, 0]):.3f} / {albedo_db(arrays, centred):.2f}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    limit = commands.add_parser("bound")
    limit.add_argument("factory")
    limit.add_argument("--train", type=int, default=2400)
    keep = commands.add_parser("capture")
    keep.add_argument("scenes")
    keep.add_argument("factory")
    keep.add_argument("--split", default="val")
    keep.add_argument("--out", type=Path, required=True)
    keep.add_argument("--resolution", type=int, default=512)
    commands.add_parser("fit").add_argument("folders", type=Path, nargs="+")
    args = parser.parse_args()
    if args.command == "bound":
        bound(args.factory, args.train)
    elif args.command == "capture":
        capture(args.scenes, args.factory, args.split, args.out, args.resolution)
    else:
        fit(args.folders)
    return 0


if __name__ == "__main__":
    sys.exit(main())
