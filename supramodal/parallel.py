"""Independent pure computations over worker processes, with the same results for any number of them.

:func:`map_in_processes` maps a module-level function over items, in order, in ``spawn``-ed worker
processes whose BLAS is held to one thread (:func:`single_threaded_children`), or in this process
when one job is asked. The arithmetic of an item does not depend on how many workers there are:
numpy's element-wise work is the same anywhere, and OpenBLAS divides a product among its threads
by blocks of the result, never along the sum (checked for the networks of a model in
tests/test_parallel.py).

This and :mod:`supramodal.experiments.runner` are the only modules of the model that know about
processes; the functions they run stay pure. Threading: call from one thread; the calling thread
waits for the results. Ctrl-C or SIGTERM in the caller terminates the workers (they ignore
Ctrl-C themselves, so that one interrupt is reported once, by the caller).
"""

from __future__ import annotations

import os
import signal
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

from supramodal.errors import InputError, SupramodalError

__all__ = ["THREAD_VARS", "WorkerLost", "default_jobs", "map_in_processes", "single_threaded_children"]

#: Environment variables that hold BLAS/OpenMP libraries to one thread in the workers.
THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "VECLIB_MAXIMUM_THREADS",
               "NUMEXPR_NUM_THREADS")

T = TypeVar("T")


def default_jobs() -> int:
    """Cores this process may use (its CPU affinity where the system tells it)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


@contextmanager
def single_threaded_children() -> Iterator[None]:
    """Set the BLAS thread variables to 1 while workers are started (restored afterwards).

    A worker's BLAS reads them when numpy loads, and two workers on two cores gain nothing from
    threads that would compete with each other.
    """
    saved = {k: os.environ.get(k) for k in THREAD_VARS}
    os.environ.update({k: "1" for k in THREAD_VARS})
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _start_worker() -> None:
    """Start a worker: leave Ctrl-C to the caller, and keep freed memory for the next array.

    Ctrl-C reaches the whole process group, and the caller alone answers it; freed memory is
    kept by :func:`supramodal.memory.keep_freed_memory`.
    """
    from supramodal.memory import keep_freed_memory

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    keep_freed_memory()


class WorkerLost(SupramodalError, RuntimeError):
    """A worker process ended in the middle of a call (killed: out of memory, a signal; or crashed).

    Also a RuntimeError.
    """


def map_in_processes(fn: Callable[[Any], T], items: Iterable[Any], jobs: int = 1,
                     done: Callable[[int, Any], None] | None = None) -> list[T]:
    """``[fn(item) for item in items]``, over ``jobs`` worker processes.

    Parameters
    ----------
    fn : callable
        A module-level function (workers import it by name), pure: its result depends on its
        item alone.
    items : iterable
        Picklable arguments, one call each, taken as workers are free for them: no more than
        ``jobs`` are held at once beyond the one in hand (a generator of large items stays small).
    jobs : int
        Worker processes, >= 1. 1: every call in this process, in order, with no process started.
    done : callable(int, result), optional
        Told the index and result of each call as it finishes, in the order they finish (from
        the calling thread).

    Returns
    -------
    list
        The results, in the order of ``items``.

    Raises
    ------
    WorkerLost
        A worker ended in the middle of a call (its exit code said, and what to try); the others
        are stopped.
    """
    if isinstance(jobs, bool) or not (isinstance(jobs, int) and jobs >= 1):
        raise InputError(f"jobs must be an integer >= 1, got {jobs!r}")
    results: dict[int, Any] = {}
    if jobs == 1:
        for i, item in enumerate(items):
            results[i] = fn(item)
            if done is not None:
                done(i, results[i])
        return [results[i] for i in range(len(results))]
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool
    from multiprocessing import get_context

    todo = enumerate(items)
    with single_threaded_children():
        pool = ProcessPoolExecutor(jobs, mp_context=get_context("spawn"), initializer=_start_worker)
    running: dict = {}
    try:
        for i, item in todo:                   # the first `jobs` calls
            running[pool.submit(fn, item)] = i
            if len(running) == jobs:
                break
        while running:
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for future in finished:
                i = running.pop(future)
                results[i] = future.result()
                if done is not None:
                    done(i, results[i])
                for j, item in todo:           # one more call for the worker now free
                    running[pool.submit(fn, item)] = j
                    break
    except BrokenProcessPool:
        codes = sorted({p.exitcode for p in _workers(pool) if p.exitcode not in (None, 0)})
        _stop(pool)
        raise WorkerLost(f"a worker process ended in the middle of its work (exit code {codes or 'unknown'}: "
                         "killed by the system, e.g. out of memory, or crashed); run with fewer jobs (--jobs 1 "
                         "trains in this process) or free memory") from None
    except BaseException:
        _stop(pool)                            # Ctrl-C, SIGTERM or a failed call: no worker is left computing
        raise
    pool.shutdown()
    return [results[i] for i in range(len(results))]


def _workers(pool) -> list:
    """Return the pool's worker processes.

    ``ProcessPoolExecutor`` keeps them in a private attribute until Python 3.14's
    ``terminate_workers``.
    """
    return list((getattr(pool, "_processes", None) or {}).values())


def _stop(pool) -> None:
    """End every worker now, a call in the middle of its work too, and wait for them."""
    terminate = getattr(pool, "terminate_workers", None)      # Python >= 3.14
    if terminate is not None:
        terminate()
    else:
        for p in _workers(pool):
            if p.exitcode is None:
                p.terminate()
    pool.shutdown(wait=True, cancel_futures=True)
