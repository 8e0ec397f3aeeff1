"""The microphone: a PortAudio input stream delivering :class:`~drivers.base.Block` objects.

sounddevice (and with it the PortAudio library) is imported lazily, by
:meth:`MicrophoneDriver.open` and by :mod:`drivers.devices`, so importing this
module needs neither: a scene without a microphone never loads them.

Threading and real-time rules
-----------------------------
Two threads touch a running driver:

* PortAudio's audio thread calls :meth:`CaptureBuffer.callback` once per block.
  The callback copies ``indata`` (PortAudio reuses that memory after the callback
  returns), hands the copy to a bounded queue and returns. It never waits: it
  takes no lock that another thread of this module can hold for more than a
  queue append, and when the buffer is full it drops the new block and counts it
  instead of waiting for the reader. It never raises: an exception escaping a
  sounddevice callback stops the stream with nothing but a traceback on stderr,
  so the callback catches everything, counts it (``errors``) and leaves it for
  :meth:`MicrophoneDriver.read` to raise.
* The node's driver thread calls :meth:`MicrophoneDriver.read`, which waits up to
  ``timeout`` seconds for the next block. One reader thread only.

The callback is Python, so it needs the GIL: a thread that holds the GIL for long
(a pure-Python loop; most numpy and scipy calls release it) delays the callback.
PortAudio's host buffer (the stream's input latency) absorbs such a delay up to
its size; beyond that PortAudio loses frames and flags ``input_overflow``, which
the driver counts and fills (see :meth:`CaptureBuffer.callback`).

:meth:`MicrophoneDriver.open` and :meth:`MicrophoneDriver.close` may be called
from any thread other than PortAudio's; ``close()`` wakes a reader blocked in
``read()``. :meth:`MicrophoneDriver.stats` may be called from any thread.

Counters (see :meth:`CaptureBuffer.stats`) are written by one thread each (the
callback's by the audio thread, ``frames`` and ``filled`` by the reader), so no
lock is needed. A snapshot taken while the stream runs may catch the callback
half-way (``callbacks`` already counted, ``captured`` not yet): the identities
documented in :meth:`CaptureBuffer.stats` hold once the stream has stopped.
"""

from __future__ import annotations

import contextlib
import math
import queue
import threading
import time
import traceback
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np

from supramodal.checks import Key, integer, one_of, positive
from supramodal.drivers.base import Block, DeviceUnavailable, DriverBase, DriverClosed, DriverError, EventLog
from supramodal.drivers.spec import BuildContext, Built, DriverSpec, given
from supramodal.errors import InputError
from supramodal.interrupts import held_interrupts

__all__ = ["MicrophoneDriver", "CaptureBuffer", "import_sounddevice"]

#: Sample formats the driver can ask PortAudio for. Blocks are float32 either way.
DTYPES = ("float32", "int16")
#: Largest magnitude a float32 capture may plausibly hold: full scale is 1.0; a converter's overshoot or a
#: hot preamp stays within a few times that, while another sample format read as float32 (int16 bytes
#: served raw) gives magnitudes up to 1e38, or NaN.
PLAUSIBLE_PEAK = 16.0

#: Where the user is told to look for device names and indices.
_LIST_HINT = (
    "list the input devices with `supramodal devices` (or `python3 -m sounddevice`) "
    "and pass one's index or part of its name as `device`"
)

# How often a waiting read() checks that PortAudio still runs the stream, s. A
# stream that dies (device unplugged) stops calling back without any other sign.
_LIVENESS_PERIOD = 0.25

# Queue item kinds (first element of each tuple on the queue).
_DATA, _GAP, _ERROR, _END = range(4)


def import_sounddevice() -> Any:
    """Import and return the sounddevice module.

    The one place where sounddevice is imported, so that the driver package
    never loads it (nor PortAudio) unless a microphone is actually used.

    Returns
    -------
    module
        ``sounddevice``.

    Raises
    ------
    DeviceUnavailable
        The PortAudio library is missing (sounddevice raises ``OSError``) or the
        sounddevice package is not installed; the message says how to fix it.
    """
    try:
        with held_interrupts():         # a Ctrl-C inside a C extension's import reads as ImportError
            import sounddevice
    except OSError as exc:  # sounddevice found no PortAudio shared library
        raise DeviceUnavailable(
            f"cannot use the microphone: {exc}. sounddevice needs the system's "
            "PortAudio library: on Debian/Ubuntu `apt-get install libportaudio2`, "
            "on Fedora `dnf install portaudio`, on macOS `brew install portaudio`"
        ) from exc
    except ImportError as exc:
        raise DeviceUnavailable(
            f"cannot use the microphone: {exc}. Install it with `pip install sounddevice`"
        ) from exc
    return sounddevice


