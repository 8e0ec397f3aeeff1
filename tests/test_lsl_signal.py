"""A source's samples out as an LSL stream (``[[sink]] type = "lsl-signal"``): cut into chunks at
fixed stream indices whatever the blocks, never sending a sample the node did not measure, each
chunk stamped with its last sample's time; a relay node in one process classified by a node in
another; the scene's checks.

Traffic stays on this machine (tests/harness/environment.py's loopback ``LSLAPICFG``, checked by every test)."""

import collections
import json
import subprocess
import sys
import time
import uuid

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from supramodal.drivers.lsl import import_pylsl, resolve_stream
from supramodal.node.runtime.ringbuffer import RingClosed
from supramodal.node.scene.schema import SceneError, scene_from_dict

from lsl_only import loopback_only, require_lsl  # noqa: F401  (the fixture applies itself)
from node_processes import assert_start_up_ends_on, start_node

require_lsl()

from supramodal.node.runtime.taps.lsl_signal import LSLSignalOutlet  # noqa: E402  (after the skip: it needs pylsl to build)
from supramodal.node.runtime.sources import Feed  # noqa: E402


class _PlannedReader:
    """A ring reader that hands out planned ``(start, data, filled)`` chunks, then is closed."""

    def __init__(self, chunks):
        self.chunks = collections.deque(chunks)

    def read(self, timeout=None):
        if not self.chunks:
            raise RingClosed("done")
        return self.chunks.popleft()


class _Pushes:
    """Stands in for the pylsl outlet: keeps each push."""

    def __init__(self):
        self.pushed = []

    def push_chunk(self, x, timestamp):
        self.pushed.append((np.array(x), timestamp))

    def have_consumers(self):
        return False


class _Source:
    def __init__(self, line):
        self._line = line

    def line(self):
        return self._line


def _expected_pushes(measured: np.ndarray, C: int, restarts=()) -> list[tuple[int, int]]:
    """The plain rule: each maximal run of measured frames inside one chunk cell ``[kC, (k+1)C)``
    and not across a restart is one push, ``(first, last)`` frame."""
    out, first = [], None
    for i, m in enumerate(measured):
        if m and first is None:
            first = i
        if first is not None and (not m or i + 1 == len(measured) or (i + 1) % C == 0 or not measured[i + 1]
                                  or i + 1 in restarts):
            last = i if m else i - 1
            out.append((first, last))
            first = None
    return out


@settings(max_examples=60, deadline=None)
@given(sizes=st.lists(st.integers(1, 130), min_size=1, max_size=30),
       holes=st.lists(st.tuples(st.integers(0, 2000), st.integers(1, 90), st.booleans()), max_size=4),
       marks=st.lists(st.tuples(st.integers(1, 2000), st.sampled_from(["restart", "overrun"])), max_size=4),
       chunk=st.sampled_from([0.001, 0.005, 0.0074, 0.01, 0.03]))
