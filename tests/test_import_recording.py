"""`supramodal import-recording`: a replayable graph recording from files a lab already has (issue
26): WAV files with per-block or per-sample timestamps (CSV), or XDF streams, written as sessions
with their replay scene; `supramodal run` on it gives the offline pipeline's windows of the same
samples, at the times the timestamps say; a bad file is refused naming the line and the fix."""

from __future__ import annotations

import json

import numpy as np
import pytest

from supramodal.banks import cochlea_bank, whisker_bank
from supramodal.node.cli import main
from supramodal.node.scene.schema import load_scene
from supramodal.pipeline import extract_features
from supramodal.replay.session import load_session
from supramodal.replay.wavio import read_wav, write_wav
from two_sense_scenes import two_sense_world_toml

T0 = 1000.0                      # the lab recorder's clock at the microphone's first sample
SECONDS = 3.0
W_RATE, M_RATE = 5000, 44100
W_PPM, M_PPM = 80e-6, -60e-6     # each device's crystal error
W_LATE = 0.037                   # the whiskers' first sample, after the microphone's
LAB_CLOCK = 1.7e9                # the CSVs' clock: Unix time (T0 s after its zero)


def _t_whiskers(i):
    return T0 + W_LATE + np.asarray(i) / (W_RATE * (1 + W_PPM))


def _t_mic(i):
    return T0 + np.asarray(i) / (M_RATE * (1 + M_PPM))


def _write_csv(path, header, rows):
    path.write_text(header + "\n" + "".join(",".join(repr(float(v)) if isinstance(v, float) else str(v)
                                                         for v in row) + "\n" for row in rows))


@pytest.fixture
def lab_files(tmp_path):
    """Whiskers: a float32 WAV at 5 kHz delivered in random blocks of 1-300 frames, each stamped
    when complete (its last sample's time plus an exponential delay, mean 0.2 ms); microphone: an
    int16 WAV at 44.1 kHz with one timestamp per sample (jittered +-10 us). Both CSVs in Unix time."""
    rng = np.random.default_rng(26)
    n_w, n_m = int(SECONDS * W_RATE), int(SECONDS * M_RATE)
    write_wav(tmp_path / "whiskers.wav", 0.2 * rng.standard_normal((n_w, 1)), W_RATE, dtype="float32")
    write_wav(tmp_path / "mic.wav", np.clip(0.2 * rng.standard_normal((n_m, 1)), -1, 1), M_RATE, dtype="int16")
    ends = np.cumsum(rng.integers(1, 301, size=n_w))
    ends = np.r_[ends[ends < n_w], n_w]
    seconds = _t_whiskers(ends - 1) + rng.exponential(0.0002, ends.size)
    seconds = np.maximum.accumulate(seconds)
    _write_csv(tmp_path / "whiskers.csv", "end_frame,seconds", zip(ends.tolist(), (seconds + LAB_CLOCK).tolist()))
    stamps = _t_mic(np.arange(n_m)) + rng.uniform(-1e-5, 1e-5, n_m)
    _write_csv(tmp_path / "mic.csv", "seconds", ((float(s),) for s in stamps + LAB_CLOCK))
    return tmp_path


def _import(folder, *extra):
    return main(["import-recording", "--out", str(folder / "rec"), "--name", "lab",
                 "--wav", f"whiskers={folder / 'whiskers.wav'}", "--times", f"whiskers={folder / 'whiskers.csv'}",
                 "--wav", f"mic={folder / 'mic.wav'}", "--times", f"mic={folder / 'mic.csv'}",
                 "--bank", "whiskers=whisker", "--bank", "mic=cochlea", *extra])


def _windows(capsys, scene):
    capsys.readouterr()
    assert main(["run", str(scene), "--speed", "max", "--json", "--quiet"]) == 0
    events = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    return {name: [e for e in events if e.get("stream") == name and "window" in e] for name in ("whiskers", "mic")}


