"""A mock whisker-array microcontroller on a pseudo-terminal, with fault injection.

:class:`MockWhiskerDevice` plays a sample array as serial frames
(``drivers.frames``) at the real rate into a pty, so :class:`SerialWhiskerDriver`
(or anything else) can open it like a USB serial board. It can insert garbage,
cut frames short, corrupt them, and unplug and replug, and keeps a
:class:`FaultLedger` of everything it did, so tests can check that every fault
shows up in the reader's counters.

The port is a symlink the mock owns, pointing at the current pty slave: an
unplug closes the pty and removes the link (reopening fails with ENOENT, as for
a vanished ``/dev/ttyACM0``); a replug makes a new pty and points the link at
it, so a reader reopens the *same path*. (``os.openpty`` cannot recreate a
given ``/dev/pts/N``.)

Threading rules
---------------
The device writes from one thread of its own, started by :meth:`start` and
joined by :meth:`close`. Writes are non-blocking, as a microcontroller's UART
would be: when the pty buffer (about 22 kB on Linux) is full, whole frames are
dropped and counted, and the writer never blocks when nobody reads.
:attr:`ledger` returns a consistent copy from any thread.

Command line (to be wired as ``supramodal mock-whisker``): :func:`add_arguments`
and :func:`run`, or ``python -m drivers.mock_whisker SOURCE.wav [options]``.
"""

from __future__ import annotations

import argparse
import copy
import os
import sys
import tempfile
import threading
import time
import tty
from dataclasses import dataclass, field

import numpy as np

