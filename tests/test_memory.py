"""supramodal/memory.py: freed memory kept for the next array, measured by the page faults it saves."""

import subprocess
import sys

import pytest

CHURN = """
import resource, sys
import numpy as np
if sys.argv[1] == "kept":
    from supramodal.memory import keep_freed_memory
    assert keep_freed_memory()
a = np.random.default_rng(0).normal(size=(2400, 20))
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(200):            # an epoch's worth of temporaries of 375 KiB, made and freed
    b = np.clip(a, -1.0, 1.0)
    c = 1.0 - b
    c *= b
    del b, c
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux") or "glibc" not in " ".join(__import__("platform").libc_ver()),
                    reason="the setting is glibc's")
def test_temporaries_reuse_heap_pages_instead_of_new_ones():
    """With glibc's defaults the heap's top is given back and faulted in again time after time (3 000
    faults here, 2026-11-29); kept, the loop faults its pages once (190)."""
    faults = {how: int(subprocess.run([sys.executable, "-c", CHURN, how], capture_output=True, text=True,
                                      check=True, timeout=120).stdout) for how in ("defaults", "kept")}
    assert faults["defaults"] > 1_500
    assert faults["kept"] < faults["defaults"] / 8


def test_it_answers_false_where_there_is_no_glibc(monkeypatch):
    from supramodal import memory

    monkeypatch.setattr(memory.sys, "platform", "darwin")
    assert memory.keep_freed_memory() is False
