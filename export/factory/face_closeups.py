"""Training data for the face refinement net, with the runtime's own coarse face shading:
`python -m export.factory.face_closeups DATA OUT [--workers N]`.

For every sample of the body dataset DATA whose face is visible, the same person, camera and
lightings are rendered again in the 128x128 face square the runtime would crop (side
FACE_CROP_MARGIN x the face box's longer side, centred on it), and the runtime's face path
runs on that close-up as it would on the person crop:

    photo under A (seen at the person crop's resolution: downsampled to a random side in
    RUNTIME_SIDE_PX, then enlarged back, as geometry.face.cut_crop enlarges it)
    -> landmark net -> ICT face model fit (geometry.face; implausible fits are skipped, as at
    run time) -> the fitted head ray-traced under B ("coarse_face_b", the runtime's effort).

Each OUT sample (export/factory/dataset.py format, 128x128) holds "shading_b" (the truth, the
refinement target), "coarse_face_b", "body_shading_b" (the body shading the face net gets:
with `--body-input coarse`, the default, the source sample's runtime coarse shading from
export.factory.coarse, resampled to the square — samples without it wait for it; with
`--body-input truth`, the truth seen at the person crop's resolution, far better than any run
time gives), "face_pixels" (the fitted
face's pixels, where the runtime blends), "mask", "albedo", "input" (the close-up photo),
"rect", "exposure"; the metadata keeps the source sample, the fit and the integrator's
statistics. Deterministic from the source samples; resumable; parallel over processes.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import cv2
import numpy as np

from relightcli.errors import RelightError
from relightcli.geometry.face_detect import FACE_CROP_MARGIN

from . import camera_model, dataset, render, scenes

SIZE = 128
# Side of the face crop in pixels of the runtime's person crop (at 512: ~35 px faces x 1.6)
RUNTIME_SIDE_PX = (40, 96)
FACE_SPP, FACE_TARGET_ERROR = 32, 0.04  # relightcli.layers' defaults
TRUTH_SPP, TRUTH_TARGET_ERROR = 64, 0.02


def closeup_rect(face_box, sample_rect, resolution: int, margin: float) -> tuple:
    """World square (x0, x1, y0, y1) of the face crop around a sample's face box (pixels
    x0, y0, x1, y1 of a `resolution` image spanning `sample_rect`)."""
    x0, x1, y0, y1 = (float(v) for v in sample_rect)
    px = (x1 - x0) / resolution
    bx0, by0, bx1, by1 = (float(v) for v in face_box)
    half = margin * max(bx1 - bx0, by1 - by0) * px / 2
    cx = x0 + (bx0 + bx1) / 2 * px
    cy = y1 - (by0 + by1) / 2 * px  # rows grow downward
    return (cx - half, cx + half, cy - half, cy + half)


def runtime_view(image, side: int) -> np.ndarray:
    """What the face crop looks like when the person crop holds the face square in `side`
    pixels: area-downsampled to side x side, then enlarged bilinearly back (cut_crop)."""
    small = cv2.resize(image, (side, side), interpolation=cv2.INTER_AREA)
    return cv2.resize(small, (SIZE, SIZE), interpolation=cv2.INTER_LINEAR).reshape(image.shape)


def body_view(source: dict, box, margin: float) -> np.ndarray | None:
    """The body shading the face net gets at run time, in the close-up's square: the source
    sample's ray-traced coarse shading of the reconstructed mesh ("coarse_shading_b", added
    by export.factory.coarse), or None when it has none (closeup_sample then uses the true
    shading at the person crop's resolution, far better than any run time gives)."""
    from export.train.data import crop_resample, face_square

    if "coarse_shading_b" not in source:
        return None
    cx, cy, square = face_square(box, margin)
    return crop_resample(source["coarse_shading_b"], cx, cy, square, SIZE)


def closeup_sample(person, spec, meta: dict, rect, landmark_net, face_model, rng,
                   body=None) -> tuple[dict, dict] | None:
    """(arrays, meta) of one close-up, or None when the runtime would skip the face.
    body: the body shading input (body_view); None: the truth at the runtime's resolution."""
    from relightcli.geometry.face import face_landmarks, implausible_fit, render_face_shading
    from relightcli.geometry.face_detect import CropRect
    from relightcli.geometry.face_fit import fit_face
    from relightcli.geometry.face_model import rotation_angles_deg
    from relightcli.render.environment import EnvironmentLight

    settings = render.RenderSettings(resolution=SIZE, spp=TRUTH_SPP, target_error=TRUTH_TARGET_ERROR,
                                     bounces=meta["settings"]["bounces"],
                                     hdri_folder=meta["settings"].get("hdri_folder"))
    scene, geometry, maps, _ = render.render_geometry(person, spec, SIZE, rect=rect)
    env_a, env_b, _, background_env = render.sample_environments(spec, settings)
    k = np.float32(meta["exposure"])
    seed = 4 * spec.index + 7
    shading_a = render.shade(scene, geometry, env_a, settings, maps["albedo"], seed).mean * k
    shading_b = render.shade(scene, geometry, env_b, settings, maps["albedo"], seed + 1).mean * k
    scene.close()
    plate = render.background_plate_for(spec, env_a, background_env, SIZE) * k
    subject = camera_model.fill_edges(maps["albedo"] * shading_a, maps["mask"] > 0)
    photo = camera_model.photograph(camera_model.composite(subject, maps["coverage"], plate), 1.0,
                                    spec.augmentation)
    side = int(rng.integers(RUNTIME_SIDE_PX[0], RUNTIME_SIDE_PX[1] + 1))
    seen = runtime_view(camera_model.decode_photo(photo), side)

    whole = CropRect(0, 0, SIZE, SIZE)
    landmarks = face_landmarks(seen, whole, landmark_net)
    depth = np.where(maps["mask"] > 0, maps["front_depth"], np.nan)
    fit = fit_face(landmarks, face_model, rect, (SIZE, SIZE), depth=depth)
    if implausible_fit(fit, landmarks):
        return None
    yaw, pitch, roll = rotation_angles_deg(fit.rotation)
    coarse, face_pixels = render_face_shading(fit, EnvironmentLight(env_b * k), spp=FACE_SPP,
                                              target_error=FACE_TARGET_ERROR, seed=seed + 2)
    body = runtime_view(shading_b, side) if body is None else body
    arrays = {"shading_b": shading_b, "coarse_face_b": coarse, "body_shading_b": body,
              "face_pixels": face_pixels.astype(np.float32), "mask": maps["mask"], "albedo": maps["albedo"],
              "input": photo, "rect": np.asarray(rect, np.float32), "exposure": k}
    record = {"source": {"split": spec.split, "id": spec.sample_id}, "spec": spec.as_dict(),
              "runtime_side_px": side, "fit": {"residual_px": round(fit.residual_px, 3),
                                               "angles_deg": [round(a, 2) for a in (yaw, pitch, roll)]}}
    return arrays, record


_STATE = {}


def _worker_init():
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[name] = "1"
    from relightcli.geometry.face_model import FaceModel
    from relightcli.nets.landmarks import LandmarkNet

    _STATE.update(net=LandmarkNet(threads=1), model=FaceModel.load())


def render_person(data_root: str, out_root: str, split: str, ids: list[str], body_input: str = "coarse") -> list[str]:
    """Close-ups of the samples `ids` (one person); returns the ids written."""
    from .person import build_person

    data, person, written = dataset.open_dataset(data_root), None, []
    margin = FACE_CROP_MARGIN
    for sample_id in ids:
        meta = data.meta(split, sample_id)
        box, rect = data.load_raw(split, sample_id, "face_box"), data.load_raw(split, sample_id, "rect")
        spec = scenes.spec_from_dict(meta["spec"])
        person = person or build_person(spec.person_seed, split)
        resolution = meta["settings"]["resolution"]
        square = closeup_rect(box, rect, resolution, margin)
        rng = np.random.default_rng([spec.index, dataset.SPLITS.index(split), 11])
        body = body_view(data.load(split, sample_id), box, margin) if body_input == "coarse" else None
        if body_input == "coarse" and body is None:
            continue  # its coarse shading is not there yet: a later run does it
        result = closeup_sample(person, spec, meta, square, _STATE["net"], _STATE["model"], rng, body)
        if result is None:
            continue
        arrays, record = result
        record["body_input"] = body_input
        dataset.write_sample(out_root, split, sample_id, arrays, record)
        written.append(sample_id)
    return written


def pending_groups(data_root, out_root, splits) -> list[tuple[str, list[str]]]:
    """(split, ids) per person of the samples with a visible face and no close-up yet
    (samples whose face the runtime would skip are retried: they stay cheap to refuse)."""
    data, groups = dataset.open_dataset(data_root), []
    done = {split: set(dataset.open_dataset(out_root).ids(split)) if (Path(out_root) / "dataset.json").is_file()
            else set() for split in splits}
    for split in splits:
        by_person = {}
        for sample_id in data.ids(split):
            if sample_id in done[split] or np.any(data.load_raw(split, sample_id, "face_box") < 0):
                continue
            person = data.meta(split, sample_id)["spec"]["person_seed"]
            by_person.setdefault(person, []).append(sample_id)
        groups += [(split, ids) for ids in by_person.values()]
    return groups


def run(data_root, out_root, splits=dataset.SPLITS, workers: int = 1, limit: int | None = None,
        body_input: str = "coarse") -> dict:
    card = {"name": "relightcli face refinement close-ups", "source": str(data_root), "size": SIZE,
            "body_input": body_input,
            "runtime_side_px": list(RUNTIME_SIDE_PX), "face_effort": [FACE_SPP, FACE_TARGET_ERROR],
            "truth_effort": [TRUTH_SPP, TRUTH_TARGET_ERROR],
            "command": "python -m export.factory.face_closeups " + " ".join(sys.argv[1:])}
    dataset.write_card(out_root, card)
    groups = pending_groups(data_root, out_root, splits)[:limit]
    print(f"{sum(len(g[1]) for g in groups)} samples in {len(groups)} person groups to do", file=sys.stderr)
    start, written, tried = time.perf_counter(), 0, 0
    with ProcessPoolExecutor(workers, initializer=_worker_init) as pool:
        futures = {pool.submit(render_person, str(data_root), str(out_root), split, ids, body_input): len(ids)
                   for split, ids in groups}
        for future in as_completed(futures):
            written += len(future.result())
            tried += futures[future]
            rate = tried / (time.perf_counter() - start) * 60
            print(f"{written} written / {tried} tried ({rate:.1f} tried/min)", file=sys.stderr, flush=True)
    out = dataset.open_dataset(out_root)
    card["counts"] = {split: len(out.ids(split)) for split in dataset.SPLITS}
    dataset.write_card(out_root, card)
    return card


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m export.factory.face_closeups",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("data", help="body dataset (python -m export.factory.generate)")
    parser.add_argument("out", help="close-up dataset folder (created)")
    parser.add_argument("--splits", default=",".join(dataset.SPLITS))
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--limit", type=int, default=None, help="at most this many persons (a trial)")
    parser.add_argument("--body-input", choices=("coarse", "truth"), default="coarse",
                        help="the face net's body shading input (see above)")
    args = parser.parse_args(argv)
    try:
        card = run(args.data, args.out, [s for s in args.splits.split(",") if s], args.workers, args.limit,
                   args.body_input)
    except RelightError as error:
        print(f"error: {error}", file=sys.stderr)
        return error.exit_code
    print(f"close-ups: {card['counts']}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
