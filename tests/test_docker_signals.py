"""`docker stop` at any moment (issue 51): SIGTERM ends `relight` with 143, no traceback, no
temporary or half-written file, and nothing written to ~ (ONNX Runtime's telemetry id).

In the image tini is PID 1 and hands SIGTERM on; here the signal goes to the process itself.
Before Python reaches `main` (interpreter start, the first imports) SIGTERM's default action
ends the process, which shells, tini and Docker report as 143, with nothing written; from the
first line of `main` on, a handler unwinds (exit status 143, a message)."""

from __future__ import annotations

import contextlib
import importlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from relightcli import cli
from tests.test_batch_stop import make_photos

REPO = Path(__file__).resolve().parents[1]
# Tiny RGBA photos (the alpha is the mask, so no mask net) at a tiny working resolution: about
# 0.1 s an item, so 60 of them run well past the last delay below on any machine.
FAST = ["--outputs", "mask,albedo,light", "--albedo", "net", "--resolution", "64", "--workers", "1"]
LAYERS = ("_mask.png", "_albedo.png", "_light.hdr")


def relight_command() -> list[str]:
    """The console script next to this Python (what `relight` runs), else `python -m relightcli`."""
    script = Path(sys.executable).parent / "relight"
    return [str(script)] if script.is_file() else [sys.executable, "-m", "relightcli"]


def make_job(root: Path, count: int) -> list[str]:
    folder = make_photos(root, count)
    return [str(folder), "--hdr", str(root / "env.hdr"), "-o", str(root / "out"), *FAST]


def start(root: Path, args: list[str], block_sigterm: bool = False) -> subprocess.Popen:
    """`relight args` with its own empty HOME and no cache folder of the caller's."""
    (root / "home").mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith("XDG_") and k != "ORT_DISABLE_TELEMETRY"}
    env["HOME"] = str(root / "home")
    preexec = (lambda: signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})) if block_sigterm else None
    return subprocess.Popen(relight_command() + args, cwd=root, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, preexec_fn=preexec)


def stop(proc: subprocess.Popen) -> tuple[str, str]:
    proc.send_signal(signal.SIGTERM)
    try:
        return proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def assert_stopped_cleanly(root: Path, proc: subprocess.Popen, stderr: str) -> None:
    if proc.returncode == -signal.SIGTERM:  # before `main`: the default action, nothing ran
        assert stderr == ""
    else:
        assert proc.returncode == 143, stderr
        assert "stopped by SIGTERM" in stderr or "stopped (rerun with --skip-existing" in stderr, stderr
    assert "Traceback" not in stderr, stderr
    out = root / "out"
    files = sorted(p.name for p in out.rglob("*")) if out.exists() else []
    assert not [name for name in files if name.startswith(".")], files  # no staging/temporary file
    stems = {name.split("_")[0] for name in files}
    for stem in stems:  # an item is complete or absent
        assert all(f"{stem}{layer}" in files for layer in LAYERS), files
    assert list((root / "home").rglob("*")) == []  # nothing under ~


def test_sigterm_pending_from_the_start_exits_143(tmp_path):
    """The signal arrives before the interpreter runs (held by a blocked mask, as a parent can
    leave it): the handler installed by main's first line takes it, before any work."""
    proc = start(tmp_path, make_job(tmp_path, 2), block_sigterm=True)
    stdout, stderr = stop(proc)
    assert proc.returncode == 143, stderr
    assert stderr.strip() == "relight: stopped by SIGTERM"
    assert not (tmp_path / "out").exists()  # planned, but nothing created
    assert list((tmp_path / "home").rglob("*")) == []


@pytest.mark.slow
@pytest.mark.parametrize("delay", [0.0, 0.05, 0.2, 0.5, 0.8, 1.1, 1.5, 3.0, 6.0])  # start-up, then the batch
def test_sigterm_at_any_moment_of_a_run(tmp_path, delay):
    proc = start(tmp_path, make_job(tmp_path, 60))
    time.sleep(delay)
    assert proc.poll() is None, "the run ended before the signal: give it more items"
    stdout, stderr = stop(proc)
    print(f"delay {delay:.2f} s: exit {proc.returncode}, {stderr.strip().splitlines()[-1:] or ''}")
    assert_stopped_cleanly(tmp_path, proc, stderr)


def test_a_stopped_program_ends_at_once_but_runs_its_atexit_callbacks(tmp_path):
    """main(None) ends a stopped process itself, skipping the interpreter's teardown; what
    atexit holds still runs and the streams are flushed."""
    program = ("import atexit, sys\n"
               "atexit.register(print, 'atexit ran')\n"
               "from relightcli.cli import main\n"
               "sys.argv = ['relight', 'info']\n"
               "print('before main')\n"  # buffered: a pipe is no terminal
               "sys.exit(main())\n")
    proc = subprocess.Popen([sys.executable, "-c", program], cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM}))
    stdout, stderr = stop(proc)
    assert proc.returncode == 143, stderr
    assert stdout.splitlines() == ["before main", "atexit ran"]
    assert stderr.strip() == "relight: stopped by SIGTERM"


