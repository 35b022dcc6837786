"""The image's entrypoint (docker/entrypoint.py, issue 51): whom it runs `relight` as, decided
on temporary folders with owners reported by a fake stat, and the privilege drop itself."""

from __future__ import annotations

import importlib.util
import os
import signal
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

REPO = Path(__file__).resolve().parents[1]
SPEC = importlib.util.spec_from_file_location("relight_entrypoint", REPO / "docker" / "entrypoint.py")
entrypoint = importlib.util.module_from_spec(SPEC)
SPEC.loader.exec_module(entrypoint)

ROOT, USER, OTHER = (0, 0), (1000, 1000), (43210, 43211)  # OTHER: no passwd entry


def owned(owners: dict[Path, tuple[int, int]]):
    """os.stat, but reporting these owners (anything else: root's, as in a fresh container)."""
    def stat(path):
        os.stat(path)  # a missing path still raises
        uid, gid = owners.get(Path(path), ROOT)
        return SimpleNamespace(st_uid=uid, st_gid=gid)
    return stat


@pytest.fixture
def mounts(tmp_path):
    """/in with a photo and a map, and /out, as the container sees them."""
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "photo.jpg").write_bytes(b"")
    (tmp_path / "in" / "sky.hdr").write_bytes(b"")
    (tmp_path / "out").mkdir()
    return tmp_path


def readme_command(root: Path) -> list[str]:
    return [str(root / "in"), "--hdr", str(root / "in" / "sky.hdr"), "-o", str(root / "out")]


@pytest.mark.parametrize("argv, expected", [
    (["a.jpg", "-o", "x"], "x"),
    (["a.jpg", "--output", "x"], "x"),
    (["a.jpg", "--output=x"], "x"),
    (["a.jpg", "-ox"], "x"),
    (["a.jpg", "-o=x"], "x"),
    (["a.jpg", "-o", "x", "-o", "y"], "y"),  # argparse keeps the last
    (["a.jpg", "--outputs", "relit,albedo"], None),
    (["info"], None),
])
def test_output_argument(argv, expected):
    assert entrypoint.output_argument(argv) == expected


def test_out_owned_by_the_user(mounts):
    stat = owned({mounts / "out": USER})
    assert entrypoint.choose_identity(readme_command(mounts), Path("/work"), stat) == (*USER, None)


def test_out_created_by_docker_as_root_is_handed_to_the_inputs_owner(mounts):
    stat = owned({mounts / "in": USER, mounts / "in" / "sky.hdr": USER})
    assert entrypoint.choose_identity(readme_command(mounts), Path("/work"), stat) == (*USER, mounts / "out")


def test_a_root_output_folder_with_files_is_not_taken_over(mounts):
    (mounts / "out" / "old.png").write_bytes(b"")
    stat = owned({mounts / "in": USER})
    assert entrypoint.choose_identity(readme_command(mounts), Path("/work"), stat) == (*USER, None)


def test_the_output_folder_wins_over_the_inputs(mounts):
    stat = owned({mounts / "out": OTHER, mounts / "in": USER})
    assert entrypoint.choose_identity(readme_command(mounts), Path("/work"), stat) == (*OTHER, None)


def test_a_missing_output_takes_its_nearest_folder(mounts):
    stat = owned({mounts / "out": USER})
    argv = [str(mounts / "in" / "photo.jpg"), "--hdr", str(mounts / "in" / "sky.hdr"),
            "-o", str(mounts / "out" / "new" / "photo.png")]
    assert entrypoint.choose_identity(argv, Path("/work"), stat) == (*USER, None)


def test_relative_paths_are_read_from_the_working_folder(mounts):
    stat = owned({mounts / "out": USER})
    argv = ["in/photo.jpg", "--hdr", "in/sky.hdr", "-o", "out/photo.png"]
    assert entrypoint.choose_identity(argv, mounts, stat) == (*USER, None)


def test_everything_roots_stays_root(mounts):
    """A root user on the host: the files are root's natively too."""
    assert entrypoint.choose_identity(readme_command(mounts), Path("/work"), owned({})) == (*ROOT, None)


def test_no_paths_runs_as_the_image_user(tmp_path):
    assert entrypoint.choose_identity(["--help"], tmp_path, owned({}))[:2] == entrypoint.IMAGE_USER
    assert entrypoint.choose_identity(["info"], tmp_path, owned({}))[:2] == entrypoint.IMAGE_USER


def test_missing_inputs_and_a_root_output_run_as_the_image_user(mounts):
    argv = [str(mounts / "absent.jpg"), "--hdr", str(mounts / "absent.hdr"), "-o", str(mounts / "out")]
    assert entrypoint.choose_identity(argv, Path("/work"), owned({}))[:2] == entrypoint.IMAGE_USER


@pytest.mark.skipif(os.geteuid() != 0, reason="only root can change its uid")
def test_drop_privileges_for_good(tmp_path):
    """In a child: groups, gid and uid become the chosen ones, the file it writes is theirs,
    and root cannot be taken back."""
    tmp_path.chmod(0o777)
    folder = os.open(tmp_path, os.O_RDONLY)  # pytest's base folder is root's alone: no path lookup after the drop
    pid = os.fork()
    if pid == 0:  # the child reports through its exit status only
        try:
            entrypoint.drop_privileges(*OTHER)
            os.close(os.open("written", os.O_CREAT | os.O_WRONLY, 0o644, dir_fd=folder))
            ok = os.getgroups() == [OTHER[1]] and os.environ["HOME"] == "/"
            try:
                os.setuid(0)
                ok = False
            except PermissionError:
                pass
            os._exit(0 if ok else 1)
        except BaseException:  # noqa: BLE001 - a forked child must never return into pytest
            os._exit(2)
    _, status = os.waitpid(pid, 0)
    os.close(folder)
    assert os.waitstatus_to_exitcode(status) == 0
    info = (tmp_path / "written").stat()
    assert (info.st_uid, info.st_gid) == OTHER


def test_it_execs_relight_with_sigterm_held_for_relights_handler(tmp_path):
    """The entrypoint run for real, with a stand-in `relight` on PATH reporting its uid, blocked
    signals and arguments. Every named path is the caller's (root's, when the tests run as
    root), so it stays that user; SIGTERM stays blocked across exec, SIGINT does not."""
    fake = tmp_path / "relight"
    fake.write_text(f"#!{sys.executable}\n"
                    "import os, sys\n"
                    "print(os.getuid())\n"
                    "print(next(l for l in open('/proc/self/status') if l.startswith('SigBlk')).split()[1])\n"
                    "print(' '.join(sys.argv[1:]))\n")
    fake.chmod(0o755)
    (tmp_path / "in").mkdir()
    argv = [str(tmp_path / "in"), "--hdr", str(tmp_path / "in"), "-o", str(tmp_path / "out")]
    run = subprocess.run([sys.executable, "-I", str(REPO / "docker" / "entrypoint.py"), *argv],
                         cwd=tmp_path, env={"PATH": f"{tmp_path}:/usr/bin:/bin"},
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    uid, blocked, args = run.stdout.splitlines()
    assert int(uid) == os.geteuid()
    mask = int(blocked, 16)
    assert mask & (1 << (signal.SIGTERM - 1)) and not mask & (1 << (signal.SIGINT - 1))
    assert args == " ".join(argv)
