"""Generate the synthetic dataset: `python -m export.factory.generate --out DIR --count N`.

Deterministic from --seed (a sample depends only on seed, split and index, see scenes.py);
resumable (samples whose file exists are skipped, files appear atomically); parallel over
--workers processes, one task per person (a group of --samples-per-person samples).
The card (dataset.json) is written before and after the run and lists what is on disk.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path

from relightcli.errors import RelightError, UsageError

from . import dataset, lighting, render, scenes

DEFAULT_FRACTIONS = {"train": 0.8, "val": 0.1, "test": 0.1}


@dataclass(frozen=True)
class GenerationConfig:
    """Everything but the counts that decides the samples."""

    seed: int = 0
    settings: render.RenderSettings = field(default_factory=render.RenderSettings)
    samples_per_person: int = scenes.SAMPLES_PER_PERSON
    sky_probability: float = lighting.SKY_PROBABILITY
    augment: bool = True
    yaw_offset_deg: float = 0.0
    pose_variety: float = 0.0  # person.build_person: how far poses leave the catalogue's


def parse_fractions(text: str | None) -> dict[str, float]:
    """"train=0.8,val=0.1,test=0.1" -> shares of --count per split (normalised to sum 1)."""
    if not text:
        return dict(DEFAULT_FRACTIONS)
    shares = {}
    for part in text.split(","):
        name, _, value = part.partition("=")
        name = name.strip()
        if name not in dataset.SPLITS or not value:
            raise UsageError(f"bad split share {part!r}",
                             fix="e.g. --splits train=0.8,val=0.1,test=0.1")
        shares[name] = float(value)
    total = sum(shares.values())
    if any(v < 0 for v in shares.values()) or not total > 0:
        raise UsageError(f"split shares must be >= 0 with a positive sum, got {text!r}")
    return {name: shares.get(name, 0.0) / total for name in dataset.SPLITS}


def split_counts(count: int, fractions: dict[str, float]) -> dict[str, int]:
    """Samples per split summing to `count` (largest remainders)."""
    if int(count) < 0:
        raise UsageError(f"count must be >= 0, got {count}")
    exact = {s: count * fractions.get(s, 0.0) for s in dataset.SPLITS}
    counts = {s: int(v) for s, v in exact.items()}
    for s in sorted(exact, key=lambda s: counts[s] - exact[s])[:count - sum(counts.values())]:
        counts[s] += 1
    return counts


def missing_tasks(root, counts: dict[str, int], samples_per_person: int) -> list[tuple]:
    """(split, [indices]) per person group that still has samples without a file."""
    tasks = []
    for split in dataset.SPLITS:
        for start in range(0, counts.get(split, 0), samples_per_person):
            group = range(start, min(start + samples_per_person, counts[split]))
            todo = [i for i in group if not dataset.sample_path(
                root, split, scenes.sample_id(i)).is_file()]
            if todo:
                tasks.append((split, todo))
    return tasks


def render_group(root, split: str, indices: list[int], config: GenerationConfig) -> list[dict]:
    """Render and write the samples `indices` of one person group. Returns per sample
    {"split", "id", "seconds", "integrator"}."""
    from .person import build_person

    hdris = lighting.hdri_splits(config.settings.hdri_folder)[split]
    person, done = None, []
    for index in indices:
        spec = scenes.sample_scene(config.seed, split, index, hdris,
                                   samples_per_person=config.samples_per_person,
                                   sky_probability=config.sky_probability, augment=config.augment,
                                   yaw_offset_deg=config.yaw_offset_deg)
        if person is None:
            person = build_person(spec.person_seed, split, config.pose_variety)
        arrays, meta = render.render_sample(spec, person, config.settings)
        meta["dataset_seed"] = config.seed
        dataset.write_sample(root, split, spec.sample_id, arrays, meta)
        done.append({"split": split, "id": spec.sample_id, "seconds": meta["seconds"],
                     "integrator": meta["integrator"]})
    return done


def _worker_init():
    # one process per core: keep BLAS / OpenMP pools from oversubscribing
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[name] = "1"
    # interruptions are the parent's to handle: it stops the workers
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def generate(root, counts: dict[str, int], config: GenerationConfig, workers: int = 1,
             on_done=None) -> dict:
    """Render every missing sample of `counts` into `root`; `on_done(record)` after each
    person group. Returns {"rendered", "skipped", "seconds", "samples_per_minute"}."""
    root = Path(root)
    tasks = missing_tasks(root, counts, config.samples_per_person)
    todo = sum(len(t[1]) for t in tasks)
    start, records = time.perf_counter(), []
    if workers <= 1:
        for split, indices in tasks:
            records += _report(render_group(root, split, indices, config), on_done)
    else:
        pool = ProcessPoolExecutor(workers, initializer=_worker_init)
        try:
            futures = [pool.submit(render_group, root, s, i, config) for s, i in tasks]
            for future in as_completed(futures):
                records += _report(future.result(), on_done)
        except KeyboardInterrupt:
            # Stop now: queued groups are dropped, running ones die with their workers
            # (samples are written atomically, so nothing half-written stays behind)
            for process in list(getattr(pool, "_processes", {}).values()):
                process.kill()
            pool.shutdown(wait=False, cancel_futures=True)
            raise
        pool.shutdown()
    seconds = time.perf_counter() - start
    return {"rendered": len(records), "skipped": sum(counts.values()) - todo,
            "seconds": round(seconds, 2), "workers": workers,
            "samples_per_minute": round(60.0 * len(records) / seconds, 2) if records else 0.0}


def _report(records, on_done):
    if on_done is not None:
        on_done(records)
    return records


def build_card(root, counts: dict[str, int], config: GenerationConfig, command: str,
               runs: list) -> dict:
    """The dataset card: what is on disk, how it was made, from what."""
    from .person import splits as body_splits

    opened_ids = {s: len(list((Path(root) / s).glob("*.npz"))) for s in dataset.SPLITS}
    return {
        "name": "relightcli synthetic full-body relighting dataset",
        "counts_on_disk": opened_ids, "counts_planned": counts,
        "seed": config.seed, "resolution": config.settings.resolution,
        "render_settings": config.settings.as_dict(),
        "samples_per_person": config.samples_per_person,
        "sky_probability": config.sky_probability, "augment": config.augment,
        "yaw_offset_deg": config.yaw_offset_deg, "pose_variety": config.pose_variety,
        "camera": {"pitch_deg": scenes.PITCHES_DEG, "yaw_deg": scenes.YAWS_DEG,
                   "scale": scenes.SCALES, "frame_fill": scenes.FRAME_FILL,
                   "background_fov_deg": scenes.BACKGROUND_FOV_DEG},
        "sources": {"hdri": {"folder": str(lighting.hdri_dir()),
                             "splits": lighting.hdri_splits(config.settings.hdri_folder),
                             "rotation_step_deg": lighting.ROTATION_STEP_DEG,
                             "license": "CC0 1.0 (Poly Haven)"},
                    "procedural_sky": {"sun_to_sky": lighting.SUN_TO_SKY,
                                       "sun_radius_deg": lighting.SUN_RADIUS_DEG,
                                       "sun_elevation_deg": lighting.SUN_ELEVATION_DEG},
                    "bodies": {"generator": "export.factory.build_person (MakeHuman, CC0)",
                               "splits": body_splits()}},
        "contract": "export/factory/DATASET_CONTRACT.md", "encodings": dataset.ENCODINGS,
        "command": command, "runs": runs,
    }


def _arguments(argv):
    parser = argparse.ArgumentParser(prog="python -m export.factory.generate",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="dataset folder")
    parser.add_argument("--count", type=int, required=True, help="samples over all splits")
    parser.add_argument("--splits", default=None, help="shares, e.g. train=0.8,val=0.1,test=0.1")
    parser.add_argument("--resolution", type=int, default=512)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--spp", type=int, default=64, help="cap of shading samples per pixel")
    parser.add_argument("--target-error", type=float, default=0.03,
                        help="relative standard error at which a pixel stops (0: never)")
    parser.add_argument("--ao-spp", type=int, default=32)
    parser.add_argument("--bounces", type=int, default=2, choices=(1, 2),
                        help="2: direct + one diffuse interreflection; 1: direct only")
    parser.add_argument("--samples-per-person", type=int, default=scenes.SAMPLES_PER_PERSON)
    parser.add_argument("--sky-probability", type=float, default=lighting.SKY_PROBABILITY)
    parser.add_argument("--no-augment", action="store_true", help="no noise/blur/colour jitter")
    parser.add_argument("--yaw-offset", type=float, default=0.0,
                        help="degrees added to every camera's yaw (180: the people from behind)")
    parser.add_argument("--pose-variety", type=float, default=0.0,
                        help="0-1: the share of limbs (and trunks) a pose takes from another pose of its "
                             "split, as it is or mirrored, and the perturbations' scale (1 + this)")
    return parser.parse_args(argv)


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def main(argv=None) -> int:
    args = _arguments(argv)
    settings = render.RenderSettings(resolution=args.resolution, spp=args.spp,
                                     target_error=args.target_error or None,
                                     ao_spp=args.ao_spp, bounces=args.bounces)
    config = GenerationConfig(seed=args.seed, settings=settings,
                              samples_per_person=args.samples_per_person,
                              sky_probability=args.sky_probability, augment=not args.no_augment,
                              yaw_offset_deg=args.yaw_offset, pose_variety=args.pose_variety)
    counts = split_counts(args.count, parse_fractions(args.splits))
    given = sys.argv[1:] if argv is None else argv
    command = "python -m export.factory.generate " + " ".join(given)
    card_path = Path(args.out) / dataset.CARD_NAME
    runs = dataset.open_dataset(args.out).card.get("runs", []) if card_path.is_file() else []
    dataset.write_card(args.out, build_card(args.out, counts, config, command, runs))
    started = time.perf_counter()

    rendered = []

    def progress(records):
        rendered.extend(records)
        rate = 60.0 * len(rendered) / (time.perf_counter() - started)
        print(f"{len(rendered)} samples ({rate:.1f}/min)", file=sys.stderr, flush=True)

    # A terminated run (SIGTERM, Ctrl-C) still leaves a card that counts what is on disk
    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        summary = generate(args.out, counts, config, args.workers, on_done=progress)
        code = 0
    except RelightError as error:
        print(f"error: {error}", file=sys.stderr)
        return error.exit_code
    except KeyboardInterrupt:
        seconds = time.perf_counter() - started
        summary = {"rendered": len(rendered), "interrupted": True, "seconds": round(seconds, 2),
                   "workers": args.workers,
                   "samples_per_minute": round(60.0 * len(rendered) / max(seconds, 1e-9), 2)}
        code = 130
    finally:
        signal.signal(signal.SIGTERM, previous)
    runs = runs + [dict(summary, command=command, time=time.strftime("%Y-%m-%dT%H:%M:%S"))]
    dataset.write_card(args.out, build_card(args.out, counts, config, command, runs))
    if code:
        print(f"interrupted after {summary['rendered']} samples; the same command resumes",
              file=sys.stderr)
        return code
    print(f"rendered {summary['rendered']}, skipped {summary['skipped']}, "
          f"{summary['samples_per_minute']} samples/min", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
