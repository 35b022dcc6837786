"""Sample passes on several cores: forked workers that inherit the render's state.

embreex holds the GIL while it traces and most of a pass is numpy on small arrays, so threads
do not scale. The calling process samples one share itself; the others go to workers forked
once per render, after the BVH is built and the render's arrays exist, so they inherit both
(copy-on-write) and nothing large is pickled: each round sends pixel indices and gets back
per-pixel sums.
"""

from __future__ import annotations

import multiprocessing

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
        chunks = [c for c in np.array_split(rows, self.workers) if c.size]
        children = self._pool.map_async(_worker_round, [(first_pass, passes, c, groups) for c in chunks[1:]])
        own = pass_statistics(self.run.values(first_pass, passes, chunks[0]), first_pass, groups)
        results = [(own, 0)] + children.get()
        self.run.scene.rays_traced += sum(r[1] for r in results)
        squares = [r[0][1] for r in results]
        return (np.concatenate([r[0][0] for r in results]),
                None if squares[0] is None else np.concatenate(squares))

    def close(self):
        self._pool.terminate()
        self._pool.join()
        self.run.scene.threads = self._threads

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
