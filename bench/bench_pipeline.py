"""End-to-end time per stage and peak memory (issue "End to end"), with the shipped models.

    python bench/bench_pipeline.py                      # 5 runs on the example, median per stage
    python bench/bench_pipeline.py --resolution 512     # the paper's crop size
    python bench/bench_pipeline.py --memory             # peak RSS relighting a 24-megapixel photo

Prints a table and writes bench/results/pipeline.json. Targets (issue): median end-to-end time
for a 512x512 crop <= 2.0 s on 2 cores; peak memory for a 24 MP photo <= 1.5 GB.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

EXAMPLE = REPO / "examples" / "skier.jpg"
MASK = REPO / "examples" / "skier_mask.png"
HDR = REPO / "examples" / "noon_grass.hdr"


def stage_times(runs: int, resolution: int, threads: int, spp, target_error,
                photo=EXAMPLE, mask_path=MASK, hdr=HDR, predict_mask: bool = False, albedo: str = "solve",
                shadows: str = "half") -> dict:
    from relightcli.batch import ItemReport
    from relightcli.io.envmap import load_envmap
    from relightcli.io.images import read_image
    from relightcli.pipeline import RelightOptions, run_stages
    from relightcli.stages.frame import Models

    image = read_image(photo)
    mask = None if predict_mask else read_image(mask_path, srgb=False).rgb[..., 0]
    env = load_envmap(hdr)
    options = RelightOptions(outputs=("relit",), resolution=resolution, threads=threads, spp=spp,
                             target_error=target_error, albedo=albedo, shadows=shadows)
    models = Models(threads)
    run_stages(image.rgb, mask, env, options, ItemReport("warm-up"), models)  # load sessions once
    rows = []
    for seed in range(runs):
        options.seed = seed
        report = ItemReport(str(photo))
        start = time.perf_counter()
        frame, _ = run_stages(image.rgb, mask, env, options, report, models)
        report.seconds["total"] = time.perf_counter() - start
        report.seconds["raytrace_rel_error"] = frame.notes["raytrace"]["rel_error"]
        report.seconds["raytrace_mrays_per_s"] = frame.notes["raytrace"]["mrays_per_s"]
        rows.append(report.seconds)
    keys = rows[0].keys()
    return {key: float(np.median([row[key] for row in rows])) for key in keys}


def peak_memory_24mp(resolution: int, threads: int, spp, predict_mask: bool = False) -> dict:
    """Relight the example upscaled to 6000x4000 in a child process; its peak RSS."""
    import cv2

    from relightcli.io.images import read_image, write_image

    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        photo = cv2.resize(read_image(EXAMPLE).rgb, (6000, 4000), interpolation=cv2.INTER_LINEAR)
        mask = cv2.resize(read_image(MASK, srgb=False).rgb[..., 0], (6000, 4000), interpolation=cv2.INTER_NEAREST)
        write_image(folder / "big.jpg", photo, quality=92)
        write_image(folder / "big_mask.png", mask, bits=8, srgb=False)
        given_mask = [] if predict_mask else ["--mask", str(folder / "big_mask.png")]
        command = [sys.executable, "-m", "relightcli", str(folder / "big.jpg"), *given_mask, "--hdr", str(HDR), "-o", str(folder / "out.png"), "--resolution", str(resolution),
                   "--threads", str(threads), "--json"] + (["--spp", str(spp)] if spp else [])
        start = time.perf_counter()
        done = subprocess.run(_peak_reporter(folder / "peak_kib") + command, capture_output=True, text=True, cwd=REPO,
                              env=os.environ | {"PYTHONPATH": str(REPO)})
        seconds = time.perf_counter() - start
        if done.returncode != 0:
            raise SystemExit(f"relight failed:\n{done.stderr[-2000:]}")
        peak_kib = int((folder / "peak_kib").read_text())
    return {"megapixels": 24.0, "peak_rss_mb": peak_kib / 1024.0, "seconds": seconds}


def _peak_reporter(path: Path) -> list[str]:
    """A small Python process that runs the command after it and writes the command's peak RSS
    (KiB, its largest process) to `path`. Linux carries a process's peak RSS over fork + exec,
    so a command started straight from this process would report at least this process's own
    peak (networks loaded, the 24 MP photo made and encoded), not its own."""
    script = ("import resource, subprocess, sys; code = subprocess.run(sys.argv[2:]).returncode; "
              "open(sys.argv[1], 'w').write(str(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)); "
              "sys.exit(code)")
    return [sys.executable, "-c", script, str(path)]


def side_by_side(count: int) -> Path:
    """A photo of `count` people: the example repeated, every other copy mirrored."""
    import cv2

    example = cv2.imread(str(EXAMPLE))
    path = Path(tempfile.mkdtemp()) / f"people_{count}.png"
    cv2.imwrite(str(path), np.hstack([example if k % 2 == 0 else example[:, ::-1] for k in range(count)]))
    return path


def scene_files(scene: Path | None) -> tuple[Path, Path, Path]:
    """(photo, mask, environment) of an eval scene folder, or the shipped example's."""
    if scene is None:
        return EXAMPLE, MASK, HDR
    return scene / "input.png", scene / "gt_mask.png", scene / "target.hdr"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--resolution", type=int, default=None, help="default: the models' training resolution")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--spp", type=int, default=None)
    parser.add_argument("--target-error", type=float, default=None)
    parser.add_argument("--memory", action="store_true", help="also measure peak memory on a 24 MP photo")
    parser.add_argument("--scene", type=Path, default=None,
                        help="an eval scene folder (input.png, gt_mask.png, target.hdr) instead of the example, "
                             "e.g. one with a face to time the face path")
    parser.add_argument("--predict-mask", action="store_true",
                        help="leave the mask out: time finding the people and their mask too")
    parser.add_argument("--albedo", default="solve", choices=("solve", "ratio", "net"),
                        help="the albedo source (relight --albedo; ratio: ~0.45 s less)")
    parser.add_argument("--shadows", default="half", choices=("half", "full"),
                        help="where shadow rays are traced (relight --shadows)")
    parser.add_argument("--people", type=int, default=None, metavar="N",
                        help="the example N times side by side (mirrored every other time), no mask: "
                             "the time for N people in one photo")
    args = parser.parse_args()
    from relightcli.layers import DEFAULT_RESOLUTION

    resolution = args.resolution or DEFAULT_RESOLUTION
    photo, mask, hdr = scene_files(args.scene)
    if args.people:
        photo, args.predict_mask = side_by_side(args.people), True
    result = {"resolution": resolution, "threads": args.threads, "cpu": os.cpu_count(),
              "median_seconds": stage_times(args.runs, resolution, args.threads, args.spp, args.target_error,
                                            photo, mask, hdr, predict_mask=args.predict_mask,
                                            albedo=args.albedo, shadows=args.shadows)}
    if args.memory:
        result["memory"] = peak_memory_24mp(resolution, args.threads, args.spp, args.predict_mask)
    print(f"median over {args.runs} runs, {resolution}x{resolution} crop, {args.threads} threads")
    for stage, seconds in result["median_seconds"].items():
        print(f"  {stage:<22} {seconds:8.3f}")
    if "memory" in result:
        print(f"24 MP photo: peak RSS {result['memory']['peak_rss_mb']:.0f} MB, {result['memory']['seconds']:.1f} s")
    suffix = ((f"_{args.scene.name}" if args.scene else "") + (f"_{args.people}_people" if args.people else "")
              + ("_predicted_mask" if args.predict_mask else "") + ("" if args.albedo == "solve" else f"_{args.albedo}")
              + ("" if args.shadows == "half" else f"_shadows_{args.shadows}"))
    out = REPO / "bench" / "results" / f"pipeline_{resolution}{suffix}.json"
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
