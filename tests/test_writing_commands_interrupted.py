"""Every command that writes files, interrupted (SIGINT, SIGTERM) or refused, leaves the files that were there
as they were and no partial output (issue 35, "done when").

What: ``record`` (a session; a graph's sessions and replay scene), ``label``, ``import-recording``, ``train``,
``fit``, ``evaluate --out`` and ``run`` with a JSON Lines and a text sink. Each works in a folder that holds its
inputs and its earlier outputs (placeholders where the command only checks that they exist, so that a replaced
file shows; real sessions where ``label`` reads and rewrites them), run with ``--force`` or ``--replace`` so that
a completed run replaces them; every path in the folder is fingerprinted (sha256) before.

How: the command runs in a process of its own (``python -m supramodal``, a session of its own) and gets SIGINT or
SIGTERM

* at a moment drawn from a fixed seed between 5 % and 130 % of the duration an uninterrupted run of it took in
  this session (while Python starts, while the command works, while it writes, or after it ended); or
* right after its N-th change to the folder (a file opened for writing or created, replaced, renamed or removed,
  a folder made or removed), N drawn from a fixed seed over the changes of an uninterrupted run: the moments a
  signal from outside seldom hits (a file half written, between two files put in place) made exact by
  :data:`_HOOK`, which wraps the file functions and sends the process the signal itself.

Then the folder is either as it was, byte for byte, or holds the complete, valid outputs of a run (each loaded as
its reader loads it) and the rest as it was; no other path is new (no temporary file, staging folder or raw file).
The exit status is 128 + the signal, with one line saying what was interrupted; 0 for a run that completed; minus
the signal where no handler of the command's was set (while Python loads its modules, or once it has returned).
``record`` and ``run`` stop cleanly on a signal once they stream: exit 0 with what was recorded or decided
(``record``: nothing if no block had come), or exit 2 and nothing written for a graph recording that cannot be
kept whole (a source that had not started). A moment never makes the test fail: wherever the signal lands the
same holds, so an early or a late one is a valid case, not a flake. A refused run (a bad input found once the
inputs are read, or an output that exists without ``--force``) leaves every file as it was.

Bounds: the inputs are the smallest that write every output: 2 textures x 2 recordings of 1.5 s at 5 kHz, 5
epochs, a fit of 2 trials; the streaming commands run 0.4 s of stream in real time so that a signal finds them
starting or streaming. Each command runs once uninterrupted (the baseline, also the case of a signal that comes
after the end) and four times interrupted (two moments, two changes; each once by SIGINT and once by SIGTERM);
about 1 to 2 s a run on two cores (most of it Python loading the command), fit and evaluate 3 to 5 s (a search;
the plots: marked slow); the whole file about a minute.
"""

from __future__ import annotations

import ast
import hashlib
import json
import math
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from supramodal.node.cli import main
from supramodal.replay.session import load_session, save_session
from supramodal.replay.wavio import write_wav
from supramodal.textures import reference_texture_set

ROOT = Path(__file__).resolve().parents[1]

#: Run ``python -c _HOOK FOLDER SIGNAL N ARGS...``: ``supramodal ARGS`` with the file functions wrapped so that
#: right after its N-th change under FOLDER the process sends itself SIGNAL (N = 0: never); at exit (unless the
#: signal ended it) it says on stderr how many changes it made, and which.
_HOOK = r"""
import atexit, builtins, io, os, runpy, sys
folder, signum, nth = os.path.abspath(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
del sys.argv[1:4]
changes = []

def changed(path, what):
    try:
        path = os.path.abspath(os.fsdecode(path))
    except TypeError:                                   # a file descriptor: no path
        return
    if path.startswith(folder + os.sep):
        changes.append(f"{what} {os.path.relpath(path, folder)}")
        if len(changes) == nth:
            os.kill(os.getpid(), signum)

def wrap(module, name, changes_it):
    real = getattr(module, name)
    def wrapped(path, *args, **kwargs):
        result = real(path, *args, **kwargs)
        if changes_it(*args, **kwargs):
            changed(path, name)
        return result
    setattr(module, name, wrapped)

def moved(real):
    def wrapped(src, dst, *args, **kwargs):
        result = real(src, dst, *args, **kwargs)
        changed(dst, real.__name__)
        return result
    return wrapped

wrap(builtins, "open", lambda mode="r", *a, **k: any(c in mode for c in "wax+"))
io.open = builtins.open                                 # pathlib's open
wrap(os, "open", lambda flags, *a, **k: bool(flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_TRUNC)))
for name in ("mkdir", "rmdir", "unlink", "remove"):
    wrap(os, name, lambda *a, **k: True)
os.replace, os.rename = moved(os.replace), moved(os.rename)
atexit.register(lambda: print(f"[hook] {len(changes)} changes: {changes}", file=sys.stderr))
runpy.run_module("supramodal", run_name="__main__", alter_sys=True)
"""

