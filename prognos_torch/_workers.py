"""Independent tasks over a pool of spawned processes, one torch thread each.

Shared by :func:`~prognos_torch.workflow.calibrate_rul` (its ``prognose`` calls) and
:func:`~prognos_torch.fleet.fleet_rul` (its shards): results come back in task order and equal
those of the sequential run, since each task carries its own seed.
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool

import torch

from .core.validation import is_int

__all__ = ["check_workers", "process_map"]


def check_workers(workers) -> int:
    """``workers`` as a count of processes: an int >= 1 (``TypeError``/``ValueError``)."""
    if not is_int(workers):
        raise TypeError(f"workers must be an int (processes), got {workers!r}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1 (processes), got {workers}")
    return int(workers)


def process_map(
    fn: Callable,
    tasks: Sequence[tuple],
    workers: int,
    sizes: Sequence[float],
    caller: str,
    on_done: Callable[[], None] | None = None,
) -> list:
    """``[fn(*task) for task in tasks]``, in order; over a pool of ``workers`` spawned processes
    (one torch thread each) when ``workers > 1`` and there is more than one task, the tasks
    handed out largest ``sizes`` first (so that no long one starts last). ``on_done()`` is
    called as each task ends (a progress bar). The first failure ends the run (tasks not yet
    started are dropped); a worker that dies (the usual cause: a script calling ``caller`` at
    its top level without the ``__main__`` guard) is a ``RuntimeError`` that says so."""
    workers = min(workers, len(tasks))
    if workers <= 1:
        out = []
        for task in tasks:
            out.append(fn(*task))
            if on_done is not None:
                on_done()
        return out
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(workers, mp_context=ctx, initializer=torch.set_num_threads,
                             initargs=(1,)) as pool:  # fmt: skip
        order = sorted(range(len(tasks)), key=lambda i: -sizes[i])
        futures = {i: pool.submit(fn, *tasks[i]) for i in order}
        try:
            pending = set(futures.values())
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for f in done:
                    f.result()  # the first failure raises here
                    if on_done is not None:
                        on_done()
            return [futures[i].result() for i in range(len(tasks))]
        except BaseException as exc:
            pool.shutdown(cancel_futures=True)
            if isinstance(exc, BrokenProcessPool):
                raise RuntimeError(
                    f"workers={workers}: a worker process ended abruptly. Spawned workers import "
                    f"the calling script again: a script that calls {caller} at its top "
                    'level needs the guard `if __name__ == "__main__":` around that call (the '
                    "workers' own error is printed above). Otherwise a worker ran out of memory "
                    "or was killed; workers=1 runs in this process"
                ) from exc
            raise
