"""A Lab Streaming Layer stream as a driver: the inlet of a stream another machine sends.

Needs the optional extra ``lsl`` (``pip install "supramodal[lsl]"``: pylsl, whose wheel carries
liblsl on x86_64 Linux with glibc >= 2.35, Windows and macOS). :func:`import_pylsl` is the one
place that imports it and turns a missing package or library into :class:`LSLUnavailable`,
which says what to do.

Threading and real-time rules
-----------------------------
Construction resolves the stream (it blocks up to ``resolve_timeout`` seconds on the network).
:meth:`LSLInletDriver.read` is called from one thread (the node's source thread) and blocks at
most ``timeout`` seconds: it waits for the first sample, then takes whatever else has arrived
without waiting (the low-latency pattern measured in TESTING-WITHOUT-HARDWARE.md: a timed chunk
pull would wait out its timeout). liblsl runs its own threads for the connection. A lost outlet
is recovered by liblsl (the inlet is made with ``recover=True``), but only seconds after it is
back, and only when the stream has a source id (without one liblsl gives up: the inlet raises
``LostError``, which the driver takes as the stream going silent, never as the node's end); so
while the stream is silent the driver also asks the network for it every :data:`PROBE_INTERVAL`
(blocking at most :data:`PROBE_TIMEOUT`), by source id or else by name, type and host, and, when a
new outlet of the same stream answers (a restarted sender), opens an inlet to it at once.

Time
----
Each sample's LSL timestamp, corrected to this machine's LSL clock (``proc_clocksync``), is put
on the host's monotonic clock (``time.monotonic()``, measured against ``pylsl.local_clock()`` at
open) and handed to the node as :attr:`Block.timestamp` of each block's last sample: the node's
clock model fits those, not the arrival times, so the sender's sample timing survives the
network's jitter.

Gaps
----
LSL samples carry no sequence number: a loss shows only in the timestamps, and a sender that
stamps each chunk when it pushes it (pylsl's default) puts its push delays in them too. Gaps are
judged on the sender's sample clock (:class:`ClockSteps`), not from two raw stamps: a block
stamped more than ``gap_tolerance`` seconds later than the clock model says is held (with what
follows) until the stamps show what it was. Stamps that come back onto the sample clock were a
backlog pushed late (a sender that held its samples and flushed them at once): nothing is filled,
the blocks are dated by the sample clock rather than by their stamps (a ``backlog`` event).
Stamps that run on at the sample rate, off the clock by the same amount for ``2 * gap_tolerance``
seconds of samples, show lost samples: that many zeros are filled before the block (``filled``,
``gaps``, a ``gap`` event), as the serial driver fills lost frames; the blocks held meanwhile
(0.1 s of samples by default) come out late by that much, once. A gap longer than ``max_gap``
seconds is not filled but marked as a restart (``Block.restarts``: stream time no longer equals
the sender's), and so is a step backwards in time beyond the tolerance (the sender restarted
with another clock). The first block is taken as on time. A loss shorter than the tolerance
cannot be told from a delay and is neither filled nor counted (:attr:`timing_slips` counts the
blocks stamped between half the tolerance and the tolerance late, as a warning sign).

Ring
----
The inlet holds what arrives in liblsl's buffer (``buffer_seconds``), so the node's ring waits
for the node (``overrun = "auto"`` is ``"block"``, :attr:`DriverSpec.buffered`) instead of
dropping: a backlog flushed at once waits in the inlet, not lost in a ring smaller than it.
"""

from __future__ import annotations

import collections
import functools
import logging
import math
import os
import time
from collections.abc import Mapping
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

import numpy as np

from supramodal.checks import Key, integer, positive, text
from supramodal.drivers.base import Block, DeviceUnavailable, DriverBase, DriverClosed, DriverError
from supramodal.drivers.spec import BuildContext, Built, DriverSpec, OptionError, given
from supramodal.drivers.timestamps import ENVELOPE_SECONDS, ClockSteps, StampedBlocks, Step, TimestampSteps  # noqa: F401  (moved; named here too)
from supramodal.errors import InputError
from supramodal.interrupts import held_interrupts
from supramodal.logs import logger

