"""The suite's shared fixtures.

The harness the suite runs in lives in tests/harness/, a pytest plugin per concern, each module saying what
it does, why and what it relies on; it is registered here (``pytest_plugins``, which pytest reads from the
conftest.py of the test paths only, so this file):

- harness.environment: one BLAS thread per test process, Hypothesis's profile, LSL and ROS 2 kept on this
  machine (first: the thread settings must come before anything imports numpy);
- harness.shared_folder: the run's temporary folder, shared by its xdist workers;
- harness.pacing: ``pytest -n auto``, the groups of tests paced in real time, each on one worker;
- harness.shared_trainings: the run's model cache, and trainings computed once per run (harness.run_once).
"""

import pytest

pytest_plugins = [
    "harness.environment",
    "harness.shared_folder",
    "harness.pacing",
    "harness.shared_trainings",
]


@pytest.fixture(scope="session")
def once():
    """:func:`harness.run_once.run_once` for fixtures: ``once("module.fixture", compute)``, computed once per
    test run by whichever xdist worker asks first."""
    # Imported here, not above: pytest imports the plugins above itself, after this file, to rewrite their
    # asserts, and harness.run_once imports one of them.
    from harness.run_once import run_once

    return run_once
