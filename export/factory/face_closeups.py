"""Training data for the face refinement net, with the runtime's own face chain and coarse face
shading: `python -m export.factory.face_closeups DATA OUT [--workers N]`.

For every sample of the body dataset DATA whose face is visible, the same person, camera and
lighting A are rendered again in a head square around its face (HEAD_CROP_SCALE x the face
box's longer side, as the runtime's head square is that many times the pose's face landmarks),
and the runtime's face chain (relightcli.stages.face.stage_face) runs on it as on a person crop:

    photo under A (seen at the person crop's resolution: downsampled to a random side in
    RUNTIME_HEAD_PX, then enlarged back, as geometry.face.cut_crop enlarges it)
    -> face detector + face mesh (relightcli.nets.face_mesh.find_face) -> the 68 landmarks
    (geometry.face_correspondence) -> ICT face model fit in the 128x128 face crop framed
    around them (geometry.face.fit_face_to_landmarks; faces outside the person mask and
    implausible fits are skipped, as at run time)
    -> the fitted head ray-traced under B ("coarse_face_b", the runtime's effort).

The close-up is then rendered in that face crop's square, so it is framed as the runtime
frames faces. Each OUT sample (export/factory/dataset.py format, 128x128) holds "shading_b"
(the truth, the refinement target), "coarse_face_b", "body_shading_b" (the body shading the
face net gets: with `--body-input coarse`, the default, the source sample's runtime coarse
shading from export.factory.coarse, resampled to the square — samples without it wait for
it; with `--body-input truth`, the truth seen at the person crop's resolution, far better
than any run time gives), "face_pixels" (the fitted face's pixels, where the runtime blends),
"mask", "albedo", "input" (the close-up photo), "rect", "exposure"; the metadata keeps the
source sample, the fit and the integrator's statistics. Deterministic from the source
samples; resumable; parallel over processes.
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
from relightcli.nets.face_mesh import HEAD_CROP_SCALE

from . import camera_model, dataset, render, scenes

SIZE = 128
# The head square's side: rendered at HEAD_SIZE, seen as the runtime's person crop holds it
# (at 512: ~35 px faces, face crops of 40-96 px, head squares ~3 / 1.6 times those)
HEAD_SIZE = 192
RUNTIME_HEAD_PX = (75, 180)
FACE_SPP, FACE_TARGET_ERROR = 32, 0.04  # relightcli.layers' defaults
TRUTH_SPP, TRUTH_TARGET_ERROR = 64, 0.02


def closeup_rect(face_box, sample_rect, resolution: int, margin: float) -> tuple:
    """World square (x0, x1, y0, y1) around a sample's face box (pixels x0, y0, x1, y1 of a
    `resolution` image spanning `sample_rect`), its side `margin` x the box's longer side."""
    x0, x1, y0, y1 = (float(v) for v in sample_rect)
    px = (x1 - x0) / resolution
    bx0, by0, bx1, by1 = (float(v) for v in face_box)
    half = margin * max(bx1 - bx0, by1 - by0) * px / 2
    cx = x0 + (bx0 + bx1) / 2 * px
    cy = y1 - (by0 + by1) / 2 * px  # rows grow downward
    return (cx - half, cx + half, cy - half, cy + half)


def square_in_pixels(square, sample_rect, resolution: int) -> tuple[float, float, float]:
    """Inverse of `closeup_rect`: (centre x, centre y, side) in pixels of the `resolution`
    image spanning `sample_rect` of the world square (x0, x1, y0, y1)."""
    x0, x1, _, y1 = (float(v) for v in sample_rect)
    px = (x1 - x0) / resolution
    sx0, sx1, sy0, sy1 = (float(v) for v in square)
    return ((sx0 + sx1) / 2 - x0) / px, (y1 - (sy0 + sy1) / 2) / px, (sx1 - sx0) / px