SEED = 35
RATE = 5000
#: Seconds of stream the streaming commands (record, run) take, in real time.
STREAM = "0.4"


# -- the commands' folders ----------------------------------------------------------------------------------------

def _recordings(folder: Path, labels=("T1", "T2"), per_label: int = 2, seconds: float = 1.5) -> None:
    """``per_label`` recordings of ``seconds`` of each of the first reference whisker textures, as ``all.csv``
    with the given labels; ``one.csv`` lists those of the first label only (a manifest training refuses)."""
    ts = reference_texture_set("whisker")
    n = int(seconds * RATE)
    rows = ["path,label"]
    for t, label in enumerate(labels):
        x = ts.synthesize(t, duration=per_label * seconds)
        for r in range(per_label):
            write_wav(folder / f"{label}_{r}.wav", x[r * n:(r + 1) * n, None], RATE)
            rows.append(f"{label}_{r}.wav,{label}")
    (folder / "all.csv").write_text("\n".join(rows) + "\n")
    (folder / "one.csv").write_text("\n".join(rows[:1 + per_label]) + "\n")


def _earlier(folder: Path, *names: str) -> None:
    """An earlier run's outputs, as files the command only checks for (replaced with --force)."""
    for name in names:
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_text(f"an earlier run's {name}\n")


def _synth_scene(seconds_per_texture: float = 0.5) -> str:
    return (f'type = "synth"\nseconds = {seconds_per_texture}\nheld_out = false\nspeed = 1.0\n')


def _prepare_record(folder: Path) -> None:
    (folder / "rec.toml").write_text("[driver]\n" + _synth_scene())
    _earlier(folder, "rec/s.wav", "rec/s.json")


def _complete_record(folder: Path) -> None:
    s = load_session(folder / "rec" / "s.wav")
    assert s.rate == RATE and 0 < s.data.shape[0] <= float(STREAM) * RATE
    assert s.labels and s.labels[0].label == "T1"                # the synth driver's truth, kept


def _prepare_record_graph(folder: Path) -> None:
    # Source b delivers its first block 0.15 s after a's first (blocks of 750 frames against 50): a recording
    # stopped before has no session of b, and cannot be kept.
    (folder / "g.toml").write_text("".join(
        f'[[source]]\nname = "{n}"\n{_synth_scene()}block = {block}\n\n[[stream]]\nname = "{n}"\nsource = "{n}"\n\n'
        for n, block in (("a", 50), ("b", 750))))
    _earlier(folder, *(f"grec/g.{n}.{ext}" for n in "ab" for ext in ("wav", "json")), "grec/g.toml")


def _complete_record_graph(folder: Path) -> None:
    from supramodal.node.scene.schema import load_scene

    replay = load_scene(folder / "grec" / "g.toml")
    assert [s.options["timing"] for s in replay.sources] == ["recorded", "recorded"]
    for n in "ab":
        s = load_session(folder / "grec" / f"g.{n}.wav")
        assert s.data.shape[0] > 0 and s.arrivals is not None


def _prepare_label(folder: Path) -> None:
    ends = np.arange(250, 5001, 250)
    for n in "ab":
        save_session(folder / f"r.{n}", np.zeros((5000, 1)), RATE, "test", labels=[(0.1, 0.2, "old")],
                     arrivals=(ends, 0.25 + ends / RATE, float(RATE)))
    (folder / "r.toml").write_text("".join(
        f'[[source]]\nname = "{n}"\ntype = "replay"\npath = "r.{n}.wav"\ntiming = "recorded"\n\n'
        f'[[stream]]\nname = "{n}"\nsource = "{n}"\n\n' for n in "ab"))
    (folder / "spans.csv").write_text("start,end,label\n0.4,0.8,felt\n")
    (folder / "late.csv").write_text("start,end,label\n0.4,0.8,felt\n9.0,9.5,grit\n")


