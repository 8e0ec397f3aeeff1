"""Interfaces, not probes (issue 24, item 2): a sink is a :class:`Sink`, a tap a :class:`Tap`, a driver a
:class:`DriverBase`; the graph calls their bases' methods, which a minimal subclass leaves as they
are, and never probes a sink, a tap or a driver for a method."""

from __future__ import annotations

import re
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from supramodal.banks import whisker_bank
from supramodal.drivers.base import Block, Driver, DriverBase, DriverClosed, DriverEvent, EventLog
from supramodal.errors import InputError
from supramodal.node.runtime.graph import Graph
from supramodal.node.runtime.ringbuffer import RingClosed
from supramodal.node.runtime.sinks import ListSink, QueuedSink, Sink
from supramodal.node.runtime.sources import Source
from supramodal.node.runtime.streams import Stream
from supramodal.node.runtime.taps import Tap
from supramodal.pipeline import FeaturePipeline

from stand_ins import StandInDriver

ROOT = Path(__file__).resolve().parents[1]
RATE = 5000.0


class _Chattering(StandInDriver):
    """One second of noise in blocks of 250 frames, and one driver event with the first block."""

    rate, channels = RATE, 1

    def __init__(self):
        self._x = np.random.default_rng(0).standard_normal((int(RATE), 1)) * 0.2
        self._at = 0

    def read(self, timeout=None):
        if self._at >= len(self._x):
            raise DriverClosed("end of the toy stream")
        block = Block(self._x[self._at:self._at + 250], self._at, time.monotonic())
        if self._at == 0:
            self._record("notice", "the toy driver began", 0)
        self._at += 250
        return block

    def stats(self):
        return {"frames": self._at, "filled": 0}


class _OnlyWindows(Sink):
    """The least a sink can be: it overrides the window call and nothing else."""

    def __init__(self):
        self.windows = []

    def emit(self, event):
        self.windows.append(event)


class _CountingTap(Tap):
    """The least a tap can be: a name and ``run``; it counts the frames it read."""

    name = "counter"

    def __init__(self):
        self.frames = 0

    def run(self, feed):
        while True:
            try:
                got = feed.reader.read(timeout=0.05)
            except RingClosed:
                return
            if got is not None:
                self.frames += got[1].shape[0]


def _graph(sinks, taps=()):
    source = Source("main", _Chattering(), overrun="block")
    stream = Stream("main", source, FeaturePipeline(whisker_bank(), ("Af",)))
    return Graph([source], [stream], sinks, taps=[("main", t) for t in taps])


def test_a_minimal_sink_and_a_minimal_tap_run_in_a_graph():
    """A sink overriding only ``emit`` (plain and queued) and a tap giving only ``run``: the graph
    makes every call of their bases (start, event, drain, stats, summary, close; prepare, start,
    summary, close) without error, and they get every window and every frame."""
    plain, queued, listed, tap = _OnlyWindows(), _OnlyWindows(), ListSink(), _CountingTap()
    summary = _graph([plain, QueuedSink(queued), listed], [tap]).run()
    assert summary["windows"] == 10
    assert len(plain.windows) == len(queued.windows) == len(listed.windows) == 10
    assert [ev.kind for ev in listed.driver_events] == ["notice"]           # events reached the sinks
    assert summary["events"]["counts"] == {"notice": 1}
    # only the queued sink counts what it wrote (a plain sink's stats() is None)
    assert [s["sink"] for s in summary["sinks"]] == ["_OnlyWindows"]
    assert summary["sinks"][0]["written"] == 10 + 1 and summary["sinks"][0]["errors"] == 0
    assert tap.frames == 5000
    assert summary["taps"]["counter"]["frames"]["delivered"] == 5000
    assert listed.final is summary


def test_the_bases_calls_are_no_ops():
    sink, tap = _OnlyWindows(), _CountingTap()
    sink.start(0.0)
    sink.event(DriverEvent("notice", "x", 0.0))
    sink.drain(0.1)
    sink.summary({})
    sink.close()
    assert sink.stats() is None and sink.path is None and sink.on_reader_left is None
    tap.prepare()
    tap.start(None, 0.0)
    tap.close()
    tap.close()
    assert tap.summary() == {} and tap.track