def runtime_view(image, side: int) -> np.ndarray:
    """What a square looks like when the person crop holds it in `side` pixels:
    area-downsampled to side x side, then enlarged bilinearly back (cut_crop)."""
    size = image.shape[0]
    small = cv2.resize(image, (side, side), interpolation=cv2.INTER_AREA)
    return cv2.resize(small, (size, size), interpolation=cv2.INTER_LINEAR).reshape(image.shape)


def body_view(coarse_shading, square, sample_rect) -> np.ndarray | None:
    """The body shading the face net gets at run time, in the close-up's world square: the
    source sample's ray-traced coarse shading of the reconstructed mesh ("coarse_shading_b",
    added by export.factory.coarse, spanning `sample_rect`) resampled to it, or None when
    there is none (closeup_sample then uses the true shading at the person crop's
    resolution, far better than any run time gives)."""
    from export.train.data import crop_resample

    if coarse_shading is None:
        return None
    cx, cy, side = square_in_pixels(square, sample_rect, coarse_shading.shape[0])
    return crop_resample(coarse_shading, cx, cy, side, SIZE)


def render_square(person, spec, meta: dict, square, size: int, seed: int, lit_b: bool) -> dict:
    """The sample's person in the world square `square` at size x size: "photo" (the camera's
    photo under lighting A), "maps" (render.render_geometry's), "env_b" (lighting B times the
    exposure) and, when `lit_b`, "shading_b" (the truth under B, exposed)."""
    settings = render.RenderSettings(resolution=size, spp=TRUTH_SPP, target_error=TRUTH_TARGET_ERROR,
                                     bounces=meta["settings"]["bounces"],
                                     hdri_folder=meta["settings"].get("hdri_folder"))
    scene, geometry, maps, _ = render.render_geometry(person, spec, size, rect=square)
    env_a, env_b, _, background_env = render.sample_environments(spec, settings)
    k = np.float32(meta["exposure"])
    shading_a = render.shade(scene, geometry, env_a, settings, maps["albedo"], seed).mean * k
    out = {"maps": maps, "env_b": env_b * k}
    if lit_b:
        out["shading_b"] = render.shade(scene, geometry, env_b, settings, maps["albedo"], seed + 1).mean * k
    scene.close()
    plate = render.background_plate_for(spec, env_a, background_env, size) * k
    subject = camera_model.fill_edges(maps["albedo"] * shading_a, maps["mask"] > 0)
    out["photo"] = camera_model.photograph(camera_model.composite(subject, maps["coverage"], plate), 1.0,
                                           spec.augmentation)
    return out


def runtime_face_fit(seen, mask, front_depth, square, face_nets, face_model):
    """relightcli.stages.face.stage_face on a head square seen as the person crop: `seen` (S, S, 3)
    float32 linear RGB, `mask` (S, S) the person, `front_depth` (S, S) world z, `square` its
    world rectangle. Returns (FaceFit, info) with the fit in the 128 face crop framed as at
    run time, or None where the runtime finds no face or skips the fit."""
    from relightcli.geometry.face import fit_face_to_landmarks
    from relightcli.geometry.face_correspondence import load_correspondence
    from relightcli.io.images import linear_to_srgb
    from relightcli.nets.face_mesh import find_face
    from relightcli.stages.face import person_mask_at

    srgb = np.clip(linear_to_srgb(np.nan_to_num(seen)), 0.0, 1.0).astype(np.float32)
    face, _ = find_face(srgb, None, *face_nets)
    if face is None:
        return None
    landmarks = load_correspondence().landmarks(face.mesh.points[:, :2]) - 0.5  # continuous -> index
    if person_mask_at(mask, landmarks.mean(axis=0)) < 0.5:
        return None
    depth = np.where(mask > 0.5, front_depth, np.nan)
    fit, info = fit_face_to_landmarks(landmarks, mask.shape, model=face_model, image_rect=square, depth=depth)
    return None if fit is None else (fit, info)


