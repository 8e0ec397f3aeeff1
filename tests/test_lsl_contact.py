"""``[decision] contact_from = "lsl:NAME"``: the robot's contact markers on an LSL stream, against real liblsl."""

from __future__ import annotations

import uuid

import pytest

from contact_edges import EDGES, expected, run_with_edges
from lsl_only import loopback_only, require_lsl  # noqa: F401  (the fixture applies itself)

require_lsl()

from supramodal.drivers.lsl import import_pylsl  # noqa: E402  (after the skip)


@pytest.mark.slow   # paced in real time, with a model trained on start (or the run's cache)
def test_contacts_follow_an_lsl_marker_stream_and_a_marker_of_no_state_is_counted_and_said():
    """Done when (issue 33): with an LSL marker stream ("touch" / "release", stamped by the sender), contacts
    follow its edges on the sender's stamps (within one window); a marker that says no state is left out,
    counted and said (a ``contact`` event)."""
    pylsl = import_pylsl()
    name = f"contacts_{uuid.uuid4().hex[:8]}"
    info = pylsl.StreamInfo(name, "Markers", 1, pylsl.IRREGULAR_RATE, pylsl.cf_string, name)
    outlet = pylsl.StreamOutlet(info)
    words = {True: "touch", False: "release"}

    def say(state: bool) -> float:
        # stamped by the sender: the time it says the edge, on its (here: this host's) LSL clock
        import time

        at = time.monotonic()
        outlet.push_sample([words[state]], pylsl.local_clock())
        return at

    first = [True]

    def matched() -> bool:
        if outlet.have_consumers() and first:
            first.clear()
            outlet.push_sample(["hello"])        # no state: refused, counted, said
        return outlet.have_consumers()

    try:
        sink, summary, edges = run_with_edges(f"lsl:{name}", say, matched, repeat=False)
    finally:
        del outlet
    assert [s for _, s in edges] == [s for _, s in EDGES]
    windows = sink.windows
    span = windows[0].end - windows[0].start
    near = [w for w in windows if min(abs(0.5 * (w.start + w.end) - t) for t, _ in edges) <= span]
    for w in windows:
        centre = 0.5 * (w.start + w.end)
        if w not in near:
            assert w.in_contact == expected(edges, centre), (w.window, centre, edges)
    assert len(near) <= 3 * len(edges)
    contact = summary["contacts"][0]
    assert contact == {"from": f"lsl:{name}", "states": 4, "touches": 2, "messages": 5, "refused": 1}
    said = [e for e in sink.driver_events if e.kind == "contact"]
    assert len(said) == 1 and "'hello'" in said[0].message and "no contact state" in said[0].message
