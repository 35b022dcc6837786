"""Add to each dataset sample what the runtime's own stages make of it, so the refinement net
trains on the shading it will refine: `python -m export.factory.coarse DATA [--splits ...]`.

Per sample, with the shipped nets (relightcli.stages, the true person mask, the whole sample
as the working crop): people -> body fit -> body maps -> geometry net (the prior net where a
fit converged) -> reconstruction + smoothing -> ray-traced coarse shading (blended with the
fitted bodies' where a fit converged)
under lighting B at the runtime's default sampling effort ("coarse_shading_b", the same units
and exposure as "shading_b"), the AO net's map ("ao_pred") and the geometry net's normals
("normal_pred", what the runtime feeds the de-lighting net). The models' sha256 go into the
sample's metadata ("coarse"); a sample whose record matches the current models is skipped, so
the command resumes, and re-running after new nets ship redoes everything.

`--normals-only` adds just "normal_pred" (the geometry net alone, no ray tracing; recorded
as "normals" in the metadata); `--priors` the fitted bodies' maps ("prior_*"); `--prior-ao`
the fitted bodies' maps again with their ray-traced AO ("prior_ao").
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed

import numpy as np

from relightcli.errors import RelightError

from . import dataset
from .eval_scenes import target_environment

# product (metadata key) -> the models it is made with
MODELS_USED = {"coarse": ("person_detector", "pose_landmarks", "body_model", "geometry", "geometry_prior", "ao"),
               "normals": ("geometry",),
               "priors": ("person_detector", "pose_landmarks", "body_model"),
               "prior_ao": ("person_detector", "pose_landmarks", "body_model")}


def models_record(product: str = "coarse") -> dict:
    """{model name: sha256} of the models the runtime would load now, for one product."""
    from relightcli.nets.manifest import load_manifest

    manifest = load_manifest()
    return {name: manifest[name].sha256 for name in MODELS_USED[product]}


def working_frame(sample: dict, meta: dict | None):
    """(Frame, RelightOptions) of a sample as the runtime's stages see it: the true person
    mask, the whole sample as the working crop, lighting B as the target (no lighting when
    `meta` is None: the stages that need none)."""
    from relightcli import compose
    from relightcli.pipeline import RelightOptions
    from relightcli.stages.frame import Frame

    size = sample["input"].shape[0]
    options = RelightOptions(resolution=size, seed=0, threads=1)
    env = None if meta is None else target_environment(meta, meta.get("settings", {}).get("hdri_folder"))
    frame = Frame(image=sample["input"], mask=sample["mask"], env=env)
    frame.box = compose.CropBox(0, 0, size, size)
    frame.crop, frame.crop_mask = sample["input"], np.clip(sample["mask"], 0.0, 1.0)
    return frame, options


def coarse_arrays(sample: dict, meta: dict, models, bodies: bool = True) -> tuple[dict, dict]:
    """({"coarse_shading_b", "ao_pred", "normal_pred"}, statistics) of one loaded sample, by the
    runtime's chain: with `bodies`, people -> body fit -> body maps first, so where a fit
    converges the geometry comes from the prior net and the coarse shading is the blend with
    the bodies' (as `relight` makes it); without, the image-alone path."""
    from relightcli.stages.body import stage_body, stage_body_maps
    from relightcli.stages.geometry import stage_ao, stage_geometry, stage_reconstruct
    from relightcli.stages.people import stage_people
    from relightcli.stages.shading import stage_raytrace

    frame, options = working_frame(sample, meta)
    chain = (stage_people, stage_body, stage_body_maps) if bodies else ()
    try:
        for stage in chain + (stage_geometry, stage_ao, stage_reconstruct, stage_raytrace):
            stage(frame, options, models)
    finally:
        for scene in (frame.scene, frame.body_scene):
            if scene is not None:
                scene.close()
    return ({"coarse_shading_b": frame.coarse_shading, "ao_pred": frame.ao, "normal_pred": frame.normal},
            {key: frame.notes["raytrace"][key] for key in ("spp_mean", "rel_error", "seconds")})


def normal_arrays(sample: dict, meta: dict, models) -> tuple[dict, dict]:
    """({"normal_pred"}, {}) of one loaded sample: the geometry net's normals, zero outside."""
    from relightcli.stages.geometry import stage_geometry

    frame, options = working_frame(sample, meta)
    stage_geometry(frame, options, models)
    return {"normal_pred": frame.normal}, {}