def closeup_sample(person, spec, meta: dict, head_square, face_nets, face_model, rng,
                   coarse_shading=None, sample_rect=None) -> tuple[dict, dict] | None:
    """(arrays, meta) of one close-up, or None when the runtime would skip the face.
    face_nets: (FaceDetector, FaceMesh); coarse_shading: the source sample's runtime body
    shading spanning `sample_rect` (body_view); None: the truth at the runtime's resolution."""
    from relightcli.geometry.face import render_face_shading
    from relightcli.geometry.face_model import rotation_angles_deg
    from relightcli.render.environment import EnvironmentLight

    seed = 4 * spec.index + 7
    head_px = int(rng.integers(RUNTIME_HEAD_PX[0], RUNTIME_HEAD_PX[1] + 1))
    head = render_square(person, spec, meta, head_square, HEAD_SIZE, seed, lit_b=False)
    seen = runtime_view(camera_model.decode_photo(head["photo"]), head_px)
    found = runtime_face_fit(seen, head["maps"]["mask"], head["maps"]["front_depth"], head_square,
                             face_nets, face_model)
    if found is None:
        return None
    fit, info = found
    # the face crop's side in pixels of the runtime's person crop
    side = max(1, int(round(info["crop"][2] * head_px / HEAD_SIZE)))
    face = render_square(person, spec, meta, fit.rect, SIZE, seed, lit_b=True)
    yaw, pitch, roll = rotation_angles_deg(fit.rotation)
    coarse, face_pixels = render_face_shading(fit, EnvironmentLight(face["env_b"]), spp=FACE_SPP,
                                              target_error=FACE_TARGET_ERROR, seed=seed + 2)
    body = body_view(coarse_shading, fit.rect, sample_rect)
    body = runtime_view(face["shading_b"], side) if body is None else body
    maps = face["maps"]
    arrays = {"shading_b": face["shading_b"], "coarse_face_b": coarse, "body_shading_b": body,
              "face_pixels": face_pixels.astype(np.float32), "mask": maps["mask"], "albedo": maps["albedo"],
              "input": face["photo"], "rect": np.asarray(fit.rect, np.float32), "exposure": np.float32(meta["exposure"])}
    record = {"source": {"split": spec.split, "id": spec.sample_id}, "spec": spec.as_dict(),
              "runtime_head_px": head_px, "runtime_side_px": side,
              "fit": {"residual_px": round(fit.residual_px, 3),
                      "angles_deg": [round(a, 2) for a in (yaw, pitch, roll)]}}
    return arrays, record


_STATE = {}


def _worker_init():
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[name] = "1"
    from relightcli.geometry.face_model import FaceModel
    from relightcli.nets.face_mesh import FaceDetector, FaceMesh

    _STATE.update(nets=(FaceDetector(threads=1), FaceMesh(threads=1)), model=FaceModel.load())


def render_person(data_root: str, out_root: str, split: str, ids: list[str], body_input: str = "coarse") -> list[str]:
    """Close-ups of the samples `ids` (one person); returns the ids written."""
    from .person import build_person

    data, person, written = dataset.open_dataset(data_root), None, []
    for sample_id in ids:
        meta = data.meta(split, sample_id)
        box, rect = data.load_raw(split, sample_id, "face_box"), data.load_raw(split, sample_id, "rect")
        spec = scenes.spec_from_dict(meta["spec"])
        person = person or build_person(spec.person_seed, split)
        head_square = closeup_rect(box, rect, meta["settings"]["resolution"], HEAD_CROP_SCALE)
        rng = np.random.default_rng([spec.index, dataset.SPLITS.index(split), 11])
        coarse_shading = data.load(split, sample_id).get("coarse_shading_b") if body_input == "coarse" else None
        if body_input == "coarse" and coarse_shading is None:
            continue  # its coarse shading is not there yet: a later run does it
        result = closeup_sample(person, spec, meta, head_square, _STATE["nets"], _STATE["model"], rng,
                                coarse_shading, rect)
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
            "head_crop_scale": HEAD_CROP_SCALE, "head_size": HEAD_SIZE,
            "runtime_head_px": list(RUNTIME_HEAD_PX), "face_effort": [FACE_SPP, FACE_TARGET_ERROR],
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
