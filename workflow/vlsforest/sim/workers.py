"""An ordered map over forked worker processes that share one object without pickling it.

The simulator's blocks run in worker processes because Embree holds the GIL. The job they
share (the scene with its Embree BVH and voxel grids, the survey) cannot be pickled cheaply, so
the workers are forked and receive it as an argument of the process itself: a forked child
inherits it from the parent's memory. Only the items and the results cross the process
boundary (pickled through queues).
"""

from __future__ import annotations

import multiprocessing as mp
import pickle
import queue
from typing import Any, Callable, Iterator, Sequence

__all__ = ["WorkerDied", "fork_map"]

#: seconds between checks of the workers' health while waiting for a result
_POLL_S = 0.5


class WorkerDied(RuntimeError):
    """A worker process ended before it delivered its results (killed, e.g. out of memory)."""


def _serve(fn, shared, tasks, results) -> None:
    """A worker's loop: ``fn(shared, item)`` for every ``(index, item)`` until the None sentinel."""
    while True:
        task = tasks.get()
        if task is None:
            break
        i, item = task
        try:
            out = (i, True, fn(shared, item))
        except Exception as exc:  # handed to the parent, which raises it
            try:
                pickle.dumps(exc)
            except Exception:
                exc = RuntimeError(f"{type(exc).__name__}: {exc}")
            out = (i, False, exc)
        results.put(out)
    results.close()
    results.join_thread()


def fork_map(fn: Callable[[Any, Any], Any], shared: Any, items: Sequence, workers: int) -> Iterator:
    """Yield ``fn(shared, item)`` for every item, in the order of ``items``, computed by forked
    worker processes.

    Parameters
    ----------
    fn : callable
        ``fn(shared, item)``; runs in the workers.
    shared : object
        Passed to every call; inherited by the forked workers, never pickled.
    items : sequence
        The work items (pickled to the workers); the workers take the next one when free.
    workers : int
        Number of worker processes (≥ 1).

    Yields
    ------
    The results, in the order of ``items`` (pickled back from the workers).

    Raises
    ------
    WorkerDied
        A worker process ended before its results came back.
    Exception
        What ``fn`` raised in a worker, for the first item (in order) whose call raised.

    Notes
    -----
    The workers are ended when the iteration stops, by exhaustion, an error or the
    generator's closing.
    """
    ctx = mp.get_context("fork")
    tasks, results = ctx.Queue(), ctx.Queue()
    procs = [ctx.Process(target=_serve, args=(fn, shared, tasks, results), daemon=True) for _ in range(workers)]
    try:
        for p in procs:
            p.start()
        for i, item in enumerate(items):
            tasks.put((i, item))
        for _ in procs:
            tasks.put(None)
        done: dict = {}
        idle_checks = 0
        for i in range(len(items)):
            while i not in done:
                try:
                    j, ok, value = results.get(timeout=_POLL_S)
                except queue.Empty:
                    codes = [p.exitcode for p in procs]
                    if any(c not in (None, 0) for c in codes):
                        raise WorkerDied(f"a worker process ended with exit code {min(c for c in codes if c)}") from None
                    idle_checks = idle_checks + 1 if all(c == 0 for c in codes) else 0
                    if idle_checks > 2:  # every worker has finished and nothing more comes
                        raise WorkerDied("the worker processes ended without delivering every result") from None
                    continue
                done[j] = (ok, value)
            ok, value = done.pop(i)
            if not ok:
                raise value
            yield value
    finally:
        for p in procs:
            if p.is_alive():
                p.terminate()
        for p in procs:
            if p.pid is not None:
                p.join()
        tasks.close()
        results.close()
        tasks.cancel_join_thread()
        results.cancel_join_thread()