from drivers.frames import (
    FULL_SCALE,
    HEADER_SIZE,
    MAX_CHANNELS,
    MAX_SAMPLES_PER_FRAME,
    SEQ_MODULUS,
    encode_frame,
)


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
        ``drop_rate + crc_rate`` must be <= 1: a frame gets at most one.
    unplug_every : float or None, default None
        Seconds connected before each unplug; None never unplugs.
    unplug_for : float, default 0.5
        Seconds unplugged. Frames are still produced meanwhile (the board runs
        on), and are lost.

    Notes
    -----
    Without ``loop`` the first and the last frame are sent clean: a decoder
    can only place a loss between two good frames, and judges a bad frame
    once bytes follow it, so a fault there would be missing from its counters
    while present in the ledger.
    """

    garbage_rate: float = 0.0
    garbage_max: int = 32
    drop_rate: float = 0.0
    drop_max: int = 64
    crc_rate: float = 0.0
    unplug_every: float | None = None
    unplug_for: float = 0.5

    def __post_init__(self) -> None:
        for name in ("garbage_rate", "drop_rate", "crc_rate"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {v}")
        if self.drop_rate + self.crc_rate > 1.0:
            raise ValueError("drop_rate + crc_rate must be <= 1")
        if self.garbage_max < 1 or self.drop_max < 1:
            raise ValueError("garbage_max and drop_max must be >= 1")
        if self.unplug_every is not None and self.unplug_every <= 0:
            raise ValueError("unplug_every must be > 0 s or None")
        if self.unplug_for < 0:
            raise ValueError("unplug_for must be >= 0 s")


@dataclass
class FaultLedger:
    """What the device did. Frame indices are unwrapped (0, 1, 2, ...);
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
    damaged_bytes : int
        Bytes written as part of truncated or altered frames.
    overflow : int
        Frames not written (or, at an unplug or at the end, not finished)
        because the pty buffer was full.
    unplugs : int
        Unplugs done.
    unplugged : int
        Frames produced while unplugged (never written).
    lost : dict of int to str
        Every frame not written intact: index -> ``"truncated"``, ``"crc"``,
        ``"overflow"`` or ``"unplugged"``.
    unplug_at : list of int
        For each unplug, the index of the first frame produced after it.
        Frames before it that were written but not yet read are lost with the
        pty (Linux discards a pty's buffer when the master closes); the ledger
        cannot know which, but they are at most one pty buffer (~22 kB) back.
    """

    frames: int = 0
    sent: int = 0
    garbage: int = 0
    garbage_bytes: int = 0
    truncated: int = 0
    dropped_bytes: int = 0
    crc: int = 0
    damaged_bytes: int = 0
    overflow: int = 0
    unplugs: int = 0
    unplugged: int = 0
    lost: dict[int, str] = field(default_factory=dict)
    unplug_at: list[int] = field(default_factory=list)


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
                 first_seq: int = 0) -> None:
        data = quantise(samples)
        if data.ndim != 2 or not 1 <= data.shape[1] <= MAX_CHANNELS or data.shape[0] < 1:
            raise ValueError(f"samples must have shape (n >= 1, 1..{MAX_CHANNELS}), "
                             f"got {data.shape}")
        if not 1 <= samples_per_frame <= MAX_SAMPLES_PER_FRAME:
            raise ValueError(f"samples_per_frame must be 1..{MAX_SAMPLES_PER_FRAME}")
        if not rate > 0:
            raise ValueError(f"rate must be > 0 Hz, got {rate}")
        self._data = np.ascontiguousarray(data)
        self.rate = float(rate)
        self.samples_per_frame = int(samples_per_frame)
        self.loop = bool(loop)
        self.faults = faults
        self.first_seq = int(first_seq) % SEQ_MODULUS
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
        self._pending: memoryview | None = None
        self._pending_frame = -1
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

    def start(self) -> "MockWhiskerDevice":
        """Start streaming (frame 0 is due one frame period from now)."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="mock-whisker", daemon=True)
            self._thread.start()
        return self

    def close(self) -> None:
        """Stop the writer, close the pty, remove the symlink (and temp dir)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self._unplug_pty()
        if self._tmpdir is not None:
            try:
                os.rmdir(self._tmpdir)
            except OSError:
                pass
            self._tmpdir = None

    def __enter__(self) -> "MockWhiskerDevice":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def ledger(self) -> FaultLedger:
        """A consistent copy of the fault ledger."""
        with self._lock:
            return copy.deepcopy(self._ledger)

    def seq_of(self, k: int) -> int:
        """Sequence number of frame index ``k``."""
        return (self.first_seq + k) % SEQ_MODULUS

    def frame_rows(self, k: int) -> np.ndarray:
        """int16 samples of frame index ``k``, shape (rows, channels)."""
        spf = self.samples_per_frame
        if self.loop:
            n = self._data.shape[0]
            return self._data[np.arange(k * spf, (k + 1) * spf) % n]
        return self._data[k * spf:(k + 1) * spf]

    # -- the pty ---------------------------------------------------------------

    def _plug(self) -> None:
        master, slave = os.openpty()
        # At once: a new pty is in cooked mode (echo, CR/LF translation).
        tty.setraw(slave)
        name = os.ttyname(slave)
        os.close(slave)  # the master keeps the pty alive; the reader opens the name
        os.set_blocking(master, False)
        tmp = f"{self.port}.{os.getpid()}.tmp"
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(name, tmp)
        os.replace(tmp, self.port)  # atomic: a reader never sees a missing link here
        self._master, self.pty = master, name

    def _unplug_pty(self) -> None:
        if os.path.islink(self.port):
            os.unlink(self.port)
        if self._master is not None:
            os.close(self._master)
        self._master, self.pty = None, None

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
        next_unplug = t0 + f.unplug_every if f.unplug_every else float("inf")
        replug_at = float("inf")
        prev_truncated = False
        while not self._stop.is_set():
            now = time.monotonic()
            if self._master is not None and now >= next_unplug:
                with self._lock:
                    if self._pending is not None:
                        self._lose(self._pending_frame, "overflow", unfinished=True)
                    self._ledger.unplugs += 1
                    self._ledger.unplug_at.append(k)
                self._pending = None
                self._unplug_pty()
                replug_at = now + f.unplug_for
                next_unplug = float("inf")
            if self._master is None and now >= replug_at:
                self._plug()
                replug_at = float("inf")
                if f.unplug_every and not self.finished.is_set():
                    next_unplug = now + f.unplug_every
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
            if self._pending is not None:
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
        frame = bytearray(encode_frame(self.seq_of(k), self.frame_rows(k)))
        # Draw every random quantity in a fixed order, whether or not the frame
        # can be written, so the schedule depends on the seed only.
        g_len = int(rng.integers(1, f.garbage_max + 1)) if rng.random() < f.garbage_rate else 0
        garbage = rng.bytes(g_len)
        u = rng.random()
        kind = "truncated" if u < f.drop_rate else "crc" if u < f.drop_rate + f.crc_rate else ""
        if kind == "truncated":
            run = int(rng.integers(1, f.drop_max + 1))
            run = min(run, len(frame) - HEADER_SIZE)
            at = int(rng.integers(HEADER_SIZE, len(frame) - run + 1))
            del frame[at:at + run]
        elif kind == "crc":
            at = HEADER_SIZE + int(rng.integers(0, len(frame) - HEADER_SIZE - 4))
            frame[at] ^= int(rng.integers(1, 256))
        if prev_truncated:
            garbage = b""
        if self.n_frames is not None and k in (0, self.n_frames - 1):
            frame = bytearray(encode_frame(self.seq_of(k), self.frame_rows(k)))
            garbage, kind = b"", ""
        with self._lock:
            led = self._ledger
            led.frames += 1
            if self._master is None:
                self._lose(k, "unplugged")
                return False
            if not self._write(k, bytes(garbage) + bytes(frame)):
                self._lose(k, "overflow")
                return prev_truncated  # still the last thing on the wire
            if garbage:
                led.garbage += 1
                led.garbage_bytes += len(garbage)
            if kind:
                led.lost[k] = kind
                led.damaged_bytes += len(frame)
                if kind == "truncated":
                    led.truncated += 1
                    led.dropped_bytes += run
                else:
                    led.crc += 1
            else:
                led.sent += 1
        return kind == "truncated"

    def _write(self, k: int, chunk: bytes) -> bool:
        """Write ``chunk`` without blocking; False if it was dropped whole.

        A partly written chunk keeps its tail pending (a frame must not be cut
        by the mock's own buffering, only by injected faults); while a tail is
        pending, new frames are dropped, like a full UART TX ring.
        """
        if self._pending is not None:
            self._flush()
            if self._pending is not None:
                return False
        try:
            n = os.write(self._master, chunk)
        except (BlockingIOError, InterruptedError):
            return False
        if n < len(chunk):
            self._pending = memoryview(chunk)[n:]
            self._pending_frame = k
        return True

    def _flush(self) -> None:
        try:
            n = os.write(self._master, self._pending)
        except (BlockingIOError, InterruptedError):
            return
        rest = self._pending[n:]
        self._pending = rest if len(rest) else None


# -- command line ------------------------------------------------------------------


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
    parser.add_argument("--garbage-rate", type=float, default=0.0, metavar="R",
                        help="probability per frame of garbage bytes before it")
    parser.add_argument("--drop-rate", type=float, default=0.0, metavar="R",
                        help="probability per frame of losing bytes from it")
    parser.add_argument("--crc-rate", type=float, default=0.0, metavar="R",
                        help="probability per frame of an altered payload byte")
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
        faults = FaultSpec(garbage_rate=args.garbage_rate, drop_rate=args.drop_rate,
                           crc_rate=args.crc_rate, unplug_every=args.unplug_every,
                           unplug_for=args.unplug_for)
        dev = MockWhiskerDevice(samples, rate, port=args.port,
                                samples_per_frame=args.samples_per_frame, loop=args.loop,
                                faults=faults, seed=args.seed, first_seq=args.first_seq)
    except (ValueError, OSError) as exc:
        print(f"mock-whisker: {exc}", file=sys.stderr)
        return 2
    with dev:
        print(dev.port, flush=True)
        print(f"mock-whisker: {samples.shape[1]} channels at {rate:g} Hz, "
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
          f"({led.garbage_bytes} B), truncated {led.truncated}, crc {led.crc}, overflow "
          f"{led.overflow}, unplugs {led.unplugs} ({led.unplugged} frames unplugged)",
          file=sys.stderr)
    return 0