def test_a_sink_or_tap_that_is_not_one_is_refused_when_the_graph_is_made():
    class Duck:
        def emit(self, event):
            pass

    with pytest.raises(InputError, match="derive from supramodal.node.runtime.sinks.Sink"):
        _graph([Duck()])
    with pytest.raises(InputError, match="queued sink runs a Sink"):
        QueuedSink(Duck())
    with pytest.raises(InputError, match="taps derive from supramodal.node.runtime.taps.Tap"):
        _graph([], [Duck()])
    with pytest.raises(TypeError):
        Sink()                      # emit is the one call a sink must give
    with pytest.raises(TypeError):
        Tap()                       # and run a tap's


def test_a_queued_sink_passes_start_and_drain_on():
    class Clocked(_OnlyWindows):
        def __init__(self):
            super().__init__()
            self.calls = []

        def start(self, epoch):
            self.calls.append(("start", epoch))

        def drain(self, timeout=5.0):
            self.calls.append(("drain", threading.current_thread() is threading.main_thread()))

    inner = Clocked()
    q = QueuedSink(inner)
    q.start(12.5)
    q.drain(1.0)
    q.close()
    assert inner.calls == [("start", 12.5), ("drain", True)]


def test_the_driver_base_gives_the_contract_but_read_and_stats():
    """A driver giving only rate, channels, read and stats (and not calling the base's __init__)
    is a Driver: no events until it logs one, then each once; a context manager; no labels; its
    fills are not drops."""
    driver = _Chattering()
    assert isinstance(driver, Driver) and isinstance(driver.event_log, EventLog)
    assert driver.take_events() == ([], {})
    assert not driver.fills_are_drops and driver.labels == () and driver.passes == 1 and driver.period is None
    with driver as d:
        assert d is driver
        d.read()
    events, dropped = driver.take_events()
    assert [(ev.kind, ev.message, ev.stream_index) for ev in events] == [("notice", "the toy driver began", 0)]
    assert dropped == {} and driver.take_events() == ([], {})
    assert len(driver.events) == 1 and driver.events[0].endswith(" the toy driver began")


def test_a_driver_notice_is_logged_then_handed_on():
    class Telling(DriverBase):
        EVENT_CAPACITY = 2

        def __init__(self, told):
            super().__init__()
            self._on_notice = told.append

    told = []
    driver = Telling(told)
    driver._notice("resampling", stream_index=3)
    driver._notice("quiet", "silence")
    driver._record("gap", "x")                          # beyond the capacity: the oldest is counted
    events, dropped = driver.take_events()
    assert told == ["resampling", "quiet"]
    assert [(ev.kind, ev.message) for ev in events] == [("silence", "quiet"), ("gap", "x")]
    assert dropped == {"notice": 1}


def test_a_driver_that_is_not_one_is_refused_when_its_source_is_made():
    class Duck:
        rate, channels = RATE, 1

        def open(self):
            pass

        def close(self):
            pass

        def read(self, timeout=None):
            return None

        def stats(self):
            return {"frames": 0, "filled": 0}

    with pytest.raises(InputError, match=r"source 'main': the driver Duck lacks take_events, fills_are_drops, "
                                         r"labels, passes, period, __enter__, __exit__ .*derive from "
                                         r"supramodal\.drivers\.base\.DriverBase"):
        Source("main", Duck())


# -- no probes ------------------------------------------------------------------------------------

#: The runtime modules that call sinks, taps or drivers.
RUNTIME = ("node/runtime/graph.py", "node/runtime/sinks/__init__.py", "node/runtime/sinks/text.py",
           "node/runtime/sinks/jsonl.py", "node/runtime/sources.py", "node/runtime/streams.py", "node/runtime/sinks/lsl.py",
           "node/runtime/taps/lsl_signal.py", "node/runtime/taps/recorder.py", "node/runtime/taps/__init__.py")
#: The probes left, each with why: (file, the probe's text). None: drivers derive from DriverBase,
#: which gives every member of the contract (take_events, fills_are_drops, labels, ...).
ALLOWED: set[tuple[str, str]] = set()


def test_the_runtime_probes_no_sink_tap_or_driver():
    """No getattr/hasattr in the runtime modules, but the probes listed in ALLOWED (none)."""
    found = set()
    for name in RUNTIME:
        for line in (ROOT / name).read_text().splitlines():
            code = line.split("#", 1)[0]
            for m in re.finditer(r"\b(?:getattr|hasattr)\([^)]*\)", code):
                found.add((name, m.group(0)))
    assert found <= ALLOWED, f"probes that are not allowed: {sorted(found - ALLOWED)}"
