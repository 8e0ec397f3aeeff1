"""Results computed once per test run and shared by its xdist workers: :func:`run_once` and
:func:`once_per_arguments` (a module of functions, not a plugin: tests/conftest.py's ``once`` fixture and
:mod:`harness.shared_trainings` use them).

Why: many tests, on every worker, need the same expensive and deterministic result (a model trained on the
spot, an experiment run in quick mode); each worker computed it again. Now whichever worker asks first
computes it and the others read it.

How: the result is pickled to a file in the run's shared folder (:mod:`harness.shared_folder`), named by
what determines it; a lock beside it (``fcntl.flock``) is held while it is computed, so that a worker that
asks meanwhile waits for the file rather than computing beside it. The kernel lets a lock go when its file
descriptor is closed or its process dies, so a computation interrupted (Ctrl-C), failed or killed leaves no
lock held and no result: the next to ask computes again.

Relies on: :mod:`harness.shared_folder` (set by the session; outside one, as in a test module run as a
script, every call computes); ``fcntl.flock`` (POSIX); :func:`supramodal.digest.feed` for
:func:`once_per_arguments`'s names.
"""

import fcntl
import functools
import hashlib
import os
import pickle
import re

from harness import shared_folder


def _shared_path(name: str):
    """Where the result of ``name`` is kept: a readable stem and a digest of the whole name."""
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "-", name)[:80]
    return shared_folder.folder() / f"{stem}-{hashlib.sha256(name.encode()).hexdigest()[:16]}"


def run_once(name: str, compute):
    """``compute()``, computed once per test run by whichever xdist worker asks first and read from a
    file by the others (without xdist: in this process, kept on disk for the run).

    Parameters
    ----------
    name : str
        Everything that determines the result (the run is one version of the code, so a fixture's module
        and name do when its inputs are fixed).
    compute : callable
        Called with no arguments; its result must pickle.

    Returns
    -------
    object
        The result; every caller gets its own copy (unpickled), but the one that computed it.

    Notes
    -----
    The first worker to ask holds the name's lock (``fcntl.flock``) while it computes; a worker that asks
    meanwhile waits for the file rather than computing the same thing beside it. A compute that raises
    (KeyboardInterrupt too) leaves nothing: the next one to ask computes (and fails) again.
    """
    if shared_folder.folder() is None:       # outside a pytest session (a test module run as a script)
        return compute()
    path = _shared_path(name)
    fd = os.open(f"{path}.lock", os.O_CREAT | os.O_RDWR, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)       # interruptible: Ctrl-C raises KeyboardInterrupt here
        try:
            with open(f"{path}.pickle", "rb") as f:
                return pickle.load(f)
        except FileNotFoundError:
            pass
        value = compute()
        tmp = f"{path}.pickle.{os.getpid()}"
        with open(tmp, "wb") as f:
            pickle.dump(value, f, protocol=pickle.HIGHEST_PROTOCOL)
        os.replace(tmp, f"{path}.pickle")    # whole or not at all: a reader never sees half a file
        return value
    finally:
        os.close(fd)                         # releases the lock


def once_per_arguments(func, label: str, quiet):
    """``func`` computed once per run for each set of arguments (:func:`run_once`), for a deterministic
    ``func`` whose result pickles.

    Parameters
    ----------
    func : callable
        The function to share.
    label : str
        The start of each result's name; a digest of the arguments' content
        (:func:`supramodal.digest.feed`) follows it.
    quiet : callable
        ``quiet(kwargs)``: whether the call may be shared. A call with a progress callback is not: its
        caller wants to see the work done.

    Returns
    -------
    callable
        ``func``'s stand-in. Called outside a session, not ``quiet`` or with arguments it cannot digest, it
        runs ``func`` as it is.
    """
    @functools.wraps(func)
    def shared(*args, **kwargs):
        if shared_folder.folder() is None or not quiet(kwargs):
            return func(*args, **kwargs)
        from supramodal.digest import feed

        digest = hashlib.sha256()
        try:
            feed(digest, (args, kwargs), objects=True)
        except TypeError:                    # something it cannot say all of: computed here
            return func(*args, **kwargs)
        return run_once(f"{label} {digest.hexdigest()}", lambda: func(*args, **kwargs))
    return shared
