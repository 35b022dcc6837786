"""Many images: find the inputs, plan every output path up front, run each item, collect a report.

Library code: it raises and returns; the CLI prints. One failing item never stops the batch.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import errno
import glob
import os
import re
import secrets
import signal
import socket
import stat
import tempfile
import threading
import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterable

from relightcli.errors import (
    EXIT_ITEMS_FAILED,
    EXIT_MISSING,
    EXIT_OK,
    InputError,
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
    A folder's entries with an image extension are kept even when they cannot be opened (a
    symlink loop, a dangling link): each fails as its own item (`unusable_items`), naming the
    file, and the batch goes on; entries with other names are no photos, whatever they are.
    A sub-folder that cannot be read is passed over with a RelightWarning.
    """
    exclude = {_resolved(Path(p)) for p in exclude}
    found: list[tuple[Path, Path]] = []
    seen: set[Path] = set()  # resolved paths: a file named twice (or via a link) is relit once

    def add(file: Path, stem: Path) -> None:
        resolved = _resolved(file)
        if resolved not in seen:
            seen.add(resolved)
            found.append((file, stem))

    for raw in paths:
        path = Path(raw)
        if os.path.isdir(path):
            _refuse_folder_in_output(path, exclude)
            for file in _folder_images(path, recursive):
                resolved = _resolved(file)
                if resolved in exclude or any(parent in exclude for parent in resolved.parents):
                    continue
                add(file, file.relative_to(path).with_suffix(""))
        elif path.suffix or os.path.lexists(path):
            # Files, including missing and broken ones: each fails as its own item.
            add(path, Path(path.stem))
        else:
            raise InputError("no such file or directory", path=path, fix="check the input path")
    if not found:
        raise UsageError("no input images found", fix=f"inputs must be files or folders with {', '.join(IMAGE_EXTENSIONS)} images")
    return found


def _folder_images(folder: Path, recursive: bool) -> list[Path]:
    """The entries of `folder` (with `recursive`, of its sub-folders too; linked folders are not
    followed) named with an image extension that are no folders, sorted. Raises InputError
    when `folder` itself cannot be read."""
    if not os.access(folder, os.R_OK | os.X_OK):
        raise InputError("permission denied: the folder cannot be read", path=folder,
                         fix="make it readable (chmod a+rx) or run as a user who may read it")
    unreadable: list[OSError] = []
    files = []
    for parent, _, names in os.walk(folder, onerror=unreadable.append):
        files += [Path(parent, name) for name in names if Path(name).suffix.lower() in IMAGE_EXTENSIONS]
        if not recursive:
            break
    for error in unreadable:
        warnings.warn(f"{error.filename}: the folder cannot be read ({error.strerror or error}): its photos "
                      "are left out", RelightWarning, stacklevel=3)
    return sorted(files)


def pair_masks(found: list[tuple[Path, Path]]) -> tuple[list[tuple[Path, Path]], dict[Path, Path]]:
    """Split `collect_inputs`'s list into photos and their masks: an input NAME_mask.EXT in
    the same folder as an input NAME.EXT2 (any image extensions; the name the mask layer is
    written under) is that photo's mask, not a photo. Returns (the photos, {photo: mask});
    a NAME_mask image without its photo stays a photo."""
    suffix = LAYERS["mask"].suffix
    by_name = {(_resolved(file.parent), file.stem): file for file, _ in found}
    masks = {}
    for file, _ in found:
        if file.stem.endswith(suffix):
            photo = by_name.get((_resolved(file.parent), file.stem[:-len(suffix)]))
            if photo is not None:
                masks[photo] = file
    mask_files = set(masks.values())
    return [(file, stem) for file, stem in found if file not in mask_files], masks


def _refuse_folder_in_output(folder: Path, exclude: set[Path]) -> None:
    """An input folder that is (or lies inside) an excluded folder, the output, would be
    scanned empty: say so instead of "no input images found"."""
    resolved = _resolved(folder)
    if resolved in exclude:
        raise UsageError("the output folder is the input folder", path=folder,
                         fix="choose another -o, e.g. a sub-folder such as -o "
                             f"{Path(folder, 'relit')}")
    if any(parent in exclude for parent in resolved.parents):
        raise UsageError("the input folder lies inside the output folder", path=folder,
                         fix="choose an -o outside the input folder")


