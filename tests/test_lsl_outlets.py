"""The node's window outlets (``[[sink]] type = "lsl"``): up before the start-up work, so that a
consumer started before the node gets window 0; ``wait_for_consumer``, a start-up wait that SIGINT
and SIGTERM end; what each outlet declares (issue 26, items 7 and 11). By default each outlet keeps
its first windows for its first consumer, so that one started before the node gets window 0 however
soon the node starts; liblsl's INFO lines stay out of the node's output (issue 36, items 7 and 6).

Traffic stays on this machine (tests/harness/environment.py's loopback ``LSLAPICFG``, checked by every test)."""

import json
import os
import threading
import time
import uuid

import numpy as np
import pytest

from supramodal.benchmarks.lsl_link import RATE, check_loopback_config, whisker_signal
from supramodal.drivers.base import DeviceUnavailable
from supramodal.drivers.lsl import import_pylsl, resolve_stream

from lsl_only import loopback_only, require_lsl  # noqa: F401  (the fixture applies itself)
from node_processes import assert_start_up_ends_on, start_node

require_lsl()

from supramodal.node.runtime.events import WindowEvent  # noqa: E402
from supramodal.node.runtime.sinks import lsl as lsl_sink  # noqa: E402  (needs pylsl)
from supramodal.node.runtime.sinks.lsl import LSLOutletSink, OutletStream, outlet_name  # noqa: E402


def _replay_scene(tmp_path, prefix: str, seconds: float, sink: str, model: str = "train_on_start = true") -> str:
    from supramodal.replay.wavio import write_wav

    write_wav(tmp_path / "s.wav", whisker_signal(seconds), RATE)
    return (f'[driver]\ntype = "replay"\npath = "s.wav"\nmapping = "per-channel"\n\n[bank]\nkind = "whisker"\n\n'
            f'[features]\nnames = ["Af", "A"]\n\n[model]\n{model}\n\n[decision]\nscope = "window"\n\n'
            f'[[sink]]\ntype = "lsl"\nprefix = "{prefix}"\n{sink}\n')


@pytest.mark.slow   # a long run: a model trained on the spot while a consumer resolves the outlets
def test_the_outlets_are_up_while_the_model_trains(tmp_path, monkeypatch):
    """Issue 26 item 7: the outlets were made after the start-up training, ~0.1 s before the first
    window, while resolving takes 0.6-1.5 s. Now a consumer resolves them while the model trains:
    the training's progress line comes after they are up."""
    from supramodal.node.scene.build import build_node
    from supramodal.node.scene.schema import scene_from_dict

    import tomllib

    monkeypatch.setenv("SUPRAMODAL_CACHE", "off")   # not a model a node process of the run left in the cache

    prefix = f"t{uuid.uuid4().hex[:8]}"
    d = tomllib.loads(_replay_scene(tmp_path, prefix, 1.0, 'outputs = ["decisions", "posteriors"]'))
    scene = scene_from_dict(d, str(tmp_path / "s.toml"), tmp_path)
    found = []

    def progress(message):
        if message.startswith("trained on"):
            try:
                found.append(resolve_stream(outlet_name(prefix, "main", "decisions"), timeout=10.0).name())
            except DeviceUnavailable as exc:
                found.append(str(exc))

    graph = build_node(scene, progress=progress)
    try:
        assert found == [outlet_name(prefix, "main", "decisions")]
    finally:
        for s in graph.sinks:
            s.close()


