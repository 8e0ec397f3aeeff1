"""The node's window outlets (``[[sink]] type = "lsl"``): up before the start-up work, so that a
consumer started before the node gets window 0; ``wait_for_consumer``, a start-up wait that SIGINT
and SIGTERM end; what each outlet declares (issue 26, items 7 and 11).

Traffic stays on this machine (conftest.py's loopback ``LSLAPICFG``, checked by every test)."""

import json
import threading
import time
import uuid

import pytest

from supramodal.benchmarks.lsl_link import RATE, whisker_signal
from supramodal.drivers.base import DeviceUnavailable
from supramodal.drivers.lsl import import_pylsl, resolve_stream

from lsl_only import loopback_only, require_lsl  # noqa: F401  (the fixture applies itself)
from node_processes import assert_start_up_ends_on, start_node

require_lsl()

from supramodal.node.runtime.sinks.lsl import LSLOutletSink, OutletStream, outlet_name  # noqa: E402  (needs pylsl)


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


@pytest.mark.slow   # a node process that trains on the spot, then streams in real time
def test_a_consumer_started_before_the_node_receives_window_0(tmp_path):
    """Done when (issue 26): a plain pylsl consumer, started before the node, receives window 0
    and every window after it; the node waits for it (``wait_for_consumer``) and says so."""
    pylsl = import_pylsl()
    prefix = f"t{uuid.uuid4().hex[:8]}"
    (tmp_path / "node.toml").write_text(_replay_scene(tmp_path, prefix, 3.0,
                                                      'outputs = ["decisions"]\nwait_for_consumer = 120\n\n'
                                                      '[[sink]]\ntype = "jsonl"\npath = "out.jsonl"'))
    got: list = []
    failed: list = []

    def consume():
        try:
            info = resolve_stream(outlet_name(prefix, "main", "decisions"), timeout=120.0)
            inlet = pylsl.StreamInlet(info)
            inlet.open_stream(timeout=30)
            end = time.monotonic() + 120
            while time.monotonic() < end and not (got and got[-1]["window"] >= 29):
                chunk, _ = inlet.pull_chunk(timeout=0.0)
                got.extend(json.loads(s[0]) for s in chunk)
                time.sleep(0.01)
        except Exception as exc:           # the assertion below says what went wrong
            failed.append(exc)

    consumer = threading.Thread(target=consume, daemon=True)
    consumer.start()                       # before the node
    node = start_node(tmp_path / "node.toml", tmp_path)
    try:
        out, err = node.communicate(timeout=300)
    finally:
        node.kill()
    consumer.join(timeout=30)
    assert node.returncode == 0 and not failed, (err[-800:], failed)
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
