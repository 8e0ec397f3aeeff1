"""The command line: one line for user errors, a traceback for bugs, output paths checked before
the work, quiet exit when the reader of stdout leaves, signals during start-up."""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from supramodal.errors import InputError
from supramodal.node import cli
from supramodal.node.cli import main
from supramodal.replay.wavio import write_wav
from supramodal.textures import reference_texture_set

ROOT = Path(__file__).resolve().parents[1]


def _env():
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


@pytest.fixture(scope="module")
def replay_scene(tmp_path_factory):
    """A whisker replay scene of 2 s of one reference texture, looping (an endless stream)."""
    folder = tmp_path_factory.mktemp("scene")
    ts = reference_texture_set("whisker")
    write_wav(folder / "w.wav", ts.synthesize(0, duration=2.0)[:, None], 5000)
    scene = folder / "s.toml"
    scene.write_text('[driver]\ntype = "replay"\npath = "w.wav"\nloop = true\n[features]\nnames = ["A"]\n'
                     '[[sink]]\ntype = "jsonl"\n')
    return scene


def _lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.strip()]


# -- errors: one line for the user's, a traceback for bugs --------------------------------------


def test_user_error_is_one_line_and_exit_2(tmp_path, capsys):
    assert main(["run", str(tmp_path / "missing.toml")]) == 2
    err = _lines(capsys.readouterr().err)
    assert err == [f"supramodal: error: no scene file at {tmp_path / 'missing.toml'}"]


def test_a_folder_given_as_scene_is_a_user_error(tmp_path, capsys):
    assert main(["run", str(tmp_path)]) == 2
    err = _lines(capsys.readouterr().err)
    assert len(err) == 1 and err[0].startswith("supramodal: error: cannot read the scene file") and str(tmp_path) in err[0]