def prior_arrays(sample: dict, meta: dict, models, with_ao: bool = False) -> tuple[dict, dict]:
    """({"prior_mask", "prior_normal", "prior_back_normal", "prior_front_depth",
    "prior_back_depth"}, statistics) of one loaded sample: the fitted bodies' maps exactly as
    the runtime makes them (stages people -> body -> body_maps on the sample as the photo, its
    true mask as the silhouette), at the sample's resolution; all zero when no fit converged
    (the statistics say why). The prior net's input is relightcli.nets.geometry.prior_channels
    of these. with_ao: also "prior_ao", the bodies' ray-traced ambient occlusion as the runtime
    traces it (relightcli.stages.geometry.body_ao) where a fit converged, zero elsewhere."""
    from relightcli.stages.body import body_shading_pixels, stage_body, stage_body_maps
    from relightcli.stages.geometry import body_ao
    from relightcli.stages.people import stage_people

    frame, options = working_frame(sample, None)
    for stage in (stage_people, stage_body, stage_body_maps):
        stage(frame, options, models)
    size = sample["mask"].shape
    maps, ao = frame.body_maps, None
    if frame.body_scene is not None:
        ao = body_ao(frame, options.seed) if with_ao else None
        frame.body_scene.close()
    if maps is None:
        zeros = np.zeros(size, np.float32)
        arrays = {"prior_mask": zeros, "prior_normal": np.zeros(size + (3,), np.float32),
                  "prior_back_normal": np.zeros(size + (3,), np.float32), "prior_front_depth": zeros,
                  "prior_back_depth": zeros}
    else:
        arrays = {"prior_mask": maps.mask.astype(np.float32), "prior_normal": maps.front_normal,
                  "prior_back_normal": maps.back_normal, "prior_front_depth": maps.front_depth,
                  "prior_back_depth": maps.back_depth}
    if with_ao:
        arrays["prior_ao"] = np.zeros(size, np.float32) if ao is None else \
            (ao * body_shading_pixels(frame)).astype(np.float32)
    people = frame.notes.get("body", {}).get("people", [])
    return arrays, {"people": len(frame.people), "converged": sum(p["converged"] for p in people),
                    "reasons": [p["reason"] for p in people if not p["converged"]]}


def prior_ao_arrays(sample: dict, meta: dict, models) -> tuple[dict, dict]:
    """`prior_arrays` with "prior_ao": the prior maps redone with it, so both come from the
    same fit (the AO prior net reads them together)."""
    return prior_arrays(sample, meta, models, with_ao=True)


PRODUCTS = {"coarse": coarse_arrays, "normals": normal_arrays, "priors": prior_arrays,
            "prior_ao": prior_ao_arrays}


_MODELS = None


def _worker_init():
    global _MODELS
    from relightcli.stages.frame import Models

    os.environ.setdefault("OMP_NUM_THREADS", "1")
    _MODELS = Models(threads=1)


def _one(root: str, split: str, sample_id: str, record: dict, product: str) -> str:
    data = dataset.open_dataset(root)
    arrays, stats = PRODUCTS[product](data.load(split, sample_id), data.meta(split, sample_id), _MODELS)
    dataset.add_arrays(root, split, sample_id, arrays, {product: dict(record, **stats)})
    return sample_id


def pending(root, splits, record: dict, product: str = "coarse") -> list[tuple[str, str]]:
    """(split, id) of the samples without the product's arrays from the current models."""
    data = dataset.open_dataset(root)
    todo = []
    for split in splits:
        for sample_id in data.ids(split):
            done = data.meta(split, sample_id).get(product, {})
            if any(done.get(name) != sha for name, sha in record.items()):
                todo.append((split, sample_id))
    return todo


def run(root, splits=dataset.SPLITS, workers: int = 1, limit: int | None = None, product: str = "coarse") -> int:
    """Add the product's arrays ("coarse": all, "normals": normal_pred only, "priors": the
    fitted bodies' maps) to every pending sample and say so in the card ("added"); returns how
    many were written."""
    record = models_record(product)
    todo = pending(root, splits, record, product)[:limit]
    print(f"{len(todo)} samples to do", file=sys.stderr)
    start, done = time.perf_counter(), 0
    # spawned, not forked: a child forked from a process whose OpenCV or ONNX Runtime thread
    # pools already ran can deadlock in them (the body fit's OpenCV calls did, under pytest)
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(workers, mp_context=context, initializer=_worker_init) as pool:
        futures = [pool.submit(_one, str(root), split, sample_id, record, product) for split, sample_id in todo]
        for future in as_completed(futures):
            future.result()
            done += 1
            if done % 50 == 0 or done == len(todo):
                rate = done / (time.perf_counter() - start) * 60
                print(f"{done}/{len(todo)} samples ({rate:.1f}/min)", file=sys.stderr, flush=True)
    if done:
        data = dataset.open_dataset(root)
        added = dict(data.card.get("added", {}))
        added[product] = {"models": record, "splits": list(splits), "samples": len(todo),
                          "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
                          "command": "python -m export.factory.coarse " + " ".join(sys.argv[1:])}
        dataset.write_card(root, {k: v for k, v in data.card.items() if k != "format_version"} | {"added": added})
    return done


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m export.factory.coarse", description=__doc__.splitlines()[0])
    parser.add_argument("data", help="dataset folder written by export.factory.generate")
    parser.add_argument("--splits", default=",".join(dataset.SPLITS), help="comma-separated (default: all)")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--limit", type=int, default=None, help="at most this many samples (a trial)")
    parser.add_argument("--normals-only", action="store_true",
                        help="add only normal_pred, the geometry net's normals (no ray tracing)")
    parser.add_argument("--priors", action="store_true",
                        help="add only the fitted bodies' prior maps (prior_*: pose net, body fit, body maps)")
    parser.add_argument("--prior-ao", action="store_true",
                        help="add the fitted bodies' prior maps again, with their ray-traced AO (prior_ao)")
    args = parser.parse_args(argv)
    try:
        run(args.data, [s for s in args.splits.split(",") if s], args.workers, args.limit,
            "prior_ao" if args.prior_ao else "priors" if args.priors else
            "normals" if args.normals_only else "coarse")
    except RelightError as error:
        print(f"error: {error}", file=sys.stderr)
        return error.exit_code
    return 0


if __name__ == "__main__":
    sys.exit(main())
