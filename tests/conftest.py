"""Shared test settings.

BLAS and OpenMP: one thread per test process, set here before numpy is loaded, and inherited by the
xdist workers and every process a test starts. The suite runs one test process per core (docs/development.md:
``pytest -n auto``); a threaded OpenBLAS in each of them, on a machine whose cores are all taken,
spends its time waiting for its own threads: a model of the default scene on features Af and A was
measured training in 199 s with OpenBLAS's threads and in 15 s with one (two cores, load 6).

Hypothesis: no deadline (the suite asserts behaviour, never wall time); example counts are set per test
so that the whole suite stays near a minute on two cores.
"""

import fcntl
import functools
import hashlib
import os
import pickle
import re

import pytest

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "VECLIB_MAXIMUM_THREADS",
             "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from hypothesis import HealthCheck, settings  # noqa: E402  (after the thread settings)

settings.register_profile(
    "supramodal",
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile("supramodal")


def pytest_configure(config):
    """LSL and ROS 2 stay on this machine in every test: before anything loads liblsl, ``LSLAPICFG`` names
    a loopback config with a session id of this run's own (tests/test_lsl.py checks it again); ROS 2's
    discovery is on localhost, in a domain of this run's own."""
    import os
    import tempfile

    from supramodal.benchmarks.lsl_link import loopback_config

    os.environ["LSLAPICFG"] = str(loopback_config(tempfile.mkdtemp(prefix="supramodal-lsl-")))
    # ROS 2 too (tests/ros2_only.py checks it again): DDS discovery on this machine only, in a domain of
    # this run's own (never the one a user's robot may use), drawn by the controller and kept by its workers.
    import random

    if "SUPRAMODAL_TEST_ROS_DOMAIN" not in os.environ:
        os.environ["SUPRAMODAL_TEST_ROS_DOMAIN"] = str(random.SystemRandom().randint(1, 100))
    os.environ["ROS_DOMAIN_ID"] = os.environ["SUPRAMODAL_TEST_ROS_DOMAIN"]
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    for stale in ("ROS_STATIC_PEERS", "ROS_LOCALHOST_ONLY"):   # the second is deprecated, and would override
        os.environ.pop(stale, None)
    # A process killed while Fast DDS made a shared-memory port (the suite kills nodes and publishers on purpose)
    # leaves /dev/shm/fastdds_portN empty, and every later participant spins on it for ever in rclpy.create_node
    # (two CI runs hung so). Under LOCALHOST discovery rmw_fastrtps sets its transports itself
    # (FASTDDS_BUILTIN_TRANSPORTS=UDPv4 is not heeded), so tests/ros2_only.py removes such segments before each
    # ROS test instead.


# -- running on every core (pytest-xdist, `-n auto`) --------------------------------------------------

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


def _cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:                   # not on Linux
        return os.cpu_count() or 1


def _paced_group(item) -> str | None:
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


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_auto_num_workers(config):
    """``-n auto``: one worker per core for the tests that compute, plus one per paced group. The paced
    tests mostly wait for their clock; the workers that compute run in idle time
    (:func:`_compute_in_idle_time`), so that they take the cores the paced tests leave idle and never
    hold up a paced test (``PYTEST_XDIST_AUTO_NUM_WORKERS`` still sets the number)."""
    if os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS"):
        return None
    return _cores() + len(PACED_GROUPS)


#: Fixtures of tests that mostly wait (:func:`pytest_collection_modifyitems`).
_WAITS = frozenset({"browser", "once"})


@pytest.hookimpl(tryfirst=True)             # before xdist reads the groups into the test ids
def pytest_collection_modifyitems(config, items):
    """The paced tests go to their xdist groups (:data:`PACED_GROUPS`), the tests marked ``alone`` last in
    theirs (by then the models they train on start are likelier to be in the run's cache, trained by a
    worker in idle time); under xdist, the ``slow`` tests that compute come before the rest (the longest
    first, so that no worker ends the run alone on one of them), then the tests that mostly wait. xdist
    hands the groups out first (the largest units of work), one to a worker."""
    rank = {}
    groups = {}
    for item in items:
        group = _paced_group(item)
        if group is not None:
            item.add_marker(pytest.mark.xdist_group(group))
            rank[item] = 0.5 if item.get_closest_marker("alone") else 0
        elif item.get_closest_marker("slow"):
            rank[item] = 1
        else:
            # Tests that mostly wait (on a browser, or on another worker computing a result shared once per
            # run) early, beside the tests that compute: at the end of a run they left cores idle.
            rank[item] = 1.5 if _WAITS.intersection(getattr(item, "fixturenames", ())) else 2
        # Every xdist group, the paced ones and those a test module names (as xdist joins several names).
        names = {m.args[0] if m.args else m.kwargs.get("name", "default") for m in item.iter_markers("xdist_group")}
        if names:
            groups[item.nodeid] = "_".join(sorted(map(str, names)))
    if hasattr(config, "workerinput"):
        # On xdist's workers (which all collect the same order; the scheduler hands tests out in it).
        items.sort(key=rank.__getitem__)
        _write_groups(groups)


# -- keeping each xdist group on one worker ---------------------------------------------------------------
#
# xdist's own channel for groups is a suffix its workers append to each test id ("...::test@group"); from
# pytest 9.2 on, test ids are structured and the suffix is silently lost (pytest-dev/pytest-xdist#1386),
# so that every paced test went to whichever worker was free, some of them to workers computing in idle
# time (slower, and an LSL test failed), and test_train_scenes's group was split (its fusion test skipped).
# The workers instead write every test's group to the run's shared folder and the controller's scheduler
# reads them (:class:`_GroupScheduling`); the controller checks at the end of the run that each group ran
# on one worker (:func:`pytest_sessionfinish`).

def _groups_path():
    return _SHARED_DIR / "groups.json"


def _write_groups(groups: dict[str, str]) -> None:
    """Write the xdist groups of the collected tests (test id -> group) for the controller's scheduler.
    Every worker writes the same (they collect the same tests), each whole file at once."""
    import json

    path = _groups_path()
    tmp = path.with_name(f"{path.name}.{os.getpid()}")
    tmp.write_text(json.dumps(groups, sort_keys=True))
    os.replace(tmp, path)


@functools.cache
def _groups() -> dict[str, str]:
    """The groups the workers wrote (:func:`_write_groups`), read once by the controller."""
    import json

    try:
        return json.loads(_groups_path().read_text())
    except FileNotFoundError:
        raise pytest.UsageError(
            f"the xdist workers wrote no test groups to {_groups_path()}: tests/conftest.py's "
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


#: On xdist's controller, the workers each group ran on (:func:`pytest_runtest_logreport`).
_group_workers: dict[str, set[str]] = {}


def pytest_runtest_logreport(report):
    """On xdist's controller, note the worker each test of a group ran on."""
    worker = getattr(getattr(report, "node", None), "gateway", None)
    if worker is None or _SHARED_DIR is None or report.when != "call":
        return
    if report.node.config.getvalue("dist") != "loadgroup":
        return                               # asked for another scheduling: no groups to keep
    group = _groups().get(report.nodeid.split("@")[0])
    if group is not None:
        _group_workers.setdefault(group, set()).add(worker.id)


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
                "not keep it together (tests/conftest.py, _GroupScheduling)")
        if reporter is not None:
            reporter.write_line(line, red=True)
    session.exitstatus = pytest.ExitCode.TESTS_FAILED


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """Under xdist, a paced test holds the run's paced lock shared while it runs (setup to teardown) and
    a test marked ``alone`` holds it exclusive: an ``alone`` test waits for the paced test running in
    the other group, and that group waits for it (``fcntl.flock``, a lock file in the run's shared
    folder). The two-sense world paced at 4x and the robot's live scene, run side by side, both failed."""
    if _SHARED_DIR is None or not hasattr(item.config, "workerinput") or _paced_group(item) is None:
        yield
        return
    fd = os.open(_SHARED_DIR / "paced.lock", os.O_CREAT | os.O_RDWR, 0o600)
    try:
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


@pytest.hookimpl(tryfirst=True)             # before the test's fixtures, which may compute too
def pytest_runtest_setup(item):
    """Where xdist runs more workers than there are cores (``-n auto``: :func:`pytest_xdist_auto_num_workers`),
    a worker that runs a test that computes goes to idle time for the rest of the run
    (:func:`_compute_in_idle_time`; an unprivileged process cannot come back, and xdist hands the paced
    groups out first, so a worker has run its paced group, if any, before it computes). On a machine
    busy with other work, those workers get only what it leaves: ``-n`` with the number of cores runs
    every worker at its normal priority."""
    global _computing
    workerinput = getattr(item.config, "workerinput", None)
    if _computing or workerinput is None or _paced_group(item) is not None:
        return
    if int(workerinput.get("workercount", 0)) > _cores():
        _compute_in_idle_time()
    _computing = True


#: Whether this worker has gone to idle time (:func:`pytest_runtest_setup`).
_computing = False


# -- computed once per run, shared by the xdist workers ---------------------------------------------------

#: The folder the results computed once per run are kept in, set by :func:`pytest_sessionstart`.
_SHARED_DIR = None


def _shared_path(name: str):
    """Where the result of ``name`` is kept: a readable stem and a digest of the whole name."""
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "-", name)[:80]
    return _SHARED_DIR / f"{stem}-{hashlib.sha256(name.encode()).hexdigest()[:16]}"


