"""A mock whisker-array microcontroller on a pseudo-terminal, with fault injection.

:class:`MockWhiskerDevice` plays a sample array as serial frames
(``drivers.frames``) at the real rate into a pty, so :class:`SerialWhiskerDriver`
(or anything else) can open it like a USB serial board. It can insert garbage,
cut frames short, corrupt them, leave them out, send them with a wrong channel
count or a wrong version, and unplug and replug, and keeps a
:class:`FaultLedger` of everything it did, so tests can check that every fault
shows up in the reader's counters, exactly.

The port is a symlink the mock owns, pointing at the current pty slave: an
unplug closes the pty and removes the link (reopening fails with ENOENT, as for
a vanished ``/dev/ttyACM0``); a replug makes a new pty and points the link at
it, so a reader reopens the *same path*. (``os.openpty`` cannot recreate a
given ``/dev/pts/N``.)

The ledger is exact across unplugs too. The device keeps the pty's slave end
open itself: at an unplug it first reads whatever the reader has not taken yet
(those bytes are what a real unplug loses with the port's buffer) and so knows
which frames were lost in the port, and how many bytes of a frame the reader
had received before the link went (it discards them). A few frames before each
unplug are sent clean, so that every fault before it has been judged by a
reader by then. After a replug the device sends nothing until a reader has
opened the port (it sees the open's input flush through the pty's packet mode),
as a USB CDC-ACM board waits for the host: frames of that wait are never written.

Threading rules
---------------
The device writes from one thread of its own, started by :meth:`start` and
joined by :meth:`close`. Writes are non-blocking, as a microcontroller's UART
would be: when the pty buffer (about 22 kB on Linux) is full, whole frames are
dropped and counted, and the writer never blocks when nobody reads.
:attr:`ledger` returns a consistent copy from any thread.

Command line (to be wired as ``supramodal mock-whisker``): :func:`add_arguments`
and :func:`run`, or ``python -m supramodal.drivers.mock_whisker SOURCE.wav [options]``.
"""

from __future__ import annotations

import argparse
import copy
import errno
import fcntl
import os
import signal
import struct
import sys
import tempfile
import termios
import threading
import time
import tty
import zlib
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass, field
from types import FrameType
from typing import NoReturn

import numpy as np

from supramodal.drivers.frames import (
    FLAG_OVERRUN,
    FULL_SCALE,
    HEADER_SIZE,
    MAX_CHANNELS,
    MAX_SAMPLES_PER_FRAME,
    SEQ_MODULUS,
    VERSION,
    encode_frame,
)
from supramodal.errors import InputError

_TIOCPKT_FLUSHREAD = 0x01  # packet-mode status bit: the slave's input queue was flushed
#: Seconds after which bytes written to the pty's master are taken to be in the slave's input queue, where the
#: input count sees them (:meth:`MockWhiskerDevice._clean_bytes_flushed`).
PTY_FLUSH_SECONDS = 0.1


