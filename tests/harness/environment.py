"""What every test process is given before any test runs (a pytest plugin, first in tests/conftest.py's
``pytest_plugins``).

BLAS and OpenMP: one thread per test process, set when this module is imported, which is before numpy is
loaded (conftest.py imports nothing that loads it, and pytest imports the plugins it names right after it),
and inherited by the xdist workers and every process a test starts. The suite runs one test process per core
(docs/development.md: ``pytest -n auto``); a threaded OpenBLAS in each of them, on a machine whose cores are
all taken, spends its time waiting for its own threads: a model of the default scene on features Af and A was
measured training in 199 s with OpenBLAS's threads and in 15 s with one (two cores, load 6).

Hypothesis: no deadline (the suite asserts behaviour, never wall time); example counts are set per test so
that the whole suite stays near a minute on two cores.

LSL and ROS 2 stay on this machine in every test (:func:`pytest_configure`).

Relies on: pytest's ``pytest_configure`` hook; Hypothesis's settings profiles.
"""

import os

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
    import atexit
    import random
    import shutil
    import tempfile

    from supramodal.benchmarks.lsl_link import loopback_config

    folder = tempfile.mkdtemp(prefix="supramodal-lsl-")
    atexit.register(shutil.rmtree, folder, True)         # each test process's own, gone with it (they piled up)
    os.environ["LSLAPICFG"] = str(loopback_config(folder))
    # ROS 2 too (tests/ros2_only.py checks it again): DDS discovery on this machine only, in a domain of
    # this run's own (never the one a user's robot may use), drawn by the controller and kept by its workers.
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
