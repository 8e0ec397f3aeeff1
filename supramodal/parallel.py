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
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, TypeVar

from supramodal.errors import InputError

__all__ = ["THREAD_VARS", "default_jobs", "map_in_processes", "single_threaded_children"]

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
    """Set the BLAS thread variables to 1 while workers are started (restored afterwards): a worker's
    BLAS reads them when numpy loads, and two workers on two cores gain nothing from threads that
    would compete with each other."""
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
    """A worker's start: Ctrl-C reaches the whole process group, and the caller alone answers it;
    freed memory is kept for the next array (:func:`supramodal.memory.keep_freed_memory`)."""
    from supramodal.memory import keep_freed_memory

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    keep_freed_memory()


def _indexed(call: tuple[Callable[[Any], Any], int, Any]) -> tuple[int, Any]:
    fn, i, item = call
    return i, fn(item)


def map_in_processes(fn: Callable[[Any], T], items: Sequence[Any], jobs: int = 1,
                     done: Callable[[int, Any], None] | None = None) -> list[T]:
    """``[fn(item) for item in items]``, over ``jobs`` worker processes.

    Parameters
    ----------
    fn : callable
        A module-level function (workers import it by name), pure: its result depends on its
        item alone.
    items : sequence
        Picklable arguments, one call each.
    jobs : int
        Worker processes, >= 1 (at most one per item is started). 1: every call in this process,
        in order, with no process started.
    done : callable(int, result), optional
        Told the index and result of each call as it finishes, in the order they finish (from
        the calling thread).

    Returns
    -------
    list
        The results, in the order of ``items``.
    """
    if not (isinstance(jobs, int) and jobs >= 1):
        raise InputError(f"jobs must be an integer >= 1, got {jobs!r}")
    items = list(items)
    if jobs == 1 or len(items) <= 1:
        results = []
        for i, item in enumerate(items):
            results.append(fn(item))
            if done is not None:
                done(i, results[-1])
        return results
    from multiprocessing import get_context

    out: list[Any] = [None] * len(items)
    with single_threaded_children():
        pool = get_context("spawn").Pool(min(jobs, len(items)), initializer=_start_worker)
    try:
        for i, result in pool.imap_unordered(_indexed, [(fn, i, item) for i, item in enumerate(items)]):
            out[i] = result
            if done is not None:
                done(i, result)
        pool.close()
    except BaseException:
        pool.terminate()               # Ctrl-C, SIGTERM or a failed call: no worker is left computing
        raise
    finally:
        pool.join()
    return out