def test_chunks_are_cut_at_fixed_indices_holes_are_not_sent_and_each_is_stamped_at_its_last_sample(sizes, holes, marks,
                                                                                                   chunk):
    """Blocks of random sizes, some frames filled by the driver and some lost by this reader (the
    ring overran it), some restart marks (the source's time jumps there): the pushes are exactly
    each run of measured frames within a chunk cell and not across a restart, in order, the
    samples as measured (float32), each stamped with its last frame's time by the line of the
    block that brought it, on LSL's clock."""
    rate, channels = 5000.0, 3
    n = sum(sizes)
    rng = np.random.default_rng(len(sizes))
    data = rng.standard_normal((n, channels))
    filled = np.zeros(n, bool)
    lost = np.zeros(n, bool)
    for a, length, is_lost in holes:
        (lost if is_lost else filled)[a:a + length] = True
    filled &= ~lost
    tap = LSLSignalOutlet("whiskers", rate, channels, chunk=chunk)
    tap._outlet = pushes = _Pushes()
    # Each block's common-time line differs, so a stamp shows which block's line it used.
    chunks, arrivals, start = [], [], 0
    for k, size in enumerate(sizes):
        end = start + size
        arrivals.append((end, 0.0, (0.25 * k, 1.0 / rate * (1 + 1e-3 * k))))
        keep = np.flatnonzero(~lost[start:end])        # a lost stretch is simply not handed out
        if keep.size:
            for a, b in _runs(keep):
                chunks.append((start + a, data[start + a:start + b], filled[start + a:start + b].copy()))
        start = end
    marks = sorted((i, kind) for i, kind in marks if i < n)
    tap.start(_Source((0.0, 1.0 / rate)), epoch=100.0)
    feed = Feed(_PlannedReader(chunks))
    feed.arrivals.extend(arrivals)
    feed.marks.extend(marks)
    tap.run(feed)
    C = tap.frames_per_chunk
    expected = _expected_pushes(~filled & ~lost, C, {i for i, kind in marks if kind == "restart"})
    assert len(pushes.pushed) == len(expected) == tap.chunks
    for (x, stamp), (first, last) in zip(pushes.pushed, expected):
        np.testing.assert_array_equal(x, data[first:last + 1].astype(np.float32))
        block = next(k for k, a in enumerate(arrivals) if a[0] > last)
        offset, slope = arrivals[block][2]
        assert stamp == pytest.approx(100.0 + offset + last * slope - tap._clock.offset, abs=1e-9)
    assert tap.samples_sent == int(np.sum(~filled & ~lost))


def _runs(idx: np.ndarray):
    """Contiguous runs ``(a, b)`` (b exclusive) of sorted indices."""
    breaks = np.flatnonzero(np.diff(idx) != 1)
    starts = np.r_[idx[0], idx[breaks + 1]]
    ends = np.r_[idx[breaks], idx[-1]] + 1
    return zip(starts.tolist(), ends.tolist())


def test_the_scene_checks_the_signal_sink():
    two = {"source": [{"name": "a", "type": "synth"}, {"name": "b", "type": "synth"}]}
    with pytest.raises(SceneError, match=r"\[\[sink\]\] #1 source: the scene has sources \['a', 'b'\]; name the one"):
        scene_from_dict({**two, "sink": [{"type": "lsl-signal"}]})
    with pytest.raises(SceneError, match=r"source: no source 'c'"):
        scene_from_dict({**two, "sink": [{"type": "lsl-signal", "source": "c"}]})
    with pytest.raises(SceneError, match=r"\[\[source\]\] 'b' feeds no \[\[stream\]\]: add a stream that reads it, "
                                         r"send its samples on"):
        scene_from_dict({**two, "sink": [{"type": "lsl-signal", "source": "a"}]})
    with pytest.raises(SceneError, match=r"chunk: expected seconds of samples per push, 0.001 to 0.1"):
        scene_from_dict({**two, "sink": [{"type": "lsl-signal", "source": "a", "chunk": 0.5}]})
    with pytest.raises(SceneError, match=r"#2 sends source 'a' with prefix 'supramodal' as \[\[sink\]\] #1 does"):
        scene_from_dict({**two, "sink": [{"type": "lsl-signal", "source": "a"}, {"type": "lsl-signal", "source": "a"},
                                         {"type": "lsl-signal", "source": "b"}]})
    relay = scene_from_dict({**two, "sink": [{"type": "lsl-signal", "source": "a"},
                                             {"type": "lsl-signal", "source": "b"}]})
    assert relay.is_graph and relay.streams == () and [s.source for s in relay.sinks] == ["a", "b"]
    one = scene_from_dict({"driver": {"type": "synth"}, "sink": [{"type": "lsl-signal"}]})
    assert one.sinks[0].source == "main"


