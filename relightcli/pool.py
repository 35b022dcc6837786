"""The local engine of a batch: a pool of spawned worker processes, each holding one worker
(models loaded once), fed one item at a time over a pipe of its own (`batch.run_items` with
workers > 1). A worker that dies fails only the item it held; workers die with their parent;
an item's files are renamed into place only with the pool's go-ahead, so a stop never leaves
half an item.
"""

from __future__ import annotations

import collections
import contextlib
import ctypes
import ctypes.util
import multiprocessing
import multiprocessing.connection
import os
import pickle
import signal
import sys
import threading
import time
import traceback
from pathlib import Path

from relightcli import batch
from relightcli.batch import (STOP_SIGNALS, Item, ItemReport, _committed_report, _discard_staged, _run_one,
                              _SignalDeferral, _staging_path, _staging_tag)
from relightcli.errors import EXIT_ITEMS_FAILED, RelightError


START_DEATHS_LIMIT = 3  # worker processes in a row ending before set-up: no more are started
COMMIT_WAIT_S = 10.0  # how long a stop waits for renames under way (milliseconds, but a hung disk)


class _PoolWorker:
    """One worker process as the pool sees it, with the pool's end of their pipe."""

    def __init__(self, process, conn):
        self.process, self.conn = process, conn
        self.ready = False  # set up: it takes items
        self.index: int | None = None  # the item it holds
        self.moving = False  # told to rename that item's files into place, not yet done
        self.ended = False  # its end of the pipe closed: the process has ended
        self.oom_kills = _oom_kill_count()  # the OOM killer's count when it started or took its item