def _complete_label(folder: Path) -> None:
    for n in "ab":
        assert [lab.label for lab in load_session(folder / f"r.{n}.wav").labels] == ["felt"]


def _prepare_import(folder: Path) -> None:
    rng = np.random.default_rng(SEED)
    write_wav(folder / "w.wav", 0.2 * rng.standard_normal((5000, 1)), RATE)
    ends = np.arange(250, 5001, 250)
    (folder / "w.csv").write_text("end_frame,seconds\n" + "".join(f"{e},{100 + e / RATE:.6f}\n" for e in ends))
    _earlier(folder, "imp/lab.w.wav", "imp/lab.w.json", "imp/lab.toml")


def _complete_import(folder: Path) -> None:
    from supramodal.node.scene.schema import load_scene

    assert [s.name for s in load_scene(folder / "imp" / "lab.toml").sources] == ["w"]
    assert load_session(folder / "imp" / "lab.w.wav").data.shape == (5000, 1)


def _prepare_train(folder: Path) -> None:
    _recordings(folder)
    _earlier(folder, "m.npz")


def _complete_train(folder: Path) -> None:
    from supramodal.model import TextureModel

    assert list(TextureModel.load(folder / "m.npz").classes) == ["T1", "T2"]


TRAIN_CV_FILES = ("m-cv.csv", "m-cv.png", "m-cv-reliability.csv", "m-cv-reliability.png")


def _prepare_train_cv(folder: Path) -> None:
    _recordings(folder)
    _earlier(folder, "m.npz", *TRAIN_CV_FILES)


def _complete_train_cv(folder: Path) -> None:
    _complete_train(folder)
    assert (folder / "m-cv.csv").read_text().startswith("truth")


def _prepare_evaluate(folder: Path) -> None:
    from supramodal.banks import whisker_bank
    from supramodal.node.workflows.reports import EVALUATION_FILES
    from supramodal.node.workflows.training import train_from_manifest

    _recordings(folder)
    # calibrated (a model of version 1 is not), so that every file is written, the anytime decisions too
    train_from_manifest(folder / "all.csv", whisker_bank(), epochs=5).save(folder / "model.npz")
    (folder / "odd.csv").write_text("path,label\nT1_0.wav,T1\nT2_0.wav,velvet\n")
    _earlier(folder, *(f"ev/{name}" for name in EVALUATION_FILES))


def _complete_evaluate(folder: Path) -> None:
    from supramodal.node.workflows.reports import EVALUATION_FILES

    for name in EVALUATION_FILES:
        data = (folder / "ev" / name).read_bytes()
        if name.endswith(".png"):
            assert data.startswith(b"\x89PNG") and data.endswith(b"IEND\xaeB`\x82"), name
        else:
            assert data.count(b"\n") >= 2, name


def _prepare_recalibrate(folder: Path) -> None:
    from supramodal.banks import whisker_bank
    from supramodal.node.workflows.training import train_from_manifest

    _recordings(folder)
    train_from_manifest(folder / "all.csv", whisker_bank(), epochs=5).save(folder / "model.npz")
    (folder / "odd.csv").write_text("path,label\nT1_0.wav,T1\nT2_0.wav,velvet\n")
    _earlier(folder, "re.npz")


def _complete_recalibrate(folder: Path) -> None:
    from supramodal.model import TextureModel

    assert "manifest all.csv" in TextureModel.load(folder / "re.npz").calibration.fitted_on["recalibrated_on"]


def _prepare_fit(folder: Path) -> None:
    _recordings(folder)
    _earlier(folder, "fit/fit.csv", "fit/fit-curve.csv", "fit/fit-curve.png", "fit/bank.json")
    (folder / "fit" / "cache").mkdir()                           # an earlier fit leaves it, emptied