# PortAudio error codes (portaudio.h, PaErrorCode) for which a specific hint helps.
_PA_INVALID_CHANNEL_COUNT = -9998
_PA_INVALID_SAMPLE_RATE = -9997
_PA_DEVICE_UNAVAILABLE = -9985
_PA_SAMPLE_FORMAT_NOT_SUPPORTED = -9994


@contextlib.contextmanager
def portaudio_errors(what: str, device_info: dict[str, Any] | None = None) -> Iterator[None]:
    """Translate ``sounddevice.PortAudioError`` into :class:`DeviceUnavailable`.

    The one place where PortAudio's errors are caught; everything that calls
    into PortAudio (opening, starting, querying) runs inside it.

    Parameters
    ----------
    what : str
        What was being done, for the message: ``"cannot open microphone (...)"``.
    device_info : dict, optional
        ``sounddevice.query_devices()`` entry of the device, when known: its
        default rate and channel count go into the hint.

    Raises
    ------
    DeviceUnavailable
        With PortAudio's message and a hint at the fix, chained to the original.
    """
    sd = import_sounddevice()
    try:
        yield
    except sd.PortAudioError as exc:
        code = exc.args[1] if len(exc.args) > 1 else None
        text = exc.args[0] if exc.args else str(exc)
        info = device_info or {}
        if code == _PA_INVALID_SAMPLE_RATE:
            hint = "choose a rate the device supports"
            if "default_samplerate" in info:
                hint += f" (its default is {info['default_samplerate']:g} Hz)"
        elif code == _PA_INVALID_CHANNEL_COUNT:
            hint = "ask for fewer channels"
            if "max_input_channels" in info:
                hint += f" (it has {info['max_input_channels']} input channel(s))"
        elif code == _PA_SAMPLE_FORMAT_NOT_SUPPORTED:
            hint = f"try another dtype of {DTYPES}"
        elif code == _PA_DEVICE_UNAVAILABLE:
            hint = "another program may be using it, or it was unplugged"
        else:
            hint = _LIST_HINT
        raise DeviceUnavailable(f"{what}: {text}; {hint}") from exc


