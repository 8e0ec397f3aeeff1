"""The suite's harness (tests/harness/) at work: small suites run by pytester in a pytest of their own, with
xdist, under the harness's plugins, each test recording what happened (when it ran, on which worker, what it
computed) to files the test here reads.

Each checks what a plugin promises, never how long anything took: the tests of a paced group run on one
worker, one after the other, and a test marked ``alone`` beside no other paced test (harness.pacing); a group
split over two workers fails the run (harness.pacing's safety net, for the day the scheduler stops keeping
groups); a result is computed once per run for every worker (harness.run_once), in a folder of the run's own
that is gone after it (harness.shared_folder); a test interrupted by Ctrl-C leaves no lock held.
"""

import json
import os
from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

#: tests/: the inner runs import the harness from it, as the suite does.
TESTS = Path(__file__).parent

INI = """\
[pytest]
markers =
    slow: as the suite's
    hardware: as the suite's (the paced group of the boards)
    alone: as the suite's
    paced: as the suite's (the paced group of LSL)
"""

CONFTEST = 'pytest_plugins = ["harness.shared_folder", "harness.pacing"]\n'

#: What every inner test module starts with: record(name, seconds) writes, when the test has slept
#: ``seconds``, when it started and ended (CLOCK_MONOTONIC: one clock for every process of the machine) and
#: on which worker, to log/NAME.json.
RECORD = """\
import json, os, time
from pathlib import Path

import pytest

LOG = Path(__file__).parent / "log"


def record(name, seconds=0.0, **more):
    start = time.monotonic()
    time.sleep(seconds)
    end = time.monotonic()
    (LOG / f"{name}.json").write_text(json.dumps(
        {"start": start, "end": end, "worker": os.environ.get("PYTEST_XDIST_WORKER"), **more}))
"""


@pytest.fixture
def inner(pytester, monkeypatch):
    """A pytester folder holding the harness's ini, a conftest registering the plugins under test and an
    empty log/; ``PYTHONPATH`` lets its runs import the harness."""
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(TESTS), os.environ.get("PYTHONPATH")])))
    # The inner run is a worker-free controller of its own, whatever process runs this test.
    for name in ("PYTEST_XDIST_WORKER", "PYTEST_XDIST_WORKER_COUNT", "PYTEST_XDIST_AUTO_NUM_WORKERS"):
        monkeypatch.delenv(name, raising=False)
    # No plugin but xdist (run()'s -p) and the harness's: an inner run then starts in about a second, not four.
    monkeypatch.setenv("PYTEST_DISABLE_PLUGIN_AUTOLOAD", "1")
    pytester.makeini(INI)
    pytester.makeconftest(CONFTEST)
    (pytester.path / "log").mkdir()
    return pytester


def run(pytester, *args):
    """The inner suite run with xdist's load-group scheduling, as the suite's addopts ask."""
    return pytester.runpytest_subprocess("-p", "xdist", "-p", "no:cacheprovider", "--dist", "loadgroup", *args,
                                         timeout=120)


def log(pytester) -> dict[str, dict]:
    return {path.stem: json.loads(path.read_text()) for path in (pytester.path / "log").glob("*.json")}


def overlap(a: dict, b: dict) -> bool:
    return a["start"] < b["end"] and b["start"] < a["end"]


def test_a_paced_group_runs_on_one_worker_one_test_after_the_other_and_an_alone_test_beside_no_paced_test(inner):
    """Two workers, both paced groups side by side: the LSL group (three paced tests, then one ``alone``)
    and the boards' (six ``hardware`` tests), and tests that compute. Each group runs on one worker, no two
    of its tests overlap in time, and the ``alone`` test overlaps no paced test of either group."""
    inner.makepyfile(test_paced=RECORD + """
@pytest.mark.paced
@pytest.mark.parametrize("i", range(3))
def test_lsl(i):
    record(f"lsl{i}", 0.15)


@pytest.mark.alone
def test_alone():
    record("alone", 0.3)


@pytest.mark.hardware
@pytest.mark.parametrize("i", range(6))
def test_board(i):
    record(f"board{i}", 0.2)


@pytest.mark.parametrize("i", range(4))
def test_computes(i):
    record(f"computes{i}")
""")
    result = run(inner, "-n", "2")
    result.assert_outcomes(passed=14)
    runs = log(inner)
    lsl = {name: r for name, r in runs.items() if name.startswith(("lsl", "alone"))}
    boards = {name: r for name, r in runs.items() if name.startswith("board")}
    assert len(lsl) == 4 and len(boards) == 6
    for group in (lsl, boards):
        assert len({r["worker"] for r in group.values()}) == 1, group       # one worker
        for a in group:
            for b in group:
                assert a == b or not overlap(group[a], group[b]), (a, b)   # one test after the other
    # The two groups ran side by side (on two workers), but never a board beside the alone test.
    assert {r["worker"] for r in lsl.values()} != {r["worker"] for r in boards.values()}
    assert not [name for name, r in boards.items() if overlap(r, lsl["alone"])]


