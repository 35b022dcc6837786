"""Learning curves of a net over width and data size: is it at its limit, or short of
capacity or of data? The de-lighting net (issue 47), the geometry prior net and the AO net
(issue 49).

    python bench/net_curves.py train --family delight --data data/factory256 --runs data/curves \
        [--sizes small_half small small_double] [--samples 1200 2400] [--steps N] [--crop 128]
    python bench/net_curves.py score --family delight --data data/factory256 --runs data/curves \
        [--eval data/evalval512 data/evaltrain512] [--out bench/results/delight_curves.json]
    python bench/net_curves.py train --family geometry_prior --data data/factory256 \
        --runs data/curves_geometry --samples 2400 --sizes small
    python bench/net_curves.py train --family ao --data data/factory256 --runs data/curves_ao
    python bench/net_curves.py ship --family delight --data data/factory256 --runs data/curves --run RUN \
        [--calibrate-to models] [--to bench/candidates/NAME]   # then: adopt bench/candidates/NAME
    python bench/net_curves.py export --family delight --data data/factory256 --runs data/curves --run RUN \
        --to /tmp/models_RUN   # then RELIGHT_MODELS_DIR=/tmp/models_RUN python bench/light_solve.py ...

`train` trains one run per (width, training samples) in turn with the runtime's inputs (for
the de-lighting net the geometry net's normals: `python -m export.factory.coarse DATA
--normals-only` first; for the geometry prior the fitted bodies' maps: `... --priors`), both
cores, checkpoints every 250 steps: rerun the same command to resume where it stopped. Runs
train for the family's STEPS; one of another --steps is another run (SIZE_N_stepsS), the length
axis; one of another --crop too (SIZE_N_cropC, or SIZE_N_whole for --crop 0: whole samples, as
the shipped de-lighting net trained). `--init models/delight.onnx` starts each run from a
shipped file's weights instead (fine-tuning: SIZE_N..._from_delight; the file's BatchNorms,
folded by its exporter, stay in eval mode); `--lr` another peak learning rate than the config's
(..._lrLR), `--set KEY=JSON ...` other settings of the trainer's config (..._KEYJSON).
`ship --run RUN` exports a scored run's net into models/ (manifest entry with its scores); with
`--to DIR` into a candidate folder instead (the net's file and its entry alone, kept where the
run's checkpoint is not: a session's data may not outlive it), which `adopt DIR` ships as it is.
`export --run RUN --to DIR` makes DIR a copy of models/ with the run's net, for other bench scripts.
With `--calibrate-to MODELS` either one sets the de-lighting net's `calibration` in its entry: the
albedo gain that brings its median level to MODELS' net's on --data's validation samples 100-299
(bench/delight_level.py; `--calibrate-to models` keeps the shipped net's level convention);
`score --eval ... --calibrate-to MODELS` scores the calibrated net, kept apart from the net as it
is, and `ship --calibrate-to MODELS` then takes those scores.
`score` reads each run's training CPU-hours; with --eval it also exports each finished run's
net into a copy of models/ and runs the product's own `relight eval` on each set of scenes with
it (relit, albedo, shading and the normals' error through the whole pipeline), beside the
shipped net on the same sets (kept in RUNS/shipped.json by its sha256), and times the exported
net (one run at its 256 side on 2 threads: the nets' budget is 0.3 s at 512). Scores are kept
by the pipeline's version (`pipeline_version`: the package's sources and the models' manifest),
so a change to the pipeline scores every run again; `--only RUN ...` scores those runs. Choose on
validation sets only: data/evalval512 (3 HDRIs: its differences of 0.2-0.3 dB are within its
noise) and new scenes of the training split's poses and maps (data/evaltrain512), never the
test scenes.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
CONFIGS = {"delight": ROOT / "export/train/configs/delight_small_runtime.json",
           "geometry_prior": ROOT / "export/train/configs/geometry_prior_small.json",
           "ao": ROOT / "export/train/configs/ao_small.json"}
THREADS = 2
# Each family's training length; a run of another length is named for it (the length axis)
STEPS = {"delight": 1500, "geometry_prior": 3000, "ao": 3000}
# Each family's training crop (None: whole samples); a run of another crop is named for it
CROP = {"delight": 128}
# Settings every run of a family takes over its config (the AO net's shipped run: a cosine schedule)
SETTINGS = {"ao": ['lr_schedule="cosine"']}


def run_dir(runs: Path, family: str, size: str, samples: int, steps: int, crop: int | None = None,
            init: str | None = None, lr: float | None = None, settings: tuple = ()) -> Path:
    return runs / (f"{size}_{samples}" + ("" if steps == STEPS[family] else f"_steps{steps}")
                   + ("" if crop == CROP.get(family) else "_whole" if crop is None else f"_crop{crop}")
                   + (f"_from_{Path(init).stem}" if init else "") + (f"_lr{lr:g}" if lr else "")
                   + "".join(f"_{setting_name(setting)}" for setting in settings))


def setting_name(setting: str) -> str:
    """A run name's part for a `--set KEY=JSON`: KEYJSON, or KEY and a digest of a long value."""
    key, _, value = setting.partition("=")
    return key + (value if len(value) <= 16 else hashlib.sha256(value.encode()).hexdigest()[:6])


