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