def test_a_group_split_over_two_workers_fails_the_run_saying_so(inner):
    """The end-of-run check, for the day the scheduler no longer keeps groups together: a plain load
    scheduler (xdist's ``--dist load``, put in by the inner conftest) hands the paced tests out over both
    workers; the tests pass, the run fails, naming the group and its workers."""
    inner.makeconftest(CONFTEST + """
import pytest


@pytest.hookimpl(tryfirst=True)
def pytest_xdist_make_scheduler(config, log):
    from xdist.scheduler import LoadScheduling

    return LoadScheduling(config, log)
""")
    inner.makepyfile(test_split=RECORD + """
@pytest.mark.paced
@pytest.mark.parametrize("i", range(4))
def test_lsl(i):
    record(f"lsl{i}", 0.1)
""")
    result = run(inner, "-n", "2")
    result.assert_outcomes(passed=4)
    assert len({r["worker"] for r in log(inner).values()}) == 2          # the group was split indeed
    assert result.ret == pytest.ExitCode.TESTS_FAILED
    result.stdout.fnmatch_lines(["*test group 'paced-lsl' ran on workers gw0, gw1, not on one*"])


def test_a_result_is_computed_once_for_every_worker_in_a_folder_of_the_run_s_own(inner):
    """Four tests on two workers ask for one result, which takes a while to compute: it is computed once
    (one line in the count file), every test gets it, and the run's folder is gone after the run."""
    inner.makepyfile(test_once=RECORD + """
from harness import shared_folder
from harness.run_once import run_once

COUNT = Path(__file__).parent / "computed"


def compute():
    with open(COUNT, "a") as f:
        f.write(f"{os.getpid()}\\n")
    time.sleep(0.5)                  # long enough for the other worker to ask meanwhile
    return {"answer": 42}


@pytest.mark.parametrize("i", range(4))
def test_shared(i):
    assert run_once("the answer", compute) == {"answer": 42}
    record(f"shared{i}", folder=str(shared_folder.folder()))
""")
    result = run(inner, "-n", "2")
    result.assert_outcomes(passed=4)
    runs = log(inner)
    assert len({r["worker"] for r in runs.values()}) == 2               # both workers asked
    assert (inner.path / "computed").read_text().count("\n") == 1        # one computed it
    folders = {r["folder"] for r in runs.values()}
    assert len(folders) == 1                                            # one folder for the run
    assert not Path(folders.pop()).exists()                             # removed after it


def test_a_test_interrupted_by_ctrl_c_leaves_no_lock_held(inner):
    """An ``alone`` test (the paced lock held exclusive) is interrupted by SIGINT (what Ctrl-C sends) while
    it computes a result once per run (that result's lock held). After the interrupt, in the same worker
    process (so the kernel has not let the locks go with the process): both locks are free, and the result
    was not kept, so the next to ask computes it."""
    inner.makeconftest(CONFTEST + """
import fcntl, json, os
from pathlib import Path


def _free(path):
    fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except BlockingIOError:
        return False
    finally:
        os.close(fd)


def pytest_sessionfinish(session):
    from harness import pacing               # here: pytest imports the plugins after this file
    from harness.run_once import _shared_path, run_once

    if hasattr(session.config, "workerinput"):           # the worker the test ran in, still alive
        after = {"paced_lock_free": _free(pacing.paced_lock()),
                 "result_lock_free": _free(f"{_shared_path('interrupted')}.lock")}
        if after["result_lock_free"]:                      # else run_once would wait for ever
            after["result"] = run_once("interrupted", lambda: "computed after")
        (Path(__file__).parent / "log" / "after.json").write_text(json.dumps(after))
""")
    inner.makepyfile(test_interrupted=RECORD + """
import signal

from harness.run_once import run_once


def interrupted():
    # Python's handler, as at a terminal: a worker started by a process that ignores SIGINT (an xdist
    # worker of the outer suite, whose children inherit it) would ignore it too
    signal.signal(signal.SIGINT, signal.default_int_handler)
    os.kill(os.getpid(), signal.SIGINT)
    time.sleep(30)                       # the interrupt comes first
    return "computed before"


@pytest.mark.alone
def test_interrupted():
    record("interrupted", result=run_once("interrupted", interrupted))
""")
    result = run(inner, "-n", "1")
    assert result.ret == pytest.ExitCode.INTERRUPTED
    result.stdout.fnmatch_lines(["*gw0* received keyboard-interrupt*"])
    after = json.loads((inner.path / "log" / "after.json").read_text())
    assert after == {"paced_lock_free": True, "result_lock_free": True, "result": "computed after"}
    assert "interrupted" not in log(inner)                             # the test did not go on