def test_a_one_source_scene_sends_its_samples_and_still_decides(tmp_path):
    """The tap beside the model: every frame sent once, the windows decided as without it."""
    from supramodal.node.scene.build import build_node
    from supramodal.node.runtime.sinks import ListSink

    scene = {"driver": {"type": "synth", "seconds": 1.0, "speed": "max", "block": 37}, "bank": {"kind": "whisker"},
             "model": {"train_on_start": True}, "decision": {"scope": "window"}}
    plain = ListSink()
    build_node(scene_from_dict(scene), sinks_override=[plain]).run()
    prefix = f"t{uuid.uuid4().hex[:8]}"
    node = build_node(scene_from_dict({**scene, "sink": [{"type": "jsonl", "path": str(tmp_path / "o.jsonl")},
                                                         {"type": "lsl-signal", "prefix": prefix}]}))
    summary = node.run()
    tap = summary["taps"][f"{prefix}-main-signal"]
    assert tap["samples_sent"] == tap["frames"]["delivered"] == tap["frames"]["stream"] == 8 * 5000
    assert tap["chunks"] == 8 * 5000 // 50 and tap["holes"] == 0
    assert summary["windows"] == len(plain.windows) == 80
    lines = [json.loads(x) for x in (tmp_path / "o.jsonl").read_text().splitlines()]
    assert [x["predicted"] for x in lines if "predicted" in x] == [e.decision for e in plain.windows]


def test_a_relay_in_another_process_sends_what_it_measured_and_the_stamps_show_the_hole(tmp_path):
    """A relay node (``supramodal run``: a replay of a session whose frames 7000-7999 the driver had
    filled, no stream) sends to a plain pylsl inlet here: the stream's name, type, source id,
    rate and labels as documented; every measured sample once, in order; none of the filled ones;
    and the timestamps step by exactly one sample period except over the hole, which they span
    by exactly its length."""
    from supramodal.node.runtime.sinks.lsl import outlet_source_id
    from supramodal.replay.session import save_session

    pylsl = import_pylsl()
    rate, n = 5000, 20000
    t = np.arange(n)
    data = np.stack([np.sin(2 * np.pi * (37 + 11 * c) * t / rate) for c in range(4)], axis=1).astype(np.float32)
    data[7000:8000] = 0.0
    save_session(tmp_path / "s", data, rate, "test", filled=[(7000, 8000)], dtype="float32")
    prefix = f"t{uuid.uuid4().hex[:8]}"
    scene = tmp_path / "relay.toml"
    scene.write_text(f'[[source]]\nname = "arm"\ntype = "replay"\npath = "s.wav"\nspeed = 4.0\nblock = 73\n\n'
                     f'[[sink]]\ntype = "lsl-signal"\nprefix = "{prefix}"\nchunk = 0.02\nwait_for_consumer = 60\n'
                     f'stream_type = "Whiskers"\n\n[[sink]]\ntype = "jsonl"\npath = "out.jsonl"\n')
    relay = subprocess.Popen([sys.executable, "-m", "supramodal", "run", str(scene), "--quiet"],
                             stderr=subprocess.PIPE, text=True)
    try:
        info = resolve_stream(f"{prefix}-arm-signal", timeout=60.0)
        inlet = pylsl.StreamInlet(info, max_buflen=60)
        inlet.open_stream(timeout=10)
        full = inlet.info(timeout=5)
        samples, stamps = [], []
        deadline = time.monotonic() + 60
        while relay.poll() is None and time.monotonic() < deadline:
            x, ts = inlet.pull_chunk(timeout=0.0)
            samples.extend(x)
            stamps.extend(ts)
            time.sleep(0.01)
        time.sleep(0.2)
        x, ts = inlet.pull_chunk(timeout=0.0)
        samples.extend(x)
        stamps.extend(ts)
        assert relay.wait(timeout=30) == 0, relay.stderr.read()
    finally:
        if relay.poll() is None:
            relay.kill()
    assert full.type() == "Whiskers" and full.channel_count() == 4 and full.nominal_srate() == rate
    assert full.source_id() == outlet_source_id(prefix, "arm", "signal")
    assert full.get_channel_labels() == ["ch1", "ch2", "ch3", "ch4"]
    assert full.desc().child("supramodal").child_value("driver") == "replay"
    measured = np.r_[data[:7000], data[8000:]]
    got = np.asarray(samples, dtype=np.float32)
    np.testing.assert_array_equal(got, measured)
    steps = np.diff(np.asarray(stamps)) * rate
    hole = 7000 - 1
    assert np.allclose(np.delete(steps, hole), 1.0, atol=1e-3)
    assert steps[hole] == pytest.approx(1001.0, abs=1e-3)
    summary = [json.loads(x) for x in (tmp_path / "out.jsonl").read_text().splitlines()][-1]
    tap = summary["taps"][f"{prefix}-arm-signal"]
    assert tap["frames"]["filled"] == 1000 and tap["samples_sent"] == tap["frames"]["delivered"] == n - 1000
    assert tap["consumer"] is True and summary["streams"] == {}