def train_command(family: str, data: str, out: Path, size: str, samples: int, steps: int,
                  crop: int | None, init: str | None = None, lr: float | None = None,
                  settings: tuple = ()) -> list[str]:
    return [sys.executable, "-m", "export.train", family, "--config", str(CONFIGS[family]), "--data", data,
            "--out", str(out), "--steps", str(steps), "--threads", str(THREADS),
            "--set", f'size="{size}"', "--set", f"train_samples={samples}",
            "--set", f"crop={'null' if crop is None else crop}"] + [
            part for setting in SETTINGS.get(family, []) for part in ("--set", setting)] + (
            ["--set", f"init={json.dumps(init)}"] if init else []) + (["--set", f"lr={lr!r}"] if lr else []) + [
            part for setting in settings for part in ("--set", setting)]


def export_command(family: str, run: Path, data: str, step: int, models: Path) -> list[str]:
    """export.train resuming a run at its last step to export its net into `models`, with the
    run's own config.json (its learning rate, its loss, whatever it was trained with)."""
    return [sys.executable, "-m", "export.train", family, "--config", str(run / "config.json"), "--data", data,
            "--out", str(run), "--steps", str(step), "--export-to", str(models)]


def train(args) -> None:
    for samples in args.samples:
        for size in args.sizes:
            out = run_dir(Path(args.runs), args.family, size, samples, args.steps, args.crop, args.init, args.lr,
                          args.set)
            print(f"{out.name}: training to step {args.steps}", flush=True)
            subprocess.run(train_command(args.family, args.data, out, size, samples, args.steps, args.crop,
                                         args.init, args.lr, args.set), cwd=ROOT, check=True)


def last_record(path: Path) -> dict:
    lines = path.read_text().splitlines() if path.is_file() else []
    return json.loads(lines[-1]) if lines else {}


def eval_scores(models: Path, scenes: str) -> dict:
    """`relight eval` on `scenes` with the models folder `models`: relit / albedo / shading dB."""
    env = {**os.environ, "RELIGHT_MODELS_DIR": str(models)}
    # (exit status 1 when a scene fails, e.g. nobody found without the mask: the others count)
    done = subprocess.run([sys.executable, "-m", "relightcli", "eval", scenes, "--json"], cwd=ROOT,
                          env=env, capture_output=True, text=True)
    if not done.stdout.strip():
        raise RuntimeError(f"relight eval failed: {done.stderr[-2000:]}")
    report = json.loads(done.stdout)
    scores = {key: round(report[key]["psnr"], 3) for key in ("relit", "albedo", "shading") if key in report}
    if report.get("normal"):
        scores["normal_deg"] = round(report["normal"]["deg"], 3)
    # each scene's dB, for the paired comparison with the shipped net (paired_difference)
    scores["per_scene"] = {row["scene"]: {key: round(row[key]["psnr"], 3) for key in ("relit", "shading") if row.get(key)}
                           for row in report.get("per_scene", []) if not row.get("error")}
    return scores


