"""Run an experiment's independent runs over worker processes, deterministically.

An experiment is planned as a list of :class:`~supramodal.experiments.common.Run`:
a key (a tuple of plain values naming the run, e.g. ``("fig5", 145.0)``), a
module-level function and its keyword arguments. :func:`run_all` executes them and returns their results
as a dict in the order of the plan, whatever the order in which they finished.

Determinism
-----------
* Each seeded run gets ``seed=run_seed(seed, key)``: derived from the experiment's
  seed and the run's key only, never from a worker or from the order of
  completion.
* Every run executes in a fresh worker process (``spawn``) whose BLAS is held
  to one thread, also with ``jobs=1``: the arithmetic of a run does not depend
  on how many runs share the machine.

So a plan gives the same results for any ``jobs``; only the timings differ.
This module is the only one of the experiments that knows about processes: the
figure modules stay pure functions.
"""

from __future__ import annotations

import hashlib
import inspect
import sys
import time
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from functools import partial
from multiprocessing import get_context

import numpy as np

from supramodal.errors import InputError
from supramodal.experiments.common import Plan, Run
from supramodal.memory import keep_freed_memory
from supramodal.parallel import default_jobs, single_threaded_children


def run_seed(seed: int, key: tuple) -> int:
    """Seed of the run ``key`` in an experiment seeded with ``seed``: a 32-bit integer.

    Derived through :class:`numpy.random.SeedSequence` from ``seed`` and a SHA-256
    digest of ``repr(key)``, so that it is the same in every process and session.
    """
    if not (isinstance(seed, (int, np.integer)) and seed >= 0):
        raise InputError(f"the seed must be an integer >= 0, got {seed!r}")
    digest = hashlib.sha256(repr(tuple(key)).encode()).digest()
    words = np.frombuffer(digest, dtype=np.uint32)
    return int(np.random.SeedSequence([int(seed), *map(int, words)]).generate_state(1)[0])


def format_key(key: tuple) -> str:
    """Return a run's key as text: its parts joined by spaces."""
    return " ".join(str(k) for k in key)


def _prefixed(prefix: str, report: Callable, message: str) -> None:
    report(f"{prefix}{message.strip()}")


def _call(run: Run, seed: int, progress) -> tuple[object, float]:
    """Worker side: one run, timed."""
    t0 = time.perf_counter()
    report = partial(_prefixed, f"  [{format_key(run.key)}] ", progress) if progress else None
    extra = {"seed": seed} if run.seeded else {}
    result = run.fn(**run.kwargs, **extra, progress=report)
    return result, time.perf_counter() - t0


def run_all(runs: list[Run], jobs: int | None = None, seed: int = 0, progress=None) -> dict:
    """Execute ``runs`` over ``jobs`` worker processes (default: all cores).

    Parameters
    ----------
    runs : list of Run
        Keys must be unique.
    jobs : int, optional
        Worker processes, >= 1.
    seed : int
        The experiment's seed; each run receives ``run_seed(seed, run.key)``.
    progress : callable(str), optional
        Receives one line per finished run (with elapsed time and an estimate of
        the time left); the runs' own progress lines too if it is a module-level
        function, which spawned workers can import and call.

    Returns
    -------
    dict
        ``{key: result}`` in the order of ``runs``.
    """
    jobs = default_jobs() if jobs is None else int(jobs)
    if jobs < 1:
        raise InputError(f"--jobs must be >= 1, got {jobs}")
    keys = [r.key for r in runs]
    if len(set(keys)) != len(keys):
        dup = next(k for k in keys if keys.count(k) > 1)
        raise InputError(f"run keys must be unique; {dup!r} repeats")
    if not runs:
        return {}
    seeds = {r.key: run_seed(seed, r.key) for r in runs}
    worker_progress = progress if _sendable_to_workers(progress) else None
    order = sorted(range(len(runs)), key=lambda i: -runs[i].cost)       # costly first; stable
    total_cost = sum(r.cost for r in runs)
    results, done_cost, t0 = {}, 0.0, time.perf_counter()
    workers = min(jobs, len(runs))
    if progress:
        progress(f"{len(runs)} runs over {workers} worker process(es)")
    with single_threaded_children(), ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"),
                                                                initializer=keep_freed_memory) as pool:
        pending = {pool.submit(_call, runs[i], seeds[runs[i].key], worker_progress): runs[i] for i in order}
        try:
            while pending:
                finished, _ = wait(pending, return_when=FIRST_COMPLETED)
                for fut in finished:
                    run = pending.pop(fut)
                    results[run.key], seconds = fut.result()
                    done_cost += run.cost
                    if progress:
                        elapsed = time.perf_counter() - t0
                        left = elapsed * (total_cost - done_cost) / done_cost if done_cost else float("nan")
                        progress(f"[{len(results)}/{len(runs)}] {format_key(run.key)}: {seconds:.1f} s "
                                 f"(elapsed {elapsed:.0f} s, about {left:.0f} s left)")
        except BaseException:
            for fut in pending:
                fut.cancel()
            raise
    return {k: results[k] for k in keys}


def _sendable_to_workers(fn) -> bool:
    """Whether ``fn`` reaches spawned workers by reference: a module-level function does, a lambda or closure not."""
    return (inspect.isfunction(fn) and "<" not in fn.__qualname__
            and getattr(sys.modules.get(fn.__module__), fn.__qualname__, None) is fn)


def run_plans(plans: dict[str, Plan], jobs: int | None = None, seed: int = 0, progress=None) -> dict:
    """Run several experiments' plans in one pool; ``{name: plan.assemble(results)}``.

    Run keys must be unique across the plans (each figure's keys start with its name).
    """
    runs = [r for p in plans.values() for r in p.runs]
    results = run_all(runs, jobs=jobs, seed=seed, progress=progress)
    return {name: p.assemble({r.key: results[r.key] for r in p.runs}) for name, p in plans.items()}