def run_once(name: str, compute):
    """``compute()``, computed once per test run by whichever xdist worker asks first and read from a
    file by the others (without xdist: in this process, kept on disk for the run).

    ``name`` must say everything that determines the result (the run is one version of the code, so a
    fixture's module and name do when its inputs are fixed). The first worker to ask holds the name's
    lock (``fcntl.flock``) while it computes; a worker that asks meanwhile waits for the file rather
    than computing the same thing beside it. A compute that raises leaves nothing: the next one to ask
    computes (and fails) again. The result must pickle; every caller gets its own copy."""
    if _SHARED_DIR is None:                  # outside a pytest session (a test module run as a script)
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
        os.replace(tmp, f"{path}.pickle")
        return value
    finally:
        os.close(fd)                         # releases the lock


def _once_per_arguments(func, label, quiet):
    """``func`` computed once per run for each set of arguments (:func:`run_once`, named by a digest
    of the arguments' content, :func:`supramodal.digest.feed`), for a deterministic ``func`` whose result pickles.
    Called with a progress callback (``quiet(kwargs)`` false) or with arguments it cannot digest,
    it runs as it is."""
    @functools.wraps(func)
    def once_per_arguments(*args, **kwargs):
        if _SHARED_DIR is None or not quiet(kwargs):
            return func(*args, **kwargs)
        from supramodal.digest import feed

        digest = hashlib.sha256()
        try:
            feed(digest, (args, kwargs), objects=True)
        except TypeError:                    # something it cannot say all of: computed here
            return func(*args, **kwargs)
        return run_once(f"{label} {digest.hexdigest()}", lambda: func(*args, **kwargs))
    return once_per_arguments