class Pool:
    """The local engine: `size` spawned processes, each holding one `worker`, fed one item at a
    time over a pipe of its own.

    A worker that dies fails the item it held and no other, and a new one takes its place;
    after START_DEATHS_LIMIT deaths in a row before set-up, none is started and the items left
    fail. A worker asks before renaming an item's files into place and says when they all are
    (`_PoolCommit`): a stop never kills one half-way through an item's renames, and an item in
    place is reported ok even when its worker died before its report came back. SIGINT and
    SIGTERM are held while the books change, so a stop finds every item waiting, held by a
    worker, or done. The workers die with this process (`_die_with_parent`).
    """

    def __init__(self, items: list[Item], worker, size: int, skip_existing: bool, overwrite: bool):
        self.items, self.size = items, size
        self.context = multiprocessing.get_context("spawn")  # fork would break ONNX Runtime / OpenMP threads
        # The first message to every worker (`_serve_items`), pickled once for all
        self.setup_message = pickle.dumps((worker, skip_existing, overwrite, _staging_tag()))
        self.todo = collections.deque(range(len(items)))  # items not yet given to a worker
        self.reports: list[ItemReport | None] = [None] * len(items)
        self.left = len(items)  # items without a report
        self.in_place: set[int] = set()  # items whose files are all renamed into place
        self.workers: list[_PoolWorker] = []
        self.start_deaths, self.start_death_cause = 0, ""
        self.closing = False
        self._deferral = _SignalDeferral()

    def run(self, on_done) -> None:
        """Every item to a worker; `on_done(report)` as each finishes."""
        while self.left:
            with self._held():
                started = self._start_workers()
                done = [] if self.workers else self._fail_todo(*self._start_failure())
            for worker in started:  # may wait for the child to read it: a stop kills the child
                with contextlib.suppress(BrokenPipeError):  # it died starting: its sentinel tells
                    worker.conn.send_bytes(self.setup_message)
            if self.workers:
                ready = set(multiprocessing.connection.wait(
                    [w.conn for w in self.workers] + [w.process.sentinel for w in self.workers]))
                with self._held():
                    done += self._handle(ready)
            for index in done:
                if on_done is not None:
                    on_done(self.reports[index])

    @contextlib.contextmanager
    def _held(self):
        """SIGINT and SIGTERM held inside, raised at its end, once the books are straight."""
        with self._deferral:
            try:
                yield
            finally:
                self._deferral.deliver_pending()

    def _start_workers(self) -> list[_PoolWorker]:
        """Processes enough for the items left, at most `size`; none once too many died starting."""
        wanted = min(self.size, len(self.todo) + sum(w.index is not None for w in self.workers))
        started = []
        while len(self.workers) < wanted and self.start_deaths < START_DEATHS_LIMIT:
            conn, child_conn = self.context.Pipe()
            process = self.context.Process(target=_pool_worker_main, args=(child_conn,), name="relight-worker")
            try:
                with _stop_signals_blocked():
                    process.start()
            except OSError as exc:  # EAGAIN, ENOMEM: a process or memory limit
                conn.close()
                self._count_start_death(f"no worker process could be started ({exc.strerror or exc})")
                continue
            finally:
                child_conn.close()
            started.append(_PoolWorker(process, conn))
            self.workers.append(started[-1])
        return started

    def _handle(self, ready: set) -> list[int]:
        """What the ready workers sent, then their deaths; returns the items finished."""
        done = []
        for worker in list(self.workers):
            if worker.conn in ready or worker.process.sentinel in ready:
                done += self._receive(worker)
                if worker.ended or worker.process.sentinel in ready:
                    done += self._bury(worker)
        return done

    def _receive(self, worker: _PoolWorker) -> list[int]:
        """Every message waiting in the worker's pipe; sets `ended` when the pipe has closed."""
        done = []
        while not worker.ended and worker.conn.poll():
            try:
                message = worker.conn.recv()
            except (EOFError, ConnectionResetError):
                worker.ended = True
                break
            done += self._on_message(worker, *message)
        return done

    def _on_message(self, worker: _PoolWorker, kind: str, *args) -> list[int]:
        if self.closing and kind not in ("committed", "report"):
            return []  # no more work and no more commits: the workers are about to be killed
        if kind == "ready":
            worker.ready, self.start_deaths = True, 0
            self._give_work(worker)
        elif kind == "commit":
            worker.moving = True
            _send(worker, "go")
        elif kind == "committed":
            self.in_place.add(args[0])
            worker.moving = False
        elif kind == "report":
            index, report = args
            worker.index, worker.moving = None, False
            self._give_work(worker)
            return self._finish(index, report)
        elif kind == "setup failed":  # a user's error (a missing model): every item would fail alike
            return self._fail_todo(*args)
        elif kind == "crashed":  # a bug: raised here, as a batch in one process would raise it
            raise RuntimeError(f"a worker process failed:\n{args[0]}")
        else:
            raise RuntimeError(f"unknown message {kind!r} from a worker process")
        return []

    def _give_work(self, worker: _PoolWorker) -> None:
        """The next item, or None when none is left (the worker then ends)."""
        if self.closing:
            return
        if not self.todo:
            _send(worker, None)
            return
        worker.index, worker.oom_kills = self.todo.popleft(), _oom_kill_count()
        _send(worker, (worker.index, self.items[worker.index]))

    def _finish(self, index: int, report: ItemReport) -> list[int]:
        self.reports[index] = report
        self.left -= 1
        return [index]

    def _bury(self, worker: _PoolWorker) -> list[int]:
        """The worker process has ended: its item fails, unless its files were all in place."""
        self.workers.remove(worker)
        worker.process.join()
        worker.conn.close()
        cause = _death_cause(worker.process.exitcode, worker.oom_kills)
        worker.process.close()
        if not worker.ready:
            self._count_start_death(cause)
        if worker.index is None:
            return []
        return self._finish(worker.index, self._lost_item_report(worker, cause))

    def _lost_item_report(self, worker: _PoolWorker, cause: str) -> ItemReport:
        item = self.items[worker.index]
        staged = [path for path in item.outputs.values() if _staging_path(path).exists()]
        if worker.index in self.in_place or (worker.moving and not staged):
            return _committed_report(item)  # whole on disk; its own report died with the worker
        _discard_staged(item, leftovers=True)
        if worker.moving and len(staged) < len(item.outputs):
            error = (f"{item.input}: {cause} while moving its outputs into place: some are this "
                     "run's, the others as they were (rerun it with --overwrite)")
        else:
            error = (f"{item.input}: {cause} while relighting it; nothing of it was written "
                     f"({_death_fix(cause)})")
        return ItemReport(str(item.input), error=error, exit_code=EXIT_ITEMS_FAILED)

    def _count_start_death(self, cause: str) -> None:
        self.start_deaths += 1
        self.start_death_cause = cause

    def _start_failure(self) -> tuple[str, int]:
        return (f"not relit: {self.start_deaths} worker processes in a row ended before they were "
                f"ready, the last: {self.start_death_cause} (retry with --workers 1)", EXIT_ITEMS_FAILED)

    def _fail_todo(self, reason: str, code: int) -> list[int]:
        """Every item not yet given to a worker fails with `reason`."""
        done = []
        while self.todo:
            item = self.items[index := self.todo.popleft()]
            done += self._finish(index, ItemReport(str(item.input), error=f"{item.input}: {reason}",
                                                   exit_code=code))
        return done

    def stop(self) -> None:
        """Stop now (the caller ignores stop signals meanwhile): let the renames under way end,
        then kill every worker; the items left without a report are the stopped ones."""
        self.closing = True
        deadline = time.monotonic() + COMMIT_WAIT_S
        while (movers := [w for w in self.workers if w.moving]) and time.monotonic() < deadline:
            ready = multiprocessing.connection.wait(
                [w.conn for w in movers] + [w.process.sentinel for w in movers],
                timeout=deadline - time.monotonic())
            self._handle(set(ready))
        self.close()

    def close(self) -> None:
        """Kill the workers left (SIGKILL: they ignore SIGINT and SIGTERM), keep the reports they
        sent before, and remove what their unfinished items had staged. Idempotent."""
        self.closing = True
        for worker in self.workers:
            worker.process.kill()
        for worker in self.workers:
            worker.process.join()
            self._receive(worker)
            worker.conn.close()
            worker.process.close()
            if worker.index is None or self.reports[worker.index] is not None:
                continue
            if worker.index in self.in_place:
                self._finish(worker.index, _committed_report(self.items[worker.index]))
            else:
                _discard_staged(self.items[worker.index], leftovers=True)
        self.workers = []