def _complete_fit(folder: Path) -> None:
    from supramodal.bankfile import load_bank

    load_bank(folder / "fit" / "bank.json")
    assert len((folder / "fit" / "fit.csv").read_text().splitlines()) == 1 + 2        # a row per trial
    assert (folder / "fit" / "fit-curve.png").read_bytes().endswith(b"IEND\xaeB`\x82")
    assert not list((folder / "fit" / "cache").iterdir())


def _prepare_run(folder: Path) -> None:
    (folder / "run.toml").write_text("[driver]\n" + _synth_scene() + '[[sink]]\ntype = "jsonl"\npath = "out.jsonl"\n'
                                     '[[sink]]\ntype = "text"\npath = "out.txt"\n')
    _earlier(folder, "out.jsonl", "out.txt")


def _complete_run(folder: Path) -> None:
    events = [json.loads(line) for line in (folder / "out.jsonl").read_text().splitlines()]
    assert events[-1].get("summary") is True and all("summary" not in e for e in events[:-1])
    assert "stopped by" in (folder / "out.txt").read_text().splitlines()[-1]


@dataclass(frozen=True)
class Command:
    """A command that writes: its folder, its arguments and what a completed run writes."""

    name: str
    prepare: Callable[[Path], None]
    argv: tuple[str, ...]
    outputs: frozenset[str]                 # files a completed run writes (each replacing an earlier one)
    complete: Callable[[Path], None]        # asserts that the outputs are those of a complete run
    refused: tuple[str, ...]                # a run refused after its inputs were read, or for an existing output
    says: str                               # what the refusal says
    slow: bool = False
    needs: tuple[str, ...] = ()             # modules its outputs need (the fit extra; matplotlib for the PNGs)
    #: A signal stops it once it streams (record, run): exit 0 with what it recorded or decided, nothing if no block
    #: had come; or exit 2, nothing written, for a graph recording that cannot be kept whole (a source not started).
    stops: bool = False


COMMANDS = (
    Command("record", _prepare_record,
            ("record", "rec.toml", "--out", "rec", "--name", "s", "--seconds", STREAM, "--force", "--quiet"),
            frozenset({"rec/s.wav", "rec/s.json"}), _complete_record,
            ("record", "rec.toml", "--out", "rec", "--name", "s", "--quiet"), "pass --force", stops=True),
    Command("record-graph", _prepare_record_graph,
            ("record", "g.toml", "--out", "grec", "--name", "g", "--seconds", STREAM, "--force", "--quiet"),
            frozenset({"grec/g.a.wav", "grec/g.a.json", "grec/g.b.wav", "grec/g.b.json", "grec/g.toml"}),
            _complete_record_graph,
            ("record", "g.toml", "--out", "grec", "--name", "g", "--quiet"), "exists; pass --force", stops=True),
    Command("label", _prepare_label, ("label", "r.toml", "spans.csv", "--replace"),
            frozenset({"r.a.json", "r.b.json"}), _complete_label,
            ("label", "r.toml", "late.csv", "--replace"), "starts after the recording ends"),
    Command("import-recording", _prepare_import,
            ("import-recording", "--out", "imp", "--name", "lab", "--wav", "w=w.wav", "--times", "w=w.csv",
             "--bank", "w=whisker", "--force"),
            frozenset({"imp/lab.w.wav", "imp/lab.w.json", "imp/lab.toml"}), _complete_import,
            ("import-recording", "--out", "imp", "--name", "lab", "--wav", "w=w.wav", "--times", "w=w.csv",
             "--bank", "w=whisker", "--mapping", "w=per-channel", "--force"), "does not run"),
    Command("train", _prepare_train,
            ("train", "--bank", "whisker", "--manifest", "all.csv", "--out", "m.npz", "--epochs", "5", "--force",
             "--quiet"),
            frozenset({"m.npz"}), _complete_train,
            ("train", "--bank", "whisker", "--manifest", "one.csv", "--out", "m.npz", "--epochs", "5", "--force",
             "--quiet"), "at least two labels"),
    # the cross-validation's files and the model together (the files came first: an interrupted training left a
    # new report beside the earlier model)
    Command("train-cv", _prepare_train_cv,
            ("train", "--bank", "whisker", "--manifest", "all.csv", "--out", "m.npz", "--epochs", "5", "--cv", "2",
             "--force", "--quiet"),
            frozenset({"m.npz", *TRAIN_CV_FILES}), _complete_train_cv,
            ("train", "--bank", "whisker", "--manifest", "one.csv", "--out", "m.npz", "--epochs", "5", "--cv", "2",
             "--force", "--quiet"), "at least two labels", slow=True, needs=("matplotlib",)),
    Command("evaluate", _prepare_evaluate,
            ("evaluate", "model.npz", "--manifest", "all.csv", "--out", "ev", "--force", "--quiet"),
            frozenset({f"ev/{name}" for name in ("confusion.csv", "confusion.png", "pooling.csv", "channels.csv",
                                                 "evaluation.png", "reliability.csv", "reliability.png",
                                                 "anytime.csv", "anytime.png")}), _complete_evaluate,
            ("evaluate", "model.npz", "--manifest", "odd.csv", "--out", "ev", "--force", "--quiet"),
            "is not a class of the model", slow=True, needs=("matplotlib",)),
    Command("recalibrate", _prepare_recalibrate,
            ("recalibrate", "model.npz", "--manifest", "all.csv", "--out", "re.npz", "--force", "--quiet"),
            frozenset({"re.npz"}), _complete_recalibrate,
            ("recalibrate", "model.npz", "--manifest", "odd.csv", "--out", "re.npz", "--force", "--quiet"),
            "not among the model's classes"),
    Command("fit", _prepare_fit,
            ("fit", "all.csv", "--out", "fit", "--cv", "2", "--quick", "--trials", "2", "--batch", "2", "--epochs",
             "5", "--max-window", "0.1", "--force", "--quiet"),
            frozenset({"fit/fit.csv", "fit/fit-curve.csv", "fit/fit-curve.png", "fit/bank.json"}), _complete_fit,
            ("fit", "one.csv", "--out", "fit", "--cv", "2", "--quick", "--force", "--quiet"), "at least two labels",
            slow=True, needs=("optuna", "matplotlib")),
    Command("run", _prepare_run, ("run", "run.toml", "--seconds", STREAM, "--force", "--quiet"),
            frozenset({"out.jsonl", "out.txt"}), _complete_run,
            ("run", "run.toml", "--seconds", STREAM, "--quiet"), "exists; pass --force", stops=True),
)


