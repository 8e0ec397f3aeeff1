"""Driver events, said as they happen: the log, the rate limit, the sinks, and the node against the
mock board on a pty (report latencies against the issue's limits: 2 s for a misconfigured or silent
board, 1 s for an unplug or a reconnect), and the restart / overrun window flags.

Latencies are measured from the mock's own monotonic timestamps (start, unplug, replug) to the
moment a sink received the event; waits are bounded and generous, assertions are on the limits.
"""

from __future__ import annotations

import json
import re
import threading
import time

import numpy as np
import pytest

from supramodal.drivers.base import Block, DriverEvent, EventLog
from supramodal.drivers.mock_whisker import FaultSpec, MockWhiskerDevice
from supramodal.drivers.serial_whisker import SerialWhiskerDriver
from supramodal.node.runtime.events import EventLimiter
from supramodal.node.runtime.graph import Node
from supramodal.node.runtime.sinks import ListSink
from supramodal.node.runtime.sinks.jsonl import JsonLinesSink
from supramodal.node.runtime.sinks.text import TextSink
from supramodal.replay.driver import ReplayDriver
from supramodal.banks import whisker_bank
from supramodal.pipeline import FeaturePipeline

RATE, SPF, W = 5000, 32, 500


# -- the pieces ------------------------------------------------------------------------------


def test_event_log_is_bounded_and_counts_what_it_drops():
    log = EventLog(capacity=3, history=2)
    for i in range(5):
        log.record("gap" if i < 2 else "unplug", f"m{i}", stream_index=i)
    events, dropped = log.take()
    assert [e.message for e in events] == ["m2", "m3", "m4"] and dropped == {"gap": 2}
    assert log.take() == ([], {})
    assert [e.message for e in log.history()] == ["m3", "m4"]
    assert events[0].as_dict() == {"event": "unplug", "message": "m2", "time": round(events[0].time, 3),
                                   "stream_index": 2, "count": 1}


def test_limiter_passes_a_burst_then_folds_repeats_into_counts():
    now = [0.0]
    lim = EventLimiter(interval=1.0, burst=2, clock=lambda: now[0])
    ev = lambda k, m: DriverEvent(k, m, 0.0)  # noqa: E731
    shown = [lim.add(ev("channels", f"c{i}")) for i in range(10)]
    assert [e.message for e in shown if e] == ["c0", "c1"]
    assert lim.add(ev("unplug", "u")) is not None  # another kind has its own budget
    assert lim.due() == []
    now[0] = 1.0
    (late,) = lim.due()
    assert (late.message, late.count) == ("c9", 8)  # the latest, standing for 8
    lim.add(ev("channels", "c10"))
    lim.add(ev("channels", "c11"))
    assert [(e.message, e.count) for e in lim.flush()] == [("c11", 1)]
    lim.add_dropped({"channels": 5})
    assert lim.summary() == {"counts": {"channels": 17, "unplug": 1}, "dropped": {"channels": 5}}
    # a texture change is a decision, each one acted on: never held back nor folded
    changes = [lim.add(DriverEvent("change", f"x{i}", 0.0, source="main")) for i in range(5)]
    assert [(e.message, e.count) for e in changes if e] == [(f"x{i}", 1) for i in range(5)]
    assert lim.summary()["counts"]["main/change"] == 5 and lim.flush() == []


def test_sinks_write_events(tmp_path, capsys):
    ev = DriverEvent("unplug", "lost /dev/x", 1.5, 640, count=4)
    TextSink(str(tmp_path / "t.txt")).event(ev)
    assert capsys.readouterr().err == "supramodal: lost /dev/x (3 more since)\n"
    js = JsonLinesSink(str(tmp_path / "e.jsonl"))
    js.event(ev)
    js.close()
    assert json.loads((tmp_path / "e.jsonl").read_text()) == {
        "event": "unplug", "message": "lost /dev/x", "time": 1.5, "stream_index": 640, "count": 4}


def test_replay_notices_and_filled_runs_are_events():
    x = np.zeros((1000, 1))
    d = ReplayDriver((x, 44100), rate=5000, speed="max", block_size=100, on_notice=None)
    events, _ = d.take_events()
    assert [e.kind for e in events] == ["notice"] and "resampling" in events[0].message