def _send(worker: _PoolWorker, message) -> None:
    """Send to a worker; one that has just died cannot take it, and its sentinel tells."""
    with contextlib.suppress(BrokenPipeError, ConnectionResetError):
        worker.conn.send(message)


OOM_CAUSE = "the worker process ran out of memory (the kernel's OOM killer ended it)"


def _death_cause(exitcode: int | None, oom_kills_before: int | None) -> str:
    """Why a worker process ended, in words. Out of memory only on evidence: it was SIGKILLed
    and the OOM killer's count (`_oom_kill_count`) rose since it took its item."""
    if exitcode is None or exitcode >= 0:
        return f"the worker process exited unexpectedly (exit code {exitcode})"
    signum = -exitcode
    oom_kills = _oom_kill_count()
    if signum == signal.SIGKILL and None not in (oom_kills, oom_kills_before) and oom_kills > oom_kills_before:
        return OOM_CAUSE
    try:
        name = signal.Signals(signum).name
    except ValueError:
        name = "unknown"
    return f"the worker process died (signal {signum}, {name})"


def _death_fix(cause: str) -> str:
    if cause == OOM_CAUSE:
        return "rerun with fewer --workers or a lower --resolution, and --skip-existing"
    return "rerun with --skip-existing to do it again"


def _oom_kill_count() -> int | None:
    """How many processes the kernel's OOM killer has ended in this process's memory cgroup
    (cgroup v2 memory.events, v1 memory.oom_control), or on the whole host (/proc/vmstat)
    where the cgroup's count cannot be read; None where neither can (not Linux)."""
    for path in _oom_counter_files():
        try:
            for line in path.read_text().splitlines():
                key, _, value = line.partition(" ")
                if key == "oom_kill":
                    return int(value)
        except (OSError, ValueError):
            continue
    return None