class CaptureBuffer:
    """Bounded, non-blocking hand-off of audio blocks from PortAudio's thread to the reader.

    :meth:`callback` is the sounddevice ``InputStream`` callback; it needs no open
    stream, so tests drive it directly with synthetic ``indata``.

    Parameters
    ----------
    rate : float
        Frames per second, Hz; used to turn PortAudio's timestamps into lost frames.
    channels : int
        Channels per frame.
    capacity : int
        Most frames held for the reader, in frames (``buffer_seconds * rate``). A
        block that would exceed it is dropped, never queued, and the reader
        later gets zero-filled frames in its place.
    gap_block : int
        Longest block, in frames, in which a gap is delivered (a long gap comes
        as several blocks, so that no consumer receives an unbounded block).
    events : EventLog, optional
        Where the callback says what happens, as it happens (thread-safe, never
        blocks for more than a short lock): ``overflow`` (PortAudio flagged
        ``input_overflow``; without a timestamp the block's first frame is also
        marked in :attr:`Block.overruns`), ``underflow``, ``dropped`` (buffer
        full: the block is filled later), ``level`` (float32 samples beyond
        :data:`PLAUSIBLE_PEAK` or not finite: the device delivers another sample
        format than it was asked for; counted in :attr:`implausible`, passed on
        as they are) and ``error`` (the callback failed).

    Notes
    -----
    The stream the reader sees tiles without holes: every frame PortAudio gave
    the callback is delivered at its index, and every frame that was not (buffer
    full, callback failure, frames PortAudio lost in an input overflow) is
    delivered as a zero marked ``True`` in :attr:`Block.filled` at the index it
    would have had, so that frame indices stay aligned with time.
    """

    def __init__(self, rate: float, channels: int, capacity: int, gap_block: int,
                 events: EventLog | None = None) -> None:
        if capacity < 1 or gap_block < 1:
            raise InputError("capacity and gap_block must be at least 1 frame")
        self.rate = float(rate)
        self.channels = int(channels)
        self.events = events if events is not None else EventLog()
        self.capacity = int(capacity)
        self.gap_block = int(gap_block)
        # SimpleQueue: put() never blocks (C implementation, no bound); the bound is
        # enforced in frames by the callback with the two counters below.
        self._queue: queue.SimpleQueue[tuple[Any, ...]] = queue.SimpleQueue()
        # Written by the audio thread only.
        self._queued_in = 0  # data frames ever queued
        self._next = 0  # stream index of the next frame (measured or filled)
        self._gap_start = 0  # index of the first frame of the pending gap
        self._gap_frames = 0  # frames of the gap not yet queued
        self._gap_arrival = 0.0
        self._expected_adc: float | None = None
        self._errors_queued = 0
        self.callbacks = 0
        self.captured = 0
        self.dropped = 0
        self.overflows = 0
        self.lost = 0
        self.errors = 0
        self.implausible = 0
        # Written by the reader thread only.
        self._queued_out = 0  # data frames ever taken off the queue
        self._errors_raised = 0
        self._fill_start = 0  # the gap being delivered in gap_block pieces
        self._fill_left = 0
        self._fill_arrival = 0.0
        self._ended = False
        self.frames = 0
        self.filled = 0
        # close() may be called from two threads at once; one end marker only.
        self._end_lock = threading.Lock()
        self._end_queued = False

    # -- audio thread --------------------------------------------------------------

    def callback(self, indata: np.ndarray, frames: int, time_info: Any, status: Any) -> None:
        """Take one block from PortAudio. Runs on PortAudio's audio thread.

        Parameters
        ----------
        indata : ndarray, shape (frames, channels), float32 or int16
            The samples. PortAudio reuses this memory after the call: copied here.
            int16 is scaled by 1/32768 (exact in float32).
        frames : int
            Frames in ``indata``.
        time_info : cdata struct or object
            PortAudio's ``PaStreamCallbackTimeInfo``; only ``inputBufferAdcTime``
            (s, the capture time of the first frame on the stream's clock, 0 when
            the host API does not know it) is used, to estimate frames lost in
            an input overflow.
        status : sounddevice.CallbackFlags
            ``input_overflow`` set means PortAudio lost frames before this block.

        Notes
        -----
        Never blocks and never raises (see the module docstring). When the buffer
        holds ``capacity`` frames the block is dropped and counted in ``dropped``.
        On ``input_overflow`` the lost frames are estimated from the jump of
        ``inputBufferAdcTime`` beyond the previous block's end, capped at
        ``capacity``, counted in ``lost`` and filled; with no usable timestamp
        only ``overflows`` counts, and the stream index runs behind time by the
        unknown loss.
        """
        arrival = time.monotonic()
        self.callbacks += 1
        try:
            frames = int(frames)
            # Everything that may fail comes before the first change of state, so
            # that a failure leaves the counters consistent.
            overflow = bool(status.input_overflow)
            adc = float(getattr(time_info, "inputBufferAdcTime", 0.0) or 0.0)
            lost = 0
            if overflow and adc > 0.0 and self._expected_adc is not None:
                lost = min(max(round((adc - self._expected_adc) * self.rate), 0), self.capacity)
            room = self.capacity - (self._queued_in - self._queued_out)
            data = None
            if frames <= room:
                if indata.dtype == np.int16:
                    data = np.multiply(indata, 1.0 / 32768.0, dtype=np.float32)
                else:
                    data = np.array(indata, dtype=np.float32, copy=True)
                if data.shape != (frames, self.channels):
                    raise InputError(
                        f"indata has shape {data.shape}, expected ({frames}, {self.channels})"
                    )
            # int16 is bounded by its scaling; float32 is checked (NaN fails the comparison too)
            implausible = 0
            if data is not None and indata.dtype != np.int16 and data.size:
                with np.errstate(invalid="ignore"):
                    if not float(np.max(np.abs(data))) <= PLAUSIBLE_PEAK:
                        implausible = int(np.count_nonzero(~(np.abs(data) <= PLAUSIBLE_PEAK)))
            # State changes.
            self._expected_adc = adc + frames / self.rate if adc > 0.0 else None
            self.captured += frames
            if overflow:
                self.overflows += 1
                self.events.record("overflow", (
                    f"microphone: input overflow, {lost} frame(s) lost (filled)" if lost else
                    "microphone: input overflow, loss unknown (no timestamp): stream time runs "
                    "behind by it") + "; the machine is too busy or the block too small",
                    self._next)
            if getattr(status, "input_underflow", False):
                self.events.record("underflow", "microphone: input underflow reported by PortAudio",
                                   self._next)
            if implausible:
                self.implausible += implausible
                self.events.record("level", (
                    f"microphone: {implausible} sample(s) of {frames * self.channels} beyond "
                    f"+-{PLAUSIBLE_PEAK:g} or not finite in float32 capture (full scale 1.0): the device delivers "
                    f"another sample format than float32 (a file of int16 served raw?); set dtype = \"int16\" in "
                    f"the scene's [driver] if so"),
                    self._next)
            if lost:
                self.lost += lost
                self._add_gap(lost, arrival)
            if data is None:
                self.dropped += frames
                self.events.record("dropped", f"microphone: buffer full, {frames} frame(s) dropped "
                                   "(filled): the node reads too slowly", self._next)
                self._add_gap(frames, arrival)
                return
            self._flush_gap()
            self._queue.put((_DATA, self._next, data, arrival, overflow and not lost))
            self._queued_in += frames
            self._next += frames
        except BaseException as exc:  # noqa: BLE001 - nothing may escape to PortAudio
            self._callback_failed(exc, frames, arrival)

    def _callback_failed(self, exc: BaseException, frames: Any, arrival: float) -> None:
        try:
            self.errors += 1
            self.events.record("error", f"microphone: the callback failed: {exc!r}", self._next)
            n = frames if isinstance(frames, int) and frames > 0 else 0
            self.captured += n
            self.dropped += n
            self._add_gap(n, arrival)
            # At most one error waits for the reader: a callback failing on every
            # block must not grow the queue without bound. The others are counted.
            if self._errors_queued == self._errors_raised:
                self._errors_queued += 1
                text = "".join(traceback.format_exception_only(type(exc), exc)).strip()
                self._queue.put((_ERROR, text, exc.with_traceback(None), arrival))
        except BaseException:  # noqa: BLE001 - still nothing may escape to PortAudio
            pass

    def _add_gap(self, n: int, arrival: float) -> None:
        if n <= 0:
            return
        if self._gap_frames == 0:
            self._gap_start = self._next
        self._gap_frames += n
        self._gap_arrival = arrival
        self._next += n

    def _flush_gap(self) -> None:
        if self._gap_frames:
            self._queue.put((_GAP, self._gap_start, self._gap_frames, self._gap_arrival))
            self._gap_frames = 0

    def end(self) -> None:
        """Mark the end of the stream: the reader gets :class:`DriverClosed` once drained.

        Call only once PortAudio will call :meth:`callback` no more (after the
        stream is stopped), from any thread. A pending gap (blocks dropped since
        the last queued one) is queued first, so that ``filled`` ends equal to
        ``dropped + lost``. Idempotent.
        """
        with self._end_lock:
            if self._end_queued:
                return
            self._end_queued = True
            self._flush_gap()
            self._queue.put((_END, None, None, None))

    # -- reader thread ---------------------------------------------------------------

    def get(self, timeout: float | None = None) -> Block | None:
        """Return the next block, waiting up to ``timeout`` s; ``None`` if none came.

        Parameters
        ----------
        timeout : float or None
            Longest wait, s. ``None`` waits until a block or the end arrives; 0
            (or less) only looks.

        Returns
        -------
        Block or None
            ``data`` float32 of shape (frames, channels). Filled blocks (a gap)
            are all zeros with ``filled`` all True.

        Raises
        ------
        DriverClosed
            The stream has ended (:meth:`end`) and every block was delivered.
        DriverError
            The callback failed; raised once, in stream order. The failed block's
            frames come afterwards as filled frames, and the stream goes on.
        """
        if self._fill_left:
            return self._fill_piece()
        if self._ended:
            raise DriverClosed("the microphone stream has ended")
        try:
            if timeout is None:
                item = self._queue.get()
            else:
                item = self._queue.get(timeout=max(0.0, timeout))
        except queue.Empty:
            return None
        kind = item[0]
        if kind == _DATA:
            _, start, data, arrival, overrun = item
            n = data.shape[0]
            self._queued_out += n
            self.frames += n
            return Block(data=data, start=start, arrival=arrival, overruns=(0,) if overrun else ())
        if kind == _GAP:
            _, self._fill_start, self._fill_left, self._fill_arrival = item
            return self._fill_piece()
        if kind == _ERROR:
            _, text, exc, _ = item
            self._errors_raised += 1
            raise DriverError(
                f"the microphone callback failed ({text}); its frames are delivered "
                "as filled frames and the stream goes on"
            ) from exc
        self._ended = True
        raise DriverClosed("the microphone stream has ended")

    def _fill_piece(self) -> Block:
        n = min(self._fill_left, self.gap_block)
        block = Block(
            data=np.zeros((n, self.channels), dtype=np.float32),
            start=self._fill_start,
            arrival=self._fill_arrival,
            filled=np.ones(n, dtype=bool),
        )
        self._fill_start += n
        self._fill_left -= n
        self.frames += n
        self.filled += n
        return block

    # -- any thread ------------------------------------------------------------------

    def stats(self) -> dict[str, int]:
        """Counters since the buffer was made, in frames unless stated.

        Returns
        -------
        dict
            ``frames``: delivered by :meth:`get`, filled ones included.
            ``filled``: delivered zeros standing for frames never measured.
            ``dropped``: frames PortAudio gave the callback that were not queued
            (buffer full, or the callback failed).
            ``lost``: frames PortAudio lost in input overflows (estimated).
            ``overflows``: callbacks flagged ``input_overflow``.
            ``callbacks``: callbacks. ``errors``: callbacks that failed.
            ``implausible``: float32 samples beyond :data:`PLAUSIBLE_PEAK` or not finite (passed on).
            ``captured``: frames PortAudio gave the callback.
            ``buffered``: frames queued and not yet read.

            Once the stream has ended and been drained,
            ``filled == dropped + lost`` and ``frames == captured + lost``.
        """
        return {
            "frames": self.frames,
            "filled": self.filled,
            "dropped": self.dropped,
            "lost": self.lost,
            "overflows": self.overflows,
            "callbacks": self.callbacks,
            "errors": self.errors,
            "implausible": self.implausible,
            "captured": self.captured,
            "buffered": max(0, self._queued_in - self._queued_out),
        }