def test_wav_and_csv_of_two_senses_replay_as_the_offline_pipeline_at_their_times(lab_files, capsys):
    assert _import(lab_files) == 0
    rec = lab_files / "rec"
    assert {p.name for p in rec.iterdir()} == {"lab.toml", "lab.whiskers.wav", "lab.whiskers.json", "lab.mic.wav",
                                                "lab.mic.json"}
    scene = load_scene(rec / "lab.toml")
    assert [(s.type, s.options["timing"]) for s in scene.sources] == [("replay", "recorded")] * 2
    # the sessions hold the very samples, at their rates
    for name, rate in (("whiskers", W_RATE), ("mic", M_RATE)):
        x, r = read_wav(lab_files / f"{name}.wav")
        s = load_session(rec / f"lab.{name}")
        assert s.rate == r == rate and np.array_equal(s.data, x)
    windows = _windows(capsys, rec / "lab.toml")
    zero = _t_mic(0)                    # the earliest first sample (the microphone's), +-10 us (LAB_CLOCK cancels)
    for name, bank, t, rate in (("whiskers", whisker_bank(), _t_whiskers, W_RATE),
                                ("mic", cochlea_bank(), _t_mic, M_RATE)):
        x, _ = read_wav(lab_files / f"{name}.wav")
        ref = extract_features(x[:, 0], bank, ("Af",)).values[:, 0]
        got = np.array([e["features"]["Af"] for e in windows[name]])
        assert [e["window"] for e in windows[name]] == list(range(len(ref))) and len(ref) == 30
        assert got.shape == ref.shape
        assert np.max(np.abs(got - ref)) <= 1e-12 * np.max(np.abs(ref))
        # each window spans its first sample's time to the next window's first on the lab's clock,
        # moved to the common zero (the node's clock model fitted to the imported times)
        W = int(round(0.1 * rate))
        k = np.arange(len(ref))
        for key, truth in (("start", t(k * W) - zero), ("end", t((k + 1) * W) - zero)):
            got_t = np.array([e[key] for e in windows[name]])
            assert np.max(np.abs(got_t - truth)) < 1e-4


@pytest.mark.parametrize("content, needle", [
    ("frame,time\n10,1.0\n", "line 1 is frame,time; the first line names the columns"),
    ("end_frame,seconds\n100,1.0\n200,nan\n", "line 3: seconds 'nan' is not a finite time"),
    ("end_frame,seconds\n100,1.0\n100,1.1\n", "line 3: end_frame 100 is not after the block before it (100)"),
    ("end_frame,seconds\n100,1.0\n200,0.9\n", "line 3: seconds 0.9 comes before the block before it"),
    ("end_frame,seconds\n100,1.0\n15000,2.0\n20000,3.0\n", "end_frame 20000 is outside 1..15000"),
    ("end_frame,seconds\n100,1.0\n14000,3.78\n", "the last block ends at frame 14000, the WAV has 15000 frames"),
    ("end_frame,seconds\n100,1.0\n1e3,1.2\n", "line 3: end_frame '1e3' is not a whole number of frames"),
    ("end_frame,seconds\n100,1.0,7\n", "line 2: 3 fields, the header names 2"),
    ("seconds\n1.0\n1.0002\n", "2 per-sample timestamps for a WAV of 15000 frames"),
    ("end_frame,seconds\n", "no timestamp after the header"),
    # milliseconds where seconds belong: 3 s of samples would take 3000 s
    ("end_frame,seconds\n7500,1500.0\n15000,3000.0\n", "its timestamps do not follow its samples at 5000 Hz"),
    ("end_frame,seconds\n7500,__import__('os')\n15000,3.0\n", "is not a number"),
])
def test_a_bad_timestamp_file_is_refused_naming_the_line_and_nothing_is_written(lab_files, capsys, content,
                                                                                needle):
    (lab_files / "whiskers.csv").write_text(content)
    assert _import(lab_files) == 2
    err = capsys.readouterr().err
    assert needle in err and "whiskers.csv" in err and err.startswith("supramodal: error:")
    assert not (lab_files / "rec").exists() or not any((lab_files / "rec").iterdir())


@pytest.mark.parametrize("argv, needle", [
    (["--bank", "wrong=whisker"], "--bank: no source 'wrong'"),
    (["--times", "mic=x.csv"], "--times: source 'mic' is given twice"),
    (["--fusion"], "a fusion fuses two streams' decisions: give exactly two sources, each with a model"),
    (["--markers", "events"], "marker labels are read from an XDF file"),
])
def test_options_that_do_not_fit_are_refused(lab_files, capsys, argv, needle):
    assert _import(lab_files, *argv) == 2
    assert needle in capsys.readouterr().err


