"""supramodal.interrupts: a Ctrl-C or SIGTERM during a held step is delivered after it, never lost or turned
into another error.

The optional imports are the case that made it: a C extension reports a signal inside its initialisation as an
ImportError, which read as "matplotlib is not installed" (``evaluate`` wrote its CSVs without plots and then
aborted at exit, -6). ``_extension`` below behaves as such an extension does, in pure Python, so that the
moment is exact: the signal comes inside the import, and a KeyboardInterrupt there becomes an ImportError.
"""

from __future__ import annotations

import os
import signal
import sys
import threading

import pytest

from supramodal.interrupts import held_interrupts, import_optional

_EXTENSION = '''
import os, signal, time
try:
    os.kill(os.getpid(), signal.{signal})
    time.sleep(0.05)            # the handler runs here, inside the import, as it would inside a C initialisation
except KeyboardInterrupt:
    raise ImportError("initialization of _extension raised unreported exception")
LOADED = True
'''


@pytest.fixture(autouse=True)
def _ctrl_c_raises():
    """Ctrl-C as a program has it (KeyboardInterrupt): a test worker of pytest-xdist ignores SIGINT, which
    would leave nothing to hold or deliver."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@pytest.fixture
def extension(tmp_path, monkeypatch):
    """A module name whose import sends SIGINT to this process and turns a KeyboardInterrupt into ImportError."""
    def make(name: str, signum: str = "SIGINT") -> str:
        (tmp_path / f"{name}.py").write_text(_EXTENSION.format(signal=signum))
        monkeypatch.syspath_prepend(str(tmp_path))
        monkeypatch.delitem(sys.modules, name, raising=False)
        return name
    return make


def test_the_extension_stand_in_turns_an_unheld_ctrl_c_into_import_error(extension):
    """The stand-in does what it stands for: imported plainly, the Ctrl-C is lost and the import fails."""
    name = extension("_unheld_extension")
    with pytest.raises(ImportError, match="initialization"):
        __import__(name)


def test_a_ctrl_c_inside_an_optional_import_is_delivered_after_it_and_the_module_is_whole(extension):
    name = extension("_held_extension")
    with pytest.raises(KeyboardInterrupt):
        import_optional(name)
    assert sys.modules[name].LOADED          # imported whole; the interruption came after


def test_a_sigterm_inside_an_optional_import_reaches_its_own_handler_after_it(extension):
    name = extension("_term_extension", "SIGTERM")
    got = []
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: got.append(signum))
    try:
        module = import_optional(name)
        assert module is not None and module.LOADED and got == [signal.SIGTERM]
        assert signal.getsignal(signal.SIGTERM) is not previous         # the test's handler is back in place
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_a_module_that_is_not_there_is_none_and_a_broken_one_raises_its_own_error(tmp_path, monkeypatch):
    assert import_optional("no_such_module_supramodal_test") is None
    (tmp_path / "_broken_module.py").write_text("raise RuntimeError('liblsl not found')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(RuntimeError, match="liblsl"):
        import_optional("_broken_module")


def test_a_signal_during_a_block_that_fails_is_delivered_with_the_failure_as_its_context():
    with pytest.raises(KeyboardInterrupt) as caught:
        with held_interrupts():
            os.kill(os.getpid(), signal.SIGINT)
            raise OSError("disk full")
    assert isinstance(caught.value.__context__, OSError)


def test_the_handlers_are_restored_and_nothing_is_held_off_the_main_thread():
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    seen = []

    def worker():
        with held_interrupts():
            seen.append(signal.getsignal(signal.SIGINT))

    thread = threading.Thread(target=worker)
    thread.start()
    thread.join()
    assert seen == [before[0]]
    with held_interrupts():
        assert signal.getsignal(signal.SIGINT) is not before[0]
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
