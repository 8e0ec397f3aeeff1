"""Driver for the elastomer whisker array on a serial port (frames: ``drivers.frames``).

The board streams frames (see ``docs/serial-frames.md``); this driver reads
whatever bytes are waiting, decodes them, checks the channel count, fills
sequence gaps with zeros (marked in :attr:`Block.filled`), and rides through
an unplug by reopening the same path with bounded exponential backoff. A port
that delivers no valid frame for ``silence_warning`` seconds (a dead board, a
wrong baud rate, the wrong port) gets a notice saying what did arrive and the
likely causes, repeated every ``silence_warning`` seconds while it lasts.

What the board does is said as it happens, as :class:`supramodal.drivers.base.DriverEvent`
objects (:meth:`SerialWhiskerDriver.take_events`); their kinds:

``open``, ``close``
    the port was opened or closed.
``baudrate``
    the configured baud rate is too low for the stream on a real UART.
``channels``
    a frame with a channel count other than the configured one (skipped), one
    event per frame, from the first one on.
``version``
    a frame of another format version (skipped), one per frame.
``gap``
    frames lost (sequence jump) and filled with zeros.
``restart``
    a sequence jump not filled (the board restarted, or longer than ``max_gap``):
    stream time is discontinuous there (:attr:`Block.restarts`).
``overrun``
    a frame flagged OVERRUN by the board (:attr:`Block.overruns`).
``unplug``, ``reopen``, ``reconnect``
    the port was lost; a reopen attempt failed (the first and every 20th);
    the reopened port delivered data.
``silence``
    no valid frame for ``silence_warning`` seconds (the notice's text).

Threading rules
---------------
* :meth:`SerialWhiskerDriver.read`, :meth:`~SerialWhiskerDriver.open` and
  :meth:`~SerialWhiskerDriver.close` are called from one thread (the node's
  driver thread). ``read`` never blocks longer than its timeout, so a node
  stops a reader by flagging it and joining, then calls ``close`` itself.
* :meth:`~SerialWhiskerDriver.stats`, :attr:`~SerialWhiskerDriver.events` and
  :meth:`~SerialWhiskerDriver.take_events` return copies and may be called from
  any thread.
* The driver starts no thread. Notices (``on_notice``) are called from
  :meth:`~SerialWhiskerDriver.read`, on the reading thread: they must not block.
"""

from __future__ import annotations

import errno
import math
import os
import stat
import termios
import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import serial

from supramodal.checks import Key, integer, positive, text
from supramodal.drivers.base import Block, DeviceUnavailable, DriverBase, DriverClosed
from supramodal.drivers.frames import (
    FLAG_OVERRUN,
    FULL_SCALE,
    MAX_CHANNELS,
    SEQ_MODULUS,
    Frame,
    FrameDecoder,
)
from supramodal.drivers.spec import BuildContext, Built, DriverSpec, OptionError, given
from supramodal.errors import InputError
from supramodal.logs import get_logger

_LOG = get_logger("drivers.serial")

# What an unplug looks like from pyserial on Linux (measured, see
# TESTING-WITHOUT-HARDWARE.md): read() -> SerialException, in_waiting -> bare
# OSError (EIO), flush/tcsetattr -> termios.error.
_LINK_ERRORS = (serial.SerialException, OSError, termios.error)

_COUNTERS = (
    "frames", "filled", "frames_ok", "sequence_gaps", "frames_lost", "discontinuities",
    "channel_mismatch", "device_overruns", "bytes_read", "reconnects", "unplugs",
    "silence_warnings",
)
_DECODER_COUNTERS = ("crc_errors", "truncated", "header_errors", "bytes_skipped")
DEFAULT_BAUDRATE = 3_000_000  #: bit/s; 20 channels at 5 kHz need about 2.02 Mbit/s (docs/serial-frames.md)


def _log_notice(message: str) -> None:
    """Log ``message`` on the package logger's ``supramodal.drivers.serial`` (INFO): the default ``on_notice``."""
    _LOG.info(message)


