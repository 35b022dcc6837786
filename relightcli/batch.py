"""Many images: find the inputs, plan every output path up front, run each item, collect a report.

Library code: it raises and returns; the CLI prints. One failing item never stops the batch.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import glob
import json
import multiprocessing
import os
import signal
import tempfile
import threading
import time
import warnings
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterable

from relightcli.errors import (
    EXIT_ITEMS_FAILED,
    EXIT_MISSING,
    EXIT_OK,
    InputError,
    MissingDependencyError,
    OutputError,
    RelightError,
    RelightWarning,
    UsageError,
)
from relightcli.layers import IMAGE_EXTENSIONS, LAYERS, OUTPUT_EXTENSIONS


@dataclass
class Item:
    """One input image, the files it will produce and its own mask file (`pair_masks`)."""

    input: Path
    outputs: dict[str, Path]  # layer name -> output path
    mask: Path | None = None


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
    seen: set[Path] = set()  # resolved paths: a file named twice (or via a link) is relit once

    def add(file: Path, stem: Path) -> None:
        resolved = file.resolve()
        if resolved not in seen:
            seen.add(resolved)
            found.append((file, stem))

    for raw in paths:
        path = Path(raw)
        if path.is_dir():
            _refuse_folder_in_output(path, exclude)
            pattern = "**/*" if recursive else "*"
            for file in sorted(path.glob(pattern)):
                resolved = file.resolve()
                if not file.is_file() or file.suffix.lower() not in IMAGE_EXTENSIONS:
                    continue
                if resolved in exclude or any(parent in exclude for parent in resolved.parents):
                    continue
                add(file, file.relative_to(path).with_suffix(""))
        elif path.exists() or path.suffix:
            # Files, including missing ones: each missing file fails as its own item.
            add(path, Path(path.stem))
        else:
            raise InputError("no such file or directory", path=path, fix="check the input path")
    if not found:
        raise UsageError("no input images found", fix=f"inputs must be files or folders with {', '.join(IMAGE_EXTENSIONS)} images")
    return found


def pair_masks(found: list[tuple[Path, Path]]) -> tuple[list[tuple[Path, Path]], dict[Path, Path]]:
    """Split `collect_inputs`'s list into photos and their masks: an input NAME_mask.EXT in
    the same folder as an input NAME.EXT2 (any image extensions; the name the mask layer is
    written under) is that photo's mask, not a photo. Returns (the photos, {photo: mask});
    a NAME_mask image without its photo stays a photo."""
    suffix = LAYERS["mask"].suffix
    by_name = {(file.parent.resolve(), file.stem): file for file, _ in found}
    masks = {}
    for file, _ in found:
        if file.stem.endswith(suffix):
            photo = by_name.get((file.parent.resolve(), file.stem[:-len(suffix)]))
            if photo is not None:
                masks[photo] = file
    mask_files = set(masks.values())
    return [(file, stem) for file, stem in found if file not in mask_files], masks


def _refuse_folder_in_output(folder: Path, exclude: set[Path]) -> None:
    """An input folder that is (or lies inside) an excluded folder, the output, would be
    scanned empty: say so instead of "no input images found"."""
    resolved = folder.resolve()
    if resolved in exclude:
        raise UsageError("the output folder is the input folder", path=folder,
                         fix="choose another -o, e.g. a sub-folder such as -o "
                             f"{Path(folder, 'relit')}")
    if any(parent in exclude for parent in resolved.parents):
        raise UsageError("the input folder lies inside the output folder", path=folder,
                         fix="choose an -o outside the input folder")


LIT_LAYERS = ("relit", "shading", "preview")  # the layers that change with the lighting


def plan_items(found, out: str | Path, layers: Iterable[str], lightings: Iterable[str] = (),
               read_only: Iterable[str | Path] = (), masks: dict[Path, Path] | None = None) -> list[Item]:
    """Decide every output path. `out` is a file when there is exactly one input and it has an
    extension (one of OUTPUT_EXTENSIONS, else a UsageError); it is a directory when there are
    several inputs, when it has no extension, ends with '/' or is an existing folder.
    `lightings`: the names of several lightings (a turntable's frames 'turn000', ..., or the
    maps' names): each lit layer becomes one file per lighting, keyed 'relit#000', ... and
    named after it (photo_turn000.png, photo_shading_sunset.exr). `masks`: each photo's own
    mask (`pair_masks`). Refuses collisions and outputs that are inputs: the photos, their
    masks and the `read_only` files (the environment maps, --mask)."""
    lightings = list(lightings)
    masks = masks or {}
    as_folder = str(out).endswith(("/", os.sep)) or Path(out).is_dir() or not Path(out).suffix
    out = Path(out)
    layers = list(layers)
    single_file = len(found) == 1 and not as_folder
    if single_file and out.suffix.lower() not in OUTPUT_EXTENSIONS:
        raise UsageError(f"unsupported output format '{out.suffix}'", path=out,
                         fix=f"name the output file with {', '.join(OUTPUT_EXTENSIONS)}, "
                             "or end -o with '/' for a folder")
    if len(found) > 1 and out.suffix.lower() in IMAGE_EXTENSIONS and not as_folder:
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
        if lightings:
            outputs = _one_per_lighting(outputs, lightings)
        items.append(Item(path, outputs, masks.get(path)))
    _refuse_collisions(items, [*read_only, *masks.values()])
    return items


def _one_per_lighting(outputs: dict[str, Path], lightings: list[str]) -> dict[str, Path]:
    numbered = {}
    for name, path in outputs.items():
        if name not in LIT_LAYERS:
            numbered[name] = path
            continue
        for k, lighting in enumerate(lightings):
            numbered[f"{name}#{k:03d}"] = path.with_name(f"{path.stem}_{lighting}{path.suffix}")
    return numbered


def _refuse_collisions(items: list[Item], read_only: Iterable[str | Path] = ()) -> None:
    """No output may replace a file that is read (a photo, the map, the mask), whatever path
    names it: resolved paths (symlinks, '..') and, for files that exist, the inode (hard links)."""
    inputs = [item.input for item in items] + [Path(p) for p in read_only]
    resolved_inputs = {path.resolve(): path for path in inputs}
    inode_inputs = {key: path for path in inputs if (key := _inode(path)) is not None}
    seen: dict[Path, Path] = {}
    for item in items:
        for path in item.outputs.values():
            resolved = path.resolve()
            overwritten = resolved_inputs.get(resolved) or inode_inputs.get(_inode(path))
            if overwritten is not None:
                raise OutputError(f"output would overwrite the input {overwritten}", path=path,
                                  fix="choose another -o")
            if resolved in seen and seen[resolved] != item.input:
                raise OutputError(
                    f"two inputs ({seen[resolved]}, {item.input}) would write the same output",
                    path=path,
                    fix="rename one input or process them into different folders",
                )
            seen[resolved] = item.input


def _inode(path: Path) -> tuple[int, int] | None:
    """(device, inode) of an existing file, None when there is none."""
    try:
        stat = path.stat()
    except OSError:
        return None
    return stat.st_dev, stat.st_ino


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


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Stopped(KeyboardInterrupt):
    """SIGINT or SIGTERM stopped a batch.

    exit_code: 128 + the signal number, as a shell reports a process that signal ended (130 for
    SIGINT, 143 for SIGTERM). reports: set by `run_items`, one per item: the finished ones as
    they came back, the others marked stopped (nothing of theirs written); None when raised
    elsewhere (the CLI's signal handler raises it bare). A KeyboardInterrupt, so code that
    only knows Ctrl-C still stops."""

    def __init__(self, signum: int = signal.SIGINT, reports: list[ItemReport] | None = None):
        self.signum = int(signum)
        self.reports = reports
        self.exit_code = 128 + self.signum
        super().__init__(signal.Signals(self.signum).name)


def _stopped(interrupt: KeyboardInterrupt, items: list[Item], reports: list) -> Stopped:
    """The Stopped to raise for `interrupt`: every item without a report is marked stopped."""
    signum = getattr(interrupt, "signum", signal.SIGINT)  # a plain KeyboardInterrupt is Ctrl-C
    name = signal.Signals(signum).name
    for index, report in enumerate(reports):
        if report is None:
            reports[index] = report = ItemReport(
                str(items[index].input), exit_code=128 + signum,
                error=f"{items[index].input}: stopped by {name} before it finished; nothing of it "
                      "was written (rerun with --skip-existing to resume)")
            report.details["stopped"] = True
    return Stopped(signum, reports)


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

    An item's outputs appear together or not at all (see `relight_staged`). A KeyboardInterrupt
    (Ctrl-C, or the CLI's SIGTERM handler raising `Stopped`) stops the batch at once: the items
    in flight are discarded, the worker processes killed, and `Stopped` is raised carrying the
    reports (finished items as they are, the others marked stopped).
    """
    if workers <= 1 or len(items) <= 1:
        return _run_sequential(items, worker, skip_existing, overwrite, on_done)
    return _run_pool(items, worker, workers, skip_existing, overwrite, on_done)


def _run_sequential(items, worker, skip_existing, overwrite, on_done) -> list[ItemReport]:
    reports: list[ItemReport | None] = [None] * len(items)
    deferral = _SignalDeferral()
    try:
        worker.setup()
        for index, item in enumerate(items):
            try:
                reports[index] = _run_one(item, worker, skip_existing, overwrite, commit_guard=deferral)
            finally:
                deferral.deliver_pending()  # a signal held since the commit stops the batch here
            if on_done is not None:
                on_done(reports[index])
    except KeyboardInterrupt as interrupt:
        raise _stopped(interrupt, items, reports) from None
    return reports


def _run_pool(items, worker, workers, skip_existing, overwrite, on_done) -> list[ItemReport]:
    # spawn, not fork: the parent may hold ONNX Runtime / OpenMP threads that fork would break.
    context = multiprocessing.get_context("spawn")
    commit_lock = context.Lock()  # held by a worker while it renames an item's files into place
    committed = context.RawArray("b", len(items))  # set under the lock: item i is in place
    reports: list[ItemReport | None] = [None] * len(items)
    futures = {}
    pool = ProcessPoolExecutor(min(workers, len(items)), mp_context=context, initializer=_init_pool_worker,
                               initargs=(worker, commit_lock, committed))
    try:
        for index, item in enumerate(items):
            futures[pool.submit(_pool_task, index, item, skip_existing, overwrite)] = index
        for future in as_completed(futures):
            index = futures[future]
            reports[index] = _pool_report(future, items[index])
            if on_done is not None:
                on_done(reports[index])
        pool.shutdown(wait=True)
    except OSError as exc:  # the workers could not be started (EAGAIN, ENOMEM, a process limit)
        pool.shutdown(wait=False, cancel_futures=True)
        raise RelightError(f"could not start {min(workers, len(items))} worker processes "
                           f"({exc.strerror or exc})", fix="retry with --workers 1") from exc
    except KeyboardInterrupt as interrupt:
        with _signals_ignored():  # a second Ctrl-C must not leave the workers running
            _kill_workers(pool, commit_lock)
            pool.shutdown(wait=True, cancel_futures=True)
            for future, index in futures.items():
                if reports[index] is None:
                    reports[index] = _report_after_kill(future, items[index], committed[index])
        raise _stopped(interrupt, items, reports) from None
    return reports


def _pool_report(future, item: Item) -> ItemReport:
    try:
        return future.result()
    except BrokenProcessPool:
        return ItemReport(
            str(item.input), exit_code=EXIT_ITEMS_FAILED,
            error=f"{item.input}: the worker process died (out of memory?); retry with fewer --workers")


def _report_after_kill(future, item: Item, committed: bool) -> ItemReport | None:
    """An uncollected item's report once the workers are dead: its own when it came back in
    time, a bare one when its files were committed but the report was lost with its worker;
    None (the item is stopped) otherwise, after removing what it had staged."""
    if future.done() and not future.cancelled() and future.exception() is None:
        return future.result()
    if committed:
        return ItemReport(str(item.input), {key: str(path) for key, path in item.outputs.items()})
    _discard_staged(item, leftovers=True)
    return None


def _kill_workers(pool: ProcessPoolExecutor, commit_lock) -> None:
    """Kill the pool's processes at once (SIGKILL: they ignore SIGINT and SIGTERM), but never
    while one renames an item's files: holding the commit lock first means a worker dies
    computing or waiting, leaving only staging files, never half an item's outputs."""
    locked = commit_lock.acquire(timeout=10)  # a commit takes milliseconds; a dead holder, forever
    try:
        processes = list((pool._processes or {}).values())  # private: there is no public handle
        for process in processes:
            process.kill()
        for process in processes:
            process.join(timeout=10)
    finally:
        if locked:
            commit_lock.release()


@contextlib.contextmanager
def _signals_ignored():
    """Ignore SIGINT and SIGTERM inside the block (main thread only; elsewhere Python runs no
    handlers anyway)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {signum: signal.signal(signum, signal.SIG_IGN) for signum in STOP_SIGNALS}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


class _SignalDeferral:
    """The commit guard of a sequential batch: from the moment an item's files start being
    renamed into place until its report is recorded, SIGINT and SIGTERM are held (a handler
    raising in between would leave half an item, or a whole one reported as stopped);
    `deliver_pending()` puts the usual handlers back and raises what came meanwhile."""

    def __init__(self):
        self.pending: int | None = None
        self._previous: dict = {}

    def _hold(self, signum, frame) -> None:
        self.pending = self.pending or signum

    def __enter__(self):
        if not self._previous and threading.current_thread() is threading.main_thread():
            self._previous = {signum: signal.signal(signum, self._hold) for signum in STOP_SIGNALS}
        return self

    def __exit__(self, *exc_info) -> None:
        pass  # held on until deliver_pending(), once the report is safe

    def deliver_pending(self) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous = {}
        if self.pending is not None:
            signum, self.pending = self.pending, None
            signal.raise_signal(signum)


class _PoolCommit:
    """The commit guard of a pool worker: holds the batch's commit lock while item `index`'s
    files are renamed into place and marks the item committed before letting go, so the
    parent, once it holds the lock, knows which items are whole on disk."""

    def __init__(self, lock, committed, index: int):
        self.lock, self.committed, self.index = lock, committed, index

    def __enter__(self):
        self.lock.acquire()
        return self

    def __exit__(self, exc_type, exc, traceback) -> None:
        if exc_type is None:
            self.committed[self.index] = 1
        self.lock.release()


_POOL_WORKER = None
_COMMIT_LOCK = None
_COMMITTED = None


def _init_pool_worker(worker, commit_lock, committed) -> None:
    global _POOL_WORKER, _COMMIT_LOCK, _COMMITTED
    # The parent decides when to stop: Ctrl-C reaches the whole process group and SIGTERM may
    # too (systemd); a worker dying on its own would lose the item it holds half-way.
    for signum in STOP_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)
    worker.setup()
    _POOL_WORKER, _COMMIT_LOCK, _COMMITTED = worker, commit_lock, committed


def _pool_task(index: int, item: Item, skip_existing: bool, overwrite: bool) -> ItemReport:
    commit = _PoolCommit(_COMMIT_LOCK, _COMMITTED, index)
    return _run_one(item, _POOL_WORKER, skip_existing, overwrite, commit_guard=commit)


def _run_one(item: Item, worker, skip_existing: bool, overwrite: bool,
             commit_guard=None) -> ItemReport:
    existing = existing_outputs(item)
    if existing and skip_existing and len(existing) == len(item.outputs):
        report = ItemReport(str(item.input), {k: str(v) for k, v in item.outputs.items()})
        report.skipped = "all outputs exist (--skip-existing)"
        return report
    # --skip-existing completes an item that has some of its layers (a layer added to --outputs
    # on a rerun, a disk that filled up, files deleted): only the missing layers are written,
    # the item being recomputed in full. Rewriting all of them would give the same bytes only
    # under the same options, seed and version, which a rerun need not use; "skip existing"
    # promises to leave an existing file alone, and its mtime stays valid for make or rsync.
    todo = {key: path for key, path in item.outputs.items() if not (skip_existing and path.exists())}
    start = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RelightWarning)
        try:
            if existing and not overwrite and not skip_existing:
                raise OutputError(
                    "output exists", path=existing[0], fix="pass --overwrite or --skip-existing"
                )
            report = relight_staged(replace(item, outputs=todo), worker,
                                     commit_guard or contextlib.nullcontext())
        except RelightError as exc:
            report = ItemReport(str(item.input), error=str(exc), exit_code=exc.exit_code)
        except MemoryError:
            report = ItemReport(str(item.input), error=f"{item.input}: out of memory", exit_code=EXIT_ITEMS_FAILED)
    if report.error is None:
        report.outputs = {key: str(path) for key, path in item.outputs.items()}
        if len(todo) < len(item.outputs):
            report.details["kept"] = [key for key in item.outputs if key not in todo]
    report.warnings.extend(str(w.message) for w in caught if issubclass(w.category, RelightWarning))
    report.seconds.setdefault("total", round(time.perf_counter() - start, 4))
    release_free_memory()
    rss = resident_memory_mb()
    if rss is not None:
        report.details["worker_rss_mb"] = rss
    return report


def relight_staged(item: Item, worker, commit_guard) -> ItemReport:
    """Run `worker` with every output going to a hidden staging file next to its final path,
    then rename them all into place under `commit_guard` (a lock, or a signal deferral): the
    item's outputs appear together or not at all, and an item stopped or failed before its
    commit leaves the files it would have replaced (--overwrite) as they were."""
    staged = {key: _staging_path(path) for key, path in item.outputs.items()}
    committed = False
    try:
        report = worker(replace(item, outputs=staged))
        if report.error is None:
            with commit_guard:
                for key, path in item.outputs.items():
                    _move_into_place(staged[key], path)
                committed = True
    finally:
        if not committed:  # a stop raised mid-write can strand a writer's temporary file too
            _discard_staged(item, leftovers=True)
    return report


def _move_into_place(staged: Path, path: Path) -> None:
    try:
        os.replace(staged, path)
    except OSError as exc:
        raise OutputError(f"cannot move the finished output into place ({exc.strerror or exc})",
                          path=path, fix="check the output folder") from exc


def _staging_path(path: Path) -> Path:
    """Where `path` is written before its item commits: hidden, same folder (so the rename is
    atomic), same extension (the writers choose the format from it)."""
    return path.with_name(f".{path.name}.relight-part{path.suffix}")


def _discard_staged(item: Item, leftovers: bool = False) -> None:
    """Remove an unfinished item's staging files; with `leftovers`, also the writers' own
    temporary files (".<staged name>.tmp-...", io.images._temporary_path), which a killed
    process, or a stop raised between their creation and their cleanup, leaves behind."""
    for path in item.outputs.values():
        staged = _staging_path(path)
        staged.unlink(missing_ok=True)
        if leftovers:
            for temporary in staged.parent.glob("." + glob.escape(staged.name) + ".tmp-*"):
                temporary.unlink(missing_ok=True)


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
    way (e.g. 4: all unreadable); 3 when every item failed and a missing or corrupt model is
    among the causes (it stops every item: fix it first); 1 otherwise (some items failed). A stopped batch exits
    128 + the signal number (130 SIGINT, 143 SIGTERM), whatever its items did."""
    stopped = [r for r in reports if r.details.get("stopped")]
    if stopped:
        return stopped[0].exit_code
    failed = [r for r in reports if r.error is not None]
    if not failed:
        return EXIT_OK
    codes = {r.exit_code for r in failed}
    if len(failed) == len(reports) and len(codes) == 1:
        return codes.pop()
    if len(failed) == len(reports) and EXIT_MISSING in codes:
        return EXIT_MISSING
    return EXIT_ITEMS_FAILED


def summary(reports: list[ItemReport]) -> dict:
    """The machine-readable report printed by `--json`; "stopped" counts the items a signal
    kept from finishing (present only when there are some)."""
    stopped = sum(bool(r.details.get("stopped")) for r in reports)
    failed = sum(r.error is not None for r in reports) - stopped
    out = {"ok": len(reports) - failed - stopped, "failed": failed}
    if stopped:
        out["stopped"] = stopped
    out["items"] = [r.as_dict() for r in reports]
    return out


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
             "outputs": json.dumps({k: str(v) for k, v in item.outputs.items()}),
             "mask": "" if item.mask is None else str(item.mask)}
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
        for path, outputs, mask in zip(batch["input"], batch["outputs"], batch["mask"]):
            item = Item(Path(str(path)), {k: Path(v) for k, v in json.loads(str(outputs)).items()},
                        Path(str(mask)) if str(mask) else None)
            report = _run_one(item, self.worker, self.skip_existing, self.overwrite)
            reports.append(json.dumps(asdict(report)))
        return {"index": batch["index"], "report": np.array(reports, dtype=object)}
