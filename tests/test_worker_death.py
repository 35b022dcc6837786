"""The local pool when processes die: a worker killed (the OOM killer, kill -9) fails the item
it held and no other, and is replaced; workers that die starting are not replaced forever;
workers die with their parent; a stop during the workers' start-up prints no traceback; two
runs writing one folder never share a staging file."""

from __future__ import annotations

import itertools
import json
import multiprocessing
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from relightcli import batch, pool
from relightcli.batch import Item, ItemReport
from relightcli.errors import MissingDependencyError

REPO = Path(__file__).resolve().parents[1]
linux_proc = pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="needs Linux /proc")


class FakeWorker:
    """A worker that writes a few bytes per output and acts on the photo's name: 'kill*'
    SIGKILLs its own process, 'exit*' exits with code 3, 'late*' dies once its outputs are in
    place, before the pool hears so, 'sleep*' sleeps for ten minutes, 'bug*' raises a ValueError. `setup_fault`:
    'kill' or 'missing' (a MissingDependencyError); each set-up leaves a file in `starts`."""

    def __init__(self, setup_fault: str | None = None, starts: Path | None = None):
        self.setup_fault, self.starts = setup_fault, starts

    def setup(self) -> None:
        _die_after_a_late_commit()
        if self.starts is not None:
            (self.starts / str(os.getpid())).touch()
        if self.setup_fault == "kill":
            os.kill(os.getpid(), signal.SIGKILL)
        if self.setup_fault == "missing":
            raise MissingDependencyError("model body.onnx is missing", fix="reinstall relightcli")

    def __call__(self, item: Item) -> ItemReport:
        global _CURRENT
        name = _CURRENT = item.input.stem
        if name.startswith("kill"):
            os.kill(os.getpid(), signal.SIGKILL)
        if name.startswith("exit"):
            os._exit(3)
        if name.startswith("sleep"):
            time.sleep(600)
        if name.startswith("bug"):
            raise ValueError("a bug in the worker")
        for staged in item.outputs.values():
            staged.write_bytes(name.encode())
        return ItemReport(str(item.input))


_CURRENT = None  # the photo a pool worker process is relighting (FakeWorker)


def _die_after_a_late_commit() -> None:
    """In a pool worker process: a 'late*' item's worker dies right after renaming its files
    into place, before it tells the pool (deterministic, unlike a thread watching the files)."""
    rename = pool._PoolCommit.__exit__

    def exit_then_die(commit, exc_type, exc, traceback):
        if exc_type is None and str(_CURRENT).startswith("late"):
            os.kill(os.getpid(), signal.SIGKILL)
        rename(commit, exc_type, exc, traceback)

    pool._PoolCommit.__exit__ = exit_then_die


def make_items(out: Path, names) -> list[Item]:
    return [Item(out.parent / "in" / f"{name}.png",
                 {"relit": out / f"{name}.png", "mask": out / f"{name}_mask.png"})
            for name in names]


def run_pool(tmp_path, names, worker=None, oom_kills=lambda: 0, monkeypatch=None):
    """Runs `names` on two workers; returns {name: report} and the names of the files in out."""
    if monkeypatch is not None:
        monkeypatch.setattr(pool, "_oom_kill_count", oom_kills)
    out = tmp_path / "out"
    out.mkdir()
    done = []
    reports = batch.run_items(make_items(out, names), worker or FakeWorker(), workers=2, on_done=done.append)
    assert sorted(r.input for r in done) == sorted(r.input for r in reports)  # on_done once per item
    assert [Path(r.input).stem for r in reports] == list(names)  # input order
    return {Path(r.input).stem: r for r in reports}, sorted(p.name for p in out.iterdir())


def written(names) -> list[str]:
    return sorted(f"{name}{suffix}.png" for name in names for suffix in ("", "_mask"))


def test_a_killed_worker_fails_only_its_item(tmp_path, monkeypatch):
    names = ["a0", "a1", "kill2", "a3", "a4", "a5"]
    reports, files = run_pool(tmp_path, names, monkeypatch=monkeypatch)
    error = reports["kill2"].error
    assert "the worker process died (signal 9, SIGKILL) while relighting it" in error
    assert "out of memory" not in error
    assert [name for name, r in reports.items() if r.error is None] == ["a0", "a1", "a3", "a4", "a5"]
    assert files == written(["a0", "a1", "a3", "a4", "a5"])  # the report matches the disk, no staging left
    assert batch.exit_code(list(reports.values())) == 1