# -- running and checking ------------------------------------------------------------------------------------------

def _fingerprint(folder: Path) -> dict[str, str]:
    """Every path under ``folder`` (relative, with ``/``) and its sha256 (``"folder"`` for a folder)."""
    return {p.relative_to(folder).as_posix(): "folder" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest()
            for p in folder.rglob("*")}


@dataclass
class Baseline:
    """A command's folder as prepared, and what an uninterrupted run of it did."""

    pristine: Path
    seconds: float
    changes: list[str]


_BASELINES: dict[str, Baseline] = {}


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _start(folder: Path, argv, signum: int = 0, nth: int = 0) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", _HOOK, str(folder), str(signum), str(nth), *argv], cwd=folder,
                            env=_env(), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)


def _finish(proc: subprocess.Popen) -> tuple[int, str]:
    try:
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    return proc.returncode, err


def _baseline(command: Command, tmp_path_factory) -> Baseline:
    """The command's folder, prepared once, and an uninterrupted run of it in a copy: how long it took and the
    changes it made (the hook's count), its outputs checked complete and nothing else touched."""
    for module in command.needs:
        pytest.importorskip(module)
    if command.name not in _BASELINES:
        pristine = tmp_path_factory.mktemp(f"{command.name}-pristine")
        command.prepare(pristine)
        work = tmp_path_factory.mktemp(f"{command.name}-baseline")
        shutil.copytree(pristine, work, dirs_exist_ok=True)
        t = time.monotonic()
        status, err = _finish(_start(work, command.argv))
        seconds = time.monotonic() - t
        assert status == 0, err
        changes = re.search(r"\[hook\] \d+ changes: (.*)", err)
        assert changes is not None, err
        _assert_complete(command, _fingerprint(pristine), work)
        _BASELINES[command.name] = Baseline(pristine, seconds, ast.literal_eval(changes.group(1)))
    return _BASELINES[command.name]