if TYPE_CHECKING:
    # pylsl ships no type information (pyproject's [tool.mypy] takes it as Any): these name what an object is.
    from pylsl import StreamInfo, StreamInlet

#: What to run to get LSL, and what to do where the wheel carries no liblsl.
INSTALL_HINT = ('install the optional extra: pip install "supramodal[lsl]" (pylsl). Its wheel carries liblsl only on '
                "x86_64 Linux with glibc >= 2.35, Windows and macOS; elsewhere (ARM boards, older Linux) build "
                "liblsl (https://github.com/sccn/liblsl, cmake) or install it from conda-forge (liblsl), and point "
                "PYLSL_LIB at the library file")

#: Seconds a stream may be silent before the driver says it is lost (an ``unplug`` event).
DEFAULT_STALL_TIMEOUT = 0.5
#: Seconds of timestamp jitter tolerated before a step counts as lost samples.
DEFAULT_GAP_TOLERANCE = 0.05
#: Longest gap, seconds, filled with zeros; a longer one is marked as a restart.
DEFAULT_MAX_GAP = 10.0
#: Seconds between two searches for a restarted sender while the stream is silent, and the
#: longest one search (and the new inlet's connection) may block the source thread.
PROBE_INTERVAL = 0.25
PROBE_TIMEOUT = 0.2
#: Seconds liblsl buffers in the inlet before it drops the oldest samples.
DEFAULT_BUFFER_SECONDS = 30.0
#: Seconds the resolver waits for the stream.
DEFAULT_RESOLVE_TIMEOUT = 5.0
#: Least seconds the resolver waits, after the first answer, for a second stream that matches
#: too (refused: which one is meant is not known).
DUPLICATE_WAIT = 1.0
#: Most seconds of that wait (a second stream answers the same resolve waves as the first).
DUPLICATE_WAIT_MAX = 3.0

#: liblsl's log level on stderr when the user's configuration sets none (loguru's verbosity: -2 errors,
#: -1 warnings too, 0 liblsl's own default, its INFO lines such as "Configuration loaded from ..." at
#: every start, which are not the node's user's business). A configuration file with a ``[log]``
#: section of its own is used as it is (docs/lsl.md: how to see liblsl's log).
LIBLSL_LOG_LEVEL = -1

# LSL channel formats (lsl_channel_format_t) -> (numpy dtype, full scale).
_FORMATS = {1: (np.float32, 1.0), 2: (np.float64, 1.0), 4: (np.int32, 2.0 ** 31), 5: (np.int16, 2.0 ** 15),
            6: (np.int8, 2.0 ** 7), 7: (np.int64, 2.0 ** 63)}
_FORMAT_NAMES = {1: "float32", 2: "double64", 3: "string", 4: "int32", 5: "int16", 6: "int8", 7: "int64"}


class LSLUnavailable(DeviceUnavailable):
    """pylsl or its liblsl cannot be loaded on this machine."""


def import_pylsl() -> ModuleType:
    """Return the pylsl module, or raise :class:`LSLUnavailable` saying what to install."""
    try:
        with held_interrupts():         # a Ctrl-C inside a C extension's import reads as ImportError
            import pylsl
    except ImportError:
        raise LSLUnavailable(f"LSL needs pylsl, which is not installed: {INSTALL_HINT}") from None
    except (OSError, RuntimeError) as exc:
        # pylsl is there but its liblsl is not (an ARM wheel, an old glibc): it raises at import.
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise LSLUnavailable(f"pylsl is installed but cannot load liblsl ({first}): {INSTALL_HINT}") from None
    module: ModuleType = pylsl      # a module, untyped (Any) to mypy
    _quiet_liblsl(module)
    return module


def liblsl_config_file(environ: Mapping[str, str] = os.environ) -> Path | None:
    """Return the configuration file liblsl reads, or None without one.

    liblsl looks, in its own order, for the file ``LSLAPICFG`` names, ``lsl_api.cfg`` in the
    working folder, ``~/lsl_api/lsl_api.cfg`` and ``/etc/lsl_api/lsl_api.cfg``.
    """
    home = environ.get("HOME") or environ.get("USERPROFILE")
    if not home and environ.get("HOMEDRIVE") and environ.get("HOMEPATH"):
        home = environ["HOMEDRIVE"] + environ["HOMEPATH"]
    places = [environ.get("LSLAPICFG"), "lsl_api.cfg", home and os.path.join(home, "lsl_api", "lsl_api.cfg"),
              "/etc/lsl_api/lsl_api.cfg"]
    for place in places:
        if place and _readable(place):
            return Path(place)
    return None


