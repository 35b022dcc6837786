"""Many images: find the inputs, plan every output path up front, run each item, collect a report.

Library code: it raises and returns; the CLI prints. One failing item never stops the batch.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import json
import multiprocessing
import os
import tempfile
import time
import warnings
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterable

from relightcli.errors import (
    EXIT_ITEMS_FAILED,
    EXIT_OK,
    InputError,
    MissingDependencyError,
    OutputError,
    RelightError,
    RelightWarning,
    UsageError,
)
from relightcli.layers import IMAGE_EXTENSIONS, LAYERS


@dataclass
class Item:
    """One input image and the files it will produce."""

    input: Path
    outputs: dict[str, Path]  # layer name -> output path


@dataclass
class ItemReport:
    input: str
    outputs: dict[str, str] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    error: str | None = None
    exit_code: int = EXIT_OK
    skipped: str | None = None  # why nothing was done (e.g. --skip-existing)
    details: dict = field(default_factory=dict)  # stage plan, integrator statistics, ...

    def as_dict(self) -> dict:
        out = {
            "input": self.input,
            "outputs": self.outputs,
            "seconds": self.seconds,
            "warnings": self.warnings,
            "error": self.error,
        }
        if self.skipped:
            out["skipped"] = self.skipped
        out.update(self.details)
        return out


def collect_inputs(paths: Iterable[str | Path], *, recursive: bool, exclude: Iterable[Path] = ()):
    """Expand files and directories into a sorted list of (input file, relative stem).

    The relative stem (input's path below the directory it was found in, without extension)
    names the outputs, so a recursive scan keeps sub-folders apart. `exclude` lists files
    (e.g. the --hdr map living in the input folder) and folders (the output) to leave out.
    """
    exclude = {Path(p).resolve() for p in exclude}
    found: list[tuple[Path, Path]] = []
    for raw in paths:
        path = Path(raw)
        if path.is_dir():
            pattern = "**/*" if recursive else "*"
            for file in sorted(path.glob(pattern)):
                resolved = file.resolve()
                if not file.is_file() or file.suffix.lower() not in IMAGE_EXTENSIONS:
                    continue
                if resolved in exclude or any(parent in exclude for parent in resolved.parents):
                    continue
                found.append((file, file.relative_to(path).with_suffix("")))
        elif path.exists() or path.suffix:
            # Files, including missing ones: each missing file fails as its own item.
            found.append((path, Path(path.stem)))
        else:
            raise InputError("no such file or directory", path=path, fix="check the input path")
    if not found:
        raise UsageError("no input images found", fix=f"inputs must be files or folders with {', '.join(IMAGE_EXTENSIONS)} images")
    return found


TURNTABLE_LAYERS = ("relit", "shading")  # the layers that change with the lighting


def plan_items(found, out: str | Path, layers: Iterable[str], turntable: int = 0) -> list[Item]:
    """Decide every output path. `out` is a file when there is exactly one input and it has an
    image extension; otherwise a directory. With a turntable of N frames the lit layers become
    N numbered files ('relit#000' -> photo_turn000.png). Refuses collisions and outputs that
    are inputs."""
    out = Path(out)
    layers = list(layers)
    single_file = len(found) == 1 and out.suffix.lower() in IMAGE_EXTENSIONS and not out.is_dir()
    if len(found) > 1 and out.suffix.lower() in IMAGE_EXTENSIONS and not out.is_dir():
        raise UsageError(f"{len(found)} inputs need an output folder, not the file {out}", fix="pass -o DIRECTORY")
    items = []
    for path, stem in found:
        outputs = {}
        for name in layers:
            layer = LAYERS[name]
            if single_file:
                base = out.with_suffix("")
                ext = out.suffix if name == "relit" else layer.extension
                outputs[name] = base.parent / f"{base.name}{layer.suffix}{ext}"
            else:
                outputs[name] = out / stem.parent / f"{stem.name}{layer.suffix}{layer.extension}"
        if turntable:
            outputs = _numbered_frames(outputs, turntable)
        items.append(Item(path, outputs))
    _refuse_collisions(items)
    return items


def _numbered_frames(outputs: dict[str, Path], frames: int) -> dict[str, Path]:
    numbered = {}
    for name, path in outputs.items():
        if name not in TURNTABLE_LAYERS:
            numbered[name] = path
            continue
        for k in range(frames):
            numbered[f"{name}#{k:03d}"] = path.with_name(f"{path.stem}_turn{k:03d}{path.suffix}")
    return numbered


def _refuse_collisions(items: list[Item]) -> None:
    inputs = {item.input.resolve() for item in items}
    seen: dict[Path, Path] = {}
    for item in items:
        for path in item.outputs.values():
            resolved = path.resolve()
            if resolved in inputs:
                raise OutputError("output would overwrite an input", path=path, fix="choose another -o")
            if resolved in seen and seen[resolved] != item.input:
                raise OutputError(
                    f"two inputs ({seen[resolved]}, {item.input}) would write the same output",
                    path=path,
                    fix="rename one input or process them into different folders",
                )
            seen[resolved] = item.input


def prepare_output_dirs(items: list[Item]) -> None:
    """Create the output folders and prove they are writable before any work starts."""
    folders = sorted({path.parent for item in items for path in item.outputs.values()})
    for folder in folders:
        try:
            folder.mkdir(parents=True, exist_ok=True)
            with tempfile.NamedTemporaryFile(dir=folder, prefix=".relight-probe-"):
                pass
        except OSError as exc:
            raise OutputError(
                f"output folder cannot be written ({exc.strerror or exc})",
                path=folder,
                fix="choose a writable -o",
            ) from exc


def existing_outputs(item: Item) -> list[Path]:
    return [path for path in item.outputs.values() if path.exists()]


def run_items(
    items: list[Item],
    worker,
    *,
    workers: int = 1,
    skip_existing: bool = False,
    overwrite: bool = False,
    on_done: Callable[[ItemReport], None] | None = None,
) -> list[ItemReport]:
    """Run `worker` on every item; an item's failure is recorded, never raised.

    worker: a picklable object with `setup()` (load models once per process) and
    `__call__(item) -> ItemReport`. workers > 1 runs items on that many processes (each calls
    `setup()` once); the reports come back in input order whatever the number of workers.
    RelightWarnings raised while processing an item are recorded into its report.
    """
    if workers <= 1 or len(items) <= 1:
        worker.setup()
        reports = []
        for item in items:
            reports.append(_run_one(item, worker, skip_existing, overwrite))
            if on_done is not None:
                on_done(reports[-1])
        return reports
    return _run_pool(items, worker, workers, skip_existing, overwrite, on_done)


def _run_pool(items, worker, workers, skip_existing, overwrite, on_done) -> list[ItemReport]:
    # spawn, not fork: the parent may hold ONNX Runtime / OpenMP threads that fork would break.
    context = multiprocessing.get_context("spawn")
    reports: list[ItemReport | None] = [None] * len(items)
    with ProcessPoolExecutor(min(workers, len(items)), mp_context=context,
                             initializer=_init_pool_worker, initargs=(worker,)) as pool:
        futures = {pool.submit(_pool_task, item, skip_existing, overwrite): index
                   for index, item in enumerate(items)}
        for future in as_completed(futures):
            index = futures[future]
            try:
                reports[index] = future.result()
            except BrokenProcessPool:
                reports[index] = ItemReport(
                    str(items[index].input), exit_code=EXIT_ITEMS_FAILED,
                    error=f"{items[index].input}: the worker process died (out of memory?); "
                          "retry with fewer --workers")
            if on_done is not None:
                on_done(reports[index])
    return reports


_POOL_WORKER = None


def _init_pool_worker(worker) -> None:
    global _POOL_WORKER
    worker.setup()
    _POOL_WORKER = worker


def _pool_task(item: Item, skip_existing: bool, overwrite: bool) -> ItemReport:
    return _run_one(item, _POOL_WORKER, skip_existing, overwrite)


def _run_one(item: Item, worker, skip_existing: bool, overwrite: bool) -> ItemReport:
    existing = existing_outputs(item)
    if existing and skip_existing and len(existing) == len(item.outputs):
        report = ItemReport(str(item.input), {k: str(v) for k, v in item.outputs.items()})
        report.skipped = "all outputs exist (--skip-existing)"
        return report
    start = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RelightWarning)
        try:
            if existing and not overwrite:
                raise OutputError(
                    "output exists", path=existing[0], fix="pass --overwrite or --skip-existing"
                )
            report = worker(item)
        except RelightError as exc:
            report = ItemReport(str(item.input), error=str(exc), exit_code=exc.exit_code)
        except MemoryError:
            report = ItemReport(str(item.input), error=f"{item.input}: out of memory", exit_code=EXIT_ITEMS_FAILED)
    report.warnings.extend(str(w.message) for w in caught if issubclass(w.category, RelightWarning))
    report.seconds.setdefault("total", round(time.perf_counter() - start, 4))
    release_free_memory()
    rss = resident_memory_mb()
    if rss is not None:
        report.details["worker_rss_mb"] = rss
    return report


def release_free_memory() -> bool:
    """Hand the heap's free pages back to the OS (glibc's malloc_trim); False where there is none.

    An item allocates and frees a few hundred MB of arrays of sizes that change with the photo.
    glibc serves many of them from its heap (its mmap threshold rises after the first large
    free), and the free holes stay resident: without a trim a long batch's RSS creeps up by
    tens of MB although nothing leaks. Trimming after each item costs about a millisecond."""
    global _MALLOC_TRIM
    if _MALLOC_TRIM is None:
        name = ctypes.util.find_library("c")
        libc = ctypes.CDLL(name) if name else None
        _MALLOC_TRIM = getattr(libc, "malloc_trim", False) or False
    if not _MALLOC_TRIM:
        return False
    _MALLOC_TRIM(0)
    return True


_MALLOC_TRIM = None  # the libc function, looked up on first use; False when the libc has none


def resident_memory_mb() -> float | None:
    """This process's resident memory now, in MB (Linux /proc; None elsewhere)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return None
    return round(pages * os.sysconf("SC_PAGE_SIZE") / 2**20, 1)