def with_people(scores: dict, scenes: str) -> dict:
    """Each scene's score marked with whose scene it is (the factory's person seed, from the
    scene's scene.json), for paired_difference."""
    for scene, row in scores.get("per_scene", {}).items():
        spec = Path(scenes) / scene / "scene.json"
        if spec.is_file():
            row["person"] = json.loads(spec.read_text()).get("spec", {}).get("person_seed")
    return scores


def paired_difference(run: dict, shipped: dict, key: str) -> str:
    """'+mean (se S over P people, better in N of M)': a run's per-scene dB of `key` against the
    shipped net's on the scenes both scored ('-' where either score predates per-scene scores).
    The factory renders each person several times (its samples_per_person), and one person's
    scenes rise and fall together: the standard error is that of the people's means (a scene
    is its own person where its score does not say)."""
    import numpy as np

    a, b = run.get("per_scene", {}), shipped.get("per_scene", {})
    both = sorted(scene for scene in a if scene in b and key in a[scene] and key in b[scene])
    if len(both) < 2:
        return "-"
    diff = np.array([a[scene][key] - b[scene][key] for scene in both])
    people: dict = {}
    for scene, d in zip(both, diff):
        people.setdefault(a[scene].get("person", scene), []).append(d)
    means = np.array([np.mean(ds) for ds in people.values()])
    se = means.std(ddof=1) / np.sqrt(means.size) if means.size > 1 else float("nan")
    return (f"{diff.mean():+.3f} (se {se:.3f} over {means.size} people, better in "
            f"{int((diff > 0).sum())} of {diff.size})")


def net_seconds(path: Path, side: int = 256, runs: int = 5) -> float:
    """The median seconds of one run of an exported net at side x side on THREADS threads."""
    import numpy as np
    import onnx

    from export.reexport import run_seconds

    rng = np.random.default_rng(0)
    shapes = {i.name: [d.dim_param or d.dim_value for d in i.type.tensor_type.shape.dim]
              for i in onnx.load(path, load_external_data=False).graph.input}
    feeds = {name: rng.random([1 if d == "N" else side if isinstance(d, str) else d for d in shape], dtype=np.float32)
             for name, shape in shapes.items()}
    return run_seconds(path, feeds, runs, THREADS, warm_up=True)[1]