class MicrophoneDriver(DriverBase):
    """A microphone (any PortAudio input device) as a :class:`~drivers.base.Driver`.

    Parameters
    ----------
    device : int or str or None, optional
        PortAudio input device: an index, or part of its name (matched as
        sounddevice does: case-insensitive space-separated substrings of
        "name, host API", which must single out one input device).
        ``None`` (default) is the system's default input device.
    rate : float, optional
        Sampling rate, Hz. Default 44100. The device must support it: PortAudio
        does not resample on every host API, and the node needs the stated rate.
    channels : int, optional
        Channels to capture. Default 1.
    blocksize : int, optional
        Frames per callback and so per block. Default 441 (10 ms at 44.1 kHz).
        0 lets PortAudio choose, possibly varying from block to block.
    dtype : {'float32', 'int16'}, optional
        Sample format asked of PortAudio. Default 'float32'. Blocks are float32
        scaled to +-1.0 either way; 'int16' is scaled by 1/32768, which is exact,
        and is the format of most sound cards' converters and of test files.
    buffer_seconds : float, optional
        Most audio held for a slow reader, s. Default 2.0. Beyond it new blocks
        are dropped and later delivered as filled frames (see :class:`CaptureBuffer`).

    Attributes
    ----------
    rate : float
        Frames per second, Hz.
    channels : int
        Channels per frame.
    device_info : dict or None
        The opened device's ``sounddevice.query_devices()`` entry, after :meth:`open`.
    fills_are_drops : bool
        True: every filled frame stands for audio the host lost (PortAudio's
        input overflow, a full capture buffer, a failed callback), never for
        audio that was not there, so the node counts them as dropped.

    Notes
    -----
    Threading: see the module docstring. PortAudio's thread runs
    :meth:`CaptureBuffer.callback`; one reader thread calls :meth:`read`.

    Events (:meth:`~drivers.base.DriverBase.take_events`): the kinds of :class:`CaptureBuffer`,
    and ``error`` when PortAudio stopped the stream.

    Blocks carry ``start`` (index of their first frame since :meth:`open`,
    filled frames included) and ``arrival`` (``time.monotonic()`` in the callback
    that delivered the block; the sound was captured about one input latency
    before).

    Examples
    --------
    >>> with MicrophoneDriver(device="USB", rate=44100) as mic:   # doctest: +SKIP
    ...     block = mic.read(timeout=1.0)
    """

    fills_are_drops = True

    def __init__(
        self,
        device: int | str | None = None,
        rate: float = 44100,
        channels: int = 1,
        blocksize: int = 441,
        dtype: str = "float32",
        buffer_seconds: float = 2.0,
    ) -> None:
        dtype = np.dtype(dtype).name
        if dtype not in DTYPES:
            raise InputError(f"dtype must be one of {DTYPES}, not {dtype!r}")
        if not rate > 0:
            raise InputError(f"rate must be positive, not {rate!r}")
        if int(channels) < 1:
            raise InputError(f"channels must be at least 1, not {channels!r}")
        if int(blocksize) < 0:
            raise InputError(f"blocksize must be 0 (PortAudio's choice) or more, not {blocksize!r}")
        capacity = math.ceil(buffer_seconds * rate)
        if capacity < max(int(blocksize), 1):
            raise InputError(
                f"buffer_seconds={buffer_seconds!r} holds less than one block of {blocksize} frames"
            )
        self.device = device
        self.rate = float(rate)
        self.channels = int(channels)
        self.blocksize = int(blocksize)
        self.dtype = dtype
        self.buffer_seconds = float(buffer_seconds)
        self.device_info: dict[str, Any] | None = None
        self._capacity = capacity
        self._buffer: CaptureBuffer | None = None
        self._stream: Any = None
        self._closed = False
        # Serialises close() against read()'s liveness check, which must not ask
        # PortAudio about a stream close() is freeing. The callback never takes it.
        self._stream_lock = threading.Lock()
        super().__init__()

    def __repr__(self) -> str:
        return (
            f"MicrophoneDriver(device={self.device!r}, rate={self.rate:.10g}, "
            f"channels={self.channels}, blocksize={self.blocksize}, dtype={self.dtype!r}, "
            f"buffer_seconds={self.buffer_seconds:g})"
        )

    def _what(self) -> str:
        return (
            f"cannot open microphone (device={self.device!r}, {self.rate:.10g} Hz, "
            f"{self.channels} channel(s), {self.dtype})"
        )

    def open(self) -> None:
        """Open the device and start capturing. Counters restart from zero.

        Raises
        ------
        DeviceUnavailable
            PortAudio is missing, no input device matches ``device``, or the
            device rejects the rate, channel count or sample format; the message
            says which and how to fix it.
        DriverError
            The driver is already open.
        """
        if self._stream is not None:
            raise DriverError(f"{self!r} is already open")
        sd = import_sounddevice()
        what = self._what()
        with portaudio_errors(what):
            if not any(d["max_input_channels"] > 0 for d in sd.query_devices()):
                raise DeviceUnavailable(
                    f"{what}: PortAudio found no input device at all: plug in a microphone "
                    "or sound card, and check access to /dev/snd (group `audio`); "
                    "`supramodal devices` (or `python3 -m sounddevice`) lists what PortAudio sees"
                )
            try:
                info = dict(sd.query_devices(self.device, kind="input"))
            except ValueError as exc:  # sounddevice: no (or more than one) name match
                raise DeviceUnavailable(f"{what}: {exc}; {_LIST_HINT}") from exc
        with portaudio_errors(what, info):
            sd.check_input_settings(
                device=info["index"], channels=self.channels, dtype=self.dtype, samplerate=self.rate
            )
            buffer = CaptureBuffer(
                self.rate,
                self.channels,
                self._capacity,
                gap_block=self.blocksize or 1024,
                events=self.event_log,
            )
            stream = sd.InputStream(
                device=info["index"],
                samplerate=self.rate,
                channels=self.channels,
                dtype=self.dtype,
                blocksize=self.blocksize,
                callback=buffer.callback,
            )
            try:
                stream.start()
            except BaseException:
                stream.close()
                raise
        self.device_info = info
        self._buffer = buffer
        self._closed = False
        self._stream = stream

    def close(self) -> None:
        """Stop and close the stream. Idempotent; any thread but PortAudio's.

        Blocks already buffered are still delivered by :meth:`read`, which then
        raises :class:`DriverClosed`.
        """
        with self._stream_lock:
            self._closed = True
            stream, self._stream = self._stream, None
            if stream is not None:
                # stop() returns once the callback has run for the last time, so
                # end() below really is the end. Errors are ignored: a vanished
                # device cannot be stopped, and is closed all the same.
                stream.stop(ignore_errors=True)
                stream.close(ignore_errors=True)
        if self._buffer is not None:
            self._buffer.end()

    def read(self, timeout: float | None = None) -> Block | None:
        """Return the next block, waiting up to ``timeout`` s; ``None`` if none came.

        Parameters
        ----------
        timeout : float or None
            Longest wait, s; ``None`` waits until a block arrives or the stream ends.

        Returns
        -------
        Block or None
            ``data`` float32, shape (frames, channels), full scale +-1.0.

        Raises
        ------
        DriverClosed
            After :meth:`close`, once the buffered blocks have been delivered.
        DeviceUnavailable
            Nothing is buffered and PortAudio no longer runs the stream (the
            device was unplugged or failed); close and reopen to recover.
        DriverError
            The callback failed (raised once per failure, in stream order; the
            stream goes on), or the driver was never opened.
        """
        buffer = self._buffer
        if buffer is None:
            raise DriverError(f"{self!r} is not open: call open() or use it in a with statement")
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            wait = _LIVENESS_PERIOD
            if deadline is not None:
                wait = min(wait, max(0.0, deadline - time.monotonic()))
            block = buffer.get(wait)
            if block is not None:
                return block
            self._check_alive()
            if deadline is not None and time.monotonic() >= deadline:
                return None

    def _check_alive(self) -> None:
        with self._stream_lock:
            stream = self._stream
            if self._closed or stream is None:
                return  # close() has queued (or will queue) the end marker
            with portaudio_errors(f"microphone stream {self!r} failed", self.device_info):
                active = stream.active
        if not active:
            self._record("error", f"microphone: PortAudio stopped the stream {self!r} "
                         "(device unplugged or failed)")
            raise DeviceUnavailable(
                f"PortAudio stopped the microphone stream {self!r} (device unplugged or "
                "failed); close() the driver and open it again"
            )

    def stats(self) -> dict[str, int]:
        """Counters since :meth:`open` (all zero before); see :meth:`CaptureBuffer.stats`."""
        if self._buffer is None:
            return dict.fromkeys(
                ("frames", "filled", "dropped", "lost", "overflows", "callbacks",
                 "errors", "implausible", "captured", "buffered"),
                0,
            )
        return self._buffer.stats()