def _assert_complete(command: Command, before: dict[str, str], folder: Path) -> None:
    after = _fingerprint(folder)
    written = {p for p in after if after[p] != before.get(p)}
    assert written == set(command.outputs), f"a completed run wrote {sorted(written)}, not {sorted(command.outputs)}"
    assert set(before) <= set(after), f"a completed run removed {sorted(set(before) - set(after))}"
    command.complete(folder)


def _assert_as_before_or_complete(command: Command, before: dict[str, str], folder: Path, status: int,
                                  signum: int, err: str) -> None:
    """After a run ``signum`` interrupted (or found ended): every earlier file as it was, or the complete outputs
    of a run; nothing else new; and an exit status that says which (see the module docstring)."""
    after = _fingerprint(folder)
    # A graph's recording stopped before one of its sources delivered a block (a moment that comes later on a
    # busy machine) keeps what the others recorded aside, says where and exits 2, as
    # test_a_graph_recording_stopped_before_a_source_started_keeps_the_earlier_recording_whole asks: nothing
    # else may be new, and every earlier file is as it was.
    aside = re.search(r"the sessions it made are kept in (\S+)\n", err)
    if aside is not None:
        assert status == 2 and "no session was recorded for source(s)" in err, err[-1500:]
        after = {k: v for k, v in after.items() if k != aside.group(1) and not k.startswith(aside.group(1) + "/")}
        assert after == before, f"besides {aside.group(1)}, changed: {sorted(set(after) ^ set(before))} {err[-1500:]}"
        return
    new = sorted(set(after) - set(before) - command.outputs)
    assert not new, f"left behind: {new} (exit {status}) {err[-1500:]}"
    gone = sorted(set(before) - set(after))
    assert not gone, f"removed: {gone} (exit {status}) {err[-1500:]}"
    written = {p for p in after if after[p] != before.get(p)}
    assert written <= command.outputs, f"changed inputs: {sorted(written - command.outputs)} {err[-1500:]}"
    if written:
        assert written == set(command.outputs), (f"partly written: {sorted(written)} new, "
                                                 f"{sorted(command.outputs - written)} as before (exit {status}) "
                                                 f"{err[-1500:]}")
        command.complete(folder)
    if status == 0:
        assert written or command.stops, f"exit 0 but no output written {err[-1500:]}"
    elif status == 2 and command.stops:
        assert not written and "nothing was written" in err, err[-1500:]
    elif status != -signum:     # -signum: the signal's own action, where no handler of the command's is set
        # (while Python loads the command's modules, or once the command has returned)
        assert status == 128 + signum, f"exit {status} {err[-1500:]}"
        assert "Traceback" not in err and "interrupted" in err, err[-1500:]


def _marks(command: Command):
    return [pytest.mark.slow] if command.slow else []


def _draws() -> tuple[list, list]:
    """Per command, from one seeded generator: a SIGINT and a SIGTERM at a share of a baseline run's duration
    (0.05 to 1.3: after the end too), and a SIGINT and a SIGTERM right after a share of its changes (the N-th of
    M, N = ceil(share x M))."""
    rng = random.Random(SEED)
    moments, changes = [], []
    for c in COMMANDS:
        for sig in (signal.SIGINT, signal.SIGTERM):
            share = round(rng.uniform(0.05, 1.3), 2)
            moments.append(pytest.param(c, sig, share, marks=_marks(c),
                                        id=f"{c.name}-{sig.name}-at-{share:.0%}-of-a-run"))
        for sig in (signal.SIGINT, signal.SIGTERM):
            share = round(rng.uniform(0.01, 1.0), 2)
            changes.append(pytest.param(c, sig, share, marks=_marks(c),
                                        id=f"{c.name}-{sig.name}-after-{share:.0%}-of-its-file-changes"))
    return moments, changes


MOMENTS, CHANGES = _draws()


@pytest.mark.parametrize("command", [pytest.param(c, marks=_marks(c), id=c.name) for c in COMMANDS])
def test_a_run_no_signal_reaches_writes_every_output_complete_and_touches_nothing_else(command, tmp_path_factory):
    """The baseline (also the case of a signal that comes after the end): exit 0, every output replaced by a
    complete one (loaded as its reader loads it), every other file as it was, nothing else new."""
    baseline = _baseline(command, tmp_path_factory)
    assert baseline.changes                      # the hook saw the command write in its folder


