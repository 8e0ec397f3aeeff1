"""What every test module that opens LSL streams starts with: a skip without the ``lsl`` extra, and
a fixture that refuses to run a test that could send packets beyond this machine (tests/harness/environment.py
points ``LSLAPICFG`` at a loopback config; this checks it again before each test).

    from lsl_only import loopback_only, require_lsl  # noqa: F401  (the fixture applies itself)
    require_lsl()
"""

import pytest

from supramodal.benchmarks.lsl_link import check_loopback_config
from supramodal.drivers.lsl import LSLUnavailable, import_pylsl


def require_lsl() -> None:
    """Skip the calling module where pylsl (and its liblsl) cannot be loaded."""
    try:
        import_pylsl()
    except LSLUnavailable as exc:
        pytest.skip(f"the LSL tests need the lsl extra (CI installs it): {exc}", allow_module_level=True)


@pytest.fixture(autouse=True)
def loopback_only():
    """A test that could send packets beyond this machine does not run."""
    check_loopback_config()