# -- as a scene names it ---------------------------------------------------------------------------

#: Highest sample rate a scene may ask of a sound card, Hz (studio cards reach 768 kHz).
MAX_RATE = 1e6
#: Most channels a scene may ask of a sound card.
MAX_CHANNELS = 1024
#: Longest capture buffer a scene may ask for, seconds.
MAX_BUFFER_SECONDS = 600.0


def _build(options: Mapping[str, Any], context: BuildContext) -> Built:
    return Built(MicrophoneDriver(**given(options, {"device": "device", "rate": "rate", "channels": "channels",
                                                    "block": "blocksize", "dtype": "dtype",
                                                    "buffer_seconds": "buffer_seconds"})))


SPEC = DriverSpec(
    type="microphone",
    summary="a sound card's input, through PortAudio (sounddevice)",
    keys={
        "device": Key(lambda v: isinstance(v, (str, int)) and not isinstance(v, bool),
                      "a device name or index (default: the system's default input)", None),
        "rate": Key(positive(MAX_RATE), f"Hz, up to {MAX_RATE:g} (default: the microphone driver's)", None),
        "channels": Key(integer(1, MAX_CHANNELS), f"an integer 1..{MAX_CHANNELS} (default: the microphone driver's)",
                        None),
        "block": Key(integer(1, 2**20), "frames per block, 1..1048576 (default: the microphone driver's)", None),
        "dtype": Key(one_of(*DTYPES), '"float32" or "int16" (capture format; default: the driver\'s)', None),
        "buffer_seconds": Key(positive(MAX_BUFFER_SECONDS),
                              "seconds the driver buffers between PortAudio and the node, "
                              f"up to {MAX_BUFFER_SECONDS:g} (default: the driver's)", None),
    },
    build=_build, live=True, signal_type=lambda options: "Audio")