def test_a_relay_is_recorded_and_its_replay_scene_sends_the_recording_on(tmp_path):
    from supramodal.node.cli import main
    from supramodal.node.scene.schema import load_scene
    from supramodal.replay.session import load_session

    prefix = f"t{uuid.uuid4().hex[:8]}"
    scene = tmp_path / "relay.toml"
    scene.write_text(f'[[source]]\nname = "arm"\ntype = "synth"\nspeed = "max"\nseconds = 1.0\n\n'
                     f'[[sink]]\ntype = "lsl-signal"\nprefix = "{prefix}"\n')
    assert main(["record", str(scene), "--out", str(tmp_path / "rec"), "--name", "r", "--quiet"]) == 0
    assert load_session(tmp_path / "rec" / "r.arm.wav").frames == 8 * 5000
    replay = load_scene(tmp_path / "rec" / "r.toml")
    assert replay.streams == () and replay.sources[0].type == "replay"
    assert [(s.type, s.source, s.options["prefix"]) for s in replay.sinks] == [("lsl-signal", "arm", prefix)]


def test_without_a_consumer_the_node_waits_as_long_as_asked_then_starts_and_says_so():
    from supramodal.node.scene.build import build_node

    prefix = f"t{uuid.uuid4().hex[:8]}"
    scene = scene_from_dict({"source": [{"name": "arm", "type": "synth", "speed": "max", "seconds": 0.2}],
                             "sink": [{"type": "lsl-signal", "prefix": prefix, "wait_for_consumer": 0.4}]})
    summary = build_node(scene).run()
    tap = summary["taps"][f"{prefix}-arm-signal"]
    assert tap["consumer"] is False and 0.4 <= tap["waited_s"] < 10
    assert tap["samples_sent"] == tap["frames"]["stream"] == 8 * 1000


@pytest.mark.slow   # paced real time: a relay in real time, stopped and started again
@pytest.mark.alone  # beside a computing worker: 5 windows after the gap where 20 are asked
def test_a_restarted_relay_is_picked_up_again_by_its_source_id(tmp_path):
    """A node's inlet resolves a relay by the source id the docs give (``PREFIX@HOST/SOURCE/signal``);
    the relay process is killed 3 s in and run again 1 s later (as a robot's computer that
    rebooted): the inlet node keeps running, finds the new outlet of the same source id, fills and
    counts the gap, and decides on measured samples again."""
    import threading

    from supramodal.benchmarks.lsl_link import _end, _inlet_node, _prepare, _run_for, relay_scene, start_relay
    from supramodal.node.runtime.sinks.lsl import outlet_source_id

    wav, model, _ = _prepare(8.0, tmp_path, lambda _: None)
    prefix = f"t{uuid.uuid4().hex[:8]}"
    scene = tmp_path / "relay.toml"
    scene.write_text(relay_scene(wav, prefix))
    first = start_relay(scene, stderr=subprocess.DEVNULL)
    second = None
    try:
        node, sink, _ = _inlet_node(None, model, source_id=outlet_source_id(prefix, "whiskers", "signal"),
                                    stall_timeout=0.3)
        summary = {}
        runner = threading.Thread(target=lambda: summary.update(_run_for(node, 9.0)))
        runner.start()
        time.sleep(3.0)
        first.kill()
        first.wait(timeout=10)
        time.sleep(1.0)
        second = start_relay(scene, stderr=subprocess.DEVNULL)
        runner.join(timeout=60)
        assert not runner.is_alive()
    finally:
        first.kill()
        if second is not None:
            _end(second)
    d = summary["driver"]
    assert d["reopened"] == 1 and d["gaps"] == 1 and d["restarts"] == 0, d
    assert d["filled"] >= 5000                       # the second relay's first sample came >= 1 s later
    numbers = [e.window for e in sink.windows]
    assert numbers == list(range(len(numbers))) and len(numbers) == 90
    after = [e for e in sink.windows if "gap" not in e.flags and e.window * 500 > d["filled"] + 3 * 5000]
    assert len(after) >= 20 and all(e.decision is not None for e in after)
    assert {"unplug", "reconnect", "gap"} <= set(summary["events"]["counts"])