def _node_with_a_consumer_from_before(tmp_path, outlet: str, pull, timeout: float) -> list:
    """Run the node of ``tmp_path/node.toml`` (a process) with a plain pylsl consumer of ``outlet`` started
    before it, on a thread: it resolves as the node's own LSL inlet does (1-3 s more, waiting for a
    duplicate), opens, and ``pull(inlet)`` reads until it has what it wants. Returns what ``pull`` returned,
    once the node has ended with status 0 and the consumer raised nothing (else the assertion says which)."""
    pylsl = import_pylsl()
    got: list = []
    failed: list = []

    def consume() -> None:
        try:
            inlet = pylsl.StreamInlet(resolve_stream(outlet, timeout=120.0))
            inlet.open_stream(timeout=30)
            got.extend(pull(inlet))
        except Exception as exc:           # the assertion below says what went wrong
            failed.append(exc)

    consumer = threading.Thread(target=consume, daemon=True)
    consumer.start()                       # before the node
    node = start_node(tmp_path / "node.toml", tmp_path)
    try:
        _, err = node.communicate(timeout=timeout)
    finally:
        node.kill()
    consumer.join(timeout=30)
    assert node.returncode == 0 and not failed, (err[-800:], failed)
    return got


@pytest.mark.slow   # a node process that trains on the spot, then streams in real time
def test_a_consumer_started_before_the_node_receives_window_0(tmp_path):
    """Done when (issue 26): a plain pylsl consumer, started before the node, receives window 0
    and every window after it; the node waits for it (``wait_for_consumer``) and says so."""
    prefix = f"t{uuid.uuid4().hex[:8]}"
    (tmp_path / "node.toml").write_text(_replay_scene(tmp_path, prefix, 3.0,
                                                      'outputs = ["decisions"]\nwait_for_consumer = 120\n\n'
                                                      '[[sink]]\ntype = "jsonl"\npath = "out.jsonl"'))

    def pull(inlet) -> list:
        got: list = []
        end = time.monotonic() + 120
        while time.monotonic() < end and not (got and got[-1]["window"] >= 29):
            chunk, _ = inlet.pull_chunk(timeout=0.0)
            got.extend(json.loads(s[0]) for s in chunk)
            time.sleep(0.01)
        return got

    got = _node_with_a_consumer_from_before(tmp_path, outlet_name(prefix, "main", "decisions"), pull, 300)
    assert [m["window"] for m in got] == list(range(30))
    summary = json.loads((tmp_path / "out.jsonl").read_text().splitlines()[-1])
    waited = [s for s in summary["sinks"] if "waited_s" in s]
    assert len(waited) == 1 and waited[0]["consumers"] == ["main-decisions"], summary["sinks"]


@pytest.mark.parametrize("signum, code", [(2, 130), (15, 143)])
def test_a_wait_for_consumers_of_the_window_outlets_is_start_up_and_a_signal_ends_it(tmp_path, signum, code):
    """``wait_for_consumer`` on an LSL sink is start-up, as on a signal outlet: SIGINT and SIGTERM
    end it at once with 130 and 143."""
    prefix = f"t{uuid.uuid4().hex[:8]}"
    (tmp_path / "node.toml").write_text(_replay_scene(tmp_path, prefix, 1.0, "wait_for_consumer = 60",
                                                      model="# none: features only"))
    proc = start_node(tmp_path / "node.toml", tmp_path)
    try:
        resolve_stream(outlet_name(prefix, "main", "features"), timeout=60.0)   # built: it waits now
        time.sleep(1.0)
        assert_start_up_ends_on(proc, signum, code)
    finally:
        proc.kill()