class SerialWhiskerDriver(DriverBase):
    """Blocks of whisker samples from a serial port (or pyserial URL).

    Parameters
    ----------
    port : str
        Device path (``/dev/ttyACM0``, ``/dev/serial/by-id/...``, a pty or a
        symlink to one) or a pyserial URL (``loop://`` for unit tests).
    rate : float
        Sample rate of the board, Hz (frames of the sample stream per second).
    channels : int
        Channels the board is configured for, 1..64. Serial frames with another
        count are skipped and counted in ``channel_mismatch``.
    baudrate : int, default 3_000_000
        For a real UART; 20 channels x 5 kHz x int16 needs about 2.02 Mbit/s
        with 8N1 framing. USB CDC-ACM boards and ptys ignore it.
    timeout : float, default 0.5
        Seconds :meth:`read` waits when called with ``timeout=None``.
    reconnect : bool, default True
        After an unplug, reopen ``port`` with backoff (0.05 s doubling to 0.5 s)
        from within :meth:`read`. If False an unplug raises
        :class:`DeviceUnavailable` and the driver closes.
    max_gap : float, default 10.0
        Longest gap, in seconds of stream, filled with zeros. A sequence jump
        that is longer, or that would put the stream ahead of the wall clock
        (the board restarted), is counted in ``discontinuities`` and not filled.
    exclusive : bool, default True
        Lock the port (flock) so a second reader fails loudly at open.
    silence_warning : float or None, default 1.0
        Seconds without a valid frame (since :meth:`open` or the last frame)
        before a notice, and between repeated notices while the silence lasts;
        each says for how long, what arrived meanwhile (no byte at all, bytes
        but no valid frame, frames with the wrong channel count, or a lost
        port) and the likely causes. None: never.
    on_notice : callable or None, default the package logger (``supramodal.drivers.serial``, INFO)
        Called with the text of each silence notice, on the reading thread, for
        a driver used on its own; None silences them. They are ``silence``
        events either way (:meth:`take_events`, :attr:`events`), and counted in
        ``silence_warnings``. The node passes None: it shows every event,
        notices included, through its sinks.

    Attributes
    ----------
    rate : float
        Hz.
    channels : int
    first_sequence : int or None
        Sequence number of the serial frame that begins stream frame 0, to
        line the stream up with the board's own log; None before any data.
    events : list of str
        Timestamped, human-readable log of the last 200 events (opens, unplugs,
        reconnects, discontinuities, misconfigurations, notices).

    Notes
    -----
    :meth:`stats` counts since :meth:`open`. ``frames`` and ``filled`` are
    frames of the *sample* stream (rows of :attr:`Block.data`), as in the
    Driver contract; the other counters count serial frames (packets):

    ``frames_ok``
        serial frames accepted (decoded, right channel count).
    ``crc_errors``, ``truncated``, ``header_errors``, ``bytes_skipped``
        from :class:`drivers.frames.FrameDecoder`: altered frames, cut-short
        frames, failed headers, bytes not in any decoded frame.
    ``sequence_gaps``, ``frames_lost``
        gaps in the sequence counter that were filled, and the serial frames
        missing in them (never arrived intact, or had the wrong channel
        count). ``filled`` equals the sum over gaps of missing frames times the
        samples per frame of the frame before the gap.
    ``discontinuities``
        sequence jumps not filled (board restart, gap > ``max_gap``).
    ``channel_mismatch``
        serial frames skipped for a channel count other than ``channels``.
    ``device_overruns``
        frames flagged by the board as following an overrun on its side.
    ``unplugs``, ``reconnects``
        lost connections; resumed connections (the reopened port delivered
        data). ``bytes_read`` counts every byte read from the port.
    ``silence_warnings``
        notices of a port delivering no valid frame (see ``silence_warning``).

    Gap filling is checked against the clock (see :meth:`_judge_gap`): within
    a burst of backlogged frames (a board that buffered while nobody read),
    only gaps up to ``BUFFER_SLACK`` can be told from a restart and filled.
    After a discontinuity, ``Block.start`` still tiles the stream but no
    longer equals the board's sample count.
    """

    BACKOFF_START = 0.05  #: s, first reopen delay after an unplug
    BACKOFF_MAX = 0.5  #: s, longest reopen delay (a reconnect is seen at most this late)
    BUFFER_SLACK = 0.25  #: s, tolerance of the gap check (delivery delay, clock drift)
    POLL = 0.05  #: s, longest single wait on the port; read() rechecks its deadline after each
    MAX_EVENTS = 200
    EVENT_HISTORY = MAX_EVENTS  #: events kept for :attr:`events`

    def __init__(self, port: str, rate: float, channels: int, baudrate: int = DEFAULT_BAUDRATE,
                 timeout: float = 0.5, reconnect: bool = True, max_gap: float = 10.0,
                 exclusive: bool = True, silence_warning: float | None = 1.0,
                 on_notice: Callable[[str], None] | None = _log_notice) -> None:
        if not 1 <= int(channels) <= MAX_CHANNELS:
            raise InputError(f"channels must be 1..{MAX_CHANNELS}, got {channels}")
        if not rate > 0:
            raise InputError(f"rate must be > 0 Hz, got {rate}")
        if silence_warning is not None and not silence_warning > 0:
            raise InputError(f"silence_warning must be > 0 s or None, got {silence_warning}")
        self.port = str(port)
        self.rate = float(rate)
        self.channels = int(channels)
        self.baudrate = int(baudrate)
        self.timeout = float(timeout)
        self.reconnect = bool(reconnect)
        self.max_gap = float(max_gap)
        self.exclusive = bool(exclusive)
        self.silence_warning = None if silence_warning is None else float(silence_warning)
        self._on_notice = on_notice
        self.first_sequence: int | None = None
        # pyserial ships no type information: its port objects are Any to mypy.
        self._ser: serial.SerialBase | None = None
        self._open = False
        super().__init__()
        self._reset_state()

    # -- lifecycle -----------------------------------------------------------

    def _reset_state(self) -> None:
        self._stats = dict.fromkeys(_COUNTERS, 0)
        self._decoder = FrameDecoder()
        self._next_seq: int | None = None
        self._spf = 0
        self._t0 = 0.0  # monotonic s when stream row 0 was taken, estimated
        self._start = 0
        self._port_timeout: float | None = None
        self._version_errors = 0
        self._reopened = False  # connected by a reconnect, no byte seen yet
        self._lost_at = 0.0
        self._backoff = self.BACKOFF_START
        self._next_attempt = 0.0
        self._attempts = 0
        self.first_sequence = None
        self._last_frame_at = time.monotonic()
        self._silence_from = self.stats()  # counters when the silence began
        self._next_warning = math.inf
        self._warnings_now = 0  # notices during the current silence

    def open(self) -> None:
        """Open the port; counters restart from zero.

        Raises
        ------
        DeviceUnavailable
            The port cannot be opened; the message names it and the fix.
        """
        if self._open:
            return
        self._reset_state()
        self._ser = self._open_port()
        self._open = True
        self._frame_seen(time.monotonic())
        self._record("open", f"opened {self.port}")
        need = self.rate * 2 * self.channels * 10  # bits/s with 8N1, payload only
        if "://" not in self.port and self.baudrate < need * 1.01:
            self._record("baudrate", f"baudrate {self.baudrate} is below the ~{need:.0f} bit/s this stream "
                        "needs on a real UART (USB CDC-ACM boards ignore it)")

    def close(self) -> None:
        """Close the port. Idempotent; :meth:`read` then raises DriverClosed."""
        was_open = self._open
        self._open = False
        self._close_port()
        if was_open:
            self._record("close", f"closed {self.port}")

    # -- public reads ----------------------------------------------------------

    def stats(self) -> dict[str, int]:
        """Counters since :meth:`open` (see class Notes); a new dict."""
        out = dict(self._stats)
        dec = self._decoder
        for k in _DECODER_COUNTERS:
            out[k] = getattr(dec, k)
        return out

    def read(self, timeout: float | None = None) -> Block | None:
        """Return the next block, or None if none arrived within ``timeout``.

        Parameters
        ----------
        timeout : float or None
            Seconds, >= 0; None uses the constructor's ``timeout``. Never
            exceeded by more than scheduling jitter, reconnect attempts included.

        Returns
        -------
        Block or None
            float32 data, shape (frames, channels), full scale +-1.0
            (int16 / 32768): every serial frame completed by the bytes read,
            with zero rows for lost frames, marked in ``filled``.

        Raises
        ------
        DriverClosed
            Before :meth:`open` or after :meth:`close`.
        DeviceUnavailable
            The device was lost and ``reconnect`` is False.
        """
        if not self._open:
            raise DriverClosed(f"{self.port}: driver is not open (call open() or use 'with')")
        wait = self.timeout if timeout is None else max(0.0, float(timeout))
        block = self._read_until(time.monotonic() + wait)
        if block is None and self.silence_warning is not None:
            now = time.monotonic()
            if now >= self._next_warning:
                self._warn_silence(now)
        return block

    def _read_until(self, deadline: float) -> Block | None:
        while True:
            if self._ser is None and not self._reopen(deadline):
                return None
            try:
                data = self._read_some(deadline)
            except _LINK_ERRORS as exc:
                self._link_lost(exc)
                continue
            now = time.monotonic()
            if data:
                self._stats["bytes_read"] += len(data)
                if self._reopened:
                    self._reopened = False
                    self._stats["reconnects"] += 1
                    self._backoff = self.BACKOFF_START
                    self._record("reconnect", f"reconnected to {self.port} after "
                                f"{now - self._lost_at:.2f} s ({self._attempts} attempt(s))", self._start)
                frames = self._decoder.feed(data)
                if self._decoder.version_errors != self._version_errors:
                    self._versions_seen()
                if frames:
                    block = self._assemble(frames, now)
                    if block is not None:
                        return block
            if now >= deadline:
                return None

    # -- port handling -----------------------------------------------------------

    def _open_port(self) -> serial.SerialBase:
        try:
            ser = serial.serial_for_url(self.port, baudrate=self.baudrate, timeout=self.POLL,
                                        exclusive=self.exclusive, do_not_open=True)
            ser.open()
        except (serial.SerialException, OSError, ValueError, termios.error) as exc:
            raise DeviceUnavailable(self._explain(exc)) from exc
        self._port_timeout = self.POLL
        return ser

    def _explain(self, exc: BaseException) -> str:
        code = getattr(exc, "errno", None)
        text = str(exc)
        kind = self._not_a_serial_device(code, text)
        if kind:
            return (f"{self.port!r} is not a serial device ({kind}). Pass the whisker board's "
                    "port, e.g. /dev/ttyACM0 (list them: ls /dev/serial/by-id/); to play a "
                    "recorded file, use a replay driver instead")
        if code == errno.ENOENT or "No such file" in text:
            return (f"serial port {self.port!r} not found ({text}). Plug the whisker board in, "
                    "or pass its path: ls /dev/ttyACM* /dev/ttyUSB* /dev/serial/by-id/")
        if code in (errno.EACCES, errno.EPERM) or "ermission denied" in text:
            return (f"permission denied on serial port {self.port!r} ({text}). Add your user to "
                    "the port's group: sudo usermod -aG dialout $USER, then log in again")
        if code in (errno.EBUSY, errno.EAGAIN) or "exclusively lock" in text:
            return (f"serial port {self.port!r} is in use by another program ({text}): close "
                    "the other reader (another node, a serial monitor, ModemManager)")
        return (f"cannot open serial port {self.port!r}: {text}. Check the path, the cable "
                "and that the board is powered")

    def _not_a_serial_device(self, code: int | None, text: str) -> str | None:
        """Return what the port is, if an open failed because it is no terminal; else None.

        pyserial opens a regular file or /dev/null, then fails to configure it
        (ENOTTY, "Inappropriate ioctl for device"); a directory fails with EISDIR.
        """
        if "://" in self.port:
            return None
        if code not in (errno.ENOTTY, errno.EISDIR) and "Inappropriate ioctl" not in text:
            return None
        try:
            mode = os.stat(self.port).st_mode
        except OSError:
            return None
        if stat.S_ISREG(mode):
            return "a regular file"
        if stat.S_ISDIR(mode):
            return "a directory"
        if stat.S_ISCHR(mode):
            return "a character device that is not a terminal, like /dev/null"
        return "not a terminal"

    def _close_port(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except Exception:  # a dead device may fail its close; it is gone either way
                pass

    def _read_some(self, deadline: float) -> bytes:
        """Bytes waiting now, else wait (<= POLL and <= deadline) for the first one."""
        ser = self._ser
        assert ser is not None, "_read_until reads only with the port open"
        waiting = ser.in_waiting
        if waiting:
            data: bytes = ser.read(waiting)
            return data
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return b""
        t = min(remaining, self.POLL)
        # Changing pyserial's timeout costs a tcsetattr: only when it matters.
        if self._port_timeout is None or abs(self._port_timeout - t) > 1e-3:
            ser.timeout = t
            self._port_timeout = t
        first: bytes = ser.read(1)
        if first:
            try:
                waiting = ser.in_waiting
                if waiting:
                    rest: bytes = ser.read(waiting)
                    return first + rest
            except _LINK_ERRORS:
                # the link went down after its first byte: keep the byte (counted like any other); the next
                # read meets the loss and reports it
                return first
        return first

    def _link_lost(self, exc: BaseException) -> None:
        now = time.monotonic()
        self._close_port()
        # Bytes of a half-received frame cannot be completed by the next connection.
        self._decoder.reset(keep_sequence=True)
        if not self.reconnect:
            self._open = False
            self._stats["unplugs"] += 1
            self._record("unplug", f"lost {self.port}: {exc}", self._start)
            raise DeviceUnavailable(
                f"serial port {self.port!r} was lost ({exc}). Check the cable and the board's "
                "power; reconnect=True rides through unplugs") from exc
        if self._reopened:
            # The reopened port died before sending a byte (a node that had
            # not vanished yet): a failed attempt, not a new unplug.
            self._reopened = False
            self._schedule_retry(now)
            return
        self._stats["unplugs"] += 1
        self._record("unplug", f"lost {self.port}: {exc}; reopening with backoff "
                    f"{self.BACKOFF_START:g} s doubling to {self.BACKOFF_MAX:g} s", self._start)
        self._lost_at = now
        self._attempts = 0
        self._backoff = self.BACKOFF_START
        self._next_attempt = now + self._backoff

    def _schedule_retry(self, now: float) -> None:
        self._backoff = min(self._backoff * 2, self.BACKOFF_MAX)
        self._next_attempt = now + self._backoff

    def _reopen(self, deadline: float) -> bool:
        """Try to reopen until it works (True) or ``deadline`` passes (False)."""
        while True:
            now = time.monotonic()
            if now >= self._next_attempt:
                self._attempts += 1
                try:
                    self._ser = self._open_port()
                except DeviceUnavailable as exc:
                    if self._attempts == 1 or self._attempts % 20 == 0:
                        self._record("reopen", f"reopen attempt {self._attempts} failed: {exc}")
                    self._schedule_retry(now)
                else:
                    self._reopened = True
                    return True
            now = time.monotonic()
            if now >= deadline:
                return False
            time.sleep(max(0.0, min(self._next_attempt, deadline) - now))

    # -- frames to blocks ------------------------------------------------------

    def _assemble(self, frames: list[Frame], arrival: float) -> Block | None:
        parts: list[np.ndarray] = []
        fills: list[tuple[int, int]] = []  # (row offset, rows) of filled runs
        restarts: list[int] = []  # row offsets where stream time is discontinuous
        overruns: list[int] = []  # row offsets of frames flagged OVERRUN
        rows = 0
        st = self._stats
        for f in frames:
            ch = f.samples.shape[1]
            if ch != self.channels:
                st["channel_mismatch"] += 1
                self._record("channels", f"frame {f.seq} has {ch} channels but the driver is "
                            f"configured for {self.channels}: skipped (fix the channels setting "
                            "or the board's firmware)", self._start + rows)
                continue
            n_rows = f.samples.shape[0]
            expected = self._next_seq
            rebase = expected is None
            if expected is None:
                if self.first_sequence is None:
                    self.first_sequence = f.seq
            elif f.seq != expected:
                lost = self._judge_gap((f.seq - expected) % SEQ_MODULUS, f.seq, arrival,
                                       self._start + rows, n_rows)
                if lost > 0:
                    n = lost * self._spf
                    self._record("gap", f"{lost} frame(s) lost before sequence {f.seq}: "
                                f"{n} rows filled with zeros", self._start + rows)
                    parts.append(np.zeros((n, ch), dtype=np.int16))
                    fills.append((rows, n))
                    rows += n
                rebase = lost < 0
                if rebase:
                    restarts.append(rows)
            if f.flags & FLAG_OVERRUN:
                st["device_overruns"] += 1
                overruns.append(rows)
                self._record("overrun", f"frame {f.seq} is flagged OVERRUN: the board lost samples "
                            "before it (not filled: stream time runs behind by the loss)",
                            self._start + rows)
            parts.append(f.samples)
            rows += n_rows
            st["frames_ok"] += 1
            self._next_seq = (f.seq + 1) % SEQ_MODULUS
            self._spf = n_rows
            # When row 0 was taken, if this frame had no delay; the least
            # delayed frame gives the best (latest-bound) estimate.
            t0 = arrival - (self._start + rows) / self.rate
            self._t0 = t0 if rebase else min(self._t0, t0)
        if not parts:
            return None
        self._frame_seen(arrival)
        data = np.concatenate(parts, axis=0).astype(np.float32)
        data *= np.float32(1.0 / FULL_SCALE)  # a power of two: exact
        filled = None
        if fills:
            filled = np.zeros(rows, dtype=bool)
            for off, n in fills:
                filled[off:off + n] = True
            st["filled"] += sum(n for _, n in fills)
        block = Block(data=data, start=self._start, arrival=arrival, filled=filled,
                      restarts=tuple(restarts), overruns=tuple(overruns))
        self._start += rows
        st["frames"] += rows
        return block

    def _judge_gap(self, jump: int, seq: int, now: float, pos: int, rows: int) -> int:
        """Return the serial frames to fill for a sequence jump of ``jump`` (0: don't fill).

        Parameters are the jump modulo 65536, the new frame's sequence number,
        its arrival time, the stream position (rows) before any fill, and the
        new frame's rows.

        The stream can never be ahead of the wall clock: a frame cannot arrive
        before its samples were taken. ``self._t0`` estimates when stream row 0
        was taken (the least-delayed frame so far says it best), so at ``now``
        at most ``(now - t0) * rate`` rows can exist. That bounds the jump,
        picks how many times the u16 counter wrapped, and tells a board restart
        (its counter means nothing) from a real gap. A reader that stalled
        while the board dropped frames still fills the whole gap: the bound
        comes from the clock, not from the time between two reads.
        """
        spf = self._spf
        room = (now - self._t0 + self.BUFFER_SLACK) * self.rate - pos - rows
        most = math.floor(room / spf)
        if jump <= most:
            lost = jump + (most - jump) // SEQ_MODULUS * SEQ_MODULUS
            lost_s = lost * spf / self.rate
            if lost_s <= self.max_gap:
                self._stats["sequence_gaps"] += 1
                self._stats["frames_lost"] += lost
                return lost
            why = f"longer than max_gap = {self.max_gap:g} s"
        else:
            lost_s = jump * spf / self.rate
            why = "more than the time elapsed allows: board restarted?"
        self._stats["discontinuities"] += 1
        self._record("restart", f"sequence jumped to {seq} (expected {self._next_seq}: {lost_s:.2f} s of "
                    f"stream, {why}): not filled, stream time is discontinuous here", pos)
        return -1

    # -- silence ---------------------------------------------------------------

    def _frame_seen(self, now: float) -> None:
        """Note that a valid frame arrived (or the port opened): a silence starts counting from here."""
        self._last_frame_at = now
        self._warnings_now = 0
        if self.silence_warning is not None:
            self._next_warning = now + self.silence_warning
            self._silence_from = self.stats()

    def _warn_silence(self, now: float) -> None:
        """Say that no valid frame came for a while, what did arrive, and why that may be."""
        assert self.silence_warning is not None, "read() warns only when silence_warning is set"
        self._warnings_now += 1
        self._stats["silence_warnings"] += 1
        self._next_warning = now + self.silence_warning
        st, was = self.stats(), self._silence_from
        got = {k: st[k] - was[k] for k in st}
        since = "since the port opened" if self._stats["frames_ok"] == 0 else "since the last frame"
        head = (f"serial port {self.port!r}: no valid frame for {now - self._last_frame_at:.1f} s "
                f"{since} (notice {self._warnings_now}")
        head += ")" if self._warnings_now == 1 else f", every {self.silence_warning:g} s)"
        if self._ser is None:
            why = (f"the port is gone (unplugged?), {self._attempts} reopen attempt(s) so far: "
                   "check the cable and the board's power")
        elif got["bytes_read"] == 0:
            why = ("no byte at all arrived: the board is not streaming (powered? firmware "
                   "running?), or this is not the board's port (ls /dev/serial/by-id/)")
        elif got["channel_mismatch"] and not got["frames_ok"]:
            why = (f"{got['channel_mismatch']} frame(s) arrived, all with a channel count other than "
                   f"the {self.channels} configured: fix the channels setting or the board's firmware")
        else:
            why = (f"{got['bytes_read']} bytes arrived but no valid frame ({got['crc_errors']} CRC "
                   f"errors, {got['header_errors']} bad headers, {got['bytes_skipped']} bytes "
                   "skipped): a wrong baud rate (set the board's; USB boards ignore it), another "
                   "device on this port, or firmware sending another format "
                   "(docs/serial-frames.md)")
        message = f"{head}: {why}"
        self._notice(message, "silence", self._start)

    def _versions_seen(self) -> None:
        """Frames of another version arrived (the decoder skipped them): say so, one event each."""
        new = self._decoder.version_errors - self._version_errors
        self._version_errors = self._decoder.version_errors
        for _ in range(new):
            self._record("version", "a frame of another format version arrived: skipped (this "
                        "driver reads version 1; update the host or flash the matching firmware, "
                        "docs/serial-frames.md)", self._start)


__all__ = ["SerialWhiskerDriver"]


# -- as a scene names it ---------------------------------------------------------------------------

#: Highest frame rate a scene may ask of the board, Hz: a UART at 12 Mbit/s carries about 1e5
#: 20-channel frames a second; more is a typo, and would size the node's buffers beyond memory.
MAX_RATE = 1e6
#: Highest baud rate a scene may open a port at, bit/s (fast USB UARTs reach 12 Mbit/s).
MAX_BAUDRATE = 100_000_000


def _build(options: Mapping[str, Any], context: BuildContext) -> Built:
    rate = options["rate"] if options["rate"] is not None else context.rate
    channels = options["channels"] if options["channels"] is not None else context.channels
    if rate is None or channels is None:
        missing = [k for k, v in (("rate", rate), ("channels", channels)) if v is None]
        raise OptionError(f"{missing[0]}: no bank reads this source, so give its {' and '.join(missing)}")
    return Built(SerialWhiskerDriver(options["port"], rate=rate, channels=channels, on_notice=None,
                                     **given(options, {"baudrate": "baudrate"})))


SPEC = DriverSpec(
    type="serial",
    summary="the whisker array's board on a serial port (or a pyserial URL such as loop://)",
    keys={
        "port": Key(text, "a serial port path or pyserial URL"),
        "rate": Key(positive(MAX_RATE), f"frames per second, Hz, up to {MAX_RATE:g} (default: the bank's rate)", None),
        "channels": Key(integer(1, MAX_CHANNELS), f"an integer 1..{MAX_CHANNELS} (default: the bank's channels)", None),
        "baudrate": Key(integer(1, MAX_BAUDRATE), f"bit/s on a real UART, an integer up to {MAX_BAUDRATE} (default: "
                        f"{DEFAULT_BAUDRATE})", None),
    },
    build=_build, live=True, signal_type=lambda options: "Whiskers")