@dataclass(frozen=True)
class FaultSpec:
    """Which faults to inject, and how often.

    Rates are probabilities per frame, drawn from the device's seeded random
    generator in frame order, so a seed fixes the schedule whatever the timing.

    Attributes
    ----------
    garbage_rate : float, default 0
        Random bytes (1..``garbage_max``) inserted before a frame. Never right
        after a truncated frame: lost bytes followed by as many garbage bytes
        look to any decoder like altered bytes, and the ledger would disagree.
    garbage_max : int, default 32
    drop_rate : float, default 0
        A frame cut short: a run of 1..``drop_max`` bytes after its header is
        removed (a UART/USB overrun). The header stays, so a decoder can see it.
    drop_max : int, default 64
    crc_rate : float, default 0
        One payload byte of a frame altered (a line error): its CRC fails.
    omit_rate : float, default 0
        A whole frame never sent (its sequence number is skipped).
    channels_rate : float, default 0
        A frame sent, intact, with one channel more (or, at 64, one fewer)
        than the stream has: a reader must skip it.
    version_rate : float, default 0
        A frame sent with version ``VERSION + 1`` (header check and CRC
        correct for it): a reader must skip its bytes. Never right after a
        truncated frame, as for garbage.

        A frame gets at most one of the five: ``drop_rate + crc_rate +
        omit_rate + channels_rate + version_rate`` must be <= 1.
    overrun_rate : float, default 0
        A frame sent intact with flag bit 0 (OVERRUN) set, as a board whose ADC
        overran before it; independent of the five faults above. Drawn only
        when > 0, so other schedules do not change.
    unplug_every : float or None, default None
        Seconds connected before each unplug; None never unplugs.
    unplug_for : float, default 0.5
        Seconds unplugged. Frames are still produced meanwhile (the board runs
        on), and are lost.
    unplug_limit : int or None, default None
        Unplug at most this many times; None: no limit.

    Notes
    -----
    The first frame, and without ``loop`` the last one, are sent clean: a
    decoder can only place a loss between two good frames, and judges a bad
    frame once bytes follow it, so a fault there would be missing from its
    counters while present in the ledger. For the same reason frames are sent
    clean from the moment an unplug is due until it happens, and after
    :meth:`MockWhiskerDevice.end_faults`.
    """

    garbage_rate: float = 0.0
    garbage_max: int = 32
    drop_rate: float = 0.0
    drop_max: int = 64
    crc_rate: float = 0.0
    omit_rate: float = 0.0
    channels_rate: float = 0.0
    version_rate: float = 0.0
    overrun_rate: float = 0.0
    unplug_every: float | None = None
    unplug_for: float = 0.5
    unplug_limit: int | None = None

    #: The frame faults, in the order they share one draw per frame.
    KINDS = ("truncated", "crc", "omitted", "channels", "version")

    def __post_init__(self) -> None:
        for name in ("garbage_rate", "drop_rate", "crc_rate", "omit_rate", "channels_rate",
                     "version_rate", "overrun_rate"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise InputError(f"{name} must be in [0, 1], got {v}")
        if sum(self.kind_rates()) > 1.0:
            raise InputError("drop_rate + crc_rate + omit_rate + channels_rate + version_rate "
                             "must be <= 1 (a frame gets at most one fault)")
        if self.garbage_max < 1 or self.drop_max < 1:
            raise InputError("garbage_max and drop_max must be >= 1")
        if self.unplug_every is not None and self.unplug_every <= 0:
            raise InputError("unplug_every must be > 0 s or None")
        if self.unplug_for < 0:
            raise InputError("unplug_for must be >= 0 s")
        if self.unplug_limit is not None and self.unplug_limit < 0:
            raise InputError("unplug_limit must be >= 0 or None")

    def kind_rates(self) -> tuple[float, ...]:
        """Probabilities of the frame faults, in the order of :attr:`KINDS`."""
        return (self.drop_rate, self.crc_rate, self.omit_rate, self.channels_rate,
                self.version_rate)


@dataclass
class FaultLedger:
    """What the device did.

    Frame indices are unwrapped (0, 1, 2, ...);
    the sequence number of frame ``k`` is ``(first_seq + k) % 65536``.

    Attributes
    ----------
    frames : int
        Frames produced (each used a sequence number).
    sent : int
        Frames written intact.
    garbage, garbage_bytes : int
        Garbage insertions written, and their bytes.
    truncated, dropped_bytes : int
        Frames written cut short, and the bytes removed from them.
    crc : int
        Frames written with an altered payload byte.
    omitted : int
        Frames left out on purpose (never written).
    wrong_channels, wrong_version : int
        Frames written with a wrong channel count, or a wrong version.
    damaged_bytes : int
        Bytes written as part of truncated, altered or wrong-version frames
        (a reader skips them).
    overflow : int
        Frames not written (or, at an unplug or at the end, not finished)
        because the pty buffer was full.
    unplugs : int
        Unplugs done.
    unplugged : int
        Frames produced while unplugged, or after a replug before a reader
        opened the port (never written).
    unplug_lost : int
        Frames written but still in the port when it was unplugged, whole or
        in part (Linux discards a pty's buffer when the master closes).
    cut_bytes : int
        Bytes of those frames that the reader had received before the unplug:
        the head of a frame whose tail was lost (a reader discards them).
    unplugs_forced : int
        Unplugs done although a fault might not have been judged by the
        reader yet (nobody read the port for a second after the unplug was
        due). Zero for an exact ledger.
    faults_ended_at : int or None
        Index of the first frame after :meth:`MockWhiskerDevice.end_faults`.
    lost : dict of int to str
        Every frame not delivered intact: index -> ``"truncated"``, ``"crc"``,
        ``"omitted"``, ``"channels"``, ``"version"``, ``"overflow"``,
        ``"unplugged"`` or ``"unplug"`` (lost in the port at an unplug).
    unplug_at : list of int
        For each unplug, the index of the first frame produced after it.
    unplug_times, replug_times : list of float
        ``time.monotonic()`` of each unplug, and of each replug (the port back).
    overrun_at : list of int
        Indices of frames written with the OVERRUN flag (intact: not lost).
    restart_at : list of int
        Indices of frames where the board's sequence counter restarted from 0.
    """

    frames: int = 0
    sent: int = 0
    garbage: int = 0
    garbage_bytes: int = 0
    truncated: int = 0
    dropped_bytes: int = 0
    crc: int = 0
    omitted: int = 0
    wrong_channels: int = 0
    wrong_version: int = 0
    damaged_bytes: int = 0
    overflow: int = 0
    unplugs: int = 0
    unplugged: int = 0
    unplug_lost: int = 0
    cut_bytes: int = 0
    unplugs_forced: int = 0
    faults_ended_at: int | None = None
    lost: dict[int, str] = field(default_factory=dict)
    unplug_at: list[int] = field(default_factory=list)
    unplug_times: list[float] = field(default_factory=list)
    replug_times: list[float] = field(default_factory=list)
    overrun_at: list[int] = field(default_factory=list)
    restart_at: list[int] = field(default_factory=list)


def quantise(samples: np.ndarray) -> np.ndarray:
    """Full-scale floats to int16 as the board's ADC would: ``round(x * 32768)``, clipped.

    Parameters
    ----------
    samples : ndarray, shape (n, channels)
        Floats (full scale +-1.0), or int16 (returned unchanged).

    Returns
    -------
    ndarray of int16, shape (n, channels)
    """
    samples = np.asarray(samples)
    if samples.dtype == np.int16:
        return samples
    return np.clip(np.round(samples * FULL_SCALE), -FULL_SCALE, FULL_SCALE - 1).astype(np.int16)


class MockWhiskerDevice:
    """A microcontroller streaming frames into a pty at the real rate.

    Parameters
    ----------
    samples : ndarray, shape (n, channels)
        Full-scale floats (quantised with :func:`quantise`) or int16.
        1 <= channels <= 64.
    rate : float
        Sample rate, Hz; frames are paced by ``time.monotonic``.
    port : str or None, default None
        Path of the symlink to create (must not exist, or be a symlink).
        None: a symlink in a new temporary directory, removed by :meth:`close`.
    samples_per_frame : int, default 32
        Samples per channel per frame (the last frame of a non-looping source
        may be shorter).
    loop : bool, default False
        Replay the samples forever. Otherwise the device stops producing after
        the last sample and sets :attr:`finished`, and keeps the pty open (a
        reader may still be draining it) until :meth:`close`.
    faults : FaultSpec, default FaultSpec()
        No faults by default.
    seed : int or None, default None
        Seed of the fault schedule.
    first_seq : int, default 0
        Sequence number of the first frame (65530 exercises the wrap).
    restart_at : sequence of int, default ()
        Frame indices at which the board restarts its sequence counter from 0,
        as after a reset (the samples go on without a pause).

    Attributes
    ----------
    port : str
        The stable path to open (the symlink).
    pty : str or None
        The current slave device behind it; None while unplugged.
    finished : threading.Event
        Set once every frame has been produced (never with ``loop=True``), or
        when the writer thread failed.
    error : BaseException or None
        Why the writer thread failed, if it did.

    Notes
    -----
    ``with MockWhiskerDevice(...) as dev:`` creates the pty but does not start
    streaming: open the reader first, then :meth:`start`, so the reader's open
    (pyserial flushes input) loses nothing.
    """

    def __init__(self, samples: np.ndarray, rate: float, port: str | None = None,
                 samples_per_frame: int = 32, loop: bool = False,
                 faults: FaultSpec = FaultSpec(), seed: int | None = None,
                 first_seq: int = 0, restart_at: Iterable[int] = ()) -> None:
        data = quantise(samples)
        if data.ndim != 2 or not 1 <= data.shape[1] <= MAX_CHANNELS or data.shape[0] < 1:
            raise InputError(f"samples must have shape (n >= 1, 1..{MAX_CHANNELS}), "
                             f"got {data.shape}")
        if not 1 <= samples_per_frame <= MAX_SAMPLES_PER_FRAME:
            raise InputError(f"samples_per_frame must be 1..{MAX_SAMPLES_PER_FRAME}")
        if not rate > 0:
            raise InputError(f"rate must be > 0 Hz, got {rate}")
        self._data = np.ascontiguousarray(data)
        self.rate = float(rate)
        self.samples_per_frame = int(samples_per_frame)
        self.loop = bool(loop)
        self.faults = faults
        self.first_seq = int(first_seq) % SEQ_MODULUS
        self.restart_at = tuple(sorted(int(k) for k in restart_at))
        if any(k < 1 for k in self.restart_at):
            raise InputError("restart_at: frame indices must be >= 1")
        self._rng = np.random.default_rng(seed)
        n = self._data.shape[0]
        self.n_frames = None if self.loop else -(-n // self.samples_per_frame)
        self.finished = threading.Event()
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._ledger = FaultLedger()
        self._thread: threading.Thread | None = None
        self._master: int | None = None
        self._slave: int | None = None  # held open to read what the reader left at an unplug
        self._await_host = False  # replugged: send nothing until a reader opens the port
        self._calm = False  # end_faults() was called
        self._quiet = False  # an unplug is due: frames go clean until it happens
        self._pending: memoryview | None = None
        self._pending_frame = -1
        # Bytes written on this connection, the recent frames' spans in them
        # (index, first byte, end if fully written), and the bytes written
        # since the last faulted frame or garbage ended.
        self._written = 0
        self._spans: deque[tuple[int, int, int]] = deque()
        self._clean_run = 0
        # (when, clean bytes written by then) since the last fault: what has surely reached the port's input
        # queue (PTY_FLUSH_SECONDS)
        self._clean_history: deque[tuple[float, int]] = deque()
        self._tmpdir = None
        if port is None:
            self._tmpdir = tempfile.mkdtemp(prefix="mock-whisker-")
            port = os.path.join(self._tmpdir, "whisker")
        elif os.path.lexists(port) and not os.path.islink(port):
            raise FileExistsError(f"{port} exists and is not a symlink: choose another --port")
        self.port = str(port)
        self.pty: str | None = None
        self._plug()

    # -- lifecycle -------------------------------------------------------------

    def start(self) -> MockWhiskerDevice:
        """Start streaming (frame 0 is due one frame period from now)."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="mock-whisker", daemon=True)
            self._thread.start()
        return self

    def wait_for_reader(self, timeout: float) -> bool:
        """Wait, before :meth:`start`, until a reader opens the port; return whether one did.

        The reader may be a node in another process starting up; waits at most ``timeout``
        seconds. Started after it, the board's faults fall at known times of the reader's run,
        however long its start-up took.
        """
        if self._thread is not None:
            raise RuntimeError("wait_for_reader() is for before start(): the writer thread reads the port's status")
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self._host_opened():
                return True
            time.sleep(0.01)
        return False

    def end_faults(self) -> None:
        """From the next frame on, send every frame clean and unplug no more.

        A reader that keeps reading a little longer has then judged every
        fault, so its counters can equal the ledger's totals.
        """
        self._calm = True

    def close(self) -> None:
        """Stop the writer, close the pty, remove the symlink (and temp dir)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self._unplug_pty(account=False)
        if self._tmpdir is not None:
            try:
                os.rmdir(self._tmpdir)
            except OSError:
                pass
            self._tmpdir = None

    def __enter__(self) -> MockWhiskerDevice:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def ledger(self) -> FaultLedger:
        """A consistent copy of the fault ledger."""
        with self._lock:
            return copy.deepcopy(self._ledger)

    def lost_kind(self, k: int) -> str | None:
        """Why frame ``k`` was not delivered intact (a key of :attr:`FaultLedger.lost`), or None.

        Thread-safe and without copying the ledger: for a reader checking every gap as it comes.
        """
        with self._lock:
            return self._ledger.lost.get(k)

    def seq_of(self, k: int) -> int:
        """Sequence number of frame index ``k``."""
        last = max((r for r in self.restart_at if r <= k), default=None)
        if last is not None:
            return (k - last) % SEQ_MODULUS
        return (self.first_seq + k) % SEQ_MODULUS

    def frame_rows(self, k: int) -> np.ndarray:
        """int16 samples of frame index ``k``, shape (rows, channels)."""
        spf = self.samples_per_frame
        if self.loop:
            n = self._data.shape[0]
            rows: np.ndarray = self._data[np.arange(k * spf, (k + 1) * spf) % n]
            return rows
        return self._data[k * spf:(k + 1) * spf]

    # -- the pty ---------------------------------------------------------------

    def _plug(self) -> None:
        master, slave = os.openpty()
        # At once: a new pty is in cooked mode (echo, CR/LF translation).
        tty.setraw(slave)
        name = os.ttyname(slave)
        os.set_blocking(master, False)
        os.set_blocking(slave, False)
        # Packet mode: a reader's open flushes its input (pyserial does), and
        # the master then reads a status byte with TIOCPKT_FLUSHREAD set.
        fcntl.ioctl(master, termios.TIOCPKT, struct.pack("i", 1))
        tmp = f"{self.port}.{os.getpid()}.tmp"
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(name, tmp)
        os.replace(tmp, self.port)  # atomic: a reader never sees a missing link here
        self._master, self._slave, self.pty = master, slave, name
        self._written = 0
        self._spans.clear()
        self._clean_run = 0
        self._clean_history.clear()

    def _host_opened(self) -> bool:
        """Tell whether a reader has opened the port since the last call (reads packet-mode status)."""
        if self._master is None:  # unplugged (a replug awaiting a reader can be unplugged again): no port
            return False
        try:
            status = os.read(self._master, 64)
        except (BlockingIOError, InterruptedError):
            return False
        except OSError as exc:  # EIO: no slave open at all yet
            if exc.errno == errno.EIO:
                return False
            raise
        return any(b & _TIOCPKT_FLUSHREAD for b in status)

    def _unread(self) -> int:
        """Bytes written to the port that the reader has not taken yet."""
        assert self._slave is not None, "asked while plugged (_plug opens the master and the slave together)"
        buf = fcntl.ioctl(self._slave, termios.FIONREAD, b"\0\0\0\0")
        count: int = struct.unpack("i", buf)[0]
        return count

    def _steal_unread(self) -> int:
        """Take every byte the reader has not read (the port's buffer); how many."""
        assert self._slave is not None, "taken while plugged (_plug opens the master and the slave together)"
        n = 0
        while True:
            try:
                chunk = os.read(self._slave, 65536)
            except (BlockingIOError, InterruptedError):
                return n
            except OSError:
                return n
            if not chunk:
                return n
            n += len(chunk)

    def _unplug_pty(self, account: bool = True) -> None:
        """Unplug; with ``account``, record in the ledger what the port's buffer held."""
        if os.path.islink(self.port):
            os.unlink(self.port)
        if self._master is not None:
            assert self._slave is not None, "_plug opens the master and the slave together"
            if account:
                self._account_unplug(self._steal_unread())
            os.close(self._master)
            os.close(self._slave)
        self._master, self._slave, self.pty = None, None, None

    def _account_unplug(self, stolen: int) -> None:
        """Frames not (fully) received by the reader: those ending after the cut."""
        cut = self._written - stolen
        with self._lock:
            led = self._ledger
            for k, a, end in self._spans:
                if end <= cut:
                    continue
                if a < cut:
                    led.cut_bytes += cut - a
                if k == self._pending_frame and self._pending is not None:
                    self._lose(k, "overflow", unfinished=True)
                elif k not in led.lost:
                    led.lost[k] = "unplug"
                    led.sent -= 1
                    led.unplug_lost += 1
        self._pending = None

    # -- the writer thread -------------------------------------------------------

    def _due(self, k: int, t0: float) -> float:
        """When frame ``k``'s last sample has been acquired (monotonic s)."""
        end = (k + 1) * self.samples_per_frame
        if not self.loop:
            end = min(end, self._data.shape[0])
        return t0 + end / self.rate

    def _run(self) -> None:
        try:
            self._serve()
        except BaseException as exc:  # a bug: say so, and let waiting readers finish
            self.error = exc
            self.finished.set()
            raise

    def _serve(self) -> None:
        f = self.faults
        t0 = time.monotonic()
        k = 0
        next_unplug = t0 + f.unplug_every if f.unplug_every and f.unplug_limit != 0 else float("inf")
        replug_at = float("inf")
        prev_truncated = False
        # Bytes that must follow the last fault before an unplug: a reader
        # judges a bad frame once its declared length plus a header has come.
        margin = f.drop_max + HEADER_SIZE
        while not self._stop.is_set():
            now = time.monotonic()
            if self._calm:
                next_unplug = float("inf")
            self._quiet = now >= next_unplug
            if self._master is not None and self._quiet:
                settled = self._clean_bytes_flushed(now) - self._unread() >= margin
                if settled or now >= next_unplug + 1.0:
                    unplugged_at = time.monotonic()
                    self._unplug_pty()
                    # counted once the port is gone and what it held is in the ledger: a reader that waits for
                    # the count (a test stalling across the unplug) then reads nothing the unplug takes as lost
                    # (counted first, a reader woken by it read from the port while the unplug emptied it)
                    with self._lock:
                        self._ledger.unplugs += 1
                        self._ledger.unplugs_forced += not settled
                        self._ledger.unplug_at.append(k)
                        self._ledger.unplug_times.append(unplugged_at)
                    replug_at = now + f.unplug_for
                    next_unplug = float("inf")
                    self._quiet = False
            if self._master is None and now >= replug_at:
                self._plug()
                with self._lock:
                    self._ledger.replug_times.append(time.monotonic())
                self._await_host = True
                replug_at = float("inf")
                if (f.unplug_every and not self.finished.is_set()
                        and (f.unplug_limit is None or self._ledger.unplugs < f.unplug_limit)):
                    next_unplug = now + f.unplug_every
            if self._await_host and self._host_opened():
                self._await_host = False
            if self._pending is not None:
                self._flush()
            while (self.n_frames is None or k < self.n_frames) and self._due(k, t0) <= now:
                prev_truncated = self._emit(k, prev_truncated)
                k += 1
            if self.n_frames is not None and k >= self.n_frames and not self.finished.is_set():
                # No unplug after the end: a reader draining the pty would lose
                # frames the ledger counts as delivered.
                next_unplug = float("inf")
                self.finished.set()
            wake = min(next_unplug, replug_at)
            if self.n_frames is None or k < self.n_frames:
                wake = min(wake, self._due(k, t0))
            if self._pending is not None or self._quiet:
                wake = min(wake, now + 0.002)
            self._stop.wait(max(0.0, min(wake, now + 0.5) - time.monotonic()))
        if self._pending is not None:
            with self._lock:
                self._lose(self._pending_frame, "overflow", unfinished=True)
            self._pending = None

    def _lose(self, k: int, kind: str, unfinished: bool = False) -> None:
        """Record frame ``k`` as not delivered intact (caller holds the lock).

        ``unfinished``: ``k`` was partly written, then its tail discarded (an
        unplug, or the end); it had been counted as written.
        """
        led = self._ledger
        if unfinished:
            if k in led.lost:  # counted as written damaged already
                return
            led.sent -= 1
        led.lost[k] = kind
        if kind == "overflow":
            led.overflow += 1
        elif kind == "unplugged":
            led.unplugged += 1

    def _emit(self, k: int, prev_truncated: bool) -> bool:
        """Produce frame ``k`` with its faults.

        ``prev_truncated`` says whether the last frame on the wire was cut
        short; returns the same for after frame ``k``.
        """
        f, rng = self.faults, self._rng
        rows = self.frame_rows(k)
        frame = bytearray(encode_frame(self.seq_of(k), rows))
        # Draw every random quantity in a fixed order, whether or not the frame
        # can be written, so the schedule depends on the seed only.
        g_len = int(rng.integers(1, f.garbage_max + 1)) if rng.random() < f.garbage_rate else 0
        garbage = rng.bytes(g_len)
        u = rng.random()
        overrun = bool(f.overrun_rate) and rng.random() < f.overrun_rate
        kind = ""
        for name, rate in zip(f.KINDS, f.kind_rates()):
            if u < rate:
                kind = name
                break
            u -= rate
        if kind == "truncated":
            run = int(rng.integers(1, f.drop_max + 1))
            run = min(run, len(frame) - HEADER_SIZE)
            at = int(rng.integers(HEADER_SIZE, len(frame) - run + 1))
            del frame[at:at + run]
        elif kind == "crc":
            at = HEADER_SIZE + int(rng.integers(0, len(frame) - HEADER_SIZE - 4))
            frame[at] ^= int(rng.integers(1, 256))
        elif kind == "channels":
            ch = rows.shape[1]
            other = rows[:, :ch - 1] if ch == MAX_CHANNELS else np.concatenate([rows, rows[:, :1]], 1)
            frame = bytearray(encode_frame(self.seq_of(k), other))
        elif kind == "version":
            frame[2] = VERSION + 1
            frame[9] ^= VERSION ^ (VERSION + 1)  # the header check stays right
            frame[-4:] = struct.pack("<I", zlib.crc32(frame[:-4]))
        if prev_truncated:
            garbage = b""
            if kind == "version":  # would make the truncated frame look altered
                kind, frame = "", bytearray(encode_frame(self.seq_of(k), rows))
        if (k == 0 or (self.n_frames is not None and k == self.n_frames - 1)
                or self._quiet or self._calm):
            frame = bytearray(encode_frame(self.seq_of(k), rows))
            garbage, kind, overrun = b"", "", False
        if overrun and kind not in ("", "omitted"):
            overrun = False  # only on frames that arrive intact: the ledger stays exact
        if overrun:
            frame = bytearray(encode_frame(self.seq_of(k), rows, flags=FLAG_OVERRUN))
        with self._lock:
            led = self._ledger
            led.frames += 1
            if self._calm and led.faults_ended_at is None:
                led.faults_ended_at = k
            if self._master is None or self._await_host:
                self._lose(k, "unplugged")
                return False
            if kind == "omitted":
                led.lost[k] = kind
                led.omitted += 1
                return prev_truncated  # nothing went on the wire
            if not self._write(k, bytes(garbage), bytes(frame)):
                self._lose(k, "overflow")
                return prev_truncated  # still the last thing on the wire
            if garbage:
                led.garbage += 1
                led.garbage_bytes += len(garbage)
            if kind:
                led.lost[k] = kind
                if kind == "channels":
                    led.wrong_channels += 1  # a whole, valid frame: a reader decodes it
                else:
                    led.damaged_bytes += len(frame)
                if kind == "truncated":
                    led.truncated += 1
                    led.dropped_bytes += run
                elif kind == "crc":
                    led.crc += 1
                elif kind == "version":
                    led.wrong_version += 1
            else:
                led.sent += 1
                if overrun:
                    led.overrun_at.append(k)
                if k in self.restart_at:
                    led.restart_at.append(k)
            self._clean_run = 0 if garbage or kind else self._clean_run + len(frame)
            if not self._clean_run:
                self._clean_history.clear()
        return kind == "truncated"

    def _clean_bytes_flushed(self, now: float) -> int:
        """Clean bytes written since the last fault that have surely reached the port's input queue by ``now``.

        Those written :data:`PTY_FLUSH_SECONDS` ago or more (the mock's own pending tail left out): the
        kernel moves what the master writes into the slave's input queue in a worker, which a busy machine
        delays, and the input count (FIONREAD, :meth:`_unread`) does not see bytes still on their way. Taken
        as read when they were only on their way, a fault's judging bytes were lost at an unplug: the reader
        never judged the fault (a truncated frame missed by the driver's count, in 1 of some 20 soak runs on
        busy cores).
        """
        written = self._clean_run - (0 if self._pending is None else len(self._pending))
        history = self._clean_history
        if not history or history[-1][1] != written:
            history.append((now, written))
        while len(history) > 1 and history[1][0] <= now - PTY_FLUSH_SECONDS:
            history.popleft()
        return history[0][1] if history[0][0] <= now - PTY_FLUSH_SECONDS else 0

    def _write(self, k: int, garbage: bytes, frame: bytes) -> bool:
        """Write ``garbage + frame`` without blocking; False if it was dropped whole.

        A partly written chunk keeps its tail pending (a frame must not be cut
        by the mock's own buffering, only by injected faults); while a tail is
        pending, new frames are dropped, like a full UART TX ring.
        """
        if self._pending is not None:
            self._flush()
            if self._pending is not None:
                return False
        chunk = garbage + frame
        assert self._master is not None, "_emit writes only while plugged"
        try:
            n = os.write(self._master, chunk)
        except (BlockingIOError, InterruptedError):
            return False
        a = self._written + len(garbage)
        self._spans.append((k, a, a + len(frame)))
        while self._spans and self._spans[0][2] < a - (1 << 20):  # far more than a pty holds
            self._spans.popleft()
        self._written += n
        if n < len(chunk):
            self._pending = memoryview(chunk)[n:]
            self._pending_frame = k
        return True

    def _flush(self) -> None:
        # A tail is pending only while plugged: an unplug discards it (_account_unplug).
        assert self._master is not None and self._pending is not None, "_flush is called with a tail pending"
        try:
            n = os.write(self._master, self._pending)
        except (BlockingIOError, InterruptedError):
            return
        self._written += n
        rest = self._pending[n:]
        self._pending = rest if len(rest) else None


# -- command line ------------------------------------------------------------------


#: The fault rates the command line sets, as FaultSpec fields, and what each does to a frame.
_FAULT_RATE_FLAGS = {
    "garbage_rate": "garbage bytes before it",
    "drop_rate": "losing bytes from it",
    "crc_rate": "an altered payload byte",
    "omit_rate": "leaving it out (its sequence number skipped)",
    "channels_rate": "sending it with one channel more (or fewer)",
    "version_rate": "sending it with a wrong version",
    "overrun_rate": "setting its OVERRUN flag (sent intact)",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``mock-whisker`` options to ``parser``."""
    parser.add_argument("source", metavar="SOURCE",
                        help="what to stream: a WAV file, a recorded session, or synth:NAME (a reference "
                             "whisker texture, e.g. synth:T3)")
    parser.add_argument("--port", metavar="PATH", default=None,
                        help="symlink to create for the pty (default: in a temporary directory)")
    parser.add_argument("--channels", type=int, default=None,
                        help="fan a mono SOURCE out to this many channels")
    parser.add_argument("--samples-per-frame", type=int, default=32, metavar="N",
                        help="samples per channel per frame (default 32)")
    parser.add_argument("--loop", action="store_true", help="replay SOURCE forever")
    for rate, what in _FAULT_RATE_FLAGS.items():
        parser.add_argument("--" + rate.replace("_", "-"), type=float, default=0.0, metavar="R",
                            help=f"probability per frame of {what}")
    parser.add_argument("--unplug-every", type=float, default=None, metavar="S",
                        help="unplug after every S seconds connected")
    parser.add_argument("--unplug-for", type=float, default=0.5, metavar="S",
                        help="seconds to stay unplugged (default 0.5)")
    parser.add_argument("--seed", type=int, default=None, help="seed of the fault schedule")
    parser.add_argument("--first-seq", type=int, default=0, help="first sequence number")
    parser.add_argument("--linger", type=float, default=2.0, metavar="S",
                        help="seconds to keep the port open after SOURCE ends (default 2)")


def run(args: argparse.Namespace, samples: np.ndarray, rate: float) -> int:
    """Serve ``samples`` as :func:`add_arguments` options say; print the port path.

    Parameters
    ----------
    args : argparse.Namespace
        From a parser set up by :func:`add_arguments`.
    samples : ndarray, shape (n,) or (n, channels)
        Full-scale floats or int16.
    rate : float
        Hz.

    Returns
    -------
    int
        Exit status. Blocks until the source ends (plus ``--linger``) or Ctrl-C.
    """
    samples = np.asarray(samples)
    if samples.ndim == 1:
        samples = samples[:, None]
    if args.channels is not None:
        if samples.shape[1] == 1:
            samples = np.repeat(samples, args.channels, axis=1)
        elif samples.shape[1] != args.channels:
            print(f"mock-whisker: SOURCE has {samples.shape[1]} channels, not {args.channels}; "
                  "--channels fans out mono sources only", file=sys.stderr)
            return 2
    try:
        faults = FaultSpec(**{rate: getattr(args, rate) for rate in _FAULT_RATE_FLAGS},
                           unplug_every=args.unplug_every, unplug_for=args.unplug_for)
        dev = MockWhiskerDevice(samples, rate, port=args.port,
                                samples_per_frame=args.samples_per_frame, loop=args.loop,
                                faults=faults, seed=args.seed, first_seq=args.first_seq)
    except (ValueError, OSError) as exc:
        print(f"mock-whisker: {exc}", file=sys.stderr)
        return 2
    # SIGTERM (a supervisor, `kill`) ends the board as Ctrl-C does: the ledger line is printed
    # and the port's symlink removed, never left pointing at a pty another program may get.
    # (Signal handlers belong to the main thread; run from another, e.g. in a test, it keeps them.)
    if threading.current_thread() is not threading.main_thread():
        return _serve(dev, args, samples.shape[1], rate)
    previous = signal.signal(signal.SIGTERM, _terminate_as_interrupt)
    try:
        return _serve(dev, args, samples.shape[1], rate)
    finally:
        signal.signal(signal.SIGTERM, previous)


def _terminate_as_interrupt(signum: int, frame: FrameType | None) -> NoReturn:
    raise KeyboardInterrupt


def _serve(dev: MockWhiskerDevice, args: argparse.Namespace, channels: int, rate: float) -> int:
    with dev:
        print(dev.port, flush=True)
        print(f"mock-whisker: {channels} channels at {rate:g} Hz, "
              f"{args.samples_per_frame} samples per frame, pty {dev.pty}", file=sys.stderr)
        dev.start()
        try:
            while not dev.finished.wait(0.5):
                pass
            time.sleep(max(0.0, args.linger))
        except KeyboardInterrupt:
            pass
        led = dev.ledger
    print(f"mock-whisker: {led.frames} frames, {led.sent} intact; garbage {led.garbage} "
          f"({led.garbage_bytes} B), truncated {led.truncated}, crc {led.crc}, omitted "
          f"{led.omitted}, wrong channels {led.wrong_channels}, wrong version {led.wrong_version}, "
          f"overflow {led.overflow}, unplugs {led.unplugs} ({led.unplugged} frames unplugged, "
          f"{led.unplug_lost} lost in the port)", file=sys.stderr)
    return 0
