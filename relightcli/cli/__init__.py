"""The `relight` command: arguments, progress, report, exit codes.

The only place that prints or exits. Heavy modules (numpy, OpenImageIO, onnxruntime, embreex)
are imported inside the commands, so `relight --help` answers at once.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import signal
import sys
import threading
from pathlib import Path

from relightcli import __version__
from relightcli.errors import EXIT_MISSING, EXIT_OK, EXIT_USAGE, RelightError, UsageError
from relightcli.layers import (ALBEDO_SOURCES, DEFAULT_ALBEDO, DEFAULT_OUTPUTS, DEFAULT_RESOLUTION,
                               DEFAULT_SHADOWS, DEFAULT_SPP_CAP, DEFAULT_TARGET_ERROR, LAYERS, METHODS, SHADOW_STEP)

SUBCOMMANDS = ("shade", "info", "eval")

# Caps on the effort options: a typo (an extra zero) should be a usage error, not an hour of
# work or an out-of-memory crash deep inside OpenCV.
MAX_SPP = 4096  # 4096 samples of a 512 x 512 crop are already about a billion rays
RESOLUTION_RANGE = (16, 2048)
# 3600 frames turn the map a tenth of a degree a frame, finer than a video needs, and take about
# an hour at 512 (a frame ~1 s on 2 cores, made one at a time in constant memory): more is a typo
MAX_TURNTABLE = 3600

DESCRIPTION = """\
Relight a photo of a person under an HDR environment map (ECCV 2022, "Geometry-aware
single-image full-body human relighting"), on the CPU.

  relight photo.jpg --hdr sky.exr -o out.png        one photo
  relight photos/ --hdr sky.hdr -o out/ --recursive  a folder
  relight photo.jpg --hdr a.hdr --hdr b.exr -o out/  several maps, the nets run once
  relight shade body.obj --hdr sky.hdr -o shading.exr
                                                     ray-traced shading of any mesh
  relight eval DATASET --method raytrace             the paper's Table 1 on scenes with ground truth
  relight info                                       models, providers, threads
"""

EXIT_CODES = """\
exit codes: 0 all ok, 1 some items failed, 2 usage, 3 missing model or dependency,
4 unreadable input, 130 stopped by Ctrl-C (SIGINT), 143 stopped by SIGTERM (docker stop)."""


# Peak memory of one batch worker (the four networks and one item; measured about 500 MB),
# with some headroom: the default --workers keeps this much memory for each.
WORKER_MEMORY = 600 * 2**20


def default_threads() -> int:
    """The cores this process may use: its CPU affinity (--cpuset-cpus, taskset), lowered to
    its cgroup's CPU quota (docker --cpus) rounded up."""
    from relightcli.cli.limits import read_limits

    return read_limits().cores


def default_workers(threads: int, memory_bytes: int | None = None) -> int:
    """Batch processes for `threads` cores: one per core, but no more than the memory holds at
    WORKER_MEMORY each. memory_bytes: the container's memory limit or the RAM, whichever is
    lower (default: read them)."""
    if memory_bytes is None:
        from relightcli.cli.limits import read_limits

        memory_bytes = read_limits().usable_memory
    if memory_bytes is None:
        return max(1, threads)
    return max(1, min(threads, memory_bytes // WORKER_MEMORY))


def add_common_arguments(parser: argparse.ArgumentParser, *, writes: bool = True) -> None:
    """Options every command shares (defined once, so they cannot drift apart). `writes`:
    the command writes files, so it takes --overwrite."""
    parser.add_argument("--threads", type=_positive_int, default=None, metavar="N",
                        help="threads for ONNX Runtime, OpenCV, OpenImageIO and the ray tracer "
                             "(default and maximum: the cores available; more is lowered to that)")
    parser.add_argument("--json", action="store_true",
                        help="print a machine-readable report on stdout")
    if writes:
        parser.add_argument("--overwrite", action="store_true",
                            help="replace existing outputs (default: refuse)")


def add_pipeline_arguments(parser: argparse.ArgumentParser) -> None:
    """Albedo source, ray-tracing effort, seed and working resolution (shared by relight and eval)."""
    parser.add_argument("--albedo", choices=ALBEDO_SOURCES, default=DEFAULT_ALBEDO,
                        help="albedo: 'solve' (default) solves the input light by inverse rendering on "
                             "the mesh and divides the photo by its ray-traced shading (cast shadows "
                             "leave the albedo); 'ratio' divides by the SH-9 shading of the de-lighting "
                             "net's light at the predicted normals (~0.25-0.5 s less at 512); 'net' keeps "
                             "the de-lighting net's own albedo (the paper's)")
    sampling = parser.add_mutually_exclusive_group()
    sampling.add_argument("--spp", type=spp_value, metavar="N",
                          help=f"ray-tracing samples per pixel, 1..{MAX_SPP}")
    sampling.add_argument("--target-error", type=_positive_float, metavar="E",
                          help="stop each pixel at this relative standard error, at most "
                               f"{DEFAULT_SPP_CAP} samples (default {DEFAULT_TARGET_ERROR})")
    parser.add_argument("--shadows", choices=tuple(SHADOW_STEP), default=DEFAULT_SHADOWS,
                        help="where rays are traced for cast shadows and occlusion: 'half' (default) "
                             "every second pixel of the crop (every fourth at 512 for the solved "
                             "input light, a 16x32 map with soft shadows), the visibility they find "
                             "applied to every pixel's own shading (normals keep full detail; the "
                             "ray tracing takes ~0.6x the time, the eval scores the same); 'full' "
                             "every pixel")
    parser.add_argument("--seed", type=seed_value, default=0,
                        help="random seed >= 0 (an item's outputs depend on its input, the options and the seed only)")
    low, high = RESOLUTION_RANGE
    parser.add_argument("--resolution", type=int_in_range(low, high), default=DEFAULT_RESOLUTION, metavar="PX",
                        help=f"working resolution of the square person crop, {low}..{high} (default "
                             f"{DEFAULT_RESOLUTION}, the paper's; 256 takes ~0.8x the time). Below {low} "
                             f"no body is left to reconstruct; above {high} the networks, trained at "
                             "512, add no detail while time and memory grow with its square")


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def int_in_range(low: int, high: int):
    """An argparse type: an integer in [low, high]; the message gives the range."""
    def parse(text: str) -> int:
        value = int(text)
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must be {low}..{high}, got {value}")
        return value

    parse.__name__ = "integer"  # argparse names the type in "invalid integer value"
    return parse


spp_value = int_in_range(1, MAX_SPP)


def seed_value(text: str) -> int:
    """A --seed: any integer >= 0 (the random streams are seeded with it)."""
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
    return value


def _positive_float(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def _outputs(text: str) -> tuple[str, ...]:
    names = tuple(dict.fromkeys(n.strip() for n in text.split(",") if n.strip()))
    unknown = [n for n in names if n not in LAYERS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(
            f"unknown output(s) {', '.join(unknown) or '(none)'}; choose from {', '.join(LAYERS)}")
    return names


def _background(text: str) -> str:
    """keep | env | transparent | #RGB | #RRGGBB (validated here, interpreted by compose)."""
    if text in ("keep", "env", "transparent") or re.fullmatch(r"#([0-9a-fA-F]{3}|[0-9a-fA-F]{6})", text):
        return text
    raise argparse.ArgumentTypeError(f"{text!r}: use keep, env, transparent or a colour like '#808080'")


def relight_parser() -> argparse.ArgumentParser:
    layers_help = "; ".join(f"{layer.name}: {layer.description}" for layer in LAYERS.values())
    parser = argparse.ArgumentParser(
        prog="relight", description=DESCRIPTION, epilog=EXIT_CODES,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"relight {__version__}")
    parser.add_argument("inputs", nargs="+", metavar="INPUT",
                        help="photos (JPEG, PNG, TIFF, WebP, EXR, HDR) and/or folders of them; an input "
                             "NAME_mask.png beside NAME.jpg is that photo's person mask, not a photo")
    parser.add_argument("--hdr", required=True, metavar="ENV", action="append",
                        help="target environment map, equirectangular .hdr/.exr (width = 2 x height); "
                             "repeat it for several maps: the networks and the mesh run once, and the "
                             "lit layers (relit, shading, preview) are written once per map, named "
                             "after it (photo_sunset.png, photo_shading_sunset.exr)")
    parser.add_argument("-o", "--output", required=True, metavar="OUT",
                        help="output file (one input; .png, .jpg, .exr or .hdr) or folder (many "
                             "inputs, a name without an extension, or a name ending in '/')")
    parser.add_argument("--outputs", type=_outputs, default=DEFAULT_OUTPUTS, metavar="LIST",
                        help=f"comma-separated layers to write (default: relit). {layers_help}")
    parser.add_argument("--recursive", action="store_true", help="descend into sub-folders of INPUT folders")
    parser.add_argument("--skip-existing", action="store_true",
                        help="skip inputs whose outputs all exist (resume an interrupted batch)")
    parser.add_argument("--method", choices=METHODS,
                        default="raytrace",
                        help="shading: ray tracing + learned refinement (paper, default), ray tracing only, "
                             "or SH-9 / SH-25 irradiance from predicted normals (baselines)")
    parser.add_argument("--mask", metavar="FILE",
                        help="person mask (grey or alpha image) for every input; skips the mask net")
    parser.add_argument("--rotate", type=float, default=0.0, metavar="DEG",
                        help="rotate the environment about +Y, counter-clockwise seen from above")
    parser.add_argument("--exposure", type=float, default=0.0, metavar="EV",
                        help="scale the environment by 2**EV")
    parser.add_argument("--turntable", type=int_in_range(1, MAX_TURNTABLE), default=0, metavar="N",
                        help="N frames with the environment turned 360/N degrees apart, written as "
                             f"numbered images (photo_turn000.png, ...), 1..{MAX_TURNTABLE}; the networks "
                             "and the mesh run once, the frames one at a time")
    parser.add_argument("--background", type=_background, default="keep", metavar="MODE",
                        help="keep (original photo), env (the environment seen by a camera), "
                             "transparent (RGBA), or a colour like '#808080'")
    add_pipeline_arguments(parser)
    parser.add_argument("--workers", type=_positive_int, metavar="N",
                        help="processes for folder/many inputs (default: one per core, no more than "
                             "the memory holds at ~600 MB each; threads are split so workers x threads <= cores)")
    parser.add_argument("--engine", choices=("local", "ray"), default="local",
                        help="local process pool (default) or Ray Data (needs the 'ray' extra)")
    parser.add_argument("--address", metavar="ADDR",
                        help="with --engine ray: an existing cluster ('auto', 'ray://head:10001'); "
                             "default: start a local Ray instance")
    parser.add_argument("--ray-timeout", type=_positive_float, default=30.0, metavar="SECONDS",
                        help="with --address: how long the cluster may take to answer (default 30)")
    parser.add_argument("--max-pixels", type=_positive_int, default=100_000_000, metavar="N",
                        help="refuse images larger than N pixels before decoding (default 100 MP)")
    add_common_arguments(parser)
    return parser


def info_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="relight info", description="Models found, ONNX Runtime providers, threads.")
    add_common_arguments(parser, writes=False)
    return parser


def eval_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="relight eval", epilog=EXIT_CODES, formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Run the pipeline on every scene folder of DATASET and print the paper's Table 1\n"
                    "(MSE x1e3 / SSIM / PSNR for relit, albedo, shading; foreground only; sRGB, clipped).\n"
                    "A scene folder holds input.png, target.hdr, gt_mask.png, gt_albedo.exr,\n"
                    "gt_shading.exr, gt_relit.exr and optionally gt_normal.exr (EXRs linear).")
    parser.add_argument("dataset", metavar="DATASET", help="a folder of scene folders (or one scene folder)")
    parser.add_argument("--method", choices=METHODS, default="raytrace", help="shading method to evaluate")
    parser.add_argument("--use-gt-mask", action="store_true",
                        help="feed the ground-truth mask instead of predicting it (isolates the relighting)")
    add_pipeline_arguments(parser)
    add_common_arguments(parser, writes=False)
    return parser


def shade_parser() -> argparse.ArgumentParser:
    from relightcli.cli import shade

    parser = argparse.ArgumentParser(
        prog="relight shade", epilog=EXIT_CODES,
        description="Ray-trace the white-Lambertian shading of a mesh under an environment map, "
                    "pixel-aligned with an orthographic camera looking along -Z.")
    shade.add_arguments(parser)
    add_common_arguments(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    """The `relight` command. SIGTERM stops it cleanly from here on (exit 143, temporary files
    removed on the way out): a batch hands the signal to its own handler, every other phase
    unwinds through `Terminated`. argv None: the program's own arguments, and the process
    then ends here (`_exit_now`)."""
    try:
        with _sigterm_unwinds():
            code = _run_command(argv)
    except Terminated as exc:  # landed outside _run_command's own handlers (while reporting)
        print("relight: stopped by SIGTERM", file=sys.stderr)
        code = exc.exit_code
    if argv is None:
        _exit_now(code)
    return code


def _exit_now(code: int) -> None:
    """End the process without the interpreter's teardown of its modules and objects (numpy,
    scipy, OpenCV, ONNX Runtime's sessions): 0.24-0.32 s of every one-photo run on 2 cores
    (issue 50), and 0.5-0.8 s after a stopped run with trimesh loaded, which `docker stop`
    would wait for. Everything of the run is done by now (outputs written and closed, the
    batch's staging files and workers gone); the atexit callbacks still run (multiprocessing's
    and weakref.finalize's among them) and the output streams are flushed."""
    import atexit

    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    os._exit(code)


class Terminated(KeyboardInterrupt):
    """SIGTERM outside a batch (`docker stop`, a service manager). A KeyboardInterrupt, so it
    unwinds like Ctrl-C through every `finally`; signum and exit_code as batch.Stopped has them."""

    reports = None

    def __init__(self, signum: int = signal.SIGTERM):
        self.signum = int(signum)
        self.exit_code = 128 + self.signum
        super().__init__(signal.Signals(self.signum).name)


@contextlib.contextmanager
def _sigterm_unwinds():
    """SIGTERM raises Terminated in the main thread while the block runs. Also unblocks SIGTERM:
    a signal mask survives exec, and one inherited blocked would hold `docker stop` until the
    end (a SIGTERM already pending then arrives here, before any work).

    A stop raised while a finalizer runs (a `__del__` the garbage collector calls) is swallowed
    by Python ("Exception ignored in ...") and the run would go on until `docker stop` kills it
    10 s later: such a stop (Terminated, batch.Stopped, Ctrl-C) is sent again from a helper
    thread, to land in ordinary code a moment later."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(signum, frame):
        if _resent_if_importing(signum, frame):
            return
        signal.signal(signum, signal.SIG_IGN)  # once: a second SIGTERM must not cut the clean-up short
        raise Terminated(signum)

    def resend_swallowed_stop(unraisable):  # sys.unraisablehook
        if not isinstance(unraisable.exc_value, KeyboardInterrupt):
            return previous_hook(unraisable)
        signum = getattr(unraisable.exc_value, "signum", signal.SIGINT)
        if isinstance(unraisable.exc_value, Terminated):
            signal.signal(signum, stop)  # it ignored further ones: this one did not take
        _resend_soon(signum)  # sent at once it would land in this hook, and be swallowed again

    previous, previous_hook = signal.signal(signal.SIGTERM, stop), sys.unraisablehook
    sys.unraisablehook = resend_swallowed_stop
    try:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGTERM})
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
        sys.unraisablehook = previous_hook


def _resent_if_importing(signum: int, frame) -> bool:
    """True, and the signal sent again a moment later, when the handler interrupted a module
    being imported: libraries guard optional imports with `except BaseException` (trimesh, in
    every item's first use), which would swallow the stop and let the run go on to the end."""
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib._bootstrap"):
            _resend_soon(signum)
            return True
        frame = frame.f_back
    return False


def _resend_soon(signum: int) -> None:
    """Send `signum` to this process again in 50 ms, from a helper thread."""
    resend = threading.Timer(0.05, os.kill, args=(os.getpid(), signum))
    resend.daemon = True
    resend.start()


def _run_command(argv: list[str] | None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = argv[0] if argv and argv[0] in SUBCOMMANDS else None
    try:
        if command == "info":
            args = info_parser().parse_args(argv[1:])
            _limit_to_cores(args)
            report = run_info(args)
            _print_report(report, args.json)
            return _check_models(report["models"])
        if command == "eval":
            args = eval_parser().parse_args(argv[1:])
            _limit_to_cores(args)
            return run_eval(args)
        if command == "shade":
            args = shade_parser().parse_args(argv[1:])
            _limit_to_cores(args)
            return run_shade(args)
        args = relight_parser().parse_args(argv)
        _limit_to_cores(args)
        return run_relight(args)
    except SystemExit as exc:  # argparse: --help, --version, usage errors
        return EXIT_OK if exc.code in (0, None) else EXIT_USAGE
    except RelightError as exc:
        print(f"relight: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM (batch.Stopped in a batch, else Terminated)
        signum = getattr(exc, "signum", signal.SIGINT)
        print("relight: interrupted" if signum == signal.SIGINT else
              f"relight: stopped by {signal.Signals(signum).name}", file=sys.stderr)
        return getattr(exc, "exit_code", 130)


def _limit_to_cores(args) -> None:
    """Lower --threads to the cores this process may use, with a warning: more only thrash
    the caches, and the default --workers follows --threads (64 processes on 2 cores). Warn
    about --workers above the cores too (kept: the user may know the memory is there).
    Not with --address: the threads and workers then run on the Ray cluster's nodes, not here."""
    cores = default_threads()
    if args.threads is not None and args.threads > cores and not getattr(args, "address", None):
        print(f"relight: warning: --threads {args.threads} is more than the {cores} core(s) "
              f"available; using {cores}", file=sys.stderr)
        args.threads = cores
    workers = getattr(args, "workers", None)
    if workers is not None and workers > cores and not getattr(args, "address", None):
        # Each worker process holds its own networks: measured ~330 MB between items and up to
        # ~750 MB while relighting (the example photo, --resolution 512); the cores are shared
        print(f"relight: warning: --workers {workers} is more than the {cores} core(s) available: "
              f"each worker takes ~330 MB, up to ~750 MB while it relights at --resolution 512 "
              f"({workers} workers: up to ~{workers * 0.75:.1f} GB), and they share the {cores} "
              "core(s): fewer are as fast", file=sys.stderr)


def _refuse_alpha_loss(items, background: str) -> None:
    """--background transparent writes an alpha channel; JPEG and Radiance HDR have none."""
    if background != "transparent":
        return
    for item in items:
        for name, path in item.outputs.items():
            if name.split("#")[0] == "relit" and path.suffix.lower() in (".jpg", ".jpeg", ".hdr"):
                raise UsageError(f"--background transparent needs an alpha channel, which "
                                 f"{path.suffix} files do not have", path=path,
                                 fix="write the relit image as .png or .exr, or choose another --background")


def run_relight(args) -> int:
    from relightcli import batch
    from relightcli.pipeline import RelightOptions, RelightWorker, prepared_models

    if args.address and args.engine != "ray":
        raise UsageError("--address goes with --engine ray", fix="add --engine ray or drop --address")
    if args.skip_existing and args.overwrite:
        raise UsageError("--skip-existing and --overwrite contradict each other", fix="pass one of them")
    threads = args.threads or default_threads()
    items, refused = _plan_relight(args)
    runnable = [item for index, item in enumerate(items) if index not in refused]
    batch.prepare_output_dirs(runnable)
    # One process per core by default; threads are split so workers x threads <= cores.
    workers = max(1, min(args.workers or default_workers(threads), len(runnable)))
    options = RelightOptions(
        outputs=args.outputs, method=args.method, albedo=args.albedo,
        mask_path=None if args.mask is None else Path(args.mask),
        rotate_deg=args.rotate, exposure_ev=args.exposure, spp=args.spp,
        target_error=args.target_error, shadows=args.shadows, seed=args.seed,
        threads=max(1, threads // workers),
        background=args.background, max_pixels=args.max_pixels, resolution=args.resolution,
        turntable=args.turntable)
    # Items relit in this process: the nets' sessions build on a background thread from here on,
    # while the map loads and the first stages run
    models = prepared_models(options) if runnable and workers == 1 and args.engine == "local" else None
    try:
        env, env_warnings = _load_environment(args)
    except BaseException:
        if models is not None:
            models.stop_prefetch()
        raise
    worker = RelightWorker(env, options, models)
    progress = _Progress(len(items), enabled=args.engine == "local" and sys.stderr.isatty() and not args.json)
    for index in refused:
        progress.step(items[index].input)
    try:
        with _signals_stop_batch():
            if not runnable:
                reports = []
            elif args.engine == "ray":
                from relightcli.ray_engine import run_items_ray

                reports = run_items_ray(
                    runnable, worker, workers=workers, threads_per_worker=options.threads,
                    address=args.address, skip_existing=args.skip_existing, overwrite=args.overwrite,
                    timeout_s=args.ray_timeout)
            else:
                reports = batch.run_items(
                    runnable, worker, workers=workers,
                    skip_existing=args.skip_existing, overwrite=args.overwrite, on_done=progress.step)
    except batch.Stopped as stopped:
        if stopped.reports is None:  # stopped before any item ran, or by Ray: nothing to report
            raise
        reports = stopped.reports  # finished items, the rest marked stopped; exit_code: 130 / 143
    finally:
        progress.close()
        if worker.models is not None:
            worker.models.stop_prefetch()
    reports = _with_refused(items, refused, reports)
    for report in reports:
        report.warnings[:0] = env_warnings
    summary = batch.summary(reports)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        _print_human_summary(summary)
    return batch.exit_code(reports)


def _plan_relight(args) -> tuple[list, dict]:
    """Every item of the run with its output paths, and {index: error} for the items refused
    before any work (`batch.unusable_items`: each fails alone, the others run). Raises for what
    concerns the whole run: a --hdr or --mask that cannot be opened, colliding outputs, ..."""
    import warnings

    from relightcli import batch
    from relightcli.errors import InputError, RelightWarning

    lightings = _lighting_names(args)
    for option, path in [("--hdr", path) for path in args.hdr] + ([("--mask", args.mask)] if args.mask else []):
        if (error := batch.path_error(Path(path))) is not None:  # a symlink loop, a name too long
            raise InputError(error.message, path=path, fix=f"{error.fix}, or pass another {option}")
    exclude = [*map(Path, args.hdr), Path(args.output)] + ([Path(args.mask)] if args.mask else [])
    with warnings.catch_warnings(record=True) as caught:  # sub-folders that cannot be read
        warnings.simplefilter("always", RelightWarning)
        found, masks = batch.pair_masks(batch.collect_inputs(args.inputs, recursive=args.recursive, exclude=exclude))
    for warning in caught:
        if issubclass(warning.category, RelightWarning):
            print(f"relight: warning: {warning.message}", file=sys.stderr)
    if masks and args.mask:
        photo, mask = next(iter(masks.items()))
        raise UsageError(f"--mask and a photo's own mask file ({mask} for {photo}) both give masks",
                         fix="drop --mask, or move the NAME_mask files away")
    items = batch.plan_items(found, args.output, args.outputs, lightings=lightings,
                             read_only=[*args.hdr] + ([args.mask] if args.mask else []), masks=masks,
                             skip_existing=args.skip_existing)
    _refuse_alpha_loss(items, args.background)
    return items, batch.unusable_items(items)


def _with_refused(items, refused: dict, reports: list) -> list:
    """The reports of every item in input order: those of the items that ran, and for each item
    refused before the run (`batch.unusable_items`: {index: error}) a failed one."""
    from relightcli.batch import ItemReport

    ran = iter(reports)
    return [ItemReport(str(item.input), error=str(refused[index]), exit_code=refused[index].exit_code)
            if index in refused else next(ran) for index, item in enumerate(items)]


@contextlib.contextmanager
def _signals_stop_batch():
    """While a batch runs, SIGINT and SIGTERM raise batch.Stopped in the main thread, so the
    batch can kill its workers, drop unfinished items and hand back what finished (SIGTERM,
    from `docker stop` or a service manager, would otherwise end this process on the spot and
    leave the workers running). Not inside an import (`_resent_if_importing`)."""
    import signal

    from relightcli.batch import Stopped

    def stop(signum, frame):
        if not _resent_if_importing(signum, frame):
            raise Stopped(signum)

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {signum: signal.signal(signum, stop) for signum in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def run_eval(args) -> int:
    from relightcli import evaluate
    from relightcli.pipeline import RelightOptions, predict_scene

    threads = args.threads or default_threads()
    options = RelightOptions(
        outputs=("relit", "albedo", "shading"), method=args.method, albedo=args.albedo, spp=args.spp,
        target_error=args.target_error, shadows=args.shadows, seed=args.seed, threads=threads,
        resolution=args.resolution)
    scenes = evaluate.find_scenes(args.dataset)
    progress = _Progress(len(scenes), enabled=sys.stderr.isatty() and not args.json)

    def predict(scene):
        try:
            return predict_scene(scene, options, use_gt_mask=args.use_gt_mask)
        except RelightError as exc:
            raise _in_eval_terms(exc, scene, args.use_gt_mask) from exc

    result = evaluate.evaluate(scenes, predict, args.method, on_done=lambda entry: progress.step(entry["scene"]))
    result["albedo_source"] = args.albedo
    progress.close()
    if args.json:
        print(json.dumps(evaluate.finite_json(result), indent=2, allow_nan=False))
    else:
        print(evaluate.format_table(result))
        for entry in result["per_scene"]:
            if entry["error"]:
                print(f"FAILED {entry['scene']}: {entry['error']}", file=sys.stderr)
    failed = [e for e in result["per_scene"] if e["error"]]
    if not failed:
        return EXIT_OK
    codes = {e["exit_code"] for e in failed}
    return codes.pop() if len(failed) == len(result["per_scene"]) and len(codes) == 1 else 1


def _in_eval_terms(error: RelightError, scene, use_gt_mask: bool) -> RelightError:
    """A pipeline error that tells a `relight` user to check or pass --mask, told in `relight
    eval`'s terms (eval has no --mask): the person mask is the scene's gt_mask.png with
    --use-gt-mask, else predicted from its input.png."""
    if "--mask" not in str(error):
        return error
    if use_gt_mask:
        path, fix = scene.folder / "gt_mask.png", "the scene's true mask marks no person: regenerate the scene"
    else:
        path, fix = scene.input_path, "pass --use-gt-mask to use the scene's gt_mask.png instead"
    return type(error)(error.message, path=path, fix=fix)


def _lighting_names(args) -> list[str]:
    """Names of the lightings that get a file each: the turntable's frames, or the maps'
    names when there are several maps; none for one map."""
    if args.turntable:
        if len(args.hdr) > 1:
            raise UsageError("--turntable turns one map; several --hdr were given",
                             fix="pass one --hdr with --turntable, or drop --turntable")
        digits = max(3, len(str(args.turntable - 1)))  # names that sort in frame order
        return [f"turn{k:0{digits}d}" for k in range(args.turntable)]
    if len(args.hdr) == 1:
        return []
    names = [Path(path).stem for path in args.hdr]
    twice = sorted({name for name in names if names.count(name) > 1})
    if twice:
        raise UsageError(f"several --hdr maps are named '{twice[0]}': their outputs would collide",
                         fix="rename or copy one of the maps")
    return names


def _load_environment(args):
    """The target environments, loaded once for the whole batch (one map, or a list of them
    when several --hdr were given), and their warnings as text."""
    import warnings

    from relightcli.errors import RelightWarning
    from relightcli.io.envmap import load_envmap

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RelightWarning)
        envs = [load_envmap(path, rotate_deg=args.rotate, exposure_ev=args.exposure) for path in args.hdr]
    env = envs[0] if len(envs) == 1 else envs
    return env, [str(w.message) for w in caught if issubclass(w.category, RelightWarning)]


def run_shade(args) -> int:
    from relightcli.cli import shade

    from relightcli.io.images import set_io_threads

    threads = args.threads or default_threads()
    set_io_threads(threads)
    return _print_report(shade.run(args, threads), args.json)


def run_info(args) -> dict:
    from relightcli.cli.limits import read_limits
    from relightcli.nets.manifest import list_models, models_dir
    from relightcli.nets.session import import_onnxruntime

    onnxruntime = import_onnxruntime()
    models = [
        {"name": m.name, "file": str(m.path), "present": m.present, "sha256_ok": m.sha256_ok}
        for m in list_models(verify=True)
    ]
    limits = read_limits()
    threads = args.threads or limits.cores
    mib = {name: None if value is None else value // 2**20
           for name, value in (("limit", limits.memory_bytes), ("ram", limits.physical_bytes))}
    return {
        "version": __version__,
        "python": sys.version.split()[0],
        "models_dir": str(models_dir()),
        "models": models,
        "onnxruntime": onnxruntime.__version__,
        "providers": onnxruntime.get_available_providers(),
        # What the defaults below come from: CPUs in the affinity mask, the cgroup's CPU quota
        # in cores (None: no quota) and its memory limit (None: none)
        "cores": {"affinity": limits.affinity_cores, "quota": limits.quota_cores, "cgroup": limits.cgroup},
        "memory_mib": mib,
        "threads": threads,
        "workers": default_workers(threads, limits.usable_memory),
    }


def _check_models(models: list[dict]) -> int:
    """EXIT_MISSING, each bad model named on stderr, when a model is absent or fails its sha256."""
    from relightcli.nets.manifest import MODELS_FIX

    bad = [m for m in models if not (m["present"] and m["sha256_ok"])]
    for model in bad:
        problem = "missing" if not model["present"] else "does not match its sha256 in the manifest"
        print(f"relight: error: model {model['name']} {problem}: {model['file']}", file=sys.stderr)
    if bad:
        print(f"relight: fix: {MODELS_FIX}", file=sys.stderr)
        return EXIT_MISSING
    return EXIT_OK


def _print_report(report: dict, as_json: bool) -> int:
    if as_json:
        print(json.dumps(report, indent=2))
    else:
        for key, value in report.items():
            print(f"{key}: {value}")
    return EXIT_OK


def _print_human_summary(summary: dict) -> None:
    for item in summary["items"]:
        if item.get("stopped"):
            print(f"stopped {item['input']}", file=sys.stderr)
        elif item["error"]:
            print(f"FAILED {item['input']}: {item['error']}", file=sys.stderr)
        elif item.get("skipped"):
            print(f"skipped {item['input']}: {item['skipped']}")
        else:
            print(f"ok {item['input']} -> {', '.join(item['outputs'].values())}")
        for warning in item["warnings"]:
            print(f"  warning: {warning}", file=sys.stderr)
    failed = [item["input"] for item in summary["items"] if item["error"] and not item.get("stopped")]
    line = f"{summary['ok']} ok, {summary['failed']} failed"
    if summary.get("stopped"):
        line += f", {summary['stopped']} stopped (rerun with --skip-existing to resume)"
    if failed:
        line += ": " + ", ".join(failed)
    print(line, file=sys.stderr if failed or summary.get("stopped") else sys.stdout)


class _Progress:
    """A one-line progress bar on stderr, only when stderr is a terminal."""

    def __init__(self, total: int, enabled: bool):
        self.total, self.done, self.enabled = total, 0, enabled

    def step(self, label) -> None:
        self.done += 1
        if self.enabled:
            width = 30
            filled = width * self.done // self.total
            text = str(getattr(label, "input", label))[-40:]
            sys.stderr.write(f"\r[{'#' * filled}{'.' * (width - filled)}] {self.done}/{self.total} {text}")
            sys.stderr.flush()

    def close(self) -> None:
        if self.enabled:
            sys.stderr.write("\n")
