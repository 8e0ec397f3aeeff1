"""The harness the test suite runs in: pytest plugins, one module per concern, registered by tests/conftest.py
(``pytest_plugins``), which keeps the fixtures.

- :mod:`harness.environment`: what every test process is given before any test runs: one BLAS thread,
  Hypothesis's profile, LSL and ROS 2 kept on this machine.
- :mod:`harness.shared_folder`: one temporary folder per test run, shared by the run's xdist workers.
- :mod:`harness.pacing`: ``pytest -n auto`` (pytest-xdist): a worker per core plus one per group of tests
  paced in real time; each group kept on one worker, a test marked ``alone`` with no other paced test beside
  it, the workers that compute in idle time.
- :mod:`harness.run_once`: results computed once per run by whichever worker asks first, read by the others.
- :mod:`harness.shared_trainings`: the trainings the suite shares that way (the run's model cache, the models
  trained on start, the fusions' trainings).

tests/ is on ``sys.path`` while the suite runs (pytest's default ``prepend`` import mode, as for
tests/lsl_only.py), so the package imports as ``harness``. tests/test_harness.py runs small suites under these
plugins (pytester) and checks what they promise.
"""