def test_a_wav_without_its_timestamps_or_bank_is_refused(lab_files, capsys):
    assert main(["import-recording", "--out", str(lab_files / "rec"), "--wav", f"mic={lab_files / 'mic.wav'}",
                 "--bank", "mic=cochlea"]) == 2
    assert "its WAV needs its timestamps: --times mic=TIMES.csv" in capsys.readouterr().err
    assert main(["import-recording", "--out", str(lab_files / "rec"), "--wav", f"mic={lab_files / 'mic.wav'}",
                 "--times", f"mic={lab_files / 'mic.csv'}"]) == 2
    assert "source 'mic' has no bank: --bank mic=whisker, cochlea or a bank file" in capsys.readouterr().err


def test_an_import_is_not_replaced_without_force(lab_files, capsys):
    assert _import(lab_files) == 0
    capsys.readouterr()
    assert _import(lab_files) == 2
    assert "exists; pass --force" in capsys.readouterr().err
    assert _import(lab_files, "--force") == 0


def test_a_failed_import_with_force_leaves_the_earlier_import_as_it_was(lab_files, capsys):
    """Issue 35, item 2: a --force import refused late (a model that does not fit its stream, found when the
    written scene is built) deleted the earlier import of that name. Now everything is written and checked
    aside, and put in place last: the earlier import's files are as they were, byte for byte."""
    from pathlib import Path

    assert _import(lab_files) == 0
    rec = lab_files / "rec"
    before = {p.name: p.read_bytes() for p in rec.iterdir()}
    model = Path(__file__).parent / "data" / "model-v1.npz"          # a whisker model of 8 channels
    capsys.readouterr()
    assert _import(lab_files, "--force", "--model", f"mic={model}") == 2
    assert "does not run" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in rec.iterdir()} == before          # nothing left aside either


