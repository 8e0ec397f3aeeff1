"""The run's shared folder: one temporary folder per test run, shared by the run's xdist workers and the
processes its tests start, seen by no other run (a pytest plugin, registered by tests/conftest.py).

Used by :mod:`harness.pacing` (the paced tests' groups, written by the workers and read by the controller's
scheduler, and the paced lock), :mod:`harness.run_once` (the results computed once per run and their locks)
and :mod:`harness.shared_trainings` (the run's cache of models trained on start).

The process that runs the session makes the folder (xdist's controller, or the one test process without
xdist), in :func:`pytest_configure`, with :func:`tempfile.mkdtemp` (under ``$TMPDIR``, else /tmp), and
removes it when the session ends (:func:`pytest_unconfigure`); a run killed outright leaves it behind. The
controller hands its path to each worker in the worker's ``workerinput`` (:func:`pytest_configure_node`),
which xdist sends to the worker before it starts, where the worker reads it as ``config.workerinput``.

Relies on public hooks only: pytest's ``pytest_configure`` and ``pytest_unconfigure``, pytest-xdist's
``pytest_configure_node`` and ``config.workerinput`` (the attribute ``xdist.is_xdist_worker`` tests for). It
was the controller's base temp, found through pytest's private ``config._tmp_path_factory``: a hook has no
public way to it (the ``tmp_path_factory`` fixture exists for fixtures only), and a folder named by
``--basetemp`` is emptied by pytest when the base temp is first used, which is after ``pytest_configure``.
"""

import shutil
import tempfile
from pathlib import Path

import pytest

#: The key of the folder's path in each xdist worker's ``workerinput``.
WORKERINPUT_KEY = "supramodal_shared_folder"

#: The run's shared folder in this process; None outside a pytest session (a test module run as a script).
_folder: Path | None = None
#: Whether this process made the folder, and so removes it at the end.
_made_here = False


def folder() -> Path | None:
    """The run's shared folder, or None outside a pytest session."""
    return _folder


@pytest.hookimpl(tryfirst=True)             # before the other plugins' pytest_configure, which may use it
def pytest_configure(config):
    """An xdist worker takes the controller's folder; the controller, or the one process without xdist,
    makes it."""
    global _folder, _made_here
    workerinput = getattr(config, "workerinput", None)
    if workerinput is not None:
        try:
            _folder = Path(workerinput[WORKERINPUT_KEY])
        except KeyError:
            raise pytest.UsageError(
                f"this xdist worker was given no shared folder ({WORKERINPUT_KEY!r} in its workerinput): "
                "its controller did not load tests/harness/shared_folder.py") from None
        _made_here = False
    else:
        _folder = Path(tempfile.mkdtemp(prefix="supramodal-run-"))
        _made_here = True


@pytest.hookimpl(optionalhook=True)         # an xdist hook: without xdist, never called
def pytest_configure_node(node):
    """On xdist's controller, as each worker starts: the folder's path goes into its ``workerinput``."""
    node.workerinput[WORKERINPUT_KEY] = str(_folder)


@pytest.hookimpl(trylast=True)              # after the other plugins' pytest_unconfigure, which may use it
def pytest_unconfigure(config):
    """The process that made the folder removes it (by then xdist's workers have ended)."""
    global _folder, _made_here
    if _made_here and _folder is not None:
        shutil.rmtree(_folder, ignore_errors=True)
    _folder, _made_here = None, False