def exit_code(reports: list[ItemReport]) -> int:
    """0 when every item is ok; the failures' common exit code when every item failed the same
    way (e.g. 4: all unreadable); 1 otherwise (some items failed)."""
    failed = [r for r in reports if r.error is not None]
    if not failed:
        return EXIT_OK
    codes = {r.exit_code for r in failed}
    if len(failed) == len(reports) and len(codes) == 1:
        return codes.pop()
    return EXIT_ITEMS_FAILED


def summary(reports: list[ItemReport]) -> dict:
    """The machine-readable report printed by `--json`."""
    failed = sum(r.error is not None for r in reports)
    return {"ok": len(reports) - failed, "failed": failed, "items": [r.as_dict() for r in reports]}


def run_items_ray(
    items: list[Item],
    worker,
    *,
    workers: int,
    threads_per_worker: int,
    address: str | None = None,
    skip_existing: bool = False,
    overwrite: bool = False,
) -> list[ItemReport]:
    """The same job on Ray Data: a pool of `workers` stateful actors, each holding one `worker`
    (models loaded once per actor), fed file paths; decoding happens inside the actors with our
    own I/O (Ray's image reader drops EXIF orientation, 16-bit and EXR).

    address: an existing cluster ("auto", "ray://host:10001"); None starts a local instance
    with `workers * threads_per_worker` CPUs. On a cluster, inputs and outputs must live on a
    filesystem every node sees at the same path. Reports come back in input order.
    """
    try:
        import ray
        import ray.data
    except ImportError as exc:
        raise MissingDependencyError(
            "--engine ray needs the optional 'ray' extra",
            fix="pip install 'relightcli[ray]', or use the default local engine",
        ) from exc

    started_here = not ray.is_initialized()
    if started_here:
        package_root = str(Path(__file__).resolve().parents[1])
        ray.init(
            address=address,
            num_cpus=None if address else workers * threads_per_worker,
            include_dashboard=False,
            log_to_driver=False,
            configure_logging=False,
            runtime_env=None if address else {"env_vars": {"PYTHONPATH": package_root}},
        )
    try:
        rows = [
            {"index": index, "input": str(item.input),
             "outputs": json.dumps({k: str(v) for k, v in item.outputs.items()})}
            for index, item in enumerate(items)
        ]
        dataset = ray.data.from_items(rows).map_batches(
            _RayItemActor,
            fn_constructor_args=(worker, skip_existing, overwrite),
            batch_size=1,
            concurrency=min(workers, len(items)),
            num_cpus=threads_per_worker,
            batch_format="numpy",
        )
        results = dataset.take_all()
    finally:
        if started_here:
            ray.shutdown()
    reports: list[ItemReport | None] = [None] * len(items)
    for row in results:
        reports[int(row["index"])] = ItemReport(**json.loads(str(row["report"])))
    missing = [items[i].input for i, r in enumerate(reports) if r is None]
    if missing:
        raise RelightError(f"Ray returned no result for {len(missing)} item(s), e.g. {missing[0]}")
    return reports


class _RayItemActor:
    """A Ray Data actor: sets the worker up once, then processes one item per call."""

    def __init__(self, worker, skip_existing: bool, overwrite: bool):
        worker.setup()
        self.worker, self.skip_existing, self.overwrite = worker, skip_existing, overwrite

    def __call__(self, batch: dict) -> dict:
        import numpy as np

        reports = []
        for path, outputs in zip(batch["input"], batch["outputs"]):
            item = Item(Path(str(path)), {k: Path(v) for k, v in json.loads(str(outputs)).items()})
            report = _run_one(item, self.worker, self.skip_existing, self.overwrite)
            reports.append(json.dumps(asdict(report)))
        return {"index": batch["index"], "report": np.array(reports, dtype=object)}