def test_an_import_never_writes_over_its_inputs_nor_leaves_a_folder_it_made_for_nothing(lab_files, capsys):
    """Issue 35, items 2 and 32: an input that is one of the outputs (a WAV in --out under the output's name,
    a model given as the .npz the import would write) is refused before anything is written, the input
    intact, no traceback; a refused import leaves no --out folder it made."""
    import shutil
    from pathlib import Path

    rec = lab_files / "rec"
    rec.mkdir()
    shutil.copyfile(lab_files / "whiskers.wav", rec / "lab.whiskers.wav")
    mine = (rec / "lab.whiskers.wav").read_bytes()
    argv = ["import-recording", "--out", str(rec), "--name", "lab", "--force",
            "--wav", f"whiskers={rec / 'lab.whiskers.wav'}", "--times", f"whiskers={lab_files / 'whiskers.csv'}",
            "--bank", "whiskers=whisker"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "is an input of the import and would be one of its outputs" in err and "Traceback" not in err
    assert (rec / "lab.whiskers.wav").read_bytes() == mine and [p.name for p in rec.iterdir()] == ["lab.whiskers.wav"]
    (rec / "lab.whiskers.npz").write_bytes(b"not a model")
    argv[argv.index(f"whiskers={rec / 'lab.whiskers.wav'}")] = f"whiskers={lab_files / 'whiskers.wav'}"
    assert main([*argv, "--model", f"whiskers={rec / 'lab.whiskers.npz'}"]) == 2
    assert "would be one of its outputs" in capsys.readouterr().err
    assert (rec / "lab.whiskers.npz").read_bytes() == b"not a model"
    new = lab_files / "new"
    model = Path(__file__).parent / "data" / "model-v1.npz"          # a whisker model: no cochlea stream's
    assert main(["import-recording", "--out", str(new), "--name", "lab", "--wav", f"mic={lab_files / 'mic.wav'}",
                 "--times", f"mic={lab_files / 'mic.csv'}", "--bank", "mic=cochlea", "--model", f"mic={model}"]) == 2
    assert "does not run" in capsys.readouterr().err and not new.exists()


def test_xdf_streams_import_to_the_windows_the_xdf_source_gives(tmp_path, capsys):
    """Two streams of an XDF file imported, and the same file run as `type = "xdf"` sources: the
    same windows, features and times (one reader of the file's times: replay.xdf)."""
    pytest.importorskip("pyxdf", reason="XDF needs pyxdf (the lsl extra)")
    from xdf_writer import XdfStream, write_xdf

    rng = np.random.default_rng(3)
    n_w, n_m = 2 * W_RATE, 2 * M_RATE
    write_xdf(tmp_path / "r.xdf", [
        XdfStream("whiskers", "Whiskers", float(W_RATE), 0.1 * rng.standard_normal((n_w, 1)),
                  _t_whiskers(np.arange(n_w)),
                  offsets=[(T0 + k, 0.0) for k in range(3)]),
        XdfStream("mic", "Audio", float(M_RATE), 0.1 * rng.standard_normal((n_m, 1)), _t_mic(np.arange(n_m)),
                  offsets=[(T0 + k, 0.0) for k in range(3)], chunk=441)])
    assert main(["import-recording", "--out", str(tmp_path / "rec"), "--name", "x", "--xdf", str(tmp_path / "r.xdf"),
                 "--xdf-stream", "whiskers=whiskers", "--xdf-stream", "mic=mic", "--bank", "whiskers=whisker",
                 "--bank", "mic=cochlea"]) == 0
    direct = tmp_path / "direct.toml"
    direct.write_text("".join(f'[[source]]\nname = "{n}"\ntype = "xdf"\npath = "r.xdf"\nstream = "{n}"\n'
                              f'speed = "max"\n\n' for n in ("whiskers", "mic"))
                      + "".join(f'[[stream]]\nname = "{n}"\nsource = "{n}"\n[stream.bank]\nkind = "{k}"\n\n'
                                for n, k in (("whiskers", "whisker"), ("mic", "cochlea"))))
    imported, reference = _windows(capsys, tmp_path / "rec" / "x.toml"), _windows(capsys, direct)
    for name in ("whiskers", "mic"):
        assert len(imported[name]) == len(reference[name]) == 20
        for a, b in zip(imported[name], reference[name]):
            assert a["features"] == b["features"] and a["window"] == b["window"]
            assert a["start"] == pytest.approx(b["start"], abs=2e-6) and a["end"] == pytest.approx(b["end"], abs=2e-6)


def test_a_graphs_own_sessions_imported_with_models_and_fusion_replay_to_its_fused_decisions(tmp_path, capsys):
    """A two-sense recording made by `record` (models trained on the spot, late fusion), exported
    as a lab would have it (each source's WAV and a CSV of its blocks' times) and imported with
    the two models and --fusion: the imported scene pairs and fuses the same windows to the same
    decisions as the recording's own replay scene, its times shifted by one constant (the import's
    zero is the earliest first sample)."""
    (tmp_path / "w.toml").write_text(two_sense_world_toml(0.5, fusion="weight = 0.5"))
    assert main(["record", str(tmp_path / "w.toml"), "--out", str(tmp_path / "own"), "--name", "t", "--quiet"]) == 0
    argv = []
    for name, kind in (("whiskers", "whisker"), ("mic", "cochlea")):
        s = load_session(tmp_path / "own" / f"t.{name}")
        ends, seconds, rate = s.arrivals
        assert rate == s.rate                                   # a simulated device on its nominal clock
        write_wav(tmp_path / f"{name}.wav", s.data, s.rate, dtype="float32")
        _write_csv(tmp_path / f"{name}.csv", "end_frame,seconds", zip(ends.tolist(), seconds.tolist()))
        argv += ["--wav", f"{name}={tmp_path / f'{name}.wav'}", "--times", f"{name}={tmp_path / f'{name}.csv'}",
                 "--bank", f"{name}={kind}", "--model", f"{name}={tmp_path / 'own' / f't.{name}.npz'}"]
    assert main(["import-recording", "--out", str(tmp_path / "lab"), "--name", "t", *argv, "--fusion"]) == 0
    assert load_scene(tmp_path / "lab" / "t.toml").fusion.streams == ("whiskers", "mic")

    def fused(scene):
        capsys.readouterr()
        assert main(["run", str(scene), "--speed", "max", "--json", "--quiet"]) == 0
        events = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
        return [e for e in events if e.get("stream") == "fused"]

    own, lab = fused(tmp_path / "own" / "t.toml"), fused(tmp_path / "lab" / "t.toml")
    assert len(own) == len(lab) == 40
    assert [(e["window"], e["senses"], e["predicted"]) for e in lab] == \
        [(e["window"], e["senses"], e["predicted"]) for e in own]
    shift = lab[0]["end"] - own[0]["end"]
    assert np.allclose([e["end"] - shift for e in lab], [e["end"] for e in own], atol=2e-6)


def test_per_sample_times_in_milliseconds_are_refused_not_read_as_gaps(lab_files, capsys):
    """Issue 35, item 20: per-sample times in milliseconds were taken as seconds with gaps between every two
    samples (2 s of 8 kHz became a 64 MB WAV of 16 M frames and 15999 filled gaps). Refused, saying so."""
    lines = (lab_files / "mic.csv").read_text().splitlines()
    first = float(lines[1])                         # milliseconds since the first sample: within MAX_TIME
    (lab_files / "mic.csv").write_text("\n".join([lines[0], *(repr((float(v) - first) * 1000) for v in lines[1:])])
                                       + "\n")
    assert _import(lab_files) == 2
    err = capsys.readouterr().err
    assert "mic.csv: its times step by 0.0226" in err and "milliseconds?" in err and "44100 Hz" in err
    assert not (lab_files / "rec").exists()


def test_a_per_sample_time_far_beyond_any_recording_is_refused_naming_its_line_in_the_csv_s_words(lab_files, capsys):
    """Issue 35, item 29: a 9e9 s jump in a per-sample CSV was said in an XDF file's words ("the file's clock
    offset chunks are damaged"); 5e9 s here, within the times' own bound. The CSV's line and frame are named, and what to correct."""
    lines = (lab_files / "mic.csv").read_text().splitlines()
    lines[-5:] = [repr(float(v) + 5e9) for v in lines[-5:]]          # times still ascending, within MAX_TIME
    (lab_files / "mic.csv").write_text("\n".join(lines) + "\n")
    assert _import(lab_files) == 2
    err = capsys.readouterr().err
    frame = len(lines) - 6
    assert f"mic.csv: line {frame + 2} (frame {frame}) is 5" in err and "correct that line's time" in err, err
    assert "XDF" not in err and "clock offset" not in err
    assert not (lab_files / "rec").exists()


def test_sources_that_never_overlap_in_time_are_refused_with_the_gap(lab_files, capsys):
    """Issue 35, item 24: sources 1e6 s apart were imported, and the replay would have waited out the gap
    (11.6 days). Refused, naming each source's span and the gap; nothing written."""
    lines = (lab_files / "mic.csv").read_text().splitlines()
    (lab_files / "mic.csv").write_text("\n".join([lines[0], *(repr(float(v) + 1e6) for v in lines[1:])]) + "\n")
    assert _import(lab_files) == 2
    err = capsys.readouterr().err
    assert "the sources never overlap in time" in err and "mic starts 99999" in err and "after whiskers ends" in err, err
    assert not (lab_files / "rec").exists()


def test_a_source_of_two_channels_is_imported_with_the_mapping_given_and_refused_without_naming_the_option(
        lab_files, capsys):
    """Issue 35, item 27: a 2-channel source was refused with "set the scene's [driver] mapping", a table the
    import does not write and the command had no option for. The refusal names ``--mapping``; with it, the
    scene's [[stream]] takes the mapping and the whisker stream's windows are those of the channels' mean."""
    data, rate = read_wav(lab_files / "whiskers.wav")
    stereo = np.hstack([data, 0.5 * data])
    write_wav(lab_files / "whiskers.wav", stereo, rate, dtype="float32")
    assert _import(lab_files) == 2
    err = capsys.readouterr().err
    assert "[[stream]] whiskers's mapping" in err and "--mapping SOURCE=mean" in err and "[driver]" not in err, err
    assert not (lab_files / "rec").exists()
    assert _import(lab_files, "--mapping", "whiskers=sideways") == 2
    assert "--mapping whiskers=sideways: expected" in capsys.readouterr().err
    assert _import(lab_files, "--mapping", "whiskers=mean") == 0
    scene = load_scene(lab_files / "rec" / "lab.toml")
    assert {s.name: s.mapping for s in scene.streams} == {"whiskers": "mean", "mic": "auto"}
    got = _windows(capsys, lab_files / "rec" / "lab.toml")["whiskers"]
    ref = extract_features(stereo.mean(axis=1), whisker_bank(), ("Af",)).values[:, 0]   # offline, of the mean
    values = np.array([e["features"]["Af"] for e in got])
    assert values.shape == ref.shape and len(ref) == 30
    assert np.max(np.abs(values - ref)) <= 1e-12 * np.max(np.abs(ref))
