"""Shared test settings.

BLAS and OpenMP: one thread per test process, set here before numpy is loaded, and inherited by the
xdist workers and every process a test starts. The suite runs one test process per core (README:
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
    """LSL stays on this machine in every test: before anything loads liblsl, ``LSLAPICFG`` names a
    loopback config with a session id of this run's own (tests/test_lsl.py checks it again)."""
    import os
    import tempfile

    from supramodal.benchmarks.lsl_link import loopback_config

    os.environ["LSLAPICFG"] = str(loopback_config(tempfile.mkdtemp(prefix="supramodal-lsl-")))


# -- running on every core (pytest-xdist, `-n auto`) --------------------------------------------------

#: The xdist group of the tests that run against a clock: pty boards, JACK-paced microphones, LSL streams
#: between processes, the soak. One worker runs them one after the other (handed out first: the group is
#: the longest unit of work), while the other workers take the rest.
REAL_TIME_GROUP = "real-time"
#: The xdist group of the tests marked ``alone``: handed out last, when the other workers have run out
#: of tests. Beside a worker that computes, a relay restarted in real time was measured deciding on 5
#: windows after its gap where the test asks for 20 (alone it passes).
ALONE_GROUP = "alone"


@pytest.hookimpl(tryfirst=True)             # before xdist reads the groups into the test ids
def pytest_collection_modifyitems(config, items):
    """Tests marked ``alone`` go to one xdist group, and so do the other tests marked ``hardware`` and
    those of the LSL modules (``loopback_only``); under xdist that group is handed out first, then the
    ``slow`` tests, then the rest, and the ``alone`` group last."""
    rank = {}
    for item in items:
        if item.get_closest_marker("alone"):
            item.add_marker(pytest.mark.xdist_group(ALONE_GROUP))
            rank[item] = 3
        elif item.get_closest_marker("hardware") or "loopback_only" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.xdist_group(REAL_TIME_GROUP))
            rank[item] = 0
        else:
            rank[item] = 1 if item.get_closest_marker("slow") else 2
    if hasattr(config, "workerinput"):
        # On xdist's workers (which all collect the same order; the scheduler hands tests out in it).
        items.sort(key=rank.__getitem__)


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


class _SharedModels(dict):
    """``supramodal.node.scene.build._trained_on_the_spot`` (the models the node trains on start, kept in
    memory by their texture set and pipeline settings) backed by :func:`run_once`'s folder, so that
    the xdist workers train each model once per run, not once each. The node's own key names the file:
    a model missing from memory is looked up there (:meth:`pop`), and a model the node trained is
    written there (:meth:`__setitem__`). While one worker trains, it holds the key's lock and a worker
    asking for the same model waits for it; the lock is let go when the model is written or, if the
    training raised, when the test ends (:func:`_release_model_locks`)."""

    def __init__(self):
        super().__init__()
        self.held = {}                       # path -> fd of a lock held while this process trains

    @staticmethod
    def _path(key):
        """The file of ``key``, or None where its repr does not say all of it (numpy elides long arrays)."""
        name = "trained-on-the-spot " + repr(key)
        return None if _SHARED_DIR is None or "..." in name else _shared_path(name)

    def pop(self, key, *default):
        path = None if key in self else self._path(key)
        if path is None:
            return super().pop(key, *default)
        if path not in self.held:
            fd = os.open(f"{path}.lock", os.O_CREAT | os.O_RDWR, 0o600)
            fcntl.flock(fd, fcntl.LOCK_EX)
            self.held[path] = fd
        try:
            with open(f"{path}.pickle", "rb") as f:
                made = pickle.load(f)
        except FileNotFoundError:
            if default:
                return default[0]            # the caller trains; __setitem__ writes it and lets go
            self.release()
            raise KeyError(key) from None
        self.release(path)
        return made

    def __setitem__(self, key, made):
        super().__setitem__(key, made)
        path = self._path(key)
        if path is not None and path in self.held:
            tmp = f"{path}.pickle.{os.getpid()}"
            with open(tmp, "wb") as f:
                pickle.dump(made, f, protocol=pickle.HIGHEST_PROTOCOL)
            os.replace(tmp, f"{path}.pickle")
            self.release(path)

    def release(self, path=None):
        for p in [path] if path is not None else list(self.held):
            fd = self.held.pop(p, None)
            if fd is not None:
                os.close(fd)


