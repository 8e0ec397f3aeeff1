"""Running the suite on every core (``pytest -n auto``, pytest-xdist) beside the tests paced in real time
(a pytest plugin, registered by tests/conftest.py).

What it does, and why
---------------------
The tests that run against a clock ("paced": pty boards, JACK-paced microphones, LSL streams between
processes, ROS 2 nodes, pages in a browser) mostly wait, and fail when a busy neighbour delays them; the other
tests compute. So:

- **Two paced groups, each on one worker** (:data:`PACED_GROUPS`, :func:`paced_group`), one test after the
  other, the two groups side by side: the tests get their xdist group (the ``xdist_group`` marker) in
  :func:`pytest_collection_modifyitems`.
- **A test marked ``alone``** runs with no other paced test beside it (:func:`pytest_runtest_protocol`): a
  paced test holds the run's paced lock shared from its setup to its teardown, an ``alone`` test holds it
  exclusive (``fcntl.flock`` on :func:`paced_lock`, which the kernel lets go when the test ends, however it
  ends, or when its process dies).
- **One worker per core plus one per paced group** (:func:`pytest_xdist_auto_num_workers`); the workers that
  run a test that computes go to Linux's idle time (:func:`pytest_runtest_setup`), so that they take the cores
  the paced tests leave idle and never hold one up.
- **An order** (:func:`pytest_collection_modifyitems`): the groups first (xdist hands them out first, one to
  a worker), ``alone`` tests last in theirs, then the ``slow`` tests that compute, the tests that mostly wait,
  the rest.
- **A run in which a group ran on more than one worker fails**, saying so (:func:`pytest_sessionfinish`).

Why a scheduler of its own
--------------------------
``--dist loadgroup`` with the ``xdist_group`` marker is what this needs (tests of a group on one worker), but
pytest-xdist passes a test's group from the worker to the controller's scheduler as a suffix it writes into
the test's id (``...::test@group``, through pytest's private ``item._nodeid``), and pytest 9.2, whose test ids
are structured, ignores it: every grouped test then goes to whichever worker is free, silently
(pytest-dev/pytest-xdist#1386, open with pytest 9.2.0 and pytest-xdist 3.8.0, the latest of each; a CI run
on a fresh install spread the paced tests over every worker and an LSL test failed). No public hook passes
a group instead. So the workers write every test's group to the run's shared folder
(:mod:`harness.shared_folder`, :func:`_write_groups`) and the controller's scheduler reads them:
:func:`pytest_xdist_make_scheduler` (a public hook) returns xdist's own ``LoadGroupScheduling`` with its
``_split_scope`` (a private method: the work unit of a test id) answered from that file. For that reason
pyproject.toml's ``test`` extra holds pytest-xdist below 3.9 (checked with 3.8.0); when xdist passes groups
another way (pytest-dev/pytest-xdist#1388 is a first attempt), ``--dist loadgroup`` alone will do again, and the
end-of-run check says whether it does. With pytest before 9.2 xdist's suffix still works, and names the same
groups the file does. (Holding pytest below 9.2 would let ``--dist loadgroup`` alone do, but would hold the
whole suite to an old pytest for a plugin's fault; the pin is on the plugin instead.)

Relies on: pytest's public hooks; pytest-xdist's hooks ``pytest_xdist_auto_num_workers`` and
``pytest_xdist_make_scheduler``, its ``config.workerinput`` and ``PYTEST_XDIST_WORKER_COUNT`` on a worker,
its ``report.worker_id`` on the controller (added for plugins: pytest-dev/pytest-xdist#118), and
``LoadGroupScheduling._split_scope`` (private, pinned); :mod:`harness.shared_folder`; Linux's ``SCHED_IDLE``
(elsewhere nice 19) and ``fcntl.flock``.
"""

import fcntl
import functools
import json
import os
from pathlib import Path

import pytest

from harness import shared_folder

#: The xdist groups of the tests that run against a clock ("paced"): each group runs on one worker, one
#: test after the other, and the two groups side by side. The pty boards, the JACK-paced microphones and
#: the soak (the ``hardware`` tests) in one, about 4 min on an otherwise idle machine; LSL streams between
#: processes, ROS 2 nodes, the two-sense world paced at 4x and the view's pages in a browser in the other,
#: about 3 min.
#: Both mostly wait for their clock (a fifth of the time on the CPU). A test marked ``alone`` (the robot's
#: live scene, the soak, a restarted sender or relay, the world at 4x) runs with no other paced test beside it
#: (:func:`pytest_runtest_protocol`), last in its group: the robot's unplug test and the soak, each run
#: beside the other, failed 3 of 14 runs beside two nice-19 processes burning both cores, 1 of 21
#: beside two in idle time (:func:`_compute_in_idle_time`), none of 7 beside nothing; the robot's and
#: the world's, side by side in a run of the suite, both failed.
PACED_DEVICES = "paced-devices"
PACED_LSL = "paced-lsl"
PACED_GROUPS = (PACED_DEVICES, PACED_LSL)