def _share_fusion_training():
    """What the node trains to fuse two senses trained on the spot, once per run: the out-of-fold
    log-posteriors a learned late-fusion weight is fitted on (``senses_out_of_fold``: 2 x 10 networks,
    as node.build calls it, looked up in supramodal.fused_model at each build) and the early-fusion
    network (``EarlyFusionModel.train``), both seeded and deterministic. Many scenes of the two-sense
    world build the same fusion; each xdist worker trained it again for each."""
    from supramodal import fused_model

    fused_model.senses_out_of_fold = _once_per_arguments(
        fused_model.senses_out_of_fold, "senses_out_of_fold", lambda kw: kw.get("progress") is None)
    train = fused_model.EarlyFusionModel.train.__func__
    fused_model.EarlyFusionModel.train = classmethod(_once_per_arguments(
        train, "EarlyFusionModel.train", lambda kw: kw.get("calibration_progress") is None))


def pytest_sessionstart(session):
    """The run's shared folder: under xdist, the controller's base temp (every worker's base temp is a
    folder in it, so the workers of one run share it and no other run sees it); without xdist, this
    process's own. The cache of models trained on start is kept there (node/scene/model_cache.py:
    ``SUPRAMODAL_CACHE``, set here before any test starts a process, which inherits it), never the user's
    own: a node run in or out of a test's process reads the model another process of the run trained; the
    trainings a test makes outside that cache, and the fusions' (:func:`_share_fusion_training`), are run
    once per run too (:func:`run_once`)."""
    global _SHARED_DIR
    config = session.config
    base = config._tmp_path_factory.getbasetemp()
    _SHARED_DIR = (base.parent if hasattr(config, "workerinput") else base) / "run-once"
    _SHARED_DIR.mkdir(exist_ok=True)
    os.environ["SUPRAMODAL_CACHE"] = str(_SHARED_DIR / "model-cache")   # model_cache.CACHE_ENV
    if config.pluginmanager.hasplugin("dsession"):
        return                               # xdist's controller: it runs no test (and starts the workers sooner)
    from supramodal.node.scene import build

    # The models the node trains on start that a test trains outside the model cache (with a cache of its
    # own, or none), once per run: seeded and deterministic, keyed by their texture set and settings.
    build.texture_set_model = _once_per_arguments(build.texture_set_model, "texture_set_model",
                                                  lambda kw: kw.get("progress") is None)
    _share_fusion_training()


@pytest.fixture(scope="session")
def once():
    """:func:`run_once` for fixtures: ``once("module.fixture", compute)``."""
    return run_once
