"""Shared test settings.

BLAS and OpenMP: one thread per test process, set here before numpy is loaded, and inherited by the
xdist workers and every process a test starts. The suite runs one test process per core (README:
``pytest -n auto``); a threaded OpenBLAS in each of them, on a machine whose cores are all taken,
spends its time waiting for its own threads: a model of the default scene on features Af and A was
measured training in 199 s with OpenBLAS's threads and in 15 s with one (two cores, load 6).

Hypothesis: no deadline (the suite asserts behaviour, never wall time); example counts are set per test
so that the whole suite stays near a minute on two cores.
"""

import os

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