def pipeline_version() -> str:
    """A digest of what `relight eval` runs besides the scored net: the package's sources and the
    models' manifest (the other nets' sha256)."""
    digest = hashlib.sha256()
    for path in sorted((ROOT / "relightcli").rglob("*.py")) + [ROOT / "models" / "manifest.json"]:
        digest.update(path.relative_to(ROOT).as_posix().encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()[:12]


def models_with_run(run: Path, family: str, data: str, step: int, models: Path) -> Path:
    """A copy of the shipped models folder at `models` with this run's net (at `step`) in place
    of the family's: what `RELIGHT_MODELS_DIR` takes for any bench script."""
    shutil.copytree(ROOT / "models", models)
    subprocess.run(export_command(family, run, data, step, models), cwd=ROOT, check=True, capture_output=True)
    return models


# The validation samples a de-lighting net's level is calibrated on (skip, count): not the 100
# its trainer validated on
CALIBRATION_SAMPLES = (100, 200)


def level_reference(args) -> dict | None:
    """bench/delight_level.py's measure() of --calibrate-to's de-lighting net, or None."""
    if not args.calibrate_to:
        return None
    if args.family != "delight":
        raise SystemExit("--calibrate-to is for the de-lighting net (--family delight)")
    import delight_level

    data = delight_level.dataset.open_dataset(args.data)
    skip, count = CALIBRATION_SAMPLES
    ids = list(data.ids("val"))[skip:skip + count]
    return {"ids": ids, **delight_level.measure(Path(args.calibrate_to), data, "val", ids)}


def calibrate(models: Path, reference: dict | None, args) -> None:
    """Set the de-lighting net's calibration in `models`' manifest: its level brought to the
    reference's (level_reference), measured on the same samples."""
    if reference is None:
        return
    import delight_level
    from export.manifest import update_manifest

    data = delight_level.dataset.open_dataset(args.data)
    net = delight_level.measure(models, data, "val", reference["ids"])
    where = f"{args.data} val samples {CALIBRATION_SAMPLES[0]}-{CALIBRATION_SAMPLES[0] + len(reference['ids']) - 1}"
    entry = json.loads((models / "manifest.json").read_text())["models"]["delight"]
    entry["calibration"] = {**delight_level.calibration(net, reference, where), "reference": args.calibrate_to}
    update_manifest(models, "delight", entry)
    print(json.dumps(entry["calibration"]))


def export(args) -> None:
    """A models folder with one run's net, for the bench scripts that score more than `score`
    does (e.g. bench/light_solve.py's level split, RELIGHT_MODELS_DIR=TO)."""
    run = Path(args.runs) / args.run
    if Path(args.to).exists():
        raise SystemExit(f"{args.to} exists: name a new folder")
    reference = level_reference(args)
    models_with_run(run, args.family, args.data, last_record(run / "log.jsonl").get("step", 0), Path(args.to))
    calibrate(Path(args.to), reference, args)
    print(args.to)


def calibration_tag(args) -> str:
    """What a calibrated net's scores are kept under beside the pipeline's version (no spaces)."""
    return f"+calibrated-to:{args.calibrate_to}" if getattr(args, "calibrate_to", None) else ""


def pipeline_scores(run: Path, family: str, data: str, sets: list, args=None, reference: dict | None = None) -> dict:
    """The product's eval on each set of scenes with this run's net in place of the shipped
    one (calibrated to `reference`'s level when given: calibrate), and the net's run time
    ("seconds"); kept in the run's pipeline.json by step, pipeline version (and calibration)
    and set, so a set is scored once per version."""
    step = last_record(run / "log.jsonl").get("step", 0)
    cache = run / "pipeline.json"
    kept = json.loads(cache.read_text()) if cache.is_file() else {}
    version = pipeline_version() + (calibration_tag(args) if reference else "")
    wanted = [scenes for scenes in sets if f"{step} {version} {scenes}" not in kept]
    if wanted or f"{step} seconds" not in kept:
        with tempfile.TemporaryDirectory() as tmp:
            models = models_with_run(run, family, data, step, Path(tmp) / "models")
            calibrate(models, reference, args)
            kept[f"{step} seconds"] = round(net_seconds(models / f"{family}.onnx"), 4)
            for scenes in wanted:
                kept[f"{step} {version} {scenes}"] = eval_scores(models, scenes)
        cache.write_text(json.dumps(kept, indent=1) + "\n")
    return {"seconds": kept[f"{step} seconds"], **{scenes: kept[f"{step} {version} {scenes}"] for scenes in sets}}


def shipped_scores(runs: Path, family: str, sets: list) -> dict:
    """pipeline_scores for the shipped models, kept in runs/shipped.json by the shipped net's
    sha256, the pipeline's version and set."""
    from relightcli.nets.manifest import sha256_file

    sha = sha256_file(ROOT / "models" / f"{family}.onnx")[:16]
    version = pipeline_version()
    cache = runs / "shipped.json"
    kept = json.loads(cache.read_text()) if cache.is_file() else {}
    if f"{sha} seconds" not in kept:
        kept[f"{sha} seconds"] = round(net_seconds(ROOT / "models" / f"{family}.onnx"), 4)
    for scenes in sets:
        if f"{sha} {version} {scenes}" not in kept:
            kept[f"{sha} {version} {scenes}"] = eval_scores(ROOT / "models", scenes)
    cache.write_text(json.dumps(kept, indent=1) + "\n")
    return {"seconds": kept[f"{sha} seconds"], **{scenes: kept[f"{sha} {version} {scenes}"] for scenes in sets}}


def score(args) -> None:
    rows = []
    reference = level_reference(args) if args.eval else None
    if args.eval:  # the shipped net on the same scenes, for the comparison
        rows.append({"run": "shipped", "pipeline": shipped_scores(Path(args.runs), args.family, args.eval)})
        print(json.dumps(rows[-1]), flush=True)
    for run in sorted(Path(args.runs).iterdir()):
        config_path = run / "config.json"
        if not config_path.is_file() or (args.only and run.name not in args.only):
            continue
        config = json.loads(config_path.read_text())
        log = last_record(run / "log.jsonl")
        row = {"run": run.name, "size": config["size"], "train_samples": config["train_samples"],
               "step": log.get("step"), "cpu_hours": round(log.get("elapsed_s", 0) * THREADS / 3600, 2)}
        finished = row["step"] is not None and row["step"] >= config["steps"]
        if args.eval and finished:  # (exporting validates the net again: on the val split as it is now)
            row["pipeline"] = pipeline_scores(run, args.family, args.data, args.eval, args, reference)
        rows.append(row)
        print(json.dumps(row), flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(rows, indent=2) + "\n")
    sets = args.eval or []
    keys = {"delight": ("relit", "albedo"), "ao": ("shading", "relit")}.get(args.family, ("shading", "normal_deg"))
    print("| run | step | CPU-hours | net s | " + " | ".join(f"{scenes}: {' / '.join(keys)}" for scenes in sets) + " |")
    print("|---|---|---|---|" + "---|" * len(sets))
    for row in rows:
        pipe = row.get("pipeline", {})
        cells = [" / ".join(str(pipe[s].get(k, "-")) for k in keys) if s in pipe else "-" for s in sets]
        print(f"| {row['run']} | {row.get('step', '-')} | {row.get('cpu_hours', '-')} | {pipe.get('seconds', '-')} | "
              + " | ".join(cells) + " |")
    if sets and len(rows) > 1:  # each run against the shipped net, scene by scene
        key = "relit" if args.family == "delight" else "shading"
        print(f"\n{key} dB against the shipped net, paired by scene:")
        for row in rows:
            for scenes in sets:
                if "pipeline" in row:
                    with_people(row["pipeline"][scenes], scenes)
        shipped = rows[0]["pipeline"]
        for row in rows[1:]:
            if "pipeline" in row:
                print(f"  {row['run']}: " + "; ".join(f"{scenes} {paired_difference(row['pipeline'][scenes], shipped[scenes], key)}"
                                                     for scenes in sets))


def ship(args) -> None:
    """Export a run's net into models/ (its manifest entry: export.train's, which keeps the
    record of a file it was fine-tuned from) with the product's scores of it on the validation
    sets (`score --eval` first) as the entry's `metrics.pipeline`. With --to, into a new
    candidate folder instead: the net's file and a manifest with its entry alone."""
    run = Path(args.runs) / args.run
    step = last_record(run / "log.jsonl").get("step", 0)
    version = pipeline_version() + calibration_tag(args)
    kept = json.loads((run / "pipeline.json").read_text()) if (run / "pipeline.json").is_file() else {}
    scores = {key.split(" ", 2)[2]: {k: v for k, v in value.items() if k != "per_scene"}
              for key, value in kept.items() if key.startswith(f"{step} {version} ")}
    if not scores:
        raise SystemExit(f"{run.name} has no scores at step {step} with today's pipeline"
                         + (f" calibrated to {args.calibrate_to}" if args.calibrate_to else "")
                         + ": run `score --eval` (with the same --calibrate-to) first")
    if getattr(args, "to", None) and Path(args.to).exists():
        raise SystemExit(f"{args.to} exists: name a new folder")
    reference = level_reference(args)  # before the shipped net is replaced
    if not getattr(args, "to", None):
        ship_into(ROOT / "models", run, step, scores, reference, args)
        return
    from export.manifest import update_manifest

    with tempfile.TemporaryDirectory() as tmp:
        models = Path(tmp) / "models"
        shutil.copytree(ROOT / "models", models)
        entry = ship_into(models, run, step, scores, reference, args)
        Path(args.to).mkdir(parents=True)
        shutil.copy2(models / entry["file"], Path(args.to) / entry["file"])
    update_manifest(args.to, args.family, entry)


def ship_into(models: Path, run: Path, step: int, scores: dict, reference: dict | None, args) -> dict:
    """The run's net at `step` exported into `models` with its scores and calibration; its entry."""
    from export.manifest import update_manifest

    subprocess.run(export_command(args.family, run, args.data, step, models), cwd=ROOT, check=True)
    entry = json.loads((models / "manifest.json").read_text())["models"][args.family]
    entry["metrics"]["pipeline"] = scores
    entry["training"]["run_dir"] = str(run.relative_to(ROOT) if run.is_relative_to(ROOT) else run)
    update_manifest(models, args.family, entry)
    calibrate(models, reference, args)
    print(json.dumps(entry["metrics"], indent=1))
    return json.loads((models / "manifest.json").read_text())["models"][args.family]


def adopt(args) -> None:
    """Ship a candidate folder (`ship --to`) into models/ (or --into, e.g. a copy of models/ to
    score it with RELIGHT_MODELS_DIR) as it is: its net's file, checked against its entry's
    sha256, and the entry."""
    from export.manifest import update_manifest
    from relightcli.nets.manifest import sha256_file

    candidate = Path(args.candidate)
    entry = json.loads((candidate / "manifest.json").read_text())["models"][args.family]
    source = candidate / entry["file"]
    if sha256_file(source) != entry["sha256"]:
        raise SystemExit(f"{source} does not match its entry's sha256: make the candidate again (`ship --to`)")
    models = Path(args.into or ROOT / "models")
    shutil.copy2(source, models / entry["file"])
    update_manifest(models, args.family, entry)
    print(f"{models / entry['file']}: {args.family} from {candidate}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for name in ("train", "score", "ship", "export"):
        command = sub.add_parser(name)
        command.add_argument("--family", choices=sorted(CONFIGS), default="delight")
        command.add_argument("--data", required=True)
        command.add_argument("--runs", required=True)
    sub.choices["train"].add_argument("--sizes", nargs="+", default=["small_half", "small", "small_double"])
    sub.choices["train"].add_argument("--samples", nargs="+", type=int, default=[1200, 2400])
    sub.choices["train"].add_argument("--steps", type=int, default=None, help="default: the family's (STEPS)")
    sub.choices["train"].add_argument("--init", help="an ONNX file of the family's net to start from "
                                      "(fine-tuning a shipped net; the run is named _from_STEM)")
    sub.choices["train"].add_argument("--lr", type=float, help="the peak learning rate, default the family's "
                                      "config's (the run is named _lrLR)")
    sub.choices["train"].add_argument("--set", nargs="+", default=(), metavar="KEY=JSON",
                                      help="other config settings (e.g. loss.level=100; the run is named for them)")
    sub.choices["train"].add_argument("--crop", type=int, default=None,
                                      help="training crop, 0: whole samples (default: the family's, CROP: 128 for "
                                           "delight, whole samples otherwise)")
    sub.choices["score"].add_argument("--eval", nargs="+",
                                      help="sets of eval scenes to run the product on with each net")
    sub.choices["score"].add_argument("--only", nargs="+", help="score these runs (names) only")
    sub.choices["score"].add_argument("--out")
    sub.choices["ship"].add_argument("--run", required=True, help="the run (a name in --runs) to ship")
    sub.choices["export"].add_argument("--run", required=True, help="the run (a name in --runs) to export")
    sub.choices["export"].add_argument("--to", required=True, help="a new folder: the shipped models with the run's net")
    for name in ("score", "ship", "export"):
        sub.choices[name].add_argument("--calibrate-to", help="a models folder whose de-lighting net's albedo level "
                                       "the run's net is brought to (its manifest's calibration)")
    sub.choices["ship"].add_argument("--to", help="a new candidate folder instead of models/ (`adopt` ships it)")
    adopting = sub.add_parser("adopt", help="ship a candidate folder (`ship --to`) into models/")
    adopting.add_argument("candidate")
    adopting.add_argument("--family", choices=sorted(CONFIGS), default="delight")
    adopting.add_argument("--into", help="a models folder other than models/ (a copy, to score the candidate)")
    args = parser.parse_args()
    if args.command == "train":
        args.steps = args.steps or STEPS[args.family]
        args.crop = CROP.get(args.family) if args.crop is None else (args.crop or None)
    {"train": train, "score": score, "ship": ship, "export": export, "adopt": adopt}[args.command](args)


if __name__ == "__main__":
    main()