def test_a_worker_killed_while_the_oom_killer_struck_ran_out_of_memory(tmp_path, monkeypatch):
    reports, _ = run_pool(tmp_path, ["a0", "kill1", "a2"], oom_kills=itertools.count().__next__,
                          monkeypatch=monkeypatch)
    assert "ran out of memory" in reports["kill1"].error and "fewer --workers" in reports["kill1"].error
    assert reports["a0"].error is None and reports["a2"].error is None


def test_a_worker_that_exits_fails_its_item_with_its_exit_code(tmp_path, monkeypatch):
    reports, files = run_pool(tmp_path, ["exit0", "a1", "a2"], monkeypatch=monkeypatch)
    assert "exited unexpectedly (exit code 3)" in reports["exit0"].error
    assert files == written(["a1", "a2"])


def test_an_item_in_place_before_its_worker_died_is_ok(tmp_path, monkeypatch):
    reports, files = run_pool(tmp_path, ["late0", "a1", "a2", "a3"], monkeypatch=monkeypatch)
    assert all(report.error is None for report in reports.values())
    assert files == written(["late0", "a1", "a2", "a3"])


def test_workers_that_die_starting_are_not_replaced_forever(tmp_path):
    starts = tmp_path / "starts"
    starts.mkdir()
    reports, files = run_pool(tmp_path, [f"a{k}" for k in range(6)], FakeWorker("kill", starts))
    assert files == []
    assert all("worker processes in a row ended before they were ready" in r.error and
               "signal 9" in r.error and "--workers 1" in r.error for r in reports.values())
    assert len(list(starts.iterdir())) <= pool.START_DEATHS_LIMIT + 1  # two workers, one more at most


def test_a_set_up_error_fails_every_item_with_its_message(tmp_path):
    reports, files = run_pool(tmp_path, ["a0", "a1", "a2"], FakeWorker("missing"))
    assert files == []
    assert all("model body.onnx is missing" in r.error for r in reports.values())
    assert batch.exit_code(list(reports.values())) == 3


def test_a_bug_in_a_worker_is_raised_with_its_traceback(tmp_path):
    with pytest.raises(RuntimeError, match="ValueError: a bug in the worker"):
        run_pool(tmp_path, ["a0", "bug1", "a2"])


def test_a_pool_that_cannot_start_processes_fails_its_items_clearly(tmp_path, monkeypatch):
    """EAGAIN from spawn (a process limit) used to end in a traceback."""
    def no_processes(self):
        raise BlockingIOError(11, "Resource temporarily unavailable")

    monkeypatch.setattr(multiprocessing.context.SpawnProcess, "start", no_processes)
    reports, files = run_pool(tmp_path, ["a0", "a1"])
    assert files == []
    assert all("no worker process could be started (Resource temporarily unavailable)" in r.error
               and "--workers 1" in r.error for r in reports.values())


# ------------------------------------------------------------------------ the parent's death
def processes_with(marker: str) -> list[str]:
    """Every live process whose environment holds `marker` (children inherit it)."""
    found = []
    for entry in Path("/proc").iterdir():
        try:
            if entry.name.isdigit() and marker.encode() in (entry / "environ").read_bytes():
                if (entry / "stat").read_text().rsplit(")", 1)[1].split()[0] != "Z":
                    found.append(f"{entry.name} {(entry / 'cmdline').read_bytes()[:100]!r}")
        except OSError:
            continue
    return found


def wait_until_gone(marker: str, bound_s: float = 60.0) -> list[str]:
    """The processes still holding `marker` once they are all gone, or after `bound_s`."""
    deadline = time.monotonic() + bound_s
    while (left := processes_with(marker)) and time.monotonic() < deadline:
        time.sleep(0.1)
    return left


POOL_DRIVER = """
import os, signal, sys
from pathlib import Path
from relightcli import batch, pool
from test_worker_death import FakeWorker, make_items

# One worker sleeps in its item; this process dies (kill -9) when the other's item is done.
out = Path(sys.argv[1])
out.mkdir()
batch.run_items(make_items(out, ["sleep0", "a1"]), FakeWorker(), workers=2,
                on_done=lambda report: os.kill(os.getpid(), signal.SIGKILL))
"""


def start_driver(code: str, *args: str) -> tuple[subprocess.Popen, str]:
    marker = uuid.uuid4().hex
    env = dict(os.environ, RELIGHT_DEATH_TEST=marker,
               PYTHONPATH=os.pathsep.join([str(REPO), str(REPO / "tests")]))
    return subprocess.Popen([sys.executable, "-c", code, *args], cwd=REPO, env=env), marker