@pytest.mark.parametrize(("command", "signum", "share"), MOMENTS)
def test_a_signal_at_any_moment_leaves_the_earlier_files_or_complete_outputs(command, signum, share, tmp_path,
                                                                             tmp_path_factory):
    """The signal ``share`` x the baseline's duration after the start (past the end: no signal, a completed run)."""
    baseline = _baseline(command, tmp_path_factory)
    shutil.copytree(baseline.pristine, tmp_path, dirs_exist_ok=True)
    before = _fingerprint(tmp_path)
    proc = _start(tmp_path, command.argv)
    try:
        proc.wait(timeout=share * baseline.seconds)
    except subprocess.TimeoutExpired:
        proc.send_signal(signum)
    status, err = _finish(proc)
    _assert_as_before_or_complete(command, before, tmp_path, status, signum, err)


@pytest.mark.parametrize(("command", "signum", "share"), CHANGES)
def test_a_signal_right_after_any_file_change_leaves_the_earlier_files_or_complete_outputs(command, signum, share,
                                                                                           tmp_path, tmp_path_factory):
    """The signal right after the N-th of the baseline's M changes, N = ceil(share x M): exact, whatever the
    machine's speed (a write half done, a file put in place and the next not yet)."""
    baseline = _baseline(command, tmp_path_factory)
    shutil.copytree(baseline.pristine, tmp_path, dirs_exist_ok=True)
    before = _fingerprint(tmp_path)
    nth = max(1, math.ceil(share * len(baseline.changes)))
    status, err = _finish(_start(tmp_path, command.argv, signum, nth))
    _assert_as_before_or_complete(command, before, tmp_path, status, signum,
                                  f"signal after change {nth} of {baseline.changes}\n{err}")


@pytest.mark.parametrize("command", [pytest.param(c, id=c.name) for c in COMMANDS])
def test_a_refused_run_leaves_every_file_as_it_was(command, tmp_path, monkeypatch, capsys):
    """A bad input found once the inputs are read (label's late span, import's mapping found when the written scene
    is built, train's and fit's manifest of one label, evaluate's unknown label) or an output that exists without
    --force (record, run): exit 2, one line, the folder as it was."""
    for module in command.needs:
        pytest.importorskip(module)
    command.prepare(tmp_path)
    before = _fingerprint(tmp_path)
    monkeypatch.chdir(tmp_path)
    assert main(list(command.refused)) == 2
    err = capsys.readouterr().err
    assert command.says in err and "Traceback" not in err, err
    assert _fingerprint(tmp_path) == before


def test_a_graph_recording_stopped_before_a_source_started_keeps_the_earlier_recording_whole(tmp_path,
                                                                                              tmp_path_factory):
    """Issue 35: ``record --force`` of a graph stopped (Ctrl-C) before one source had delivered its first block
    replaced the other sources' sessions and wrote a replay scene that paired them with an earlier recording's
    session of that source, exit 0 (without an earlier recording: their sessions and no scene, exit 2). Now the
    recording is written aside and put in place only whole: refused, exit 2, every earlier file as it was. SIGINT
    right after the first change (source a's first block; b's comes 0.15 s later)."""
    command = next(c for c in COMMANDS if c.name == "record-graph")
    baseline = _baseline(command, tmp_path_factory)
    shutil.copytree(baseline.pristine, tmp_path, dirs_exist_ok=True)
    before = _fingerprint(tmp_path)
    status, err = _finish(_start(tmp_path, command.argv, signal.SIGINT, 1))
    assert status == 2 and "no session was recorded for source(s) ['b']" in err, err
    after = _fingerprint(tmp_path)
    kept = sorted({"/".join(path.split("/")[:2]) for path in set(after) - set(before)})
    # what was recorded is the user's: source a's session, kept aside and said, never in the recording's place
    assert len(kept) == 1 and kept[0].startswith("grec/g.incomplete-") and f"kept in {kept[0]}" in err, err
    assert any(k.startswith(kept[0] + "/") and k.endswith(".wav") for k in after)
    assert {k: v for k, v in after.items() if not k.startswith(kept[0])} == before
    # and the check of a signal at a random moment takes it, for that moment can come before b's first block
    _assert_as_before_or_complete(command, before, tmp_path, status, signal.SIGINT, err)