def test_debug_shows_the_traceback_of_a_user_error(tmp_path, capsys):
    for argv in (["--debug", "run", str(tmp_path / "missing.toml")], ["run", "--debug", str(tmp_path / "missing.toml")]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "Traceback" in err and "SceneError" in err
        assert err.rstrip().splitlines()[-1].startswith("supramodal: error: no scene file")


@pytest.mark.parametrize("planted", [ZeroDivisionError("division by zero"), ValueError("a bare ValueError"),
                                     KeyError("k")])
def test_a_planted_bug_shows_its_traceback(monkeypatch, tmp_path, capsys, planted):
    import supramodal.node.scene.schema

    def broken(path):
        raise planted

    monkeypatch.setattr(supramodal.node.scene.schema, "load_scene", broken)
    assert main(["run", str(tmp_path / "s.toml")]) == cli.EXIT_BUG
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err and "in broken\n    raise planted" in err
    assert type(planted).__name__ in err
    assert "this is a bug in supramodal" in err.splitlines()[-1]
    assert "supramodal: error:" not in err


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
@pytest.mark.parametrize("how", ["cause", "context"])
def test_a_signal_a_library_turned_into_its_own_error_is_still_the_signal(monkeypatch, tmp_path, capsys, sig, how):
    """A signal that lands while a C extension initialises comes back as that import's ImportError (pybind11's
    "initialization failed", raised from the handler's exception: a CI run of an interrupted ``evaluate`` exited 1
    as a bug). It is the interruption: one line, 128 + the signal, no traceback."""
    import supramodal.node.scene.schema
    from supramodal.node.cli.signals import StartupInterrupted

    def importing(path):
        try:
            raise StartupInterrupted(sig, "the test's work")
        except StartupInterrupted as interrupted:
            if how == "cause":
                raise ImportError("initialization failed") from interrupted
            raise ImportError("initialization failed")      # noqa: B904 (the context, as a library may leave it)

    monkeypatch.setattr(supramodal.node.scene.schema, "load_scene", importing)
    assert main(["run", str(tmp_path / "s.toml")]) == 128 + sig
    assert _lines(capsys.readouterr().err) == [f"supramodal: interrupted by {signal.Signals(sig).name} during the "
                                               "test's work"]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_whose_error_lost_it_is_still_the_signal(monkeypatch, tmp_path, capsys, sig):
    """numpy's C parts, interrupted as they import, raise "PyCapsule_Import could not import module" with the
    handler's exception lost from the chain. A real signal to this process, through the command's own handler:
    whatever error follows is the interruption. The next command in the same process starts afresh: a bug there
    is a bug."""
    import supramodal.node.scene.schema
    from supramodal.node.cli.signals import interrupt_until_running

    def importing(path):
        interrupt_until_running("the test's work")
        try:
            os.kill(os.getpid(), sig)
            time.sleep(5)                           # the handler raises at the next bytecode, long before this ends
        except BaseException:                       # noqa: S110 (as the C code does: the exception cleared)
            pass
        else:
            raise AssertionError("the signal did not arrive")
        raise ImportError("PyCapsule_Import could not import module")     # no cause, no context

    monkeypatch.setattr(supramodal.node.scene.schema, "load_scene", importing)
    assert main(["run", str(tmp_path / "s.toml")]) == 128 + sig
    assert _lines(capsys.readouterr().err) == [f"supramodal: interrupted by {signal.Signals(sig).name} during the "
                                               "test's work"]

    def broken(path):
        raise ImportError("PyCapsule_Import could not import module")

    monkeypatch.setattr(supramodal.node.scene.schema, "load_scene", broken)
    assert main(["run", str(tmp_path / "s.toml")]) == cli.EXIT_BUG
    assert "this is a bug in supramodal" in capsys.readouterr().err.splitlines()[-1]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_a_garbage_collector_callback_swallowed_is_delivered_again(monkeypatch, tmp_path, capsys, sig):
    """The handler's exception, raised in a gc callback (Dask's GCDiagnosis: an interrupted fit of a CI run kept
    searching, "Exception ignored in" on its stderr), is swallowed by the interpreter: its signal is delivered
    again, and the command ends as interrupted, in one line."""
    import gc
    import threading

    import supramodal.node.scene.schema
    from supramodal.node.cli.signals import interrupt_until_running

    def importing(path):
        interrupt_until_running("the test's work")
        armed = [True]

        def busy(phase, info):
            if armed[0] and phase == "start":
                armed[0] = False
                t0 = time.monotonic()
                while time.monotonic() - t0 < 0.5:       # in the callback when the signal comes
                    pass

        gc.callbacks.append(busy)
        try:
            threading.Timer(0.1, os.kill, (os.getpid(), sig)).start()
            gc.collect()
        finally:
            gc.callbacks.remove(busy)
        assert not armed[0]
        time.sleep(5)                                   # the signal delivered again ends this
        raise AssertionError("the command went on: the interruption was swallowed")

    monkeypatch.setattr(supramodal.node.scene.schema, "load_scene", importing)
    t0 = time.monotonic()
    assert main(["run", str(tmp_path / "s.toml")]) == 128 + sig
    assert time.monotonic() - t0 < 4
    assert _lines(capsys.readouterr().err) == [f"supramodal: interrupted by {signal.Signals(sig).name} during the "
                                               "test's work"]


def test_a_bug_raised_while_handling_another_error_is_still_a_bug(monkeypatch, tmp_path, capsys):
    """Only an interruption on the chain makes an error the interruption: a chain of ordinary errors is a bug."""
    import supramodal.node.scene.schema

    def broken(path):
        try:
            raise KeyError("k")
        except KeyError as first:
            raise ImportError("initialization failed") from first

    monkeypatch.setattr(supramodal.node.scene.schema, "load_scene", broken)
    assert main(["run", str(tmp_path / "s.toml")]) == cli.EXIT_BUG
    assert "this is a bug in supramodal" in capsys.readouterr().err.splitlines()[-1]


@pytest.mark.parametrize("raised, one_line", [(InputError("the pipeline refused it"), True),
                                              (ValueError("unexpected in a thread"), False)])
def test_an_error_in_a_node_thread(monkeypatch, replay_scene, capsys, raised, one_line):
    """A SupramodalError from a thread stays one line; any other exception there is a bug with its traceback.
    (A sink's own failures are counted, not raised: tests/test_node.py.)"""
    from supramodal.pipeline import FeaturePipeline

    def process(self, block):
        raise raised

    monkeypatch.setattr(FeaturePipeline, "process", process)
    rc = main(["run", str(replay_scene), "--json", "--quiet", "--speed", "max", "--seconds", "5"])
    err = capsys.readouterr().err
    if one_line:
        assert rc == 2 and "Traceback" not in err
        assert _lines(err) == ["supramodal: error: the processing thread failed: InputError: the pipeline refused it"]
    else:
        assert rc == cli.EXIT_BUG
        assert "Traceback" in err and "raise raised" in err and "ValueError: unexpected in a thread" in err
        assert "this is a bug in supramodal" in err.splitlines()[-1]


# -- output paths: checked before the work ------------------------------------------------------


@pytest.mark.parametrize("argv, message", [
    (["train", "--bank", "whisker", "--manifest", "{tmp}/m.csv", "--out", "{tmp}/missing/m.npz"],
     "the folder {tmp}/missing does not exist"),
    (["train", "--bank", "whisker", "--manifest", "{tmp}/m.csv", "--out", "{tmp}"],
     "{tmp} is a folder; give a file name in it"),
    (["experiment", "fig1", "--out", "{tmp}/file"], "{tmp}/file is a file; give a folder"),
    (["synth", "--out", "{tmp}/file/sub"], "{tmp}/file/sub cannot be created: {tmp}/file is a file"),
    (["record", "scene.toml", "--out", "{tmp}/file"], "{tmp}/file is a file; give a folder"),
    (["bench", "--out", "{tmp}/file"], "{tmp}/file is a file; give a folder"),
])
def test_output_paths_are_checked_before_any_work(monkeypatch, tmp_path, capsys, argv, message):
    (tmp_path / "file").write_text("not a folder")

    def no_work(args):
        raise AssertionError("the command started its work although its output path is unusable")

    for name in ("train", "experiment", "synth", "record", "bench"):
        monkeypatch.setattr(cli.command_module(name), "run", no_work)
    with pytest.raises(SystemExit) as stop:
        main([a.format(tmp=tmp_path) for a in argv])
    assert stop.value.code == 2
    assert message.format(tmp=tmp_path) in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]     # nothing written


