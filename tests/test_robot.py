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
from supramodal.node.scene.build import train_on_texture_set
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
mapping = "per-channel"
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
@pytest.mark.alone  # beside another paced test (the two-sense world at 4x, the soak) its fusion waited past max_wait
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
    # 1.5 s unplugged (15 windows), up to 0.5 s until the driver's next reopen (BACKOFF_MAX), the two
    # windows it straddles, and up to 1 s of a loaded machine's scheduling (26 seen at load 10): a
    # driver that did not reconnect would leave every window from the unplug on (80) a gap.
    assert 10 <= sum(bool(d.get("gap")) for d in windows["whiskers"]) <= 32
    fates = summary["streams"]["whiskers"]["frames"]
    assert fates["delivered"] + fates["filled"] + fates["dropped"] == fates["stream"] == int(SECONDS * WHISKER_RATE)
    assert summary["streams"]["mic"]["frames"]["dropped"] == 0

    # fused: paired before and after the outage, the microphone alone during it (at the very
    # ends, a window whose partner's stream has not begun or has ended is decided alone too)
    fused = windows["fused"]
    inner = [d for d in fused if 5 <= d["window"] < len(fused) - 5]
    alone = [d for d in inner if d.get("alone")]
    assert 5 <= len(alone) <= 20 and all(d["senses"] == ["mic"] for d in alone)
    # one run through the outage; at its edges a window may still find its partner in time (a CI run at load: the
    # whiskers' windows 38 and 39 straddling the unplug came late and on time, 38 decided alone, 39 paired)
    first, last = alone[0]["window"], alone[-1]["window"]
    paired_within = sorted(set(range(first, last + 1)) - {d["window"] for d in alone})
    assert all(min(w - first, last - w) <= 2 for w in paired_within), (first, last, paired_within)
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
@pytest.mark.alone  # the robot scene live, as above
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


# -- docs/own-robot.md: from examples/robot.toml to a fused model running live, six commands ----------

EXAMPLE = ROOT / "examples" / "robot.toml"


