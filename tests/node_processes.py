"""A node run as its own process (`python -m supramodal run SCENE`), and what a signal does to it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path


def start_node(scene: Path, cwd: Path) -> subprocess.Popen:
    """`supramodal run SCENE --quiet` in a process of its own, its output captured as text."""
    return subprocess.Popen([sys.executable, "-m", "supramodal", "run", str(scene), "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=cwd)


def assert_start_up_ends_on(proc: subprocess.Popen, signum: int, code: int) -> None:
    """``proc``, still starting up (waiting for a consumer), ends at once on ``signum`` with exit
    ``code`` (130 for SIGINT, 143 for SIGTERM), saying so, and prints nothing on stdout."""
    assert proc.poll() is None, proc.communicate()
    t = time.monotonic()
    os.kill(proc.pid, signum)
    out, err = proc.communicate(timeout=20)
    waited = time.monotonic() - t
    assert proc.returncode == code and waited < 10, (proc.returncode, waited, err[-500:])
    assert f"interrupted by {signal.Signals(signum).name} during start-up" in err
    assert out == ""