def _oom_counter_files() -> list[Path]:
    try:
        groups = Path("/proc/self/cgroup").read_text().splitlines()  # "id:controllers:/path"
    except OSError:
        groups = []
    files = []
    for line in groups:
        _, controllers, group = line.split(":", 2)
        if not controllers:
            files.append(Path("/sys/fs/cgroup", group.lstrip("/"), "memory.events"))
        elif "memory" in controllers.split(","):
            files.append(Path("/sys/fs/cgroup/memory", group.lstrip("/"), "memory.oom_control"))
    return files + [Path("/proc/vmstat")]


@contextlib.contextmanager
def _stop_signals_blocked():
    """SIGINT and SIGTERM blocked in this thread inside the block (where the OS can block them).
    A process started inside inherits the mask, so a stop sent to the whole process group
    (Ctrl-C) waits until the worker ignores it (`_pool_worker_main`) instead of ending it with
    a traceback half-way through its start-up; this process gets what came once the block ends."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()  # first: starting the tracker unblocks both signals
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


class _PoolCommit:
    """The commit guard of a pool worker: asks the pool before item `index`'s files are renamed
    into place and tells it once they all are. The pool answers at once unless it is stopping;
    then it kills this worker, which has renamed nothing."""

    def __init__(self, conn, index: int):
        self.conn, self.index = conn, index

    def __enter__(self):
        self.conn.send(("commit", self.index))
        answer = self.conn.recv()
        if answer != "go":
            raise RuntimeError(f"the pool answered {answer!r} to a commit")
        return self

    def __exit__(self, exc_type, exc, traceback) -> None:
        if exc_type is None:
            self.conn.send(("committed", self.index))


def _pool_worker_main(conn) -> None:
    """A pool worker process (`Pool`): takes the worker from the pipe, sets it up, then
    relights the items that come one by one, until None comes or the pipe closes."""
    # Stopping is the parent's: Ctrl-C reaches the whole process group and SIGTERM may too
    # (systemd); a worker ending on its own would lose the item it holds. Both signals have
    # been blocked since this process started (`_stop_signals_blocked`): what came is dropped.
    for signum in STOP_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
    _die_with_parent()
    try:
        _serve_items(conn)
    except (EOFError, BrokenPipeError, ConnectionResetError):
        return  # the parent closed the pipe or died: there is nobody left to report to


def _serve_items(conn) -> None:
    worker, skip_existing, overwrite, tag = pickle.loads(conn.recv_bytes())
    batch._STAGING_TAG = tag  # the parent's: it removes what a dead worker staged
    try:
        worker.setup()
    except RelightError as exc:
        conn.send(("setup failed", str(exc), exc.exit_code))
        return
    except Exception:  # a bug: the parent raises it with this traceback
        conn.send(("crashed", traceback.format_exc()))
        return
    conn.send(("ready",))
    while (task := conn.recv()) is not None:
        index, item = task
        try:
            report = _run_one(item, worker, skip_existing, overwrite, commit_guard=_PoolCommit(conn, index))
        except Exception:  # a bug, as above
            conn.send(("crashed", traceback.format_exc()))
            return
        conn.send(("report", index, report))


PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def _die_with_parent() -> None:
    """End this worker process when the batch's process ends, however it ends (kill -9 too): a
    worker left behind keeps its memory and goes on writing outputs that nobody will report.
    On Linux the kernel sends SIGKILL (PR_SET_PDEATHSIG; if the parent died before the call,
    this process has been handed to another already); everywhere, a thread waits for the
    parent's end of the spawn pipe to close."""
    parent = multiprocessing.parent_process()
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
        if os.getppid() != parent.pid:
            os._exit(1)
    threading.Thread(target=_exit_after, args=(parent,), name="relight-parent-watch", daemon=True).start()


def _exit_after(parent) -> None:
    parent.join()  # returns once the parent has ended
    os._exit(1)