def _readable(path: str) -> bool:
    return os.path.isfile(path) and os.access(path, os.R_OK)


def quiet_config(text: str | None) -> str | None:
    """Return a liblsl configuration's ``text`` with ``[log] level =`` :data:`LIBLSL_LOG_LEVEL` added.

    ``text`` None stands for no file. Return None where the configuration is to be left as it
    is: it has a ``[log]`` section of its own (the user's choice), or lines liblsl would refuse
    (its own error says why). Read as liblsl reads it: a section starts at a line's first
    character, a key is ``name = value``.
    """
    added = f"[log]\nlevel = {LIBLSL_LOG_LEVEL}\n"
    if text is None:
        return added
    for line in text.splitlines():
        if not line.strip() or line.startswith(";"):
            continue
        if line.startswith("["):
            if "]" not in line:
                return None
            if line[1:line.index("]")] == "log":
                return None
        elif "=" not in line:
            return None
    return text + ("" if text.endswith("\n") or not text else "\n") + added


@functools.cache                   # once per process: liblsl reads its configuration once
def _quiet_liblsl(pylsl: ModuleType) -> None:
    """Hold liblsl's log on stderr to :data:`LIBLSL_LOG_LEVEL`, before liblsl's first use in this process.

    liblsl is given its configuration (the user's file, read as liblsl reads it, or none) with
    that log level, as content (it takes that before any file). Nothing where the user's file
    has a ``[log]`` section, where ``LSLAPICFG`` names a file that cannot be read (liblsl says
    so), or where liblsl is older than 1.17.7 (no such call), or where the package logger shows
    debugging lines (``supramodal -v``: liblsl's own log is then shown as liblsl sets it).
    """
    if logger.isEnabledFor(logging.DEBUG):
        return
    named = os.environ.get("LSLAPICFG")
    if named and not _readable(named):
        return                                  # liblsl's error says so; a quieter log would hide it
    path = liblsl_config_file()
    try:
        content = quiet_config(None if path is None else path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError):
        return                                  # left to liblsl, which reads it or says why not
    setter = getattr(pylsl, "set_config_content", None)
    if content is None or setter is None:
        return
    try:
        setter(content)
    except NotImplementedError:                 # pylsl's word for a liblsl older than 1.17.7
        return


def _lost_error(pylsl: ModuleType) -> type[Exception]:
    """Return pylsl's ``LostError`` (raised by an inlet whose sender, without a source id, went away)."""
    error: type[Exception] = getattr(pylsl, "LostError", None) or pylsl.util.LostError
    return error


def lsl_clock_offset(pylsl: ModuleType) -> float:
    """Return ``time.monotonic() - pylsl.local_clock()``, seconds.

    The offset is the midpoint of the tightest of a few brackets of one LSL clock reading
    between two host clock readings.
    """
    best = (math.inf, 0.0)
    for _ in range(9):
        a = time.monotonic()
        lsl = pylsl.local_clock()
        b = time.monotonic()
        best = min(best, (b - a, (a + b) / 2 - lsl))
    return best[1]


def describe_stream(info: StreamInfo) -> str:
    """One line naming an LSL stream: name, type, source_id, channels, rate, host."""
    return (f"name={info.name()!r} type={info.type()!r} source_id={info.source_id()!r} "
            f"{info.channel_count()} ch at {info.nominal_srate():g} Hz from {info.hostname()}")


