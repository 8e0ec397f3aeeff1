"""Shared test settings.

Hypothesis: no deadline (the suite asserts behaviour, never wall time); example counts are set per test
so that the whole suite stays near a minute on two cores.
"""

from hypothesis import HealthCheck, settings

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
