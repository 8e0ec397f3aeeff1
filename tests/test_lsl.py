"""LSL between processes on this machine (the ``lsl`` extra): a node's inlet classifies what another
process sends, as the same signal fed locally; survives its sender being killed and restarted;
names what it found when the stream it asks for is not there.

Traffic stays on this machine: tests/harness/environment.py points ``LSLAPICFG`` at a loopback config before liblsl
loads, and every test checks it first. The sender always runs in a child process."""

import time
import uuid

import numpy as np
import pytest

from supramodal.benchmarks.lsl_link import (RATE, run, run_restart, start_sender,
                                            whisker_signal)
from supramodal.drivers.base import DeviceUnavailable
from supramodal.drivers.lsl import import_pylsl, resolve_stream

from lsl_only import loopback_only, require_lsl  # noqa: F401  (the fixture applies itself)

require_lsl()


@pytest.mark.slow   # paced real time: a sender process streams while the node decides
@pytest.mark.parametrize("sender", ["node", "plain"])
def test_a_stream_from_another_process_is_decided_as_the_same_signal_fed_locally(tmp_path, sender):
    """6 s of 20 whiskers at 5 kHz from a sender process (a relay node, ``supramodal run`` with a
    signal outlet; or plain pylsl), in 10 ms chunks: every sample arrives, none is filled, and
    each of the 60 windows is decided as the same WAV replayed locally."""
    result = run(6.0, tmp_path, progress=lambda _: None, sender=sender)
    assert result["samples_received"] == result["samples_sent"] == 30000
    assert result["driver"]["filled"] == 0 and result["driver"]["gaps"] == 0
    assert result["windows_remote"] == result["windows_local"] == result["decisions_compared"] == 60
    assert result["decisions_equal"] == 60
    # Both sides on one machine: a block's arrival follows its last sample's time.
    assert 0 <= result["transport_lag_ms"]["p50"] < 100


@pytest.mark.slow   # paced real time: a sender process in real time, killed and restarted
@pytest.mark.alone  # a process restarted in real time, like the relay of test_lsl_signal.py
def test_a_sender_killed_and_restarted_leaves_a_counted_gap_and_the_node_decides_again_within_2_s(tmp_path):
    """The sender killed 3 s in and started again 1 s later (found again by its source id): the
    node keeps running to the end of its 8 s, fills exactly the samples never sent (counted, their
    windows flagged), says so, and decides on measured samples again within 2 s."""
    r = run_restart(8.0, tmp_path, kill_at=3.0, down=1.0, progress=lambda _: None)
    d = r["driver"]
    assert d["gaps"] == 1 and d["restarts"] == 0 and d["stalls"] == 1
    # The fill covers the outage and what the new sender sent before the node found it again
    # (the driver looks for it every 0.25 s while the stream is silent).
    assert r["outage_s"] >= 1.0 and r["outage_s"] - 0.05 <= r["filled_s"] <= r["outage_s"] + 1.0, r
    assert d["reopened"] == 1
    assert r["windows"] == 80 and r["window_numbers_contiguous"] and r["gap_windows"] >= 10
    assert {"unplug", "reconnect", "gap"} <= set(r["events"])
    assert r["decides_again_after_s"] is not None and r["decides_again_after_s"] < 2.0, r


def test_a_stream_that_is_not_there_is_refused_naming_what_was_found(tmp_path):
    import subprocess

    from supramodal.replay.wavio import write_wav

    wav = tmp_path / "s.wav"
    write_wav(wav, whisker_signal(2.0), RATE)
    name = f"present-{uuid.uuid4().hex[:6]}"
    sender = start_sender(wav, name, f"supramodal-test-{uuid.uuid4().hex[:8]}", stderr=subprocess.DEVNULL)
    try:
        assert resolve_stream(name, timeout=10.0).name() == name           # it is up
        with pytest.raises(DeviceUnavailable, match=rf"no stream with name='absent' within 0.5 s; found .*{name}"):
            resolve_stream("absent", timeout=0.5)
    finally:
        sender.kill()
        sender.wait(timeout=10)


def _pull_all(inlets: dict, done, clock) -> dict:
    """Every sample each inlet gets until ``done()`` is true, taking what has come (never
    waiting in liblsl: a pull that waits for a chunk to fill can outlast a closed outlet):
    per inlet (samples, timestamps, the LSL time each was received)."""
    got = {k: ([], [], []) for k in inlets}
    while not done():
        for k, inlet in inlets.items():
            chunk, ts = inlet.pull_chunk(timeout=0.0)
            now = clock()
            got[k][0].extend(chunk)
            got[k][1].extend(ts)
            got[k][2].extend([now] * len(ts))
        time.sleep(0.01)
    return got