def resolve_stream(name: str | None = None, stream_type: str | None = None, source_id: str | None = None,
                   timeout: float = DEFAULT_RESOLVE_TIMEOUT) -> StreamInfo:
    """Return the one stream matching every property given.

    Raises :class:`DeviceUnavailable` naming the streams that were found instead (or that none
    was); more than one match is refused too, listing them (say which with ``source_id``). After
    the first answer the resolver waits
    :data:`DUPLICATE_WAIT` seconds more (or twice the time the first took, at most
    :data:`DUPLICATE_WAIT_MAX`) for a second one.
    """
    pylsl = import_pylsl()
    wanted = {"name": name, "type": stream_type, "source_id": source_id}
    wanted = {k: v for k, v in wanted.items() if v is not None}
    if not wanted:
        raise InputError("an LSL inlet needs the stream's name, type or source_id")
    for key, value in wanted.items():
        if not isinstance(value, str) or not value or "'" in value:
            raise InputError(f"an LSL stream {key} must be a non-empty string without quotes, got {value!r}")
    predicate = " and ".join(f"{k}='{v}'" for k, v in wanted.items())
    asked = ", ".join(f"{k}={v!r}" for k, v in wanted.items())
    try:
        t = time.monotonic()
        found = pylsl.resolve_bypred(predicate, minimum=1, timeout=float(timeout))
        if len(found) == 1:
            # resolve_bypred returns at the first answer: a second stream of the same name would
            # answer in the same wave or the next; wait for one as long again (at least
            # DUPLICATE_WAIT) and compare.
            # The first answer's time may hold a wait for a sender still starting up: bounded, so
            # that a long resolve_timeout does not become a long wait for a duplicate.
            wait = min(float(timeout), DUPLICATE_WAIT_MAX, max(DUPLICATE_WAIT, 2 * (time.monotonic() - t)))
            found = _distinct(found + pylsl.resolve_bypred(predicate, minimum=2, timeout=wait))
    except Exception as exc:  # liblsl's errors, one place
        raise DriverError(f"LSL: resolving {asked} failed: {exc}") from None
    if not found:
        others = pylsl.resolve_streams(wait_time=1.0)
        seen = "; ".join(describe_stream(i) for i in others[:10]) if others else "no stream at all"
        raise DeviceUnavailable(f"LSL: no stream with {asked} within {timeout:g} s; found {seen}. Check the sender "
                                "runs, the name, and that both machines share the LSL session (LSLAPICFG)")
    if len(found) > 1:
        ids = "; ".join(describe_stream(i) for i in found[:10])
        raise DeviceUnavailable(f"LSL: {len(found)} streams match {asked} ({ids}); name one by its source_id "
                                "(source_id = ...), or stop the other sender")
    return found[0]


def _distinct(infos: list[StreamInfo]) -> list[StreamInfo]:
    """Return the streams of ``infos`` with one of each ``uid`` (one outlet answers each query)."""
    seen: dict[str, StreamInfo] = {}
    for info in infos:
        seen.setdefault(info.uid(), info)
    return list(seen.values())