def test_every_outlet_declares_its_channels_and_the_fused_posteriors_no_regular_rate():
    """Issue 26 item 11: the decisions outlet had no ``channels`` element (docs/lsl.md says every
    stream has one); the fused posteriors declared 10 Hz though a fused window is stamped when its
    pair is complete (0.062-0.138 s apart measured): it is irregular now, as its decisions."""
    pylsl = import_pylsl()
    prefix = f"t{uuid.uuid4().hex[:8]}"
    classes = ("a", "b")
    streams = [OutletStream("main", "whisker", 5000.0, ("C1",), (100.0,), ("A",), 0.1, classes),
               OutletStream("fused", "fused", 0.0, (), (), (), 0.1, classes)]
    sink = LSLOutletSink(streams, prefix=prefix)
    try:
        infos = {}
        for stream in ("main", "fused"):
            for output in ("decisions", "posteriors"):
                inlet = pylsl.StreamInlet(resolve_stream(outlet_name(prefix, stream, output), timeout=10.0))
                infos[stream, output] = inlet.info(timeout=10)
        for (stream, output), info in infos.items():
            labels = info.get_channel_labels()
            assert labels == (["decision"] if output == "decisions" else list(classes)), (stream, output, labels)
        decisions = infos["main", "decisions"].desc().child("channels").child("channel")
        assert decisions.child_value("unit") == "json" and decisions.child_value("type") == "marker"
        assert infos["main", "posteriors"].nominal_srate() == pytest.approx(10.0)
        assert infos["fused", "posteriors"].nominal_srate() == pylsl.IRREGULAR_RATE
        assert infos["fused", "decisions"].nominal_srate() == pylsl.IRREGULAR_RATE
    finally:
        sink.close()


# -- issue 36, item 7: window 0 for a consumer started before the node, with the default keys -------------

CLASSES = ("a", "b")


def _decision(window: int) -> WindowEvent:
    return WindowEvent(stream="main", window=window, start=0.1 * window, end=0.1 * (window + 1), t=0.0,
                       posteriors=np.array([0.9, 0.1]), decision="a", confidence=0.9)


def test_by_default_an_outlet_keeps_its_first_windows_for_its_first_consumer():
    """Issue 36 item 7: with the default keys a consumer that connected after the first windows were
    pushed never got them (liblsl sends a new consumer nothing pushed before it connected; windows 0-23
    were lost). Now the windows sent before any consumer came wait for it, stamped as they were, and
    the summary says which outlets had one in time; the node itself never waited."""
    pylsl = import_pylsl()
    prefix = f"t{uuid.uuid4().hex[:8]}"
    sink = LSLOutletSink([OutletStream("main", "whisker", 5000.0, ("C1",), (100.0,), ("A",), 0.1, CLASSES)],
                         outputs=["decisions"], prefix=prefix)
    try:
        sink.prepare()
        t = time.monotonic()
        sink.start(time.monotonic())
        for k in range(3):                           # before any consumer can be there
            sink.emit(_decision(k))
        assert time.monotonic() - t < 1.0            # nothing waited
        found = pylsl.resolve_byprop("name", outlet_name(prefix, "main", "decisions"), timeout=10.0)
        inlet = pylsl.StreamInlet(found[0])
        inlet.open_stream(timeout=10)
        for k in range(3, 10):                       # windows go on coming, 0.05 s apart
            time.sleep(0.05)
            sink.emit(_decision(k))
        sink.drain()
        got: list = []
        stamps: list = []
        end = time.monotonic() + 10
        while len(got) < 10 and time.monotonic() < end:
            chunk, ts = inlet.pull_chunk(timeout=0.2)
            got += [json.loads(x[0])["window"] for x in chunk]
            stamps += ts
        assert got == list(range(10))
        assert np.allclose(np.diff(stamps), 0.1, atol=1e-6)        # each stamped with its own window's end
        assert sink.stats() == {"sink": "LSLOutletSink", "held_s": lsl_sink.HOLD_FOR_CONSUMER_SECONDS,
                                "consumers": ["main-decisions"]}
    finally:
        sink.close()