#: Fixtures of tests that mostly wait (:func:`pytest_collection_modifyitems`): on a browser, or on another
#: worker computing a result shared once per run (the ``once`` fixture, :mod:`harness.run_once`).
_WAITS = frozenset({"browser", "once"})


def _cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:                   # not on Linux
        return os.cpu_count() or 1


def paced_group(item) -> str | None:
    """The paced group of a test, or None for a test that computes."""
    if item.get_closest_marker("hardware"):
        return PACED_DEVICES
    fixtures = getattr(item, "fixturenames", ())
    # A page in a browser waits on the clock as well: in a worker computing in idle time, a browser test
    # waited 60 s for its first window in a CI dry run while the robot's live tests (paced, at normal
    # priority, training models in their node processes) took the cores.
    # ROS 2's tests (their fixture localhost_only) wait on DDS discovery and on nodes paced in real time, as LSL's;
    # so do the tests marked paced (a document's commands that run the node in real time: tests/test_docs_commands.py),
    # which in a computing worker would hold it while they wait.
    if (item.get_closest_marker("alone") or item.get_closest_marker("paced") or "loopback_only" in fixtures
            or "localhost_only" in fixtures or "browser" in fixtures):
        return PACED_LSL
    return None


def paced_lock() -> Path:
    """The run's paced lock file (:func:`pytest_runtest_protocol`)."""
    return shared_folder.folder() / "paced.lock"


# -- how many workers, and in which order they take the tests ---------------------------------------------

@pytest.hookimpl(optionalhook=True)
def pytest_xdist_auto_num_workers(config):
    """``-n auto``: one worker per core for the tests that compute, plus one per paced group. The paced
    tests mostly wait for their clock; the workers that compute run in idle time
    (:func:`_compute_in_idle_time`), so that they take the cores the paced tests leave idle and never
    hold up a paced test (``PYTEST_XDIST_AUTO_NUM_WORKERS`` still sets the number)."""
    if os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS"):
        return None
    return _cores() + len(PACED_GROUPS)


@pytest.hookimpl(tryfirst=True)             # before xdist's own, which reads the groups into the test ids
def pytest_collection_modifyitems(config, items):
    """The paced tests go to their xdist groups (:data:`PACED_GROUPS`), the tests marked ``alone`` last in
    theirs (by then the models they train on start are likelier to be in the run's cache, trained by a
    worker in idle time); under xdist, the ``slow`` tests that compute come before the rest (the longest
    first, so that no worker ends the run alone on one of them), then the tests that mostly wait. xdist
    hands the groups out first (the largest units of work), one to a worker."""
    rank = {}
    groups = {}
    for item in items:
        group = paced_group(item)
        if group is not None:
            item.add_marker(pytest.mark.xdist_group(group))
            rank[item] = 0.5 if item.get_closest_marker("alone") else 0
        elif item.get_closest_marker("slow"):
            rank[item] = 1
        else:
            # Tests that mostly wait (on a browser, or on another worker computing a result shared once per
            # run) early, beside the tests that compute: at the end of a run they left cores idle.
            rank[item] = 1.5 if _WAITS.intersection(getattr(item, "fixturenames", ())) else 2
        # Every xdist group, the paced ones and those a test module names, joined as xdist joins several.
        names = {m.args[0] if m.args else m.kwargs.get("name", "default") for m in item.iter_markers("xdist_group")}
        if names:
            groups[item.nodeid] = "_".join(sorted(map(str, names)))
    if hasattr(config, "workerinput"):
        # On xdist's workers (which all collect the same order; the scheduler hands tests out in it).
        items.sort(key=rank.__getitem__)
        _write_groups(groups)


# -- keeping each xdist group on one worker (see the module's docstring) ------------------------------------

def _groups_path() -> Path:
    return shared_folder.folder() / "groups.json"


def _write_groups(groups: dict[str, str]) -> None:
    """Write the xdist groups of the collected tests (test id -> group) for the controller's scheduler.
    Every worker writes the same (they collect the same tests), each whole file at once."""
    path = _groups_path()
    tmp = path.with_name(f"{path.name}.{os.getpid()}")
    tmp.write_text(json.dumps(groups, sort_keys=True))
    os.replace(tmp, path)


