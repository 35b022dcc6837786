"""Where the MakeHuman data lives: the shared archives, extracted once into a cache directory.

The archives (`makehuman_core_data.tar.xz`, `makehuman_assets.tar.xz`, CC0) sit in
`../shared/data/makehuman` relative to the repository root. They are extracted on first use into
`$RELIGHT_CACHE/makehuman` (default `export/.cache/makehuman`, gitignored): each archive goes to a
temporary directory first and is renamed into place, so a crashed or concurrent extraction never
leaves a half-filled cache behind.
"""

from __future__ import annotations

import os
import shutil
import tarfile
import tempfile
from pathlib import Path

from relightcli.errors import MissingDependencyError

REPO_ROOT = Path(__file__).resolve().parents[2]
DEFAULT_DATA_DIR = REPO_ROOT / ".." / "shared" / "data" / "makehuman"
ARCHIVES = {"core": "makehuman_core_data.tar.xz", "assets": "makehuman_assets.tar.xz"}


def data_dir() -> Path:
    """The folder holding `base.obj` and the two archives (env var RELIGHT_MAKEHUMAN_DATA
    overrides the default `../shared/data/makehuman`)."""
    return Path(os.environ.get("RELIGHT_MAKEHUMAN_DATA", DEFAULT_DATA_DIR)).resolve()


def cache_dir() -> Path:
    """The extraction cache: `$RELIGHT_CACHE/makehuman`, default `export/.cache/makehuman`."""
    root = os.environ.get("RELIGHT_CACHE")
    base = Path(root) if root else REPO_ROOT / "export" / ".cache"
    return (base / "makehuman").resolve()


def base_obj_path() -> Path:
    """Path of the hm08 base mesh; raises MissingDependencyError when absent."""
    path = data_dir() / "base.obj"
    if not path.is_file():
        raise MissingDependencyError(
            "MakeHuman base mesh not found", path=path,
            fix="put the shared data in ../shared/data/makehuman or set RELIGHT_MAKEHUMAN_DATA")
    return path


def _extract_atomically(archive: Path, target: Path) -> None:
    # Extract into a sibling temp dir, then rename: readers see all of it or nothing.
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}-", dir=target.parent))
    try:
        with tarfile.open(archive, "r:xz") as tar:
            tar.extractall(tmp, filter="data")
        try:
            os.rename(tmp, target)
        except OSError:
            if not target.is_dir():  # a concurrent extraction may have won the race
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def extracted(which: str) -> Path:
    """Root of the extracted archive `which` ("core" or "assets"), extracting on first use.

    Core files live under `<root>/makehuman/data/`, assets under `<root>/base/`.
    """
    if which not in ARCHIVES:
        raise ValueError(f"unknown archive {which!r}; expected one of {sorted(ARCHIVES)}")
    target = cache_dir() / which
    if target.is_dir():
        return target
    archive = data_dir() / ARCHIVES[which]
    if not archive.is_file():
        raise MissingDependencyError(
            "MakeHuman archive not found", path=archive,
            fix="put the shared data in ../shared/data/makehuman or set RELIGHT_MAKEHUMAN_DATA")
    _extract_atomically(archive, target)
    return target


def core_path(relative: str) -> Path:
    """A file of MakeHuman's core data, e.g. `core_path("rigs/default.mhskel")`."""
    return extracted("core") / "makehuman" / "data" / relative


def asset_path(relative: str) -> Path:
    """A file of the MakeHuman assets, e.g. `asset_path("poses/sit01.bvh")`."""
    return extracted("assets") / "base" / relative