def test_a_consumer_gets_the_last_windows_pushed_before_the_sink_closes():
    """liblsl sends from threads of its own and an outlet released drops what it has not sent: a consumer on a
    busy machine missed a run's last windows as the node exited. The sink keeps its outlets open a moment at
    close while they have consumers: a burst pushed right before close all arrives."""
    import threading

    pylsl = import_pylsl()
    prefix = f"t{uuid.uuid4().hex[:8]}"
    sink = LSLOutletSink([OutletStream("main", "whisker", 5000.0, ("C1",), (100.0,), ("A",), 0.1, CLASSES)],
                         outputs=["decisions"], prefix=prefix, wait_for_consumer=10.0)
    found = pylsl.resolve_byprop("name", outlet_name(prefix, "main", "decisions"), timeout=10.0)
    inlet = pylsl.StreamInlet(found[0], max_buflen=600, recover=False)     # a lost outlet ends the pull
    inlet.open_stream(timeout=10)
    got: list = []

    def consume() -> None:                           # as a consumer does: pulling all along
        end = time.monotonic() + 20
        while len(got) < 3000 and time.monotonic() < end:
            try:
                chunk, _ = inlet.pull_chunk(timeout=0.05)
            except pylsl.util.LostError:             # the outlet is gone
                return
            got.extend(json.loads(x[0])["window"] for x in chunk)

    consumer = threading.Thread(target=consume, daemon=True)
    try:
        sink.prepare()
        assert sink.consumers == ["main-decisions"]
        consumer.start()
        sink.start(time.monotonic())
        for k in range(3000):
            sink.emit(_decision(k))
    finally:
        sink.close()                                 # at once, as a node at the end of its run
    consumer.join(timeout=30)
    assert got == list(range(3000)), (len(got), got[-3:])


def test_a_sink_that_sent_nothing_closes_at_once_though_it_has_a_consumer(monkeypatch):
    """The outlets are made when the node is built, and a consumer may connect while a model trains: a start
    that fails or is stopped then closes a sink that sent nothing, with nothing to wait for."""
    monkeypatch.setattr(lsl_sink, "CLOSE_LINGER_SECONDS", 60.0)
    pylsl = import_pylsl()
    prefix = f"t{uuid.uuid4().hex[:8]}"
    sink = LSLOutletSink([OutletStream("main", "whisker", 5000.0, ("C1",), (100.0,), ("A",), 0.1, CLASSES)],
                         outputs=["decisions"], prefix=prefix, wait_for_consumer=10.0)
    found = pylsl.resolve_byprop("name", outlet_name(prefix, "main", "decisions"), timeout=10.0)
    inlet = pylsl.StreamInlet(found[0], recover=False)
    inlet.open_stream(timeout=10)
    sink.prepare()
    assert sink.consumers == ["main-decisions"]
    t = time.monotonic()
    sink.close()
    assert time.monotonic() - t < 30.0                      # not the 60 s linger: nothing was sent


class _Outlet:
    """An outlet without a consumer: counts what is pushed."""

    def __init__(self):
        self.pushed: list = []

    def push_sample(self, x, timestamp=0.0):
        self.pushed.append(timestamp)

    def have_consumers(self):
        return False


@pytest.mark.parametrize("wait", [None, 0.0])
def test_with_no_consumer_the_hold_ends_in_its_time_and_0_never_holds(monkeypatch, wait):
    """The hold keeps at most ``HOLD_FOR_CONSUMER_SECONDS`` of windows: with no consumer by then the windows
    go as they come (liblsl drops them), and the summary names no consumer; ``wait_for_consumer = 0`` sends
    every window at once, as before, and neither waits nor holds."""
    monkeypatch.setattr(lsl_sink, "HOLD_FOR_CONSUMER_SECONDS", 0.3)
    sink = LSLOutletSink([OutletStream("main", "whisker", 5000.0, ("C1",), (100.0,), ("A",), 0.1, CLASSES)],
                         outputs=["decisions"], prefix=f"t{uuid.uuid4().hex[:8]}", wait_for_consumer=wait)
    try:
        fake = sink._outlets["main", "decisions"] = _Outlet()
        sink.prepare()
        sink.start(time.monotonic())
        sink.emit(_decision(0))
        assert len(fake.pushed) == (0 if wait is None else 1)
        time.sleep(0.4)
        sink.emit(_decision(1))
        assert len(fake.pushed) == (1 if wait is None else 2)        # the kept one is not sent late to nobody
        sink.drain()
        assert sink.stats() == (None if wait == 0 else {"sink": "LSLOutletSink", "held_s": 0.3, "consumers": []})
    finally:
        sink.close()