def test_block_marks_default_to_none():
    b = Block(np.zeros((4, 1)), 0, 0.0)
    assert b.restarts == () and b.overruns == ()


# -- the node against the mock board ---------------------------------------------------------


class TimedSink(ListSink):
    """Keeps driver events with the monotonic time each one reached the sinks."""

    def __init__(self):
        super().__init__()
        self.received: list[tuple[float, DriverEvent]] = []

    def event(self, ev):
        self.received.append((time.monotonic(), ev))
        super().event(ev)

    def first(self, kind):
        return next((t for t, e in self.received if e.kind == kind), None)


def source(seconds, channels=1, seed=0):
    rng = np.random.default_rng(seed)
    return 0.3 * rng.standard_normal((int(seconds * RATE), channels))


def run_node(dev, channels, tmp_path, start_board=True, stop_after=None, node_kw=None):
    """Run a node on the serial driver against ``dev`` with a timed, a text and a JSON sink.

    Returns (timed sink, summary, driver, ledger, node start time, board start time)."""
    driver = SerialWhiskerDriver(dev.port, rate=RATE, channels=channels, on_notice=None)
    timed = TimedSink()
    text = TextSink(str(tmp_path / "windows.txt"))
    js = JsonLinesSink(str(tmp_path / "out.jsonl"))
    node = Node(driver, FeaturePipeline(whisker_bank(), ("Af",)), [timed, text, js],
                mapping=0 if channels > 1 else "auto", **(node_kw or {}))
    times = {}

    def board():
        time.sleep(0.3)                       # the node has opened the port by then
        if start_board:
            times["board"] = time.monotonic()
            dev.start()
            dev.finished.wait(60)
            time.sleep(0.6)                   # the last frames through the pty
        else:
            time.sleep(stop_after)
        node.stop("test done")

    with dev:
        t = threading.Thread(target=board, daemon=True)
        times["node"] = time.monotonic()
        t.start()
        summary = node.run()
        t.join(10)
        ledger = dev.ledger
    return timed, summary, driver, ledger, times


def jsonl_events(tmp_path):
    lines = [json.loads(s) for s in (tmp_path / "out.jsonl").read_text().splitlines()]
    return [d for d in lines if "event" in d]


@pytest.mark.hardware
def test_misconfigured_board_is_reported_on_its_first_frame(tmp_path, capsys):
    # The board sends 19 channels; the scene expects 20.
    dev = MockWhiskerDevice(source(1.5, 19), RATE, samples_per_frame=SPF)
    timed, summary, driver, ledger, times = run_node(dev, 20, tmp_path)
    latency = timed.first("channels") - times["board"]
    with capsys.disabled():
        print(f"channel mismatch reported {latency * 1e3:.0f} ms after the board started")
    assert latency < 2.0
    err = capsys.readouterr().err
    assert "supramodal: frame 0 has 19 channels but the driver is configured for 20" in err
    assert "more since)" in err  # every frame is bad: repeats are folded, not flooded
    lines = [ln for ln in err.splitlines() if "channels but the driver" in ln]
    assert len(lines) <= 3 * (summary["wall_seconds"] + 1)
    assert any(d["event"] == "channels" for d in jsonl_events(tmp_path))
    # Nothing lost silently: every skipped frame is counted, in the events and the driver.
    assert summary["events"]["counts"]["channels"] == driver.stats()["channel_mismatch"] == ledger.frames
    assert sum(e.count for e in timed.driver_events if e.kind == "channels") == ledger.frames
    assert summary["windows"] == 0


@pytest.mark.hardware
def test_silent_board_is_reported_within_two_seconds(tmp_path, capsys):
    dev = MockWhiskerDevice(np.zeros((64, 1)), RATE)   # never started: the port stays silent
    timed, summary, driver, _, times = run_node(dev, 1, tmp_path, start_board=False, stop_after=2.2)
    latency = timed.first("silence") - times["node"]
    with capsys.disabled():
        print(f"silent port reported {latency * 1e3:.0f} ms after the node started")
    assert latency < 2.0
    assert "no byte at all" in capsys.readouterr().err
    assert any(d["event"] == "silence" and "no byte at all" in d["message"] for d in jsonl_events(tmp_path))
    assert summary["events"]["counts"]["silence"] == driver.stats()["silence_warnings"] >= 1


