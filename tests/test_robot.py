"""The robot scene end to end, with real streams and no hardware: the whisker array is the mock
board on a pty (the real serial driver reads it), the microphone is ALSA's file plugin paced by a
private JACK server (the real PortAudio stream reads it), both in one `supramodal run` process,
each on its own clock, fused; the board is unplugged for 1.5 s mid-stream."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from supramodal.banks import cochlea_bank, whisker_bank
from supramodal.drivers.mock_whisker import FaultSpec, MockWhiskerDevice, quantise
from supramodal.node.build import train_on_texture_set
from supramodal.pipeline import FeaturePipeline
from supramodal.twosense import OneSense, two_sense_set

from test_microphone import ROOT, _paced_file_device, _require_portaudio, jack_server  # noqa: F401 (fixture)

PLAYED = "F1a"          # a felt pair's texture: the whiskers separate it from F1b, the microphone less so
SECONDS = 12.0          # of stream per source
WHISKER_RATE, MIC_RATE, SPF = 5000, 44100, 32


def _scene(tmp_path, port: str) -> str:
    return f"""
[[source]]
name = "whiskers"
type = "serial"
port = "{port}"
rate = {float(WHISKER_RATE)}
channels = 20
mapping = "per-channel"

[[source]]
name = "mic"
type = "microphone"
rate = {float(MIC_RATE)}
channels = 1
block = 441
dtype = "float32"

[[stream]]
name = "whiskers"
source = "whiskers"
[stream.bank]
kind = "whisker"
[stream.model]
path = "{tmp_path / 'whiskers.npz'}"

[[stream]]
name = "mic"
source = "mic"
[stream.bank]
kind = "cochlea"
[stream.model]
path = "{tmp_path / 'mic.npz'}"