def test_output_paths_that_are_fine_pass(tmp_path):
    parser = cli.build_parser()
    args = parser.parse_args(["train", "--bank", "whisker", "--manifest", "m.csv", "--out", str(tmp_path / "m")])
    assert args.out == tmp_path / "m"
    args = parser.parse_args(["synth", "--out", str(tmp_path / "new" / "deeper")])   # created when written
    assert args.out == tmp_path / "new" / "deeper" and not args.out.exists()


# -- the reader of stdout leaves: a quiet exit ------------------------------------------------


def test_run_into_head_exits_quietly_with_status_0(replay_scene):
    """`supramodal run | head` under `set -o pipefail`: the script does not fail, nothing on stderr."""
    script = f"set -o pipefail; {sys.executable} -m supramodal.node.cli run {replay_scene} --json --quiet --speed max | head -n 3"
    proc = subprocess.run(["bash", "-c", script], capture_output=True, text=True, env=_env(), cwd=ROOT, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert len(proc.stdout.splitlines()) == 3
    assert proc.stderr == ""


# -- signals during start-up ------------------------------------------------------------------


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_during_start_up_training(tmp_path, sig):
    """The cochlea scene trains its model for tens of seconds at start-up: a signal there
    prints one line and exits 128 + signal, nothing on stdout."""
    scene = tmp_path / "s.toml"
    scene.write_text('[driver]\ntype = "synth"\n[bank]\nkind = "cochlea"\n[model]\ntrain_on_start = true\n')
    # It trains: not a model another test of the run left in the cache of models trained on start.
    proc = subprocess.Popen([sys.executable, "-m", "supramodal.node.cli", "run", str(scene), "--json"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**_env(), "SUPRAMODAL_CACHE": "off"}, cwd=ROOT)
    try:
        first = proc.stderr.readline()               # printed just before the scene is built
        assert first.startswith("supramodal: scene "), first
        time.sleep(0.5)
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 128 + sig, err
    assert out == ""
    assert _lines(err) == [f"supramodal: interrupted by {signal.Signals(sig).name} during start-up (building the "
                           "scene, training its model); nothing was processed"]


# -- numbers on the command line and in scenes ---------------------------------------------------


@pytest.mark.parametrize("argv, option", [
    (["run", "--seconds", "nan"], "--seconds"),
    (["run", "--seconds", "0"], "--seconds"),
    (["run", "--seconds", "-1"], "--seconds"),
    (["run", "--seconds", "soon"], "--seconds"),
    (["synth", "--duration", "inf"], "--duration"),
    (["synth", "--duration", "0"], "--duration"),
    (["synth", "--duration", "nan"], "--duration"),
    (["train", "--bank", "whisker", "--manifest", "m.csv", "--out", "m.npz", "--window", "inf"], "--window"),
    (["train", "--bank", "whisker", "--manifest", "m.csv", "--out", "m.npz", "--epochs", "0"], "--epochs"),
    (["experiment", "fig3", "--jobs", "0"], "--jobs"),
    (["experiment", "fig3", "--sets", "-2"], "--sets"),
    (["experiment", "fig3", "--seed", "-1"], "--seed"),
    # issue 35, items 11, 13 and 16: one seed range for every command (numpy's and Optuna's 32 bits; fit's
    # Optuna raised a ValueError traceback past it), --jobs at most the cores, a cluster address with its port
    (["fit", "m.csv", "--seed", "4294967296"], "--seed"),
    (["train", "--bank", "whisker", "--manifest", "m.csv", "--out", "m.npz", "--seed", "4294967296"], "--seed"),
    (["evaluate", "m.npz", "--manifest", "m.csv", "--cv", "2", "--seed", "4294967296"], "--seed"),
    (["fit", "m.csv", "--jobs", "1000"], "--jobs"),
    (["experiment", "fig3", "--jobs", "1000"], "--jobs"),
    (["train", "--bank", "whisker", "--manifest", "m.csv", "--out", "m.npz", "--jobs", "1000"], "--jobs"),
    (["train", "--bank", "whisker", "--manifest", "m.csv", "--out", "m.npz", "--jobs", "0"], "--jobs"),
    (["fit", "m.csv", "--cluster", "notanaddress"], "--cluster"),
    (["fit", "m.csv", "--cluster", "tcp://host:notaport"], "--cluster"),
    # issue 34: gain augmentation, COPIES[,SPREAD[,per-channel|shared]]
    *[(["train", "--bank", "whisker", "--manifest", "m.csv", "--out", "m.npz", "--augment-gains", bad],
       "--augment-gains") for bad in ("0", "33", "four", "4,-0.1", "4,nan", "4,2", "4,0.03,per-vibrissa",
                                      "4,0.03,shared,1", "")],
])
def test_bad_numbers_on_the_command_line_name_their_option(capsys, argv, option):
    with pytest.raises(SystemExit) as stop:
        cli.build_parser().parse_args(argv)
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert f"argument {option}" in err and "Traceback" not in err


def test_seconds_inf_means_no_limit(replay_scene):
    args = cli.build_parser().parse_args(["run", str(replay_scene), "--seconds", "inf"])
    assert args.seconds is None
    assert cli.build_parser().parse_args(["run", "--seconds", "2.5"]).seconds == 2.5


@pytest.mark.parametrize("section, key", [("driver", "seconds"), ("features", "window"), ("buffer", "seconds")])
def test_a_scene_refuses_infinite_seconds_naming_the_key(section, key):
    from supramodal.node.scene.schema import SceneError, scene_from_dict

    driver = {"type": "synth"} if section != "driver" else {"type": "synth", "seconds": float("inf")}
    sections = {"driver": driver} | ({section: {key: float("inf")}} if section != "driver" else {})
    with pytest.raises(SceneError, match=rf"\[{section}\] (\(synth\) )?{key}: .*got inf"):
        scene_from_dict(sections)


@pytest.mark.parametrize("driver, needle", [
    ({"type": "synth", "seconds": 1e5, "held_out": False}, r"\[driver\] seconds: duration 100000 s"),
    ({"type": "synth", "seconds": 3000, "held_out": False, "order": ["T1", "T2", "T3"] * 4},
     r"\[driver\] seconds x order: 12 textures of 3000 s .* more than the 134217728"),
    ({"type": "twosense", "sense": "microphone", "seconds": 300, "pairs": 3},
     r"\[driver\] seconds x order: 12 textures of 300 s .* or set loop = true"),
])
def test_a_synthesised_source_too_long_to_hold_is_refused_before_it_is_made(driver, needle):
    """A synthesised source is generated whole: a length beyond what it may hold is refused,
    naming the key, before anything is allocated (1e5 s of 20-channel texture would be 80 GB)."""
    from supramodal.node.scene.build import build_node
    from supramodal.node.scene.schema import SceneError, scene_from_dict

    bank = {"kind": "cochlea"} if driver["type"] == "twosense" else {"kind": "whisker"}
    with pytest.raises(SceneError, match=needle):
        build_node(scene_from_dict({"driver": driver, "bank": bank}), sinks_override=[])


def test_a_refused_synth_leaves_no_folder(tmp_path, capsys):
    out = tmp_path / "big"
    assert main(["synth", "--duration", "1e9", "--out", str(out)]) == 2
    assert "--duration: duration 1e+09 s" in capsys.readouterr().err
    assert not out.exists()


def test_node_run_takes_inf_as_no_limit_and_refuses_nan():
    import numpy as np

    from supramodal.banks import whisker_bank
    from supramodal.node.runtime.graph import Node
    from supramodal.node.runtime.sinks import ListSink
    from supramodal.pipeline import FeaturePipeline
    from supramodal.replay.driver import ReplayDriver

    def node():
        x = np.zeros((5000, 1))
        return Node(ReplayDriver((x, 5000.0), speed="max", on_notice=None), FeaturePipeline(whisker_bank(), ("A",)),
                    [ListSink()], overrun="block")

    assert node().run(max_seconds=float("inf"))["stream_seconds"] == 1.0
    with pytest.raises(InputError, match="max_seconds"):
        node().run(max_seconds=float("nan"))


def test_version_and_python_m_supramodal():
    """`supramodal --version` and `python -m supramodal` (where the script is not on PATH) both work."""
    from supramodal import __version__

    proc = subprocess.run([sys.executable, "-m", "supramodal", "--version"], capture_output=True, text=True,
                          env=_env(), cwd=ROOT, timeout=60)
    assert proc.returncode == 0 and proc.stdout.strip() == f"supramodal {__version__}"
    proc = subprocess.run([sys.executable, "-m", "supramodal", "run", "--seconds", "nan"], capture_output=True,
                          text=True, env=_env(), cwd=ROOT, timeout=60)
    assert proc.returncode == 2 and "argument --seconds" in proc.stderr


# -- nothing left behind, nothing replaced by accident --------------------------------------------


def _serial_scene(folder: Path, port: str) -> Path:
    scene = folder / "serial.toml"
    scene.write_text(f'[driver]\ntype = "serial"\nport = "{port}"\nrate = 5000.0\nchannels = 20\n'
                     'mapping = "per-channel"\n[bank]\nkind = "whisker"\n[[sink]]\ntype = "jsonl"\n'
                     'path = "out/decisions.jsonl"\n')
    (folder / "out").mkdir()
    return scene


def test_a_port_that_does_not_open_leaves_no_file(tmp_path, capsys):
    """No board: exit 2 naming the port, and the scene's sink file is not created."""
    scene = _serial_scene(tmp_path, str(tmp_path / "no-such-port"))
    assert main(["run", str(scene), "--quiet"]) == 2
    assert "no-such-port" in capsys.readouterr().err
    assert list((tmp_path / "out").iterdir()) == []


def test_a_failed_record_leaves_no_folder_and_no_raw_file(tmp_path, capsys):
    scene = _serial_scene(tmp_path, str(tmp_path / "no-such-port"))
    assert main(["record", str(scene), "--out", str(tmp_path / "sessions"), "--name", "s", "--quiet"]) == 2
    assert not (tmp_path / "sessions").exists()


def test_record_refuses_to_replace_a_session_unless_forced(replay_scene, tmp_path, capsys):
    out = tmp_path / "sessions"
    assert main(["record", str(replay_scene), "--out", str(out), "--name", "s", "--seconds", "1", "--quiet"]) == 0
    first = (out / "s.wav").read_bytes()
    assert main(["record", str(replay_scene), "--out", str(out), "--name", "s", "--seconds", "0.5", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "a session 's' exists" in err and "--force" in err
    assert (out / "s.wav").read_bytes() == first
    assert sorted(p.name for p in out.iterdir()) == ["s.json", "s.wav"]
    assert main(["record", str(replay_scene), "--out", str(out), "--name", "s", "--seconds", "0.5", "--quiet",
                 "--force"]) == 0
    assert len((out / "s.wav").read_bytes()) < len(first)


def test_run_refuses_to_replace_a_sink_file_unless_forced(tmp_path, capsys):
    folder = tmp_path
    ts = reference_texture_set("whisker")
    write_wav(folder / "w.wav", ts.synthesize(0, duration=1.0)[:, None], 5000)
    scene = folder / "s.toml"
    scene.write_text('[driver]\ntype = "replay"\npath = "w.wav"\nspeed = "max"\n[features]\nnames = ["A"]\n'
                     '[[sink]]\ntype = "jsonl"\npath = "d.jsonl"\n')
    (folder / "d.jsonl").write_text("earlier results\n")
    assert main(["run", str(scene), "--quiet"]) == 2
    assert "d.jsonl exists; pass --force" in capsys.readouterr().err
    assert (folder / "d.jsonl").read_text() == "earlier results\n"
    assert main(["run", str(scene), "--quiet", "--force"]) == 0
    assert (folder / "d.jsonl").read_text().count("\n") == 11       # 10 windows + the summary


def test_train_refuses_an_existing_model_before_training(monkeypatch, tmp_path, capsys):
    import supramodal.node.workflows.training

    def no_training(*a, **k):
        raise AssertionError("trained although the output would be refused")

    monkeypatch.setattr(supramodal.node.workflows.training, "train_from_manifest", no_training)
    (tmp_path / "m.npz").write_bytes(b"an earlier model")
    argv = ["train", "--bank", "whisker", "--manifest", str(tmp_path / "m.csv"), "--out", str(tmp_path / "m.npz")]
    assert main(argv) == 2
    assert "m.npz exists; pass --force" in capsys.readouterr().err
    assert (tmp_path / "m.npz").read_bytes() == b"an earlier model"


def test_synth_refuses_to_replace_textures_unless_forced(tmp_path, capsys):
    out = tmp_path / "tex"
    assert main(["synth", "--out", str(out), "--duration", "0.1"]) == 0
    names = sorted(p.name for p in out.iterdir())
    before = {n: (out / n).stat().st_size for n in names}
    assert main(["synth", "--out", str(out), "--duration", "0.2"]) == 2
    assert "exists; pass --force" in capsys.readouterr().err
    assert {n: (out / n).stat().st_size for n in names} == before
    assert main(["synth", "--out", str(out), "--duration", "0.2", "--force"]) == 0
    assert all((out / n).stat().st_size > before[n] for n in names)


def test_print_scene_writes_a_scene_that_loads_back_the_same(tmp_path, capsys, replay_scene):
    """`run --print-scene` (the embedded default, or a file) prints TOML that load_scene reads
    back to the same scene: every key, defaults filled in."""
    from supramodal.node.scene.schema import default_scene, load_scene

    for argv, expected in ((["run", "--print-scene"], default_scene()), (["run", str(replay_scene), "--print-scene"],
                                                                        load_scene(replay_scene))):
        assert main(argv) == 0
        path = tmp_path / "printed.toml"
        path.write_text(capsys.readouterr().out)
        again = load_scene(path)
        for part in ("sources", "streams", "sinks"):                # every key but where each is written
            assert _keys(getattr(again, part)) == _keys(getattr(expected, part)), part


def _keys(specs) -> list:
    """A scene's sources, streams or sinks without the names of their tables in messages."""
    return [{k: dict(v) if k == "options" else v for k, v in vars(s).items() if k not in ("where", "index")}
            for s in specs]


def test_a_bank_above_the_recordings_band_is_warned_even_when_quiet(tmp_path, capsys):
    """A cochlea (44.1 kHz) trained on 5 kHz recordings: the channels above 2.5 kHz see nothing;
    the command says how many, as a warning --quiet does not hide."""
    from supramodal.banks import cochlea_bank

    ts = reference_texture_set("whisker")
    for i in range(2):
        write_wav(tmp_path / f"t{i}.wav", ts.synthesize(i, duration=0.5)[:, None], 5000)
    (tmp_path / "m.csv").write_text("path,label\nt0.wav,a\nt1.wav,b\n")
    argv = ["train", "--bank", "cochlea", "--manifest", str(tmp_path / "m.csv"), "--out", str(tmp_path / "m.npz"),
            "--epochs", "2", "--quiet"]
    assert main(argv) == 0
    err = capsys.readouterr().err
    above = int((cochlea_bank().cf >= 2500).sum())
    # one per recording, and one more since issue 34: a texture in one recording is calibrated on its spans
    assert err.count("supramodal: warning:") == 2 + 1 and err.count("calibrated on spans of each recording") == 1
    assert f"{above} of the cochlea bank's 50 channels" in err and "sampled at 5000 Hz" in err


def test_messages_point_at_what_the_user_sets(tmp_path, capsys):
    """Each refusal names what to change where the user changes it: --mapping for train, the
    scene's key for a missing recording or sink folder."""
    import numpy as np

    write_wav(tmp_path / "st.wav", np.zeros((6000, 2)), 5000)
    write_wav(tmp_path / "st2.wav", np.zeros((6000, 2)), 5000)
    (tmp_path / "m.csv").write_text("path,label\nst.wav,a\nst2.wav,b\n")
    assert main(["train", "--bank", "whisker", "--manifest", str(tmp_path / "m.csv"), "--out",
                 str(tmp_path / "m.npz"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "m.csv, line 2" in err and 'set --mapping to "mean"' in err
    (tmp_path / "gone.toml").write_text('[driver]\ntype = "replay"\npath = "gone.wav"\n')
    assert main(["run", str(tmp_path / "gone.toml"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "[driver] path: no recording at" in err and "scene file's folder" in err and "Errno" not in err
    (tmp_path / "sink.toml").write_text('[driver]\ntype = "replay"\npath = "st.wav"\nmapping = "mean"\n'
                                        '[[sink]]\ntype = "jsonl"\npath = "nodir/x.jsonl"\n')
    assert main(["run", str(tmp_path / "sink.toml"), "--quiet"]) == 2
    assert "[[sink]] #1 path:" in capsys.readouterr().err


def test_the_first_run_says_what_it_shows_and_where_to_go(capsys):
    """`supramodal run` with no scene: how long it runs and at what pace, what each column means
    (-- explained), and the next steps; the columns are named above the first window."""
    assert main(["run", "--speed", "max", "--seconds", "0.3"]) == 0
    out, err = capsys.readouterr()
    assert "8 reference textures (80 s of stream) at once" in err
    assert "ok or -- (wrong)" in err and "Ctrl-C stops" in err
    assert "supramodal train --help" in err and "examples/whisker_serial.toml" in err and "--print-scene" in err
    lines = out.splitlines()
    assert "decision" in lines[0] and "confidence" in lines[0] and "-- = wrong" in lines[0]
    assert lines[1].strip().startswith("0.100 s")
    assert main(["run", "--seconds", "0.1", "--quiet", "--speed", "max"]) == 0
    assert "default scene" not in capsys.readouterr().err                # --quiet: no guide either


def test_mock_whisker_ends_on_sigterm_as_on_ctrl_c(tmp_path):
    """SIGTERM: the ledger line is printed, the exit status is 0 and the port's symlink is gone."""
    link = tmp_path / "whisker0"
    proc = subprocess.Popen([sys.executable, "-m", "supramodal.node.cli", "mock-whisker", "synth:T1", "--loop", "--port", str(link)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env(), cwd=ROOT)
    try:
        assert proc.stdout.readline().strip() == str(link)
        assert link.is_symlink()
        time.sleep(0.3)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=20)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    assert "mock-whisker: " in err and " frames, " in err and "unplugs" in err
    assert not link.exists() and not link.is_symlink()


def test_every_option_has_help_stating_its_default():
    import argparse

    parser = cli.build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    missing = []
    for name, sub in commands.items():
        for action in sub._actions:
            if action.dest in ("help", "debug"):
                continue
            text = action.help or ""
            if not text or (action.default not in (None, False, argparse.SUPPRESS) and "default" not in text):
                missing.append(f"{name} {'/'.join(action.option_strings) or action.dest}")
    assert not missing, f"options without help, or whose help does not state the default: {missing}"


def test_main_gives_the_callers_signal_handlers_back(tmp_path):
    """`supramodal run` stops its node on SIGINT/SIGTERM; called in-process (a test, a program), it
    must not leave that handler behind, or the caller could no longer be interrupted."""
    import signal

    from supramodal.node.cli import main

    mine = lambda signum, frame: None          # noqa: E731
    before = {sig: signal.signal(sig, mine) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        assert main(["run", "--seconds", "0.3", "--speed", "max", "--quiet", "--json"]) == 0
        assert signal.getsignal(signal.SIGINT) is mine and signal.getsignal(signal.SIGTERM) is mine
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)


def test_the_seed_range_the_jobs_bound_and_a_cluster_address_are_said_and_good_ones_taken():
    from supramodal.node.cli.arguments import MAX_SEED, cluster_address, cores, jobs, seed

    assert seed("0") == 0 and seed(str(MAX_SEED)) == MAX_SEED == 2**32 - 1
    assert jobs("1") == 1 and jobs(str(cores())) == cores()
    assert cluster_address("10.0.0.2:8786") == "tcp://10.0.0.2:8786"
    assert cluster_address("tls://sched.lab:8786") == "tls://sched.lab:8786"
    for bad in ("notanaddress", "tcp://:8786", "http://h:1", "tcp://h:99999", "tcp://h:1/x"):
        with pytest.raises(argparse.ArgumentTypeError, match="tcp://HOST:PORT"):
            cluster_address(bad)
    with pytest.raises(argparse.ArgumentTypeError, match=f"at most the {cores()} cores here"):
        jobs(str(cores() + 1))


def test_every_command_s_help_says_what_it_does_lists_debug_and_names_no_issue():
    """`supramodal CMD --help` opens with the command's line (devices and bench showed only options), lists
    --debug, and no help text names an internal issue."""
    import re

    from supramodal.node.cli import COMMANDS, build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    assert set(sub.choices) == set(COMMANDS)
    for name, command in sub.choices.items():
        text = command.format_help()
        assert command.description, name
        # whitespace aside: argparse wraps lines, at a hyphen too ("cross-" / "validation")
        assert "".join(command.description.split()) in "".join(text.split()), name
        assert "--debug" in text, name
        assert not re.search(r"\bissue \d", text), (name, re.search(r".{40}\bissue \d.{10}", text))


def test_the_user_documents_name_no_internal_issue():
    """README.md, docs/*.md and the examples say what a user needs, not which internal issue a thing came from."""
    import re

    root = Path(__file__).resolve().parents[1]
    files = [root / "README.md", *sorted((root / "docs").glob("*.md")), *sorted((root / "examples").glob("*.toml"))]
    found = [(f.name, n, line.strip()[:80]) for f in files for n, line in enumerate(f.read_text().splitlines(), 1)
             if re.search(r"\bissues? \d", line, re.IGNORECASE)]
    assert found == []


def test_speed_on_a_live_scene_is_said_to_be_ignored_once():
    """--speed paces replayed sources only: on a scene whose sources are all live, run says so (once, before the
    run); on a replayed scene, or without --speed, nothing."""
    from supramodal.node.cli.run import speed_notice
    from supramodal.node.scene.schema import default_scene, scene_from_dict

    live = scene_from_dict({"source": [{"name": "w", "type": "serial", "port": "/dev/null", "rate": 5000.0,
                                        "channels": 20},
                                       {"name": "m", "type": "microphone"}],
                            "stream": [{"name": "w", "source": "w", "bank": {"kind": "whisker"}},
                                       {"name": "m", "source": "m", "bank": {"kind": "cochlea"}}]})
    said = speed_notice(live, "max")
    assert said is not None and said.startswith("--speed max is ignored") and "(serial, microphone)" in said
    assert speed_notice(live, None) is None
    assert speed_notice(default_scene(), "max") is None


def test_ci_runs_exactly_the_readme_s_test_command():
    """The README's test command is the one .ci/run runs (after its system packages), word for word."""
    root = Path(__file__).resolve().parents[1]
    readme = (root / "README.md").read_text()
    command = next(line for line in readme.splitlines() if line.startswith("python3 -m pip install") and "pytest" in line)
    ci = [line for line in (root / ".ci/run").read_text().splitlines() if line and not line.startswith("#")]
    assert command in ci


_TOY_COMMAND = '''
SUMMARY = "greet a name"
README_ROWS = (("supramodal toy NAME", SUMMARY + " ([a page](docs/toy.md))"),)


def add_parser(subparsers, common):
    p = subparsers.add_parser("toy", parents=[common], help=SUMMARY)
    p.add_argument("name")
    return p


def run(args):
    print(f"hello {args.name}")
    return 0
'''


def test_a_new_command_is_one_module_and_one_line(tmp_path, monkeypatch, capsys):
    """The recipe of node/cli/__init__.py holds: a module with add_parser, run and its README rows, and its line in
    COMMANDS, are all a command needs (its --help, its run, its place in the list, its rows in the README's
    command table); nothing else is edited."""
    from supramodal.node.cli import COMMANDS, build_parser, main
    from supramodal.node.cli import docs as cli_docs

    (tmp_path / "toy_command.py").write_text(_TOY_COMMAND)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(COMMANDS, "toy", "toy_command")                 # the one line
    assert main(["toy", "world"]) == 0
    assert capsys.readouterr().out == "hello world\n"
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    assert list(sub.choices)[-1] == "toy" and sub.choices["toy"].description == "greet a name"
    assert main(["toy", "--debug", "you"]) == 0 and capsys.readouterr().out == "hello you\n"
    # the README's table gains its row, last as in --help; the committed README now lacks it, and says so
    assert cli_docs.command_table().endswith("\n| `supramodal toy NAME` | greet a name ([a page](docs/toy.md)) |")
    assert cli_docs.check(ROOT) == ["README.md"]


def test_the_readme_command_table_is_the_command_modules():
    """README.md's command table is made from each command's README_ROWS (python -m supramodal.node.cli.docs), in
    COMMANDS' order: a command added, removed or reworded without regenerating it fails here. Each command's
    line has one home, its module's SUMMARY: --help opens with it, and a command of one form's row says it."""
    from supramodal.node.cli import COMMANDS, build_parser, command_module
    from supramodal.node.cli import docs as cli_docs
    from supramodal.node.scene.docs import rewrite

    assert cli_docs.check(ROOT) == [], "README.md's command table is stale: run python -m supramodal.node.cli.docs"
    table = cli_docs.command_table()
    readme = (ROOT / "README.md").read_text()
    assert "<!-- BEGIN generated: commands -->\n" + table + "\n<!-- END generated: commands -->" in readme
    rows = table.splitlines()[2:]
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    named = []
    for name in COMMANDS:
        module = command_module(name)
        assert sub.choices[name].description == module.SUMMARY, name
        forms = module.README_ROWS
        # every row is its own command's: its synopsis starts with the command's name
        assert all(synopsis.split()[:2] == ["supramodal", name] for synopsis, _ in forms), name
        if len(forms) == 1:
            assert forms[0][1].startswith(module.SUMMARY), name
        named += [name] * len(forms)
    assert [row.split("`")[1].split()[1] for row in rows] == named
    # a pipe in a synopsis is escaped, or the row would have more cells than the header
    assert all(row.replace("\\|", "").count("|") == 3 for row in rows)
    # a stale table is found, and the rewrite puts it back
    stale = readme.replace("| list audio inputs and serial ports |", "| list the devices |")
    assert stale != readme and rewrite(stale, ["commands"], cli_docs.blocks()) == readme
