"""The Ray engine of a batch (`relight ... --engine ray`): the items as a Ray Data dataset, one
actor per worker holding the models, the same per-item staging and reports as the local engine.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import logging
import signal
import threading
import time
from dataclasses import asdict
from pathlib import Path

from relightcli.batch import (STOP_SIGNALS, Item, ItemReport, Stopped, _committed_report, _run_one, _signals_ignored,
                              _stopped, remove_dead_runs_staging)
from relightcli.errors import MissingDependencyError, RelightError, UsageError


RAY_TIMEOUT_S = 30.0  # how long a Ray cluster named by --address may take to answer


def run_items_ray(
    items: list[Item],
    worker,
    *,
    workers: int,
    threads_per_worker: int,
    address: str | None = None,
    skip_existing: bool = False,
    overwrite: bool = False,
    timeout_s: float = RAY_TIMEOUT_S,
) -> list[ItemReport]:
    """The same job on Ray Data: a pool of `workers` stateful actors, each holding one `worker`
    (models loaded once per actor), fed file paths; decoding happens inside the actors with our
    own I/O (Ray's image reader drops EXIF orientation, 16-bit and EXR).

    address: an existing cluster ("auto", "ray://host:10001"), which must answer within
    `timeout_s` seconds; None starts a local instance with `workers * threads_per_worker` CPUs.
    On a cluster, inputs and outputs must live on a filesystem every node sees at the same
    path. Reports come back in input order. A KeyboardInterrupt stops the batch as in
    `run_items`: `Stopped` carries the reports of the items done, the others marked stopped.
    """
    ray = _import_ray(address)
    started_here = not ray.is_initialized()
    if started_here:
        _start_ray(ray, address, workers * threads_per_worker, timeout_s)
    reports: list[ItemReport | None] = [None] * len(items)
    start_ns = time.time_ns()
    try:
        remove_dead_runs_staging(items)
        for row in _ray_dataset(ray, items, worker, workers, threads_per_worker, skip_existing,
                                overwrite).iter_rows():  # each report as its item finishes
            reports[int(row["index"])] = ItemReport(**json.loads(str(row["report"])))
    except KeyboardInterrupt as interrupt:
        _shut_down_ray(ray, items, started_here)
        for index, item in enumerate(items):
            if reports[index] is None and _written_since(item, start_ns):
                reports[index] = _committed_report(item)  # in place before its report came back
        raise _stopped(interrupt, items, reports) from None
    finally:
        _shut_down_ray(ray, items, started_here)
    missing = [items[i].input for i, r in enumerate(reports) if r is None]
    if missing:
        raise RelightError(f"Ray returned no result for {len(missing)} item(s), e.g. {missing[0]}")
    return reports


def _shut_down_ray(ray, items: list[Item], started_here: bool) -> None:
    """End the Ray instance this batch started (its actors killed), then remove what those
    actors had staged on this machine. Idempotent."""
    if started_here and ray.is_initialized():
        with _signals_ignored():  # a second Ctrl-C must not leave Ray's processes running
            ray.shutdown()
        remove_dead_runs_staging(items)


def _written_since(item: Item, start_ns: int) -> bool:
    """Every output of `item` is a file written since `start_ns` (time.time_ns): a Ray actor
    committed it, whether or not its report reached this process."""
    try:
        return all(path.stat().st_mtime_ns >= start_ns for path in item.outputs.values())
    except OSError:
        return False


def _import_ray(address: str | None):
    try:
        import ray
        import ray.data
    except ImportError as exc:
        raise MissingDependencyError(
            "--engine ray needs the optional 'ray' extra",
            fix="pip install 'relightcli[ray]', or use the default local engine",
        ) from exc
    if address and address.startswith("ray://") and importlib.util.find_spec("grpc") is None:
        raise MissingDependencyError(
            f"--address {address} connects through Ray Client, which needs the 'ray[client]' extra",
            fix="pip install 'ray[client]', or run relight on a node of the cluster with --address auto")
    return ray


def _start_ray(ray, address: str | None, num_cpus: int, timeout_s: float) -> None:
    """Connect to the cluster at `address`, or start a local one (None). The connection is
    tried in a thread of its own and abandoned after `timeout_s` (ray.init retries an address
    where nothing answers for minutes), and from there Ray installs no signal handlers; a local
    start installs SIGTERM handlers that end the process with sys.exit, so it runs here, with
    this process's own handlers put back after it."""
    if address is None:
        package_root = str(Path(__file__).resolve().parents[1])
        with _own_stop_handlers_kept():
            ray.init(num_cpus=num_cpus, include_dashboard=False, log_to_driver=False,
                     configure_logging=False, runtime_env={"env_vars": {"PYTHONPATH": package_root}})
        return
    failure: list[BaseException] = []

    def connect() -> None:
        try:
            ray.init(address=address, include_dashboard=False, log_to_driver=False, configure_logging=False)
        except Exception as exc:  # reported to the main thread, which raises it as ours
            failure.append(exc)

    fix = ("check --address and that the cluster runs (`ray status` on its head node), raise "
           "--ray-timeout, or drop --address to start Ray on this machine")
    attempt = threading.Thread(target=connect, name="relight-ray-connect", daemon=True)
    ray_worker_log = logging.getLogger("ray._private.worker")
    ray_worker_log.addFilter(_no_sigterm_notice)  # Ray's notice that it leaves SIGTERM to us
    attempt.start()
    attempt.join(timeout_s)
    if attempt.is_alive():  # abandoned, still trying: the process ends without it
        raise UsageError(f"no Ray cluster answered at {address} within {timeout_s:g} s", fix=fix)
    ray_worker_log.removeFilter(_no_sigterm_notice)
    if failure:
        text = str(failure[0]).strip() or type(failure[0]).__name__
        raise UsageError(f"cannot connect to a Ray cluster at {address} ({text.splitlines()[0]})",
                         fix=fix) from failure[0]


def _no_sigterm_notice(record: logging.LogRecord) -> bool:
    return not str(record.msg).startswith("SIGTERM handler is not set")


@contextlib.contextmanager
def _own_stop_handlers_kept():
    """This process's SIGINT and SIGTERM handlers put back after the block (ray.init replaces
    SIGTERM's with one that ends the process by sys.exit); a SystemExit raised by Ray's handler
    inside the block is the SIGTERM that stops the batch."""
    on_main_thread = threading.current_thread() is threading.main_thread()
    previous = {signum: signal.getsignal(signum) for signum in STOP_SIGNALS}
    try:
        yield
    except SystemExit:
        raise Stopped(signal.SIGTERM) from None
    finally:
        for signum, handler in previous.items():
            if on_main_thread and handler is not None:
                signal.signal(signum, handler)


def _ray_dataset(ray, items, worker, workers, threads_per_worker, skip_existing, overwrite):
    rows = [
        {"index": index, "input": str(item.input),
         "outputs": json.dumps({k: str(v) for k, v in item.outputs.items()}),
         "mask": "" if item.mask is None else str(item.mask)}
        for index, item in enumerate(items)
    ]
    return ray.data.from_items(rows).map_batches(
        _RayItemActor,
        fn_constructor_args=(worker, skip_existing, overwrite),
        batch_size=1,
        concurrency=min(workers, len(items)),
        num_cpus=threads_per_worker,
        batch_format="numpy",
    )


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
