"""The image's entrypoint: start `relight` as the owner of the folders it is given.

tini (PID 1) starts this as root. It picks the user the files on the host should belong to,
drops to it (groups, gid, uid, in that order) and execs `relight` with the same arguments,
which then runs as tini's only child. Started with `docker run --user`, it execs at once.

Who to become, from the paths on the command line as the container sees them:
  1. the owner of the output (-o), or of its nearest existing parent folder, unless root;
  2. else (Docker created a missing out/ as root) the owner of the first named path that
     exists and is not root's: the input folder, the map; an empty root-owned output folder
     is then handed to that user (chown), since Docker made it for this run;
  3. else, when the output's folder exists and every named path is root's, root: the caller
     is root on the host and would own the files anyway;
  4. else (no paths: --help, info) the image's own user, uid 10001.

SIGTERM (docker stop) is blocked from this script's first line until relight's `main` takes
it (the mask survives exec): one arriving while relight's interpreter starts waits for the
handler there, which then exits 143 with a message, instead of ending it without one.

Standard library only, run with `python -I`: nothing of the caller's environment changes
what runs as root.
"""

from __future__ import annotations

import os
import pwd
import signal
import sys
from pathlib import Path
from typing import NamedTuple

IMAGE_USER = (10001, 10001)
OUTPUT_FLAGS = ("-o", "--output")


def output_argument(argv: list[str]) -> str | None:
    """The value of -o / --output as argparse reads it (-o X, -oX, -o=X, --output X, --output=X);
    the last one wins, as in argparse. None when there is none."""
    found = None
    for index, arg in enumerate(argv):
        if arg == "--":
            break
        if arg in OUTPUT_FLAGS and index + 1 < len(argv):
            found = argv[index + 1]
        elif arg.startswith("--output="):
            found = arg.split("=", 1)[1]
        elif arg.startswith("-o") and not arg.startswith("--") and len(arg) > 2:
            found = arg[2:].removeprefix("=")
    return found


def nearest_existing(path: Path) -> Path | None:
    """`path` itself when it exists, else its closest parent that does."""
    for candidate in (path, *path.parents):
        if candidate.exists():
            return candidate
    return None


class Identity(NamedTuple):
    uid: int
    gid: int
    adopt: Path | None = None  # an empty root-owned output folder to chown to uid:gid first


def choose_identity(argv: list[str], cwd: Path, stat=os.stat) -> Identity:
    """Whom to run `relight argv` as (rules 1-4 of the module docstring). `stat` is os.stat;
    tests pass one that reports other owners."""
    def owner(path: Path) -> tuple[int, int]:
        info = stat(path)
        return info.st_uid, info.st_gid

    output = output_argument(argv)
    output_folder = None if output is None else nearest_existing(cwd / output)
    if output_folder is not None and owner(output_folder)[0] != 0:
        return Identity(*owner(output_folder))
    named = [cwd / arg for arg in argv if arg and not arg.startswith("-") and arg != output]
    existing = [path for path in named if path.exists()]
    for path in existing:
        if owner(path)[0] != 0:
            fresh = output_folder is not None and output_folder.is_dir() and not any(output_folder.iterdir())
            return Identity(*owner(path), adopt=output_folder if fresh else None)
    if output_folder is not None and existing:
        return Identity(0, 0)
    return Identity(*IMAGE_USER)


def drop_privileges(uid: int, gid: int) -> None:
    """Become uid:gid for good: supplementary groups first (only root may set them), then the
    group, then the user; HOME follows (the user's home when it has one, else /)."""
    os.setgroups([gid] if uid != 0 else [0])
    os.setgid(gid)
    os.setuid(uid)
    if os.getuid() != uid or os.geteuid() != uid or os.getgid() != gid:
        raise RuntimeError(f"could not become {uid}:{gid}")
    try:
        os.environ["HOME"] = pwd.getpwuid(uid).pw_dir
    except KeyError:  # a host user the image does not know
        os.environ["HOME"] = "/"


def main(argv: list[str]) -> None:
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})  # relight's main unblocks it
    if os.geteuid() == 0:
        uid, gid, adopt = choose_identity(argv, Path.cwd())
        if adopt is not None:
            os.chown(adopt, uid, gid)
        if uid != 0:
            drop_privileges(uid, gid)
    os.execvp("relight", ["relight", *argv])


if __name__ == "__main__":
    main(sys.argv[1:])