@functools.cache
def _groups() -> dict[str, str]:
    """The groups the workers wrote (:func:`_write_groups`), read once by the controller."""
    try:
        return json.loads(_groups_path().read_text())
    except FileNotFoundError:
        raise pytest.UsageError(
            f"the xdist workers wrote no test groups to {_groups_path()}: tests/harness/pacing.py's "
            "pytest_collection_modifyitems did not run on them") from None


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadgroup`` (pyproject's addopts): xdist's load-group scheduling, with the groups read
    from the workers' file rather than from the test ids (:func:`_write_groups`)."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadGroupScheduling

    class _GroupScheduling(LoadGroupScheduling):
        """A test's work unit: its group, else the test alone (and a group xdist's own suffix names,
        should that channel work again)."""

        def _split_scope(self, nodeid: str) -> str:
            # First asked in schedule(), once every worker has collected (and written the file).
            return _groups().get(nodeid) or super()._split_scope(nodeid)

    return _GroupScheduling(config, log)


#: On xdist's controller: whether the run keeps groups (``--dist loadgroup``), and the workers each group
#: ran on (:func:`pytest_runtest_logreport`).
_keeps_groups = False
_group_workers: dict[str, set[str]] = {}


def pytest_configure(config):
    global _keeps_groups
    _keeps_groups = config.getvalue("dist") == "loadgroup" and not hasattr(config, "workerinput")
    _group_workers.clear()


def pytest_runtest_logreport(report):
    """On xdist's controller, note the worker each test of a group ran on."""
    worker = getattr(report, "worker_id", None)      # set on the reports the workers send
    if worker is None or not _keeps_groups or report.when != "call":
        return
    group = _groups().get(report.nodeid.split("@")[0])   # without xdist's suffix, where it still writes one
    if group is not None:
        _group_workers.setdefault(group, set()).add(worker)


def pytest_sessionfinish(session):
    """On xdist's controller, a group that ran on more than one worker fails the run, saying so: paced
    tests then ran beside each other and on workers computing in idle time, and a group's tests that
    share files did not find them."""
    split = {group: sorted(workers) for group, workers in _group_workers.items() if len(workers) > 1}
    if not split:
        return
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    for group, workers in split.items():
        line = (f"test group {group!r} ran on workers {', '.join(workers)}, not on one: the scheduler did "
                "not keep it together (tests/harness/pacing.py)")
        if reporter is not None:
            reporter.write_line(line, red=True)
    session.exitstatus = pytest.ExitCode.TESTS_FAILED


# -- pacing each test ---------------------------------------------------------------------------------

@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """Under xdist, a paced test holds the run's paced lock shared while it runs (setup to teardown) and
    a test marked ``alone`` holds it exclusive: an ``alone`` test waits for the paced test running in
    the other group, and that group waits for it (``fcntl.flock``, :func:`paced_lock`). The two-sense
    world paced at 4x and the robot's live scene, run side by side, both failed."""
    if not hasattr(item.config, "workerinput") or paced_group(item) is None:
        yield
        return
    fd = os.open(paced_lock(), os.O_CREAT | os.O_RDWR, 0o600)
    try:
        # Interruptible: Ctrl-C while waiting raises KeyboardInterrupt here, and the finally lets the fd go.
        fcntl.flock(fd, fcntl.LOCK_EX if item.get_closest_marker("alone") else fcntl.LOCK_SH)
        yield
    finally:
        os.close(fd)                         # lets the lock go


def _compute_in_idle_time() -> None:
    """Let this thread, and the processes and threads it starts, run only on a core nothing else wants:
    Linux's idle scheduling class (SCHED_IDLE), else the lowest priority (nice 19). A paced test then
    takes a core as soon as it wakes (nice 19 was not enough for two paced board tests side by side:
    :data:`PACED_DEVICES`). With both paced groups beside two processes burning both cores in idle time,
    every paced test passed in the time it takes on an idle machine."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):        # not Linux
        try:
            os.nice(19 - os.nice(0))
        except (AttributeError, OSError):    # no niceness either: as it is
            pass


#: Whether this worker has gone to idle time (:func:`pytest_runtest_setup`).
_computing = False


@pytest.hookimpl(tryfirst=True)             # before the test's fixtures, which may compute too
def pytest_runtest_setup(item):
    """Where xdist runs more workers than there are cores (``-n auto``: :func:`pytest_xdist_auto_num_workers`),
    a worker that runs a test that computes goes to idle time for the rest of the run
    (:func:`_compute_in_idle_time`; an unprivileged process cannot come back, and xdist hands the paced
    groups out first, so a worker has run its paced group, if any, before it computes). On a machine
    busy with other work, those workers get only what it leaves: ``-n`` with the number of cores runs
    every worker at its normal priority."""
    global _computing
    if _computing or not hasattr(item.config, "workerinput") or paced_group(item) is not None:
        return
    if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0")) > _cores():   # set by xdist on each worker
        _compute_in_idle_time()
    _computing = True
