"""A short soak (benchmarks/soak.py): the node on the serial driver against the mock board on a
real pty with every fault kind and unplugs; the driver's counts equal the mock's ledger exactly.

The full run (an hour, 100 unplugs) is ``python3 -m supramodal.benchmarks.soak --minutes 60 --unplugs 100``.
"""

from __future__ import annotations

import pytest

from supramodal.benchmarks.soak import FAULT_RATES, format_report, run_soak

# alone: run beside the robot's live scene (and busy cores), its counts missed a truncated frame at an unplug in 3 of 22
# runs; the cause, found 2026-11-30 (the mock took bytes still on their way to the port as read), is mended in the mock
pytestmark = [pytest.mark.hardware, pytest.mark.slow, pytest.mark.alone]


def test_short_soak_counts_equal_the_ledger_and_nothing_stalls():
    # Fault rates 4x the full soak's, so that a short run injects every kind many times.
    rates = {k: 4 * v for k, v in FAULT_RATES.items()}
    rep = run_soak(20.0, unplugs=5, seed=3, sample_every=1.0, faults=rates)
    text = format_report(rep)
    rows = {r["count"]: r for r in rep["rows"]}
    # Every fault kind was injected, and every unplug happened.
    spec = rep["params"]["spec"]
    assert spec["unplug_limit"] == 5
    for name in ("truncated frames", "altered frames (CRC)", "frames left out", "wrong channel count",
                 "wrong version (header errors >=)", "frames while unplugged"):
        assert rows[name]["ledger"] > 0, name
    assert rows["unplugs"]["ledger"] == rows["unplugs"]["driver"] == 5, text
    assert rep["ledger_garbage"]["insertions"] > 0
    # The counts match exactly, row by row (header errors: at least the wrong-version frames).
    for r in rep["rows"]:
        assert r["ok"], f"{r['count']}: ledger {r['ledger']}, driver {r['driver']}, checked {r['checked']}\n{text}"
    assert rep["exact"]
    # The node ran until stopped, never stalled, and made windows all along.
    assert rep["node_error"] is None and rep["mock_error"] is None
    assert rep["stopped_by"] == "soak finished" and rep["stalls"] == 0
    assert rep["windows"] >= 0.9 * rep["stream_s"] * 10 - 2
    assert rep["passed"]
