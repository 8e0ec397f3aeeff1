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
#: between processes, the soak. One worker runs them one after the other, last, when the other workers
#: have run out of tests: beside a worker that computes, a relay restarted in real time was measured
#: deciding on 5 windows after its gap where the test asks for 20 (it passes alone).
REAL_TIME_GROUP = "real-time"


@pytest.hookimpl(tryfirst=True)             # before xdist reads the groups into the test ids
def pytest_collection_modifyitems(config, items):
    """Tests marked ``hardware`` and those of the LSL modules (``loopback_only``) go to one xdist group;
    under xdist the ``slow`` tests are handed out first and that group last."""
    real_time = set()
    for item in items:
        if item.get_closest_marker("hardware") or "loopback_only" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.xdist_group(REAL_TIME_GROUP))
            real_time.add(item)
    if hasattr(config, "workerinput"):
        # On xdist's workers (which all collect the same order; the scheduler hands tests out in it):
        # the long tests first, so that none of them is left to run alone at the end, and the
        # real-time group last, so that it runs when nothing else does.
        items.sort(key=lambda item: (item in real_time, item.get_closest_marker("slow") is None))