def _live(tmp_path, server, texture: str, take: int, argv: list[str], stdin: str = "", seconds: float = 4.0):
    """``supramodal ARGV`` on the example robot scene (its port the mock board's) in its own process,
    the board playing the two-sense world's touch of ``texture`` (contact ``take``) and the paced
    microphone its sound; ``stdin`` typed at once. Returns (stdout, stderr, returncode)."""
    _require_portaudio()
    surfaces = two_sense_set()
    index = OneSense(surfaces, "whiskers").names.index(texture)
    touch = OneSense(surfaces, "whiskers", seconds + 4.0, 0, take=take).synthesize(index)
    sound = OneSense(surfaces, "microphone", seconds + 8.0, 0, take=take).synthesize(index)
    here = tmp_path / f"dev-{texture}-{take}-{argv[0]}"
    here.mkdir()
    raw = here / "mic.raw"
    sound.astype("<f4").tofile(raw)
    board = quantise(np.repeat(touch[:, None], 20, axis=1)) / 32768.0
    port = tmp_path / "whisker0"             # the board's one path, as a udev rule would give it
    dev = MockWhiskerDevice(board, WHISKER_RATE, port=str(port), samples_per_frame=SPF, loop=True)
    env = {**os.environ, **_paced_file_device(here, raw, server)}
    with dev:
        if argv[0] == "run":
            scene = argv[1]
        else:
            (tmp_path / "robot.toml").write_text(EXAMPLE.read_text().replace('"/tmp/whisker0"', f'"{port}"'))
            scene = str(tmp_path / "robot.toml")
        rest = argv[2:] if argv[0] == "run" else argv[1:]
        proc = subprocess.Popen([sys.executable, "-m", "supramodal", argv[0], scene, *rest,
                                 "--quiet", "--seconds", str(seconds)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path)
        try:
            proc.stdin.write(stdin)
            proc.stdin.flush()
            time.sleep(1.0)                 # the node has opened the port
            dev.start()
            out, err = proc.communicate(timeout=180)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    return out, err, proc.returncode


@pytest.mark.hardware
@pytest.mark.slow   # paced real time: four recordings and a run, the board and the JACK-paced microphone live
@pytest.mark.alone  # the robot scene live, as above
def test_own_robot_six_commands_from_the_example_scene_to_a_fused_model_deciding_live(tmp_path, jack_server,
                                                                                      capsys, monkeypatch):
    """docs/own-robot.md worked through: (1) `record examples/robot.toml --marks` (a texture name
    typed), four recordings of two felt textures; (2) `label` one of them after the fact; (3, 4)
    `train --scene --stream` each sense on two recordings; (5) `train --fusion early` on the two
    others, with those models, writing the live scene; (6) `run` it: the fused model decides live,
    on a fifth contact, and gets the texture right."""
    from supramodal.node.cli import main
    from supramodal.replay.session import load_session

    monkeypatch.chdir(tmp_path)
    # (1) record with marks: the texture's name typed as the recording starts
    for name, texture, take in (("a1", "F1a", 1), ("a2", "F1b", 1), ("b1", "F1a", 2)):
        out, err, code = _live(tmp_path, jack_server, texture, take,
                               ["record", "--out", "rec", "--name", name, "--marks"], stdin=f"{texture}\n")
        assert code == 0, err
        for source in ("whiskers", "mic"):
            labels = load_session(tmp_path / "rec" / f"{name}.{source}.wav").labels
            assert [lab.label for lab in labels] == [texture] and labels[0].end - labels[0].start > 2.5
    # (2) label after the fact: a recording made without marks, labelled from a spans file
    out, err, code = _live(tmp_path, jack_server, "F1b", 2, ["record", "--out", "rec", "--name", "b2"])
    assert code == 0, err
    (tmp_path / "b2.csv").write_text("start,end,label\n0,60,F1b\n")
    assert main(["label", "rec/b2.toml", "b2.csv"]) == 0
    assert load_session(tmp_path / "rec" / "b2.mic.wav").labels[0].label == "F1b"
    # (3, 4) each sense trained straight from two recordings
    (tmp_path / "models").mkdir()
    for stream in ("whiskers", "mic"):
        assert main(["train", "--scene", "rec/a1.toml", "--scene", "rec/a2.toml", "--stream", stream,
                     "--out", f"models/{stream}.npz", "--quiet"]) == 0
    # (5) the fusion on the two other recordings, with those models: their own posteriors, unseen
    capsys.readouterr()
    fusion = ["--scene", "rec/b1.toml", "--scene", "rec/b2.toml", "--model", "whiskers=models/whiskers.npz",
              "--model", "mic=models/mic.npz", "--live", "robot.toml", "--write-scene", "fused.toml", "--quiet"]
    code = main(["train", "--fusion", "early", *fusion, "--out", "models/fused.npz"])
    if code != 0:
        # Two recordings of one contact each are little to learn a network from: on some recordings its held-out
        # log loss is worse than a sense's alone, and train refuses to write it, saying why (a CI run: 0.237
        # against 0.099). That refusal is the product's; the walkthrough then goes on with the late fusion,
        # which learns two numbers, not a network.
        err = capsys.readouterr().err
        assert "does worse on its held-out windows than" in err and not (tmp_path / "models/fused.npz").exists(), err
        assert main(["train", "--fusion", "late", *fusion]) == 0
    said = capsys.readouterr().out
    assert "sense posteriors: unseen" in said and "supramodal run fused.toml" in said
    # (6) run: the fused model decides live on a contact none of the models saw
    out, err, code = _live(tmp_path, jack_server, "F1a", 3, ["run", "fused.toml", "--json"])
    assert code == 0, err
    fused = [d for d in map(json.loads, out.splitlines()) if d.get("stream") == "fused"]
    paired = [d for d in fused if d.get("senses") == ["whiskers", "mic"]]
    assert len(paired) >= 25, len(fused)
    right = sum(d["predicted"] == "F1a" for d in paired) / len(paired)
    assert right >= 0.7, right