LIT_LAYERS = ("relit", "shading", "preview")  # the layers that change with the lighting


def plan_items(found, out: str | Path, layers: Iterable[str], lightings: Iterable[str] = (),
               read_only: Iterable[str | Path] = (), masks: dict[Path, Path] | None = None,
               skip_existing: bool = False) -> list[Item]:
    """Decide every output path. `out` is a file when there is exactly one input and it has an
    extension (one of OUTPUT_EXTENSIONS, else a UsageError); it is a directory when there are
    several inputs, when it has no extension, ends with '/' or is an existing folder.
    `lightings`: the names of several lightings (a turntable's frames 'turn000', ..., or the
    maps' names): each lit layer becomes one file per lighting, keyed 'relit#000', ... and
    named after it (photo_turn000.png, photo_shading_sunset.exr). `masks`: each photo's own
    mask (`pair_masks`). Refuses, before any work: an `out` that cannot be opened
    (`path_problem`), two outputs that are one file (two inputs' or one input's two layers)
    and outputs that are inputs: the photos, their masks and the `read_only` files (the
    environment maps, --mask); unless `skip_existing` keeps every existing output, also a
    photo's mask file NAME_mask beside it that was not given (`_masks_beside`)."""
    lightings = list(lightings)
    masks = masks or {}
    out_error = path_error(Path(out), OutputError, "choose another -o")
    if out_error is not None:
        raise out_error
    as_folder = str(out).endswith(("/", os.sep)) or os.path.isdir(out) or not Path(out).suffix
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
        _refuse_layer_collisions(outputs, lightings)
        items.append(Item(path, outputs, masks.get(path)))
    own_masks = {} if skip_existing else _masks_beside([item.input for item in items])
    own_masks.update({mask: photo for photo, mask in masks.items()})
    _refuse_collisions(items, read_only, own_masks)
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


def _refuse_layer_collisions(outputs: dict[str, Path], lightings: list[str]) -> None:
    """Two layers of one input named alike: under a map called albedo.hdr the relit image is
    photo_albedo.png, which is also the albedo layer's name; with maps sun.hdr and
    preview_sun.hdr the relit image under the second is the preview under the first."""
    taken: dict[Path, str] = {}
    for key, path in outputs.items():
        if path in taken:
            lit = [k.partition("#") for k in (taken[path], key) if "#" in k]
            maps = sorted({lightings[int(index)] for _, _, index in lit})
            raise OutputError(f"{_layer_words(taken[path], lightings)} and {_layer_words(key, lightings)} "
                              "would both be written to this file", path=path,
                              fix=f"rename the map '{maps[0]}' (its name is part of the output names)"
                              if maps else "choose other --outputs or another -o")
        taken[path] = key


def _layer_words(key: str, lightings: list[str]) -> str:
    """'the albedo layer', 'the relit layer under sunset' for the output keys 'albedo', 'relit#001'."""
    name, _, index = key.partition("#")
    return f"the {name} layer" + (f" under {lightings[int(index)]}" if index else "")


def _masks_beside(photos: list[Path]) -> dict[Path, Path]:
    """{mask file: photo} for every existing image NAME_mask.EXT beside a photo NAME.EXT2:
    the photo's own mask by its name (the name the mask layer is written under), also when
    it was not given as an input. Each folder is listed once."""
    suffix = LAYERS["mask"].suffix
    by_folder: dict[Path, dict[str, list[str]]] = {}
    found = {}
    for photo in photos:
        folder = _resolved(photo.parent)
        if folder not in by_folder:
            by_folder[folder] = _images_by_stem(folder)
        for name in by_folder[folder].get(photo.stem + suffix, ()):
            found[photo.parent / name] = photo
    return found