[fusion]
streams = ["whiskers", "mic"]
weight = 0.8
max_wait = 0.5
"""


def _run_robot(tmp_path, server, command: list[str], faults: FaultSpec | None = None, sink: str = ""):
    """Models of the two-sense world (trained on other contacts than the one played), the board
    playing the whisker side of PLAYED on a pty, the microphone its sound on the paced file device;
    ``supramodal COMMAND robot.toml ...`` in its own process. Returns (stdout, stderr, returncode,
    the board's ledger)."""
    _require_portaudio()
    surfaces = two_sense_set()
    senses = {s: OneSense(surfaces, s, seed=0) for s in ("whiskers", "microphone")}
    for name, sense, bank in (("whiskers", "whiskers", whisker_bank()), ("mic", "microphone", cochlea_bank())):
        train_on_texture_set(senses[sense], FeaturePipeline(bank, ("Af",))).save(tmp_path / f"{name}.npz")
    index = senses["whiskers"].names.index(PLAYED)
    touch = OneSense(surfaces, "whiskers", 6.0, 0, take=1).synthesize(index)
    sound = OneSense(surfaces, "microphone", 20.0, 0, take=1).synthesize(index)
    raw = tmp_path / "mic.raw"
    sound.astype("<f4").tofile(raw)
    board = quantise(np.repeat(touch[:, None], 20, axis=1)) / 32768.0
    dev = MockWhiskerDevice(board, WHISKER_RATE, samples_per_frame=SPF, loop=True, faults=faults or FaultSpec())
    scene = tmp_path / "robot.toml"
    env = {**os.environ, **_paced_file_device(tmp_path, raw, server)}
    with dev:
        scene.write_text(_scene(tmp_path, dev.port) + sink)
        proc = subprocess.Popen([sys.executable, "-m", "supramodal", command[0], str(scene), *command[1:], "--quiet",
                                 "--seconds", str(SECONDS)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True, env=env, cwd=ROOT)
        try:
            time.sleep(1.0)                 # the node has opened the port
            dev.start()
            out, err = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
        return out, err, proc.returncode, dev.ledger


@pytest.mark.hardware
@pytest.mark.slow   # paced real time: the board and the JACK-paced microphone live
def test_the_robot_scene_runs_both_senses_fused_and_survives_the_board_unplugged(tmp_path, jack_server):
    # Unplugged 4 s after the board starts, for 1.5 s, once.
    out, err, code, ledger = _run_robot(tmp_path, jack_server, ["run", "--json"],
                                        FaultSpec(unplug_every=4.0, unplug_for=1.5, unplug_limit=1))
    assert code == 0, err
    lines = [json.loads(line) for line in out.splitlines()]
    summary = lines[-1]
    events = [d for d in lines if "event" in d]
    windows = {s: [d for d in lines if d.get("stream") == s] for s in ("whiskers", "mic", "fused")}

    # the board's unplug and reconnect, then fusion saying the whiskers dropped out and came back
    said = [(d["source"], d["event"]) for d in events]
    assert ledger.unplugs == 1
    for expected in [("whiskers", "unplug"), ("whiskers", "reconnect"), ("fused", "sense_lost"), ("fused", "sense_back")]:
        assert said.count(expected) == 1, said
    assert said.index(("whiskers", "unplug")) < said.index(("fused", "sense_back"))
    assert "no window from 'whiskers'" in next(d["message"] for d in events if d["event"] == "sense_lost")

    # the microphone kept deciding throughout; the whiskers' outage is filled and flagged
    n = int(SECONDS * 10)
    assert len(windows["mic"]) == n and [d["window"] for d in windows["mic"]] == list(range(n))
    assert len(windows["whiskers"]) == n
    assert 10 <= sum(bool(d.get("gap")) for d in windows["whiskers"]) <= 25
    fates = summary["streams"]["whiskers"]["frames"]
    assert fates["delivered"] + fates["filled"] + fates["dropped"] == fates["stream"] == int(SECONDS * WHISKER_RATE)
    assert summary["streams"]["mic"]["frames"]["dropped"] == 0

    # fused: paired before and after the outage, the microphone alone during it (at the very
    # ends, a window whose partner's stream has not begun or has ended is decided alone too)
    fused = windows["fused"]
    inner = [d for d in fused if 5 <= d["window"] < len(fused) - 5]
    alone = [d for d in inner if d.get("alone")]
    assert 5 <= len(alone) <= 20 and all(d["senses"] == ["mic"] for d in alone)
    assert [d["window"] for d in alone] == list(range(alone[0]["window"], alone[-1]["window"] + 1))
    after = [d for d in inner if d["window"] > alone[-1]["window"]]
    assert len(after) >= 20 and all(d["senses"] == ["whiskers", "mic"] for d in after)
    f = summary["fusion"]
    assert f["dropouts"] == {"whiskers": 1, "mic": 0} and f["late"]["whiskers"] >= len(alone) - 3
    # One contact with a felt texture, which the microphone hears poorly: fused decisions beat it.
    paired = [d for d in fused if d["senses"] == ["whiskers", "mic"]]
    right = sum(d["predicted"] == PLAYED for d in paired) / len(paired)
    mic_right = sum(d["predicted"] == PLAYED for d in windows["mic"]) / n
    assert len(paired) >= 80 and right >= 0.6 and right > mic_right + 0.2, (right, mic_right)

    # each source on its own clock, found from its arrivals
    clocks = summary["clocks"]
    assert clocks["whiskers"]["fitted"] and clocks["mic"]["fitted"]
    assert abs(clocks["mic"]["ppm"]) < 500 and abs(clocks["whiskers"]["ppm"]) < 500


@pytest.mark.hardware
@pytest.mark.slow   # paced real time: the board and the JACK-paced microphone live
def test_the_robot_recorded_live_replays_with_the_same_fused_decisions(tmp_path, jack_server, capsys):
    """`supramodal record` of the robot scene, the real serial driver and PortAudio stream on their
    own clocks: the replay scene it writes, run at max speed, pairs and fuses the same windows to
    the same decisions as the live run did (its decisions were written by a sink as it ran)."""
    from supramodal.node.cli import main

    sink = '\n[[sink]]\ntype = "jsonl"\npath = "live.jsonl"\n'
    out, err, code, _ = _run_robot(tmp_path, jack_server, ["record", "--out", str(tmp_path / "rec"), "--name", "r"],
                                   sink=sink)
    assert code == 0, err
    assert "replay them in step: supramodal run" in err
    live = [json.loads(x) for x in (tmp_path / "live.jsonl").read_text().splitlines()]
    capsys.readouterr()
    assert main(["run", str(tmp_path / "rec" / "r.toml"), "--json", "--quiet"]) == 0
    again = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    fused = lambda events: [(e["window"], tuple(e["senses"]), e["predicted"]) for e in events   # noqa: E731
                            if e.get("stream") == "fused"]
    assert len(fused(live)) >= 100 and fused(again) == fused(live)
    times = lambda events: [(e["start"], e["end"]) for e in events if e.get("stream") == "fused"]  # noqa: E731
    assert times(again) == times(live)           # the clocks were fed the very same stamps