@linux_proc
def test_workers_die_with_their_parent(tmp_path):
    """A SIGKILLed batch used to leave its workers (and the resource tracker) running forever."""
    driver, marker = start_driver(POOL_DRIVER, str(tmp_path / "out"))
    assert driver.wait(timeout=300) == -signal.SIGKILL
    assert wait_until_gone(marker) == []


WATCH_DRIVER = """
import multiprocessing, os, signal, sys, threading, time
from relightcli import batch, pool


def watched_child(ready):
    # Only the portable watch: no PR_SET_PDEATHSIG in this child
    threading.Thread(target=pool._exit_after, args=(multiprocessing.parent_process(),), daemon=True).start()
    ready.set()
    time.sleep(600)


if __name__ == "__main__":
    context = multiprocessing.get_context("spawn")
    ready = context.Event()
    context.Process(target=watched_child, args=(ready,)).start()
    ready.wait(300)
    os.kill(os.getpid(), signal.SIGKILL)
"""


@linux_proc
def test_the_portable_watch_ends_a_worker_whose_parent_died(tmp_path):
    script = tmp_path / "watch_driver.py"  # spawn needs the main module as a file
    script.write_text(WATCH_DRIVER)
    driver, marker = start_driver(f"import runpy; runpy.run_path({str(script)!r}, run_name='__main__')")
    assert driver.wait(timeout=300) == -signal.SIGKILL
    assert wait_until_gone(marker) == []


# ------------------------------------------------------------------- a stop during start-up
@linux_proc
@pytest.mark.parametrize("how, expected", [("SIGTERM", 143), ("Ctrl-C", 130)])
def test_a_stop_while_the_workers_start_prints_no_traceback(tmp_path, how, expected):
    from tests.test_batch_stop import make_photos

    folder = make_photos(tmp_path, 4)
    out = tmp_path / "out"
    marker = uuid.uuid4().hex
    proc = subprocess.Popen(
        [sys.executable, "-m", "relightcli", str(folder), "--hdr", str(tmp_path / "env.hdr"), "-o", str(out),
         "--outputs", "mask", "--workers", "2", "--json"],
        cwd=REPO, env=dict(os.environ, RELIGHT_DEATH_TEST=marker), stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        while proc.poll() is None and not any("spawn_main" in p for p in processes_with(marker)):
            time.sleep(0.005)  # until the first worker process is starting
        if how == "Ctrl-C":
            os.killpg(proc.pid, signal.SIGINT)
        else:
            proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == expected, stderr
    assert "Traceback" not in stderr and "Error" not in stderr, stderr
    report = json.loads(stdout)
    assert report["ok"] + report.get("stopped", 0) == 4 and report["failed"] == 0
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []
    assert wait_until_gone(marker) == []


# -------------------------------------------------------------------------- staging names
def staging_name_elsewhere(path: Path) -> str:
    code = ("from pathlib import Path; from relightcli.batch import _staging_path; "
            f"print(_staging_path(Path({str(path)!r})))")
    return subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True,
                          check=True).stdout.strip()


def test_two_runs_never_share_a_staging_file(tmp_path):
    """Two runs writing one folder used to stage to the same name: one run's rename took the
    other's file, which then failed 'cannot move the finished output into place'."""
    path = tmp_path / "photo.png"
    names = {str(batch._staging_path(path)), staging_name_elsewhere(path), staging_name_elsewhere(path)}
    assert len(names) == 3
    assert all(Path(name).parent == tmp_path and Path(name).name.startswith(".photo.png.relight-part-")
               and name.endswith(".png") for name in names)


def test_only_ended_runs_staging_files_are_removed(tmp_path):
    ended = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                           text=True, check=True).stdout.strip()
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
    try:
        host = batch._host_label()
        leftovers = {
            "ended": f".a.png.relight-part-{host}-{ended}-0123abcd.png",
            "ended writer's": f"..a.png.relight-part-{host}-{ended}-0123abcd.png.tmp-89ab4567.png",
            "live": f".a.png.relight-part-{host}-{live.pid}-0123abcd.png",
            "this run's": batch._staging_path(tmp_path / "a.png").name,
            "another host's": f".a.png.relight-part-{host}x-{ended}-0123abcd.png",
            "unmarked": ".a.png.relight-part.png",
            "a photo": "a.png",
        }
        for name in leftovers.values():
            (tmp_path / name).write_bytes(b"")
        batch.remove_dead_runs_staging([Item(Path("in.png"), {"relit": tmp_path / "a.png"})])
        kept = {key for key, name in leftovers.items() if (tmp_path / name).exists()}
    finally:
        live.kill()
        live.wait()
    assert kept == {"live", "this run's", "another host's", "unmarked", "a photo"}