def _images_by_stem(folder: Path) -> dict[str, list[str]]:
    """The names of the regular files in `folder` with an image extension, by stem; {} when it
    cannot be listed."""
    names: dict[str, list[str]] = {}
    try:
        with os.scandir(folder) as entries:
            for entry in entries:
                stem, ext = os.path.splitext(entry.name)
                if ext.lower() in IMAGE_EXTENSIONS and _is_regular_file(Path(entry.path)):
                    names.setdefault(stem, []).append(entry.name)
    except OSError:
        return {}
    return names


def _refuse_collisions(items: list[Item], read_only: Iterable[str | Path] = (),
                       masks: dict[Path, Path] | None = None) -> None:
    """No output may replace a file that is read (a photo, the map, the mask) nor a photo's
    own mask file (`masks`: {mask file: its photo}), whatever path names it: resolved paths
    (symlinks, '..') and, for files that exist, the inode (hard links). No two inputs may write
    one file."""
    protected = [(Path(mask), f"the mask file {mask} of the photo {photo}") for mask, photo in (masks or {}).items()]
    protected += [(path, f"the input {path}") for path in [item.input for item in items] + [Path(p) for p in read_only]]
    by_path, by_inode = {}, {}
    for path, words in protected:
        by_path.setdefault(_resolved(path), words)
        if (key := _inode(path)) is not None:
            by_inode.setdefault(key, words)
    seen: dict[Path, Path] = {}
    for item in items:
        for path in item.outputs.values():
            resolved = _resolved(path)
            overwritten = by_path.get(resolved) or by_inode.get(_inode(path))
            if overwritten is not None:
                raise OutputError(f"output would overwrite {overwritten}", path=path,
                                  fix="choose another -o: inputs and photos' own NAME_mask files are never written over")
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
        info = os.stat(path)
    except (OSError, ValueError):
        return None
    return info.st_dev, info.st_ino


def _resolved(path: Path) -> Path:
    """`path` made absolute with its symlinks followed as far as they lead, to compare paths;
    never raises. Path.resolve raises on a symlink loop (RuntimeError up to Python 3.12,
    OSError from 3.13) and on some names too long; os.path.realpath, not strict, stops there,
    and the error is reported where the file is used (`path_problem`)."""
    try:
        return Path(os.path.realpath(path))
    except (OSError, ValueError):
        return Path(os.path.abspath(path))


# What a path error means to a user, and what to do about it: errno -> (words, fix)
_PATH_ERRORS = {
    errno.ELOOP: ("a symlink loop (following its links never ends)", "point the link at a file, or remove it"),
    errno.ENAMETOOLONG: ("the name is too long for the filesystem", "use a shorter name"),
    errno.EACCES: ("permission denied (a folder on its path cannot be searched)",
                   "make the folders on its path searchable (chmod a+x)"),
    errno.ENOTDIR: ("a part of its path that should be a folder is a file", "check the path"),
}


def path_problem(path: Path) -> tuple[str, str] | None:
    """(what keeps `path` from being opened, the fix), in words, for the path errors a reader
    reports badly or not at all: a symlink loop, a dangling symlink, a name too long, a folder
    on its path that is a file or cannot be searched. None when the path leads to something, or
    to nothing at all (a missing file: its reader says so)."""
    try:
        os.stat(path)
        return None
    except FileNotFoundError:
        if not os.path.islink(path):
            return None
        try:
            target = os.readlink(path)
        except OSError:
            target = "?"
        return f"a dangling symlink (to {target}, which does not exist)", "point the link at a file, or remove it"
    except OSError as exc:
        return _PATH_ERRORS.get(exc.errno, (exc.strerror or str(exc), "check the path"))
    except ValueError:  # an embedded NUL byte
        return "not a valid path (it holds a NUL byte)", "check the path"


def path_error(path: Path, kind: type[RelightError] = InputError, fix: str | None = None) -> RelightError | None:
    """`path_problem` as a project error of `kind` naming the file (its fix, or `fix`), or None."""
    problem = path_problem(path)
    return None if problem is None else kind(problem[0], path=path, fix=fix or problem[1])