class LSLInletDriver(DriverBase):
    """Samples of one LSL stream, as blocks (see the module notes on threads, time and gaps).

    Parameters
    ----------
    name, stream_type, source_id : str, optional
        What the stream must match (at least one; all that are given).
    rate : float, optional
        The rate the caller expects, Hz: a stream at another nominal rate is refused. Default:
        the stream's.
    channels : int, optional
        The channel count expected; default the stream's.
    resolve_timeout : float, default :data:`DEFAULT_RESOLVE_TIMEOUT`
        Seconds to wait for the stream at construction, and for its connection at open.
    gap_tolerance, max_gap, stall_timeout, buffer_seconds : float
        Seconds; see the module notes and the constants of the same names.

    Attributes
    ----------
    rate : float
        The stream's nominal rate, Hz.
    channels : int
    info : str
        The stream resolved, one line (:func:`describe_stream`).

    Events (:meth:`take_events`): ``unplug`` (no sample for ``stall_timeout``), ``reconnect``
    (samples again, with the pause), ``gap`` (samples filled), ``restart`` (a step in the
    timestamps that cannot be filled).
    """

    def __init__(self, name: str | None = None, stream_type: str | None = None, source_id: str | None = None, *,
                 rate: float | None = None, channels: int | None = None,
                 resolve_timeout: float = DEFAULT_RESOLVE_TIMEOUT, gap_tolerance: float = DEFAULT_GAP_TOLERANCE,
                 max_gap: float = DEFAULT_MAX_GAP, stall_timeout: float = DEFAULT_STALL_TIMEOUT,
                 buffer_seconds: float = DEFAULT_BUFFER_SECONDS) -> None:
        for key, v in (("resolve_timeout", resolve_timeout), ("gap_tolerance", gap_tolerance), ("max_gap", max_gap),
                       ("stall_timeout", stall_timeout), ("buffer_seconds", buffer_seconds)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise InputError(f"{key} must be a positive number of seconds, got {v!r}")
        self._pylsl = import_pylsl()
        self._stream = resolve_stream(name, stream_type, source_id, resolve_timeout)
        self.info = describe_stream(self._stream)
        fmt = self._stream.channel_format()
        if fmt not in _FORMATS:
            raise DeviceUnavailable(f"LSL: the stream {self.info} carries {_FORMAT_NAMES.get(fmt, fmt)} samples; "
                                    "the node reads numeric streams (float32, double64, int8..int64)")
        self._dtype, self._full_scale = _FORMATS[fmt]
        self.rate = float(self._stream.nominal_srate())
        if not self.rate > 0:
            raise DeviceUnavailable(f"LSL: the stream {self.info} has no nominal rate (an irregular stream, such as "
                                    "markers); the node filters regularly sampled signals")
        if rate is not None and abs(rate - self.rate) > 1e-9 * self.rate:
            raise DeviceUnavailable(f"LSL: the stream {self.info} runs at {self.rate:g} Hz, not the {rate:g} Hz "
                                    "expected; give the stream a bank at its rate")
        self.channels = int(self._stream.channel_count())
        if channels is not None and channels != self.channels:
            raise DeviceUnavailable(f"LSL: the stream {self.info} has {self.channels} channels, not {channels}")
        self.resolve_timeout = float(resolve_timeout)
        self.gap_tolerance, self.max_gap = float(gap_tolerance), float(max_gap)
        self.stall_timeout, self.buffer_seconds = float(stall_timeout), float(buffer_seconds)
        self._max_chunk = max(1, int(self.rate * 0.1))        # at most 100 ms per block
        self._inlet: StreamInlet | None = None
        self._lost = False           # the sender went away for good (no source id): no inlet until it is back
        super().__init__()
        self._reset_counters()

    # -- life cycle ---------------------------------------------------------------------------

    def _reset_counters(self) -> None:
        self._chunks = self._stalls = self._reopened = 0
        self._next_probe = 0.0
        self._steps = ClockSteps(self.rate, self.gap_tolerance, self.max_gap)
        self._blocks = StampedBlocks(self.channels, lambda: f"LSL: {self.info}", "sender", self.max_gap, self._record)
        self._held: collections.deque[tuple[np.ndarray, np.ndarray, float]] = collections.deque()
        self._ready: collections.deque[Block] = collections.deque()
        self._last_data = time.monotonic()
        self._stalled = False

    def open(self) -> None:
        """Connect to the stream (waits up to ``resolve_timeout`` for it)."""
        pylsl = self._pylsl
        self._reset_counters()
        self.event_log.clear()
        try:
            self._inlet = pylsl.StreamInlet(self._stream, max_buflen=max(1, math.ceil(self.buffer_seconds)),
                                            recover=True, processing_flags=pylsl.proc_clocksync)
            self._inlet.open_stream(timeout=self.resolve_timeout)
        except Exception as exc:
            self._inlet = None
            raise DeviceUnavailable(f"LSL: cannot open the stream {self.info}: {exc}") from None
        self._offset = lsl_clock_offset(self._pylsl)
        self._buf = np.empty((self._max_chunk, self.channels), dtype=self._dtype)
        self._last_data = time.monotonic()

    def close(self) -> None:
        """Close the inlet (idempotent)."""
        inlet, self._inlet, self._lost = self._inlet, None, False
        if inlet is not None:
            try:
                inlet.close_stream()
            except Exception:  # closing: nothing left to tell
                pass

    # -- reading (the source thread) ----------------------------------------------------------

    def read(self, timeout: float | None = None) -> Block | None:
        """Return the samples that arrived (up to 100 ms of them) as a block; None if none came.

        Waits at most ``timeout`` s for the first.
        """
        if self._ready:
            return self._ready.popleft()
        inlet = self._inlet
        wait = 0.0 if timeout is None else max(0.0, float(timeout))
        if inlet is None:
            if not self._lost:
                raise DriverClosed("the LSL inlet is closed")
            time.sleep(min(wait, PROBE_INTERVAL))   # no inlet to wait on: the sender is gone
            stamps: np.ndarray | list[float] = []
        else:
            try:
                _, stamps = inlet.pull_chunk(timeout=wait, max_samples=self._max_chunk, dest_obj=self._buf,
                                             min_samples=1, as_numpy=True)
            except _lost_error(self._pylsl):
                # A sender without a source id cannot be recovered by liblsl: its inlet says so
                # once. Not the node's end: the stream is silent, and searched for by name,
                # type and host until a new sender of it answers.
                self._inlet, self._lost = None, True
                try:
                    inlet.close_stream()
                except Exception:  # the stream is gone already
                    pass
                stamps = []
            except Exception as exc:  # liblsl's errors, one place
                raise DriverError(f"LSL: reading {self.info} failed: {exc}") from None
        now = time.monotonic()
        n = len(stamps)
        if n == 0:
            if self._held and now - self._last_data > self.stall_timeout:
                self._judged(self._steps.flush())   # silent: judge the held blocks on what came
                return self._ready.popleft() if self._ready else None
            if not self._stalled and now - self._last_data > self.stall_timeout:
                self._stalled = True
                self._stalls += 1
                self._next_probe = now
                self._record("unplug", f"LSL: no sample from {self.info} for {self.stall_timeout:g} s; waiting "
                                 "for it to come back", self._blocks.frames)
            if self._stalled and now >= self._next_probe:
                self._next_probe = now + PROBE_INTERVAL
                self._look_for_a_new_sender()
            return None
        data = self._buf[:n].astype(np.float64)
        if self._full_scale != 1.0:
            data /= self._full_scale
        host = np.asarray(stamps, dtype=np.float64) + self._offset
        if self._stalled:
            self._stalled = False
            self._record("reconnect", f"LSL: samples from {self.info} again after {now - self._last_data:.2f} s",
                             self._blocks.frames)
        self._last_data = now
        self._chunks += 1
        self._held.append((data, host, now))
        self._judged(self._steps.add(n, float(host[0]), float(host[-1])))
        return self._ready.popleft() if self._ready else None

    def _judged(self, steps: list[Step]) -> None:
        """Make the held blocks the clock model has judged (``steps``) into blocks ready to return."""
        for step in steps:
            data, host, now = self._held.popleft()
            self._ready.append(self._blocks.block(data, float(host[-1]), now, step))

    def _look_for_a_new_sender(self) -> None:
        """Ask the network for the stream again while it is silent.

        A sender that was restarted is a new outlet of the same stream (same source id, or same
        name, type and host), which liblsl's own recovery finds only seconds later (about 3 s
        measured here); an inlet to it is made at once. Blocks the source thread for at most
        :data:`PROBE_TIMEOUT` s.
        """
        pylsl = self._pylsl
        old = self._stream
        query = (f"source_id='{old.source_id()}'" if old.source_id() and "'" not in old.source_id() else
                 f"name='{old.name()}' and type='{old.type()}' and hostname='{old.hostname()}'")
        try:
            found = pylsl.resolve_bypred(query, minimum=1, timeout=PROBE_TIMEOUT)
        except Exception:  # the network's trouble: liblsl's own recovery goes on
            return
        fresh = [i for i in found if i.uid() != old.uid()]
        if not fresh:
            return
        new = fresh[0]
        if (new.channel_count(), new.nominal_srate(), new.channel_format()) != \
                (old.channel_count(), old.nominal_srate(), old.channel_format()):
            raise DriverError(f"LSL: the stream came back as {describe_stream(new)}, no longer {self.info}; "
                              "restart the node for the new stream")
        try:
            inlet = pylsl.StreamInlet(new, max_buflen=max(1, math.ceil(self.buffer_seconds)), recover=True,
                                      processing_flags=pylsl.proc_clocksync)
            inlet.open_stream(timeout=PROBE_TIMEOUT)
        except Exception:  # not ready yet: the next probe tries again
            return
        self.close()
        self._inlet, self._stream, self._lost = inlet, new, False
        self._reopened += 1

    # -- counters and events ------------------------------------------------------------------

    def stats(self) -> dict[str, int]:
        """Return the driver's counters since ``open()``.

        ``frames`` (delivered, filled ones included), ``filled``, ``chunks`` (reads that
        brought samples), ``gaps``, ``restarts``, ``stalls``, ``reopened`` (inlets made to a
        restarted sender), ``timing_slips``, ``backlogs`` (late stamps that came back onto the
        sample clock: nothing filled).
        """
        b = self._blocks
        return {"frames": b.frames, "filled": b.filled, "chunks": self._chunks, "gaps": b.gaps,
                "restarts": b.restarts, "stalls": self._stalls, "reopened": self._reopened,
                "timing_slips": b.slips, "backlogs": b.backlogs}

    def __repr__(self) -> str:
        return f"LSLInletDriver({self.info})"


# -- as a scene names it ---------------------------------------------------------------------------

#: Bounds of the inlet's times a scene may set, seconds: what a real link could need. A longer
#: gap than ``max_gap`` is a restart, not samples to fill (1e300 s would fill beyond any memory).
LIMITS = {"resolve_timeout": 3600.0, "gap_tolerance": 10.0, "max_gap": 60.0, "stall_timeout": 60.0,
          "buffer_seconds": 3600.0}
#: Highest nominal rate a scene may require of a stream, Hz.
MAX_RATE = 1e6
#: Keys that name the stream to resolve: a scene gives at least one.
WHICH = ("stream", "stream_type", "source_id")


def _seconds(key: str, what: str, default: float) -> Key:
    return Key(positive(LIMITS[key]), f"{what}, up to {LIMITS[key]:g} s (default: {default:g})", None)


def _check(options: Mapping[str, Any]) -> None:
    if all(options[k] is None for k in WHICH):
        raise OptionError('type "lsl" needs the stream\'s name (stream = ...), stream_type or source_id')


def _build(options: Mapping[str, Any], context: BuildContext) -> Built:
    try:
        driver = LSLInletDriver(options["stream"], options["stream_type"], options["source_id"],
                                **given(options, {k: k for k in ("rate", "channels", *LIMITS)}))
    except DriverError:
        raise
    except InputError as exc:
        raise OptionError(str(exc)) from None
    if context.rate is not None and abs(driver.rate - context.rate) > 1e-9 * context.rate:
        raise OptionError(f"the LSL stream {driver.info} runs at {driver.rate:g} Hz but the bank at "
                          f"{context.rate:g} Hz; give the stream a bank at its rate ([bank] fs, or a bank file)")
    return Built(driver)


SPEC = DriverSpec(
    type="lsl",
    summary="a stream another program sends over the Lab Streaming Layer (the lsl extra)",
    keys={
        "stream": Key(text, "the LSL stream's name", None),
        "stream_type": Key(text, 'the LSL stream\'s type, e.g. "Whiskers"', None),
        "source_id": Key(text, "the LSL stream's source_id (stable across restarts of its sender)", None),
        "rate": Key(positive(MAX_RATE), f"Hz the stream must run at, up to {MAX_RATE:g} (default: its nominal rate)",
                    None),
        "channels": Key(integer(1, 4096), "the channel count the stream must have, 1..4096 (default: its own)", None),
        "resolve_timeout": _seconds("resolve_timeout", "seconds to wait for the stream", DEFAULT_RESOLVE_TIMEOUT),
        "gap_tolerance": _seconds("gap_tolerance", "seconds of timestamp jitter before a step counts as lost samples",
                                  DEFAULT_GAP_TOLERANCE),
        "max_gap": _seconds("max_gap", "longest gap filled with zeros, seconds (a longer one is a restart)",
                            DEFAULT_MAX_GAP),
        "stall_timeout": _seconds("stall_timeout", "seconds without a sample before the stream is reported lost",
                                  DEFAULT_STALL_TIMEOUT),
        "buffer_seconds": _seconds("buffer_seconds", "seconds liblsl buffers in the inlet", DEFAULT_BUFFER_SECONDS),
    },
    build=_build, live=True, check=_check, buffered=True)
