"""The package logger (supramodal/logs.py) and the command line's -q / -v: what the package says on its own
goes through ``logging.getLogger("supramodal")``, which a library user quiets or redirects, and the command
line's -q leaves only the results and the warnings."""

from __future__ import annotations

import logging
import os

import numpy as np
import pytest

from supramodal.logs import LOGGER_NAME, get_logger, logger, set_log_level
from supramodal.node.cli import main
from supramodal.replay.driver import ReplayDriver


@pytest.fixture(autouse=True)
def _level_kept():
    level = logger.level
    yield
    set_log_level(level)


def _resampled() -> ReplayDriver:
    """A replay that resamples 4.41 kHz to 5 kHz: a notice, by default through the logger."""
    return ReplayDriver((np.zeros((441, 1)), 4410.0), rate=5000.0, speed="max")


def test_a_drivers_notice_goes_through_the_package_logger_to_the_current_stderr(capsys):
    _resampled()
    err = capsys.readouterr().err
    assert err.count("supramodal: replay: resampling") == 1 and "up=500 down=441" in err


def test_a_library_user_quiets_the_package_or_sends_one_part_to_a_file(capsys, tmp_path):
    logging.getLogger(LOGGER_NAME).setLevel(logging.WARNING)           # the standard call, no helper
    _resampled()
    assert capsys.readouterr().err == ""
    set_log_level("INFO")
    drivers = logging.getLogger(f"{LOGGER_NAME}.drivers")
    handler = logging.FileHandler(tmp_path / "drivers.log")
    drivers.addHandler(handler)
    try:
        _resampled()
    finally:
        drivers.removeHandler(handler)
        handler.close()
    assert "replay: resampling" in (tmp_path / "drivers.log").read_text()
    assert "replay: resampling" in capsys.readouterr().err            # and still on stderr, once


def test_the_package_logger_does_not_print_twice_through_an_applications_root_handler(caplog, capsys):
    root = logging.getLogger()
    handler = logging.StreamHandler()                                   # an application's own configuration
    root.addHandler(handler)
    try:
        get_logger("drivers.replay").info("one line")
    finally:
        root.removeHandler(handler)
    assert capsys.readouterr().err.count("one line") == 1


def test_quiet_and_verbose_are_global_options_before_or_after_the_command(capsys):
    for argv in (["-q", "devices", "--help"], ["devices", "-q", "--help"], ["devices", "--verbose", "--help"]):
        with pytest.raises(SystemExit) as done:
            main(argv)
        assert done.value.code == 0
    capsys.readouterr()
    with pytest.raises(SystemExit) as done:
        main(["-q", "-v", "devices"])
    assert done.value.code == 2
    assert "-q/--quiet and -v/--verbose: choose one" in capsys.readouterr().err


def test_quiet_run_prints_the_decisions_and_the_summary_and_nothing_on_stderr(capsys, tmp_path):
    wav = tmp_path / "tone.wav"
    from supramodal.replay.wavio import write_wav

    t = np.arange(4410) / 4410.0
    write_wav(wav, 0.1 * np.sin(2 * np.pi * 300 * t)[:, None], 4410)
    scene = tmp_path / "s.toml"
    scene.write_text(f'[driver]\ntype = "replay"\npath = "{wav.name}"\nspeed = "max"\n[bank]\nkind = "whisker"\n'
                     '[[sink]]\ntype = "text"\n')
    assert main(["-q", "run", str(scene)]) == 0
    quiet = capsys.readouterr()
    assert quiet.err == ""                                              # no progress, no resampling notice
    assert "windows" in quiet.out
    assert logger.level == logging.INFO                                 # main() puts the level back
    assert main(["run", str(scene)]) == 0
    loud = capsys.readouterr()
    assert "supramodal: replay: resampling" in loud.err and quiet.out.splitlines()[-3:] != []


def test_quiet_keeps_a_driver_events_alarms_and_warnings_and_leaves_out_the_news(capsys):
    from supramodal.drivers.base import DriverEvent
    from supramodal.node.runtime.sinks.text import TextSink

    sink = TextSink()
    set_log_level("WARNING")
    for kind in ("gap", "level", "open"):                                # an alarm, a warning, news
        sink.event(DriverEvent(kind, f"the {kind} event", 0.0))
    err = capsys.readouterr().err
    assert "supramodal: the gap event" in err and "supramodal: the level event" in err and "open" not in err


def _dask_level_in_a_child() -> int:
    """The ``distributed`` logger's level in a new process that imports Dask (as a fit's local workers do)."""
    import subprocess
    import sys

    code = "import logging, distributed; print(logging.getLogger('distributed').getEffectiveLevel())"
    return int(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                              timeout=120).stdout.split()[-1])


@pytest.mark.parametrize("verbose", [False, True])
def test_dask_s_own_log_lines_show_only_with_verbose_here_and_in_the_processes_a_command_starts(
        monkeypatch, verbose):
    """Without -v, Dask's lines (a nanny killing a worker, a heartbeat failing) are kept out: its logger at
    ERROR in the command's process and in every process the command starts (a fit's local workers, which
    import Dask on their own); with -v they show at Dask's own level. Undone when the command returns."""
    pytest.importorskip("distributed")
    import supramodal.node.cli as cli

    monkeypatch.delenv(cli.DASK_LOGGING_ENV, raising=False)
    seen = {}

    def run(args) -> int:
        seen["here"] = logging.getLogger("distributed").getEffectiveLevel()
        seen["child"] = _dask_level_in_a_child()
        return 0

    monkeypatch.setattr(cli, "_run", run)
    before = logging.getLogger("distributed").level
    assert main(["-v", "devices"] if verbose else ["devices"]) == 0
    if verbose:
        assert seen["child"] < logging.WARNING             # Dask's own (INFO): its warnings show
    else:
        assert seen == {"here": logging.ERROR, "child": logging.ERROR}
    assert logging.getLogger("distributed").level == before and cli.DASK_LOGGING_ENV not in os.environ


def test_a_users_own_dask_log_level_is_kept(monkeypatch):
    """A DASK_LOGGING__DISTRIBUTED the user set (quieter or louder than ERROR) is theirs: the command leaves it,
    and Dask's logger, as they are."""
    import supramodal.node.cli as cli

    for chosen in ("critical", "debug"):
        monkeypatch.setenv(cli.DASK_LOGGING_ENV, chosen)
        level = logging.getLogger("distributed").level
        seen = {}
        monkeypatch.setattr(cli, "_run", lambda args: seen.update(env=os.environ[cli.DASK_LOGGING_ENV],
                                                                 level=logging.getLogger("distributed").level) or 0)
        assert main(["devices"]) == 0
        assert seen == {"env": chosen, "level": level} and os.environ[cli.DASK_LOGGING_ENV] == chosen