_shared_models = _SharedModels()


def _once_per_arguments(func, label, quiet):
    """``func`` computed once per run for each set of arguments (:func:`run_once`, named by a digest
    of the arguments' content, :func:`_digest`), for a deterministic ``func`` whose result pickles.
    Called with a progress callback (``quiet(kwargs)`` false) or with arguments it cannot digest,
    it runs as it is."""
    @functools.wraps(func)
    def once_per_arguments(*args, **kwargs):
        if _SHARED_DIR is None or not quiet(kwargs):
            return func(*args, **kwargs)
        digest = hashlib.sha256()
        try:
            _digest(digest, (args, kwargs))
        except TypeError:                    # something it cannot say all of: computed here
            return func(*args, **kwargs)
        return run_once(f"{label} {digest.hexdigest()}", lambda: func(*args, **kwargs))
    return once_per_arguments


def _digest(h, x, depth=0):
    """Feed ``x``'s content to the hash ``h``: numbers, strings, arrays (dtype, shape, bytes), lists,
    tuples, dicts and the attributes of plain objects (by class), so that a model and its unpickled
    copy digest alike (their pickles differ in how arrays are shared). TypeError for anything else
    (functions, locks, files) or nesting deeper than 40."""
    import numpy as np

    if depth > 40:
        raise TypeError("too deep")
    if x is None or isinstance(x, (bool, int, float, complex, str, bytes, np.generic)):
        h.update(f"{type(x).__name__}:{x!r};".encode())
    elif isinstance(x, np.ndarray):
        if x.dtype.hasobject:
            raise TypeError("object array")
        h.update(f"ndarray:{x.dtype.str}:{x.shape};".encode())
        h.update(np.ascontiguousarray(x).tobytes())
    elif isinstance(x, (list, tuple, frozenset, set)):
        items = sorted(x, key=repr) if isinstance(x, (set, frozenset)) else x
        h.update(f"{type(x).__name__}:{len(items)}(".encode())
        for item in items:
            _digest(h, item, depth + 1)
        h.update(b")")
    elif isinstance(x, dict):
        h.update(f"dict:{len(x)}(".encode())
        for key in sorted(x, key=repr):
            _digest(h, key, depth + 1)
            _digest(h, x[key], depth + 1)
        h.update(b")")
    elif isinstance(x, type):
        h.update(f"type:{x.__module__}.{x.__qualname__};".encode())
    elif hasattr(x, "__dict__") and not callable(x):
        h.update(f"object:{type(x).__module__}.{type(x).__qualname__}(".encode())
        state = dict(vars(x))
        for slot in getattr(type(x), "__slots__", ()):
            if hasattr(x, slot):
                state[slot] = getattr(x, slot)
        _digest(h, state, depth + 1)
        h.update(b")")
    else:
        raise TypeError(f"cannot digest {type(x).__name__}")


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
    process's own. The node's models trained on start are kept there too (:class:`_SharedModels`), and
    so is the cache of models trained on start (node/workflows/model_cache.py: ``SUPRAMODAL_CACHE``,
    set here before any test starts a process, which inherits it), never the user's own: a node run as
    a process by a test reads the model another process of the run trained."""
    global _SHARED_DIR
    config = session.config
    base = config._tmp_path_factory.getbasetemp()
    _SHARED_DIR = (base.parent if hasattr(config, "workerinput") else base) / "run-once"
    _SHARED_DIR.mkdir(exist_ok=True)
    from supramodal.node.workflows.model_cache import CACHE_ENV

    os.environ[CACHE_ENV] = str(_SHARED_DIR / "model-cache")
    from supramodal.node.scene import build

    build._trained_on_the_spot = _shared_models
    _share_fusion_training()


@pytest.fixture(autouse=True)
def _release_model_locks():
    """A model training that raised leaves its lock held (:class:`_SharedModels`): let it go."""
    yield
    _shared_models.release()


@pytest.fixture(scope="session")
def once():
    """:func:`run_once` for fixtures: ``once("module.fixture", compute)``."""
    return run_once