@pytest.mark.hardware
def test_every_unplug_and_reconnect_is_reported_within_a_second(tmp_path, capsys):
    faults = FaultSpec(unplug_every=0.7, unplug_for=0.4, unplug_limit=2)
    dev = MockWhiskerDevice(source(3.5), RATE, samples_per_frame=SPF, faults=faults, seed=1)
    timed, summary, driver, ledger, _ = run_node(dev, 1, tmp_path)
    unplugs = [t for t, e in timed.received if e.kind == "unplug"]
    reconnects = [t for t, e in timed.received if e.kind == "reconnect"]
    assert ledger.unplugs >= 2 and len(unplugs) == len(reconnects) == ledger.unplugs
    unplug_lat = [a - b for a, b in zip(unplugs, ledger.unplug_times)]
    reconnect_lat = [a - b for a, b in zip(reconnects, ledger.replug_times)]
    with capsys.disabled():
        print(f"unplug reported after {[round(x * 1e3) for x in unplug_lat]} ms, reconnect after "
              f"{[round(x * 1e3) for x in reconnect_lat]} ms (from the port's return)")
    assert all(0 <= x < 1.0 for x in unplug_lat) and all(0 <= x < 1.0 for x in reconnect_lat)
    err = capsys.readouterr().err
    assert err.count("supramodal: lost ") == err.count("supramodal: reconnected to ") == ledger.unplugs
    kinds = [d["event"] for d in jsonl_events(tmp_path)]
    assert kinds.count("unplug") == kinds.count("reconnect") == ledger.unplugs
    assert summary["events"]["counts"]["unplug"] == driver.stats()["unplugs"] == ledger.unplugs