@pytest.mark.slow   # a node process streaming a replay in real time
def test_a_consumer_started_before_a_node_that_starts_at_once_receives_window_0_with_the_default_keys(tmp_path):
    """Done when (issue 36 item 7): a consumer started before a node with nothing to do before it starts
    (no model to train: its features) receives window 0 and every window after it, with the sink's default
    keys. The consumer resolves as the node's own LSL inlet does (on another machine, say), which waits
    1-3 s for a second stream of the name: it connects seconds after the node started (it got the
    last 28-35 of the 60 windows before)."""
    prefix = f"t{uuid.uuid4().hex[:8]}"
    (tmp_path / "node.toml").write_text(_replay_scene(tmp_path, prefix, 6.0, '\n[[sink]]\ntype = "jsonl"\n'
                                                      'path = "out.jsonl"', model="# none: features only"))

    def pull(inlet) -> list:
        stamps: list = []
        end = time.monotonic() + 60
        while time.monotonic() < end and len(stamps) < 60:
            stamps.extend(inlet.pull_chunk(timeout=0.2)[1])
        return stamps

    got = _node_with_a_consumer_from_before(tmp_path, outlet_name(prefix, "main", "features"), pull, 120)
    summary = json.loads((tmp_path / "out.jsonl").read_text().splitlines()[-1])
    assert len(got) == 60, (len(got), summary["sinks"])           # windows 0 to 59: 6 s of 0.1 s windows
    assert np.allclose(np.diff(got), 0.1, atol=1e-3)
    held = [s for s in summary["sinks"] if "held_s" in s]
    assert len(held) == 1 and held[0]["consumers"] == ["main-features"], summary["sinks"]


# -- issue 36, item 6: liblsl's log ------------------------------------------------------------------------

def _config_without_log(folder) -> str:
    """The suite's loopback LSL config (tests/harness/environment.py) without its ``[log]`` section: as a user's own."""
    text = check_loopback_config().read_text()
    path = folder / "lsl_api.cfg"
    path.write_text(text[:text.index("[log]")])
    return str(path)


@pytest.mark.parametrize("log", [None, "[log]\nlevel = 0\n"])
def test_liblsl_says_nothing_in_the_nodes_output_unless_the_users_config_asks_for_its_log(tmp_path, log):
    """Issue 36 item 6: liblsl printed its INFO lines ("Configuration loaded from ...", its build) on the
    node's stderr at every start with a configuration file that sets no log level, as a lab's usually does.
    They are gone; a user's config with a ``[log]`` section of its own is followed (``level = 0``: they
    show); and the rest of the user's config still applies: its session, in which this test's consumer
    finds the outlet the node waits for."""
    import subprocess
    import sys

    config = _config_without_log(tmp_path)
    if log:
        with open(config, "a") as fh:
            fh.write(log)
    prefix = f"t{uuid.uuid4().hex[:8]}"
    (tmp_path / "node.toml").write_text(_replay_scene(tmp_path, prefix, 0.5, "wait_for_consumer = 60",
                                                      model="# none: features only"))
    node = subprocess.Popen([sys.executable, "-m", "supramodal", "run", str(tmp_path / "node.toml"), "--speed", "max"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
                            env={**os.environ, "LSLAPICFG": config})
    try:
        inlet = import_pylsl().StreamInlet(resolve_stream(outlet_name(prefix, "main", "features"), timeout=60.0))
        inlet.open_stream(timeout=30)                      # the node's wait ends: it runs its 0.5 s
        out, err = node.communicate(timeout=120)
    finally:
        node.kill()
    assert node.returncode == 0, err[-2000:]
    said = out + err
    assert ("Configuration loaded from" in said) == bool(log), said[-2000:]
    if not log:
        assert "INFO|" not in said, said[-2000:]
