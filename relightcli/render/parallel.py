"""Sample passes on several cores: forked workers that inherit the render's state.

embreex holds the GIL while it traces and most of a pass is numpy on small arrays, so threads
do not scale. The calling process samples one share itself; the others go to workers forked
once per render, after the BVH is built and the render's arrays exist, so they inherit both
(copy-on-write) and nothing large is pickled: each round sends pixel indices and gets back
per-pixel sums.
"""

from __future__ import annotations

import multiprocessing
import signal

import numpy as np

_RUN = None  # the render a forked worker inherited


def pass_statistics(values, first_pass, groups):
    """Per-pixel sums of pass values (k, N, 3) for running estimates: (group_sums (N, groups,
    3), square_sums (N, 3), or None with several groups: the error then comes from the group
    means); pass first_pass + j belongs to group (first_pass + j) % groups."""
    group_sums = np.empty((values.shape[1], groups, 3))
    for group in range(groups):
        group_sums[:, group] = values[(group - first_pass) % groups::groups].sum(axis=0)
    return group_sums, (np.square(values).sum(axis=0) if groups == 1 else None)


def _worker_start():
    # Stopping is the parent's: it ends the workers by SIGTERM when it closes the pool. A
    # handler inherited from it (the CLI's raises batch.Stopped) would print a traceback from
    # each worker it ends, and Ctrl-C reaches the whole process group
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # The worker traces on its own: never through the parent's tracing pool
    _RUN.scene.detach_workers()


def _worker_round(task):
    first_pass, passes, rows, groups = task
    before = _RUN.scene.rays_traced
    stats = pass_statistics(_RUN.values(first_pass, passes, rows), first_pass, groups)
    return stats, _RUN.scene.rays_traced - before


class ForkedPasses:
    """`workers` processes evaluating rounds of passes of one render: this one and
    `workers - 1` forked children, each taking a share of the round's pixels."""

    def __init__(self, run, workers: int):
        global _RUN
        run.scene.commit()  # build the BVH in the parent: the children inherit it
        _RUN = run
        try:
            self._pool = multiprocessing.get_context("fork").Pool(workers - 1, initializer=_worker_start)
        finally:
            _RUN = None
        self.run, self.workers = run, workers
        # This process samples a share too, tracing alone (a scene's own pool would compete)
        self._threads, run.scene.threads = run.scene.threads, 1

    def statistics(self, first_pass, passes, rows, groups):
        """`pass_statistics` of `rows`, split over the processes; adds their rays to the scene."""
        # Every `workers`-th pixel to each process: neighbouring pixels cost alike, so the
        # shares balance (halves of the mask, head and legs, did not)
        shares = [slice(k, None, self.workers) for k in range(min(self.workers, rows.size))]
        children = self._pool.map_async(_worker_round, [(first_pass, passes, rows[s], groups) for s in shares[1:]])
        own = pass_statistics(self.run.values(first_pass, passes, rows[shares[0]]), first_pass, groups)
        results = [(own, 0)] + children.get()
        self.run.scene.rays_traced += sum(r[1] for r in results)
        group_sums = np.empty((rows.size,) + own[0].shape[1:])
        squares = None if own[1] is None else np.empty((rows.size, 3))
        for share, ((sums, square_sums), _) in zip(shares, results):
            group_sums[share] = sums
            if squares is not None:
                squares[share] = square_sums
        return group_sums, squares

    def close(self):
        self._pool.terminate()
        self._pool.join()
        self.run.scene.threads = self._threads

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