@pytest.mark.slow   # a node process that trains on the spot, then streams in real time
def test_the_outlets_carry_the_documented_labels_units_classes_and_window_times(tmp_path):
    """A node in another process sends a replay's features, decisions and posteriors; a plain
    pylsl inlet reads them back: channel labels FEATURE/FILTER with units, class names as the
    posteriors' labels, the meta-data, one sample per window stamped with the window's end on
    LSL's clock, and the decisions the node's own JSON Lines sink wrote."""
    import json
    import subprocess
    import sys

    from supramodal.banks import whisker_bank
    from supramodal.node.runtime.sinks.lsl import outlet_name, outlet_source_id
    from supramodal.replay.wavio import write_wav

    pylsl = import_pylsl()
    wav = tmp_path / "s.wav"
    # 12 s: the three inlets are resolved, opened and clock-synced one after the other (a few seconds on a
    # busy machine) while the node streams; since its model trains in 1 s, a 6 s stream could end first
    write_wav(wav, whisker_signal(12.0), RATE)
    prefix = f"t{uuid.uuid4().hex[:8]}"
    scene = tmp_path / "node.toml"
    scene.write_text(f'[driver]\ntype = "replay"\npath = "s.wav"\nmapping = "per-channel"\n\n[bank]\nkind = "whisker"\n\n'
                     f'[features]\nnames = ["Af", "A"]\n\n[model]\ntrain_on_start = true\n\n[decision]\nscope = "window"\n\n'
                     f'[[sink]]\ntype = "jsonl"\npath = "out.jsonl"\n\n[[sink]]\ntype = "lsl"\nprefix = "{prefix}"\n')
    node = subprocess.Popen([sys.executable, "-m", "supramodal", "run", str(scene), "--quiet"],
                            stderr=subprocess.PIPE, text=True)
    try:
        inlets = {}
        for output in ("features", "decisions", "posteriors"):
            info = resolve_stream(outlet_name(prefix, "main", output), timeout=60.0)
            assert info.source_id() == outlet_source_id(prefix, "main", output)
            inlets[output] = pylsl.StreamInlet(info, processing_flags=pylsl.proc_clocksync)
            inlets[output].open_stream(timeout=10)
            # the inlet's first clock offset, measured here: with proc_clocksync, the first pull measures it
            # and blocks ~1 s, which once the node trained faster than the inlets opened held back windows
            # already streaming (a lag of 1.2 s)
            inlets[output].time_correction(timeout=5)
        full = {k: v.info(timeout=5) for k, v in inlets.items()}
        # The outlets are up while the node trains (seconds): pull until it has sent its 12 s and
        # ended (1 s more for the last samples), at most 5 minutes.
        ended: list = []
        limit = time.monotonic() + 300

        def done():
            if node.poll() is not None and not ended:
                ended.append(time.monotonic())
            return time.monotonic() > limit or bool(ended) and time.monotonic() > ended[0] + 1.0

        got = _pull_all(inlets, done, pylsl.local_clock)
        assert node.wait(timeout=30) == 0, node.stderr.read()
    finally:
        if node.poll() is None:
            node.kill()
    bank = whisker_bank()
    features = full["features"]
    assert features.type() == "Features" and features.nominal_srate() == pytest.approx(10.0)
    assert features.get_channel_labels() == [f"{f}/{n}" for f in ("Af", "A") for n in bank.names]
    assert features.get_channel_units() == ["Hz*fullscale"] * 20 + ["fullscale"] * 20
    meta = features.desc().child("supramodal")
    assert meta.child_value("stream") == "main" and meta.child_value("features") == "Af,A"
    assert float(meta.child_value("window")) == 0.1 and meta.child("bank").child_value("kind") == "whisker"
    classes = json.loads(meta.child_value("classes"))
    assert full["posteriors"].get_channel_labels() == classes and full["decisions"].type() == "Markers"
    samples, stamps, received = got["features"]
    assert len(samples) >= 30
    # One sample per window, stamped with its end: 0.1 s apart (a replay's own time), on LSL's
    # clock: a replay in real time sends each window just after the instant it stamps, once the
    # backlog the outlet held for the new inlet has come: the windows stamped after the inlet's first
    # sample came (the inlets may open after the stream began: since the training got faster, 3.3 s
    # after, and a fixed half of the windows then still held some of the backlog). LSL's time
    # correction, re-estimated as it runs, moves the stamps by microseconds.
    assert np.allclose(np.diff(stamps), 0.1, atol=1e-4)
    live = np.asarray(stamps) > received[0] + 0.5
    assert live.sum() >= 10, (received[0], stamps[-1])
    lag = (np.asarray(received) - np.asarray(stamps))[live]
    # "received" is when this process pulled: a window this process was descheduled over comes late by
    # that much (0.24 s once in a CI run on 2 busy cores). Live, not a backlog: most windows within 0.1 s,
    # the typical one well within it, none by a second (a held backlog is seconds behind).
    assert np.all(lag > -0.02) and np.median(lag) < 0.05, (lag.min(), np.median(lag))
    assert np.mean(lag < 0.1) >= 0.9 and lag.max() < 1.0, (np.mean(lag < 0.1), lag.max())
    lines = [json.loads(x) for x in (tmp_path / "out.jsonl").read_text().splitlines()]
    written = {x["window"]: x for x in lines if "window" in x}
    markers = [json.loads(s[0]) for s in got["decisions"][0]]
    assert len(markers) >= 30
    for m, stamp in zip(markers, got["decisions"][1]):
        assert m["decision"] == written[m["window"]]["predicted"]
        # The same instant as the window's features: the first feature sample's plus 0.1 s a window.
        k = m["window"] - markers[0]["window"]
        assert stamp == pytest.approx(got["decisions"][1][0] + 0.1 * k, abs=1e-4)
    # Each inlet's time correction is its own estimate (they differ by up to about 0.1 ms): a
    # window is found by its place on the 0.1 s grid of the features' stamps.
    def slot(t):
        k = (t - stamps[0]) / 0.1
        assert abs(k - round(k)) < 0.01, k
        return round(k)

    assert {slot(t) for t in got["decisions"][1]} & {slot(t) for t in stamps}
    # The posteriors: normalised, their winner the decision of the same window.
    post, post_stamps, _ = got["posteriors"]
    by_time = {slot(t): int(np.argmax(p)) for p, t in zip(post, post_stamps)}
    decided = {slot(t): classes.index(m["decision"]) for m, t in zip(markers, got["decisions"][1])}
    common = set(by_time) & set(decided)
    assert len(common) >= 30 and all(by_time[t] == decided[t] for t in common)
    assert np.allclose(np.sum(post, axis=1), 1.0, atol=1e-5)