def unusable_items(items: list[Item]) -> dict[int, RelightError]:
    """{index: why} for the items that cannot be done, found before any work: an input or its
    own mask that cannot be opened (`path_problem`: InputError), an output that cannot be
    written where it goes (`output_problem`: OutputError). Each fails as its own item; the
    others are not concerned."""
    limits: dict[Path, tuple[int, int]] = {}  # per folder: the filesystem's name and path limits
    refused = {}
    for index, item in enumerate(items):
        if (error := _item_error(item, limits)) is not None:
            refused[index] = error
    return refused


def _item_error(item: Item, limits: dict[Path, tuple[int, int]]) -> RelightError | None:
    """The first reason `unusable_items` finds for this item, or None."""
    for path in (item.input, item.mask):
        if path is not None and (error := path_error(path)) is not None:
            return error
    return output_error(item, limits)


def output_error(item: Item, limits: dict[Path, tuple[int, int]] | None = None) -> OutputError | None:
    """The first of the item's outputs that cannot be written where it goes (`output_problem`),
    as an OutputError naming it, or None. `limits`: a cache of `_name_limits` by folder."""
    limits = {} if limits is None else limits
    for path in item.outputs.values():
        if path.parent not in limits:
            limits[path.parent] = _name_limits(path.parent)
        if (problem := output_problem(path, *limits[path.parent])) is not None:
            return OutputError(problem[0], path=path, fix=problem[1])
    return None


# The writers' temporary files add at most this to their staging file's name:
# ".<name>.tmp-<8 hex><ext>" (io.images._temporary_path), ".<name>.<8 hex>.tmp" (geometry.mesh)
WRITER_TEMPORARY_BYTES = 24


def output_problem(path: Path, name_max: int = 255, path_max: int = 4096) -> tuple[str, str] | None:
    """(what keeps an output file from being written at `path`, the fix), or None: a name too
    long once staged (`_staging_path` and the writers' temporary names are longer than the
    output's), a path error (`path_problem`: a symlink loop, a dangling link), or a folder or
    other non-file where the file goes. `name_max`, `path_max`: the filesystem's limits in bytes."""
    staged = _staging_path(path)
    longest = len(os.fsencode(staged.name)) + WRITER_TEMPORARY_BYTES
    if longest > name_max:
        return (f"the name is too long for the filesystem: writing it takes a temporary name of {longest} "
                f"bytes, and a name may have {name_max}", "give the photo a shorter name, or choose a shorter -o")
    if len(os.fsencode(os.path.abspath(staged))) + WRITER_TEMPORARY_BYTES >= path_max:
        return (f"the path is too long for the filesystem (a path may have {path_max} bytes)",
                "choose an -o with a shorter path")
    problem = path_problem(path)
    if problem is not None:
        return problem
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return None  # nothing there yet
    if stat.S_ISDIR(mode):
        return "a folder is where this output file goes", "move the folder away, or choose another -o"
    if not stat.S_ISREG(mode):
        return ("a pipe, device or socket is where this output file goes",
                "remove it, or choose another -o")
    return None


def _name_limits(folder: Path) -> tuple[int, int]:
    """(longest name, longest path) in bytes on the filesystem of `folder` or, while it does not
    exist yet, of the nearest folder above it that does; (255, 4096) where it cannot be asked."""
    for candidate in [folder, *Path(os.path.abspath(folder)).parents]:
        try:
            return os.pathconf(candidate, "PC_NAME_MAX"), os.pathconf(candidate, "PC_PATH_MAX")
        except (OSError, ValueError):
            continue
    return 255, 4096


def prepare_output_dirs(items: list[Item]) -> None:
    """Create the output folders and prove they are writable before any work starts."""
    folders = sorted({path.parent for item in items for path in item.outputs.values()})
    for folder in folders:
        try:
            folder.mkdir(parents=True, exist_ok=True)
            with tempfile.NamedTemporaryFile(dir=folder, prefix=".relight-probe-"):
                pass
        except OSError as exc:
            problem = path_problem(folder)
            raise OutputError(
                f"output folder cannot be written ({problem[0] if problem else exc.strerror or exc})",
                path=folder,
                fix="choose a writable -o",
            ) from exc