def test_relight_info_writes_nothing_to_home_and_does_not_warn(tmp_path):
    proc = start(tmp_path, ["info"])
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 0, stderr
    assert stderr == ""  # no telemetry warning, no colour codes
    assert list((tmp_path / "home").rglob("*")) == []


# --- in-process: the handler main installs ------------------------------------------------

def test_sigterm_in_any_phase_unwinds_through_finally_and_returns_143(monkeypatch, capsys):
    cleaned = []

    def run_info(args):
        try:
            signal.raise_signal(signal.SIGTERM)
        finally:
            signal.raise_signal(signal.SIGTERM)  # a second one must not cut the clean-up short
            cleaned.append(True)
        raise AssertionError("SIGTERM did not stop the command")

    before = signal.getsignal(signal.SIGTERM)
    monkeypatch.setattr(cli, "run_info", run_info)
    assert cli.main(["info"]) == 143
    assert cleaned == [True]
    assert capsys.readouterr().err.strip() == "relight: stopped by SIGTERM"
    assert signal.getsignal(signal.SIGTERM) == before  # main leaves the process as it found it


def test_sigterm_while_reporting_still_returns_143(monkeypatch, capsys):
    """After the command's own handlers (printing the summary) main still catches it."""
    def run_command(argv):
        signal.raise_signal(signal.SIGTERM)
        return 0

    monkeypatch.setattr(cli, "_run_command", run_command)
    assert cli.main(["info"]) == 143
    assert "stopped by SIGTERM" in capsys.readouterr().err


def test_help_lists_the_signal_exit_codes(capsys):
    assert cli.main(["--help"]) == 0
    epilog = capsys.readouterr().out.split("exit codes:")[1]
    assert "130" in epilog and "143" in epilog and "SIGTERM" in epilog


class _StopsWhileFinalized:
    """Raises `signum` while the garbage collector finalizes it: Python swallows an exception
    raised in a __del__ ("Exception ignored in ...")."""

    def __init__(self, signum):
        self.signum = signum

    def __del__(self):
        signal.raise_signal(self.signum)  # the handler runs here, inside __del__


def _wait_for_the_stop():
    for _ in range(500):  # the stop ends this loop; 5 s only bound a failure
        time.sleep(0.01)
    raise AssertionError("the stop was lost")


def test_a_sigterm_swallowed_by_a_finalizer_still_stops(monkeypatch, capsys):
    def run_info(args):
        _StopsWhileFinalized(signal.SIGTERM)
        _wait_for_the_stop()

    monkeypatch.setattr(cli, "run_info", run_info)
    assert cli.main(["info"]) == 143
    assert capsys.readouterr().err.strip() == "relight: stopped by SIGTERM"


def test_a_batch_stop_swallowed_by_a_finalizer_still_stops(monkeypatch, capsys):
    """The same inside a batch, where the batch's own handler raises batch.Stopped."""
    def run_info(args):
        with cli._signals_stop_batch():
            _StopsWhileFinalized(signal.SIGTERM)
            _wait_for_the_stop()

    monkeypatch.setattr(cli, "run_info", run_info)
    assert cli.main(["info"]) == 143


def _module_swallowing_a_stop(folder: Path, name: str) -> None:
    """A module that, like trimesh's optional imports, guards an import with `except
    BaseException`, the imported module raising SIGTERM while it loads."""
    (folder / f"{name}_inner.py").write_text("import signal\nsignal.raise_signal(signal.SIGTERM)\n")
    (folder / f"{name}.py").write_text(f"try:\n    import {name}_inner\nexcept BaseException as exc:\n"
                                       "    swallowed = exc\n")


@pytest.mark.parametrize("in_batch", [False, True])
def test_a_sigterm_during_a_guarded_import_still_stops(monkeypatch, tmp_path, capsys, in_batch):
    name = f"guarded_{'batch' if in_batch else 'cli'}"
    _module_swallowing_a_stop(tmp_path, name)
    monkeypatch.syspath_prepend(str(tmp_path))

    def run_info(args):
        with cli._signals_stop_batch() if in_batch else contextlib.nullcontext():
            importlib.import_module(name)
            _wait_for_the_stop()

    monkeypatch.setattr(cli, "run_info", run_info)
    assert cli.main(["info"]) == 143
    assert "stopped by SIGTERM" in capsys.readouterr().err


@pytest.mark.parametrize("args, code", [(["info"], 0), (["missing.jpg", "--hdr", "missing.hdr", "-o", "out.png"], 4)])
def test_every_program_run_ends_without_the_teardown_keeping_its_exit_code_atexit_and_output(tmp_path, args, code):
    """main(None) ends every run itself (issue 50: the interpreter's teardown took 0.24-0.32 s
    of a one-photo run): the exit code, what atexit holds and the buffered output survive."""
    program = ("import atexit, sys\n"
               "atexit.register(print, 'atexit ran')\n"
               "from relightcli.cli import main\n"
               f"sys.argv = ['relight', *{args!r}]\n"
               "print('before main')\n"
               "main()\n"
               "print('after main')\n")  # not reached: main(None) ends the process
    proc = subprocess.run([sys.executable, "-c", program], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert proc.returncode == code, proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[0] == "before main" and lines[-1] == "atexit ran" and "after main" not in lines
    assert len(lines) > 2 or code != 0  # relight info printed its report