@pytest.mark.parametrize("signum, code", [(2, 130), (15, 143)])
def test_a_wait_for_a_consumer_is_start_up_and_a_signal_ends_it_at_once(tmp_path, signum, code):
    """Issue 25 item 9: with wait_for_consumer = 40, SIGINT and SIGTERM were ignored for the whole
    wait and the node then ran; the README promises 130 / 143 at once during start-up."""
    prefix = f"wait-{uuid.uuid4().hex[:8]}"
    (tmp_path / "relay.toml").write_text(
        f'[[source]]\nname = "a"\ntype = "synth"\nseconds = 2.0\n\n[[sink]]\ntype = "lsl-signal"\n'
        f'prefix = "{prefix}"\nwait_for_consumer = 40\n')
    proc = start_node(tmp_path / "relay.toml", tmp_path)
    try:
        # Its outlet is up: it waits now (a fixed 4 s was not always enough for start-up on a busy machine).
        resolve_stream(f"{prefix}-a-signal", timeout=60.0)
        time.sleep(1.0)
        assert_start_up_ends_on(proc, signum, code)
    finally:
        proc.kill()


class _SilentReader(_PlannedReader):
    """A planned reader that, once its chunks are handed out, is silent for ``silence`` seconds
    (reads that time out, as a ring whose source stopped), then closed; it keeps how many pushes
    had been made when the silence ended."""

    def __init__(self, chunks, silence, pushes):
        super().__init__(chunks)
        self.end = None
        self.silence, self.pushes, self.pushed_in_silence = silence, pushes, None

    def read(self, timeout=None):
        if self.chunks:
            return self.chunks.popleft()
        if self.end is None:
            self.end = time.monotonic() + self.silence
        if time.monotonic() < self.end:
            time.sleep(timeout or 0.0)
            return None
        self.pushed_in_silence = len(self.pushes.pushed)
        raise RingClosed("done")


def test_a_partial_chunk_goes_when_the_source_falls_silent():
    """Issue 26 item 11: after a live source went silent its partial last chunk was held back
    (22 samples not sent in 100 s): pushed only when the chunk completed or the ring closed. Now
    it goes after 0.1 s without a frame, stamped at its last sample."""
    rate = 5000.0
    tap = LSLSignalOutlet("whiskers", rate, 2, chunk=0.01)
    tap._outlet = pushes = _Pushes()
    data = np.arange(2 * 72, dtype=float).reshape(72, 2)          # one chunk of 50, then 22 frames
    reader = _SilentReader([(0, data, None)], silence=1.0, pushes=pushes)
    tap.start(_Source((0.0, 1.0 / rate)), epoch=100.0)
    feed = Feed(reader)
    feed.arrivals.append((72, 0.0, (0.0, 1.0 / rate)))
    tap.run(feed)
    assert reader.pushed_in_silence == 2 and [len(x) for x, _ in pushes.pushed] == [50, 22]
    assert pushes.pushed[1][1] == pytest.approx(100.0 + 71 / rate - tap._clock.offset, abs=1e-9)
    assert tap.samples_sent == 72 and tap.holes == 0