@pytest.mark.hardware
def test_restart_window_is_flagged(tmp_path):
    dev = MockWhiskerDevice(source(2.0), RATE, samples_per_frame=SPF, restart_at=(100,))
    timed, summary, driver, ledger, _ = run_node(dev, 1, tmp_path)
    assert ledger.restart_at == [100]
    offset = driver.first_sequence * SPF   # frames before the first one read (normally none)
    lost_before = sum(1 for k in ledger.lost if k < 100)   # pty overflow on a loaded machine: filled
    assert driver.stats()["discontinuities"] == 1
    at = 100 * SPF - offset
    assert lost_before == 0 or driver.stats()["filled"] == lost_before * SPF
    windows = {e["window"] for e in timed.events if e.get("restart")}
    assert windows == {at // W}
    assert not any(e.get("overrun") for e in timed.events)
    assert summary["events"]["counts"]["restart"] == 1
    assert any(e.kind == "restart" and e.stream_index == at for e in timed.driver_events)


@pytest.mark.hardware
def test_overrun_windows_are_flagged(tmp_path):
    dev = MockWhiskerDevice(source(2.0), RATE, samples_per_frame=SPF,
                            faults=FaultSpec(overrun_rate=0.03), seed=5)
    timed, summary, driver, ledger, _ = run_node(dev, 1, tmp_path)
    assert len(ledger.overrun_at) >= 3
    offset = driver.first_sequence * SPF
    received = [k for k in ledger.overrun_at if k not in ledger.lost]
    assert driver.stats()["device_overruns"] == len(received)
    emitted = {e["window"] for e in timed.events}
    expected = {(k * SPF - offset) // W for k in received} & emitted
    assert {e["window"] for e in timed.events if e.get("overrun")} == expected
    assert not any(e.get("restart") for e in timed.events)
    assert summary["events"]["counts"]["overrun"] == len(received)


@pytest.mark.hardware
@pytest.mark.parametrize("json_mode", [True, False])
def test_the_command_line_says_what_the_board_does_as_it_happens(tmp_path, json_mode):
    """`supramodal run SCENE [--json]` in its own process against a board configured for 19 channels
    that unplugs once: the mismatch and the unplug and reconnect appear while the node runs (JSON
    objects on stdout with --json, one line each on stderr in text), repeats folded into counts."""
    import subprocess
    import sys

    faults = FaultSpec(unplug_every=1.0, unplug_for=0.4, unplug_limit=1)
    dev = MockWhiskerDevice(source(3.0, 19), RATE, samples_per_frame=SPF, faults=faults, seed=2)
    scene = tmp_path / "s.toml"
    with dev:
        scene.write_text(f'[driver]\ntype = "serial"\nport = "{dev.port}"\nrate = {RATE}.0\nchannels = 20\n'
                         'mapping = "per-channel"\n[bank]\nkind = "whisker"\n')
        # not -q: it would leave out the news (the reconnect), keeping only the alarms and warnings
        proc = subprocess.Popen([sys.executable, "-m", "supramodal.node.cli", "run", str(scene),
                                 "--seconds", "inf"] + ["--json"] * json_mode,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            # the node's start-up (imports, the bank) takes over a second on a busy machine: start the
            # board once it has the port open, so that the unplug falls inside its run
            assert dev.wait_for_reader(60), "the node never opened the port"
            dev.start()
            dev.finished.wait(60)
            time.sleep(1.5)                   # the reconnect's report, and the last frames
        finally:
            proc.send_signal(2)               # Ctrl-C: the node stops with its summary
            out, err = proc.communicate(timeout=60)
        ledger = dev.ledger
    assert proc.returncode == 0, err
    assert ledger.unplugs == 1
    if json_mode:
        events = [d for d in map(json.loads, out.splitlines()) if "event" in d]
        kinds = [d["event"] for d in events]
        assert "channels" in kinds and kinds.count("unplug") == kinds.count("reconnect") == 1
        mismatch = [d for d in events if d["event"] == "channels"]
        assert len(mismatch) <= 3 * 6                   # at most 3 a second are shown ...
        summary = json.loads(out.splitlines()[-1])
        # ... and every frame the driver saw counted; it saw the frames sent, but for those still in
        # the pty when Ctrl-C came (none on a quiet machine; a few tens of ms of them under load)
        seen = summary["driver"]["channel_mismatch"]
        assert summary["events"]["counts"]["channels"] == seen and ledger.sent - 60 <= seen <= ledger.sent
        assert any(d["count"] > 1 for d in mismatch)     # repeats folded into the next one shown
        assert sum(d["count"] for d in mismatch) <= ledger.sent
    else:
        # the first frame the node saw (frame 0, or a later one when the node opened the port after
        # the board had started: the board drops frames while nobody reads)
        assert re.search(r"frame \d+ has 19 channels but the driver is configured for 20", err), err
        assert "more since)" in err
        assert err.count("supramodal: lost ") == err.count("supramodal: reconnected to ") == 1


@pytest.mark.hardware
def test_a_recorded_session_replays_with_the_live_runs_restart_and_overrun_flags(tmp_path):
    """Recorded from a board that restarts once and overruns now and then, a session keeps the
    marks (its sidecar's "marks"), and replaying it flags exactly the windows the live run flagged,
    in any block size."""
    from supramodal.node.runtime.taps.recorder import SessionRecorder
    from supramodal.replay.session import load_session

    dev = MockWhiskerDevice(source(2.5), RATE, samples_per_frame=SPF, restart_at=(120,),
                            faults=FaultSpec(overrun_rate=0.03), seed=7)
    recorder = SessionRecorder(tmp_path / "rec", "s", "mock board")
    timed, summary, driver, ledger, _ = run_node(dev, 1, tmp_path, node_kw={"recorder": recorder})
    assert ledger.restart_at == [120] and len(ledger.overrun_at) >= 3
    live = {e["window"]: (bool(e.get("restart")), bool(e.get("overrun"))) for e in timed.events}
    assert any(r for r, _ in live.values()) and any(o for _, o in live.values())
    session = load_session(tmp_path / "rec" / "s")
    kinds = [k for _, k in session.marks]
    assert kinds.count("restart") == 1 and kinds.count("overrun") == driver.stats()["device_overruns"]
    for block in (SPF, 37, 1000):
        sink = ListSink()
        Node(ReplayDriver(session, block_size=block, speed="max", on_notice=None),
             FeaturePipeline(whisker_bank(), ("Af",)), [sink]).run()
        replayed = {e["window"]: (bool(e.get("restart")), bool(e.get("overrun"))) for e in sink.events}
        assert replayed == live, block