def existing_outputs(item: Item) -> list[Path]:
    """The item's outputs that exist as regular files (or links to one): those --skip-existing
    keeps and --overwrite replaces. Anything else where an output goes is refused before the
    run (`unusable_items`), never taken for a finished output."""
    return [path for path in item.outputs.values() if _is_regular_file(path)]


def _is_regular_file(path: Path) -> bool:
    try:
        return stat.S_ISREG(os.stat(path).st_mode)
    except (OSError, ValueError):
        return False


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
    A worker process that dies (the OOM killer, kill -9) fails only the item it held, and
    another takes its place (`relightcli.pool`). RelightWarnings raised while processing an item are
    recorded into its report. Staging files that ended runs left behind are removed first.

    An item's outputs appear together or not at all (see `relight_staged`). A KeyboardInterrupt
    (Ctrl-C, or the CLI's SIGTERM handler raising `Stopped`) stops the batch at once: the items
    in flight are discarded, the worker processes killed, and `Stopped` is raised carrying the
    reports (finished items as they are, the others marked stopped).
    """
    remove_dead_runs_staging(items)
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
    from relightcli.pool import Pool  # the pool's worker processes import this module

    pool = Pool(items, worker, min(workers, len(items)), skip_existing, overwrite)
    try:
        pool.run(on_done)
    except KeyboardInterrupt as interrupt:
        with _signals_ignored():  # a second Ctrl-C must not leave the workers running
            pool.stop()
        raise _stopped(interrupt, items, pool.reports) from None
    finally:
        pool.close()
    return pool.reports


def _committed_report(item: Item) -> ItemReport:
    """The report of an item whose files are all in place but whose worker died before its own
    report came back."""
    return ItemReport(str(item.input), {key: str(path) for key, path in item.outputs.items()})


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
        try:
            report = worker(replace(item, outputs=staged))
        except RelightError as exc:  # a writer's error names the file the user asked for
            final = {str(staged[key]): path for key, path in item.outputs.items()}.get(exc.path)
            if final is None:
                raise
            raise type(exc)(exc.message, path=final, fix=exc.fix) from exc
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
    atomic), same extension (the writers choose the format from it), marked with this run
    (`_staging_tag`): two runs writing one folder never share a staging file."""
    return path.with_name(f".{path.name}.relight-part-{_staging_tag()}{path.suffix}")


_STAGING_TAG = None  # made on first use (`_staging_tag`); a pool worker takes its parent's
# A staging file's name, or its writer's temporary file's ('..NAME.relight-part-...EXT.tmp-...')
_STAGING_NAME = re.compile(r"^\..*\.relight-part-(?P<host>[A-Za-z0-9]*)-(?P<pid>\d+)-[0-9a-f]{8}\.")


def _staging_tag() -> str:
    """This run's mark in its staging files' names: host, process id and a random token."""
    global _STAGING_TAG
    if _STAGING_TAG is None:
        _STAGING_TAG = f"{_host_label()}-{os.getpid()}-{secrets.token_hex(4)}"
    return _STAGING_TAG


def _host_label() -> str:
    return re.sub(r"[^A-Za-z0-9]", "", socket.gethostname().split(".")[0])[:32]


def remove_dead_runs_staging(items: list[Item]) -> None:
    """Remove the staging files, and their writers' temporary files, left in the items' output
    folders by runs on this host that have ended (a killed run cannot clean up after itself).
    A live run's are left alone, and so are another host's and older versions' unmarked ones:
    none of them can collide with this run's."""
    if os.name != "posix":
        return  # no way to ask whether a process lives without touching it
    host = _host_label()
    for folder in sorted({path.parent for item in items for path in item.outputs.values()}):
        try:
            names = os.listdir(folder)
        except OSError:
            continue
        for name in names:
            match = _STAGING_NAME.match(name)
            if match and match["host"] == host and not _process_alive(int(match["pid"])):
                with contextlib.suppress(OSError):  # gone already, or not ours to remove: harmless
                    os.unlink(os.path.join(folder, name))


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # another user's
    return True


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
