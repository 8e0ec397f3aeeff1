"""Record a node's raw driver blocks as a session that the replay driver plays back exactly.

The recorder is a tap (:class:`supramodal.node.runtime.taps.Tap`): another reader of a source's ring
buffer, on its own thread, run by the graph as every tap is. It sees the frames before any
processing, with their ``filled`` marks (and, from the source thread, the board's restart and
overrun marks and each block's time on common time: :meth:`SessionRecorder.note`,
:meth:`SessionRecorder.arrival`, which the source calls once :meth:`SessionRecorder.start` has
made the recorder its ``recorder``), and appends
them to a raw file in the output folder as they come (memory stays flat however
long the recording). At the end the raw file becomes ``NAME.wav`` + ``NAME.json``
(:func:`supramodal.replay.session.save_session`): float32 samples when every sample is
exactly a float32 (serial and microphone drivers), float64 otherwise, so that
replaying the session feeds the node bit-identical samples.

Labels are time ranges in seconds of the device's own stream (frame / rate; see
:mod:`supramodal.node.workflows.labels`): those the driver carries (a synthesised or replayed stream knows
its truth) are kept with their times, unless ``replace``; otherwise :meth:`SessionRecorder.mark`
starts one at the current stream position (or ends the current one), from any thread, and
:meth:`SessionRecorder.mark_at` (a graph's recorders, one label typed for every source) at a time
on the node's common time, mapped to this source's frames through its clock when the session is
written.

Threading rules
---------------
``start`` (and ``attach``) on the caller's thread before the run; ``note`` and ``arrival`` on
the source thread; ``run`` on the recorder's own thread; ``mark`` from any thread; every list
two threads share is guarded by the recorder's lock, or appended by one thread and read after
it has ended.
"""

from __future__ import annotations

import array
import io
import math
import os
import threading
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from supramodal.errors import InputError
from supramodal.node.runtime.clock import frames_at
from supramodal.node.runtime.ringbuffer import Reader, RingClosed, flag_runs
from supramodal.node.runtime.sources import Feed, Source
from supramodal.node.runtime.taps import Tap
from supramodal.records import JsonValue
from supramodal.replay.session import MAX_SIDECAR_BYTES, save_session, session_paths

_CHUNK = 1 << 18  # frames per pass when converting the raw file
#: Bytes of sidecar the block arrivals may take (about 22 bytes a block): beyond, every other one
#: is dropped (two blocks replay as one) until they fit, so the session stays loadable.
ARRIVALS_BUDGET = MAX_SIDECAR_BYTES // 2


class SessionRecorder(Tap):
    """Writes what a ring reader delivers to ``folder/name.wav`` + ``.json``: a tap of the graph.

    Parameters
    ----------
    folder : path
        Created if missing.
    name : str
        Session base name.
    source : str
        Free text stored in the sidecar: the driver and its options.
    label : str, optional
        A label for the whole recording.
    overwrite : bool
        Whether an existing session of that name may be replaced (default False: refused).
    keep_arrivals : bool
        Keep each block's end frame and time on the node's common time (:meth:`arrival`) in the
        session's ``arrivals`` (default False): a node of several sources records them, so that
        its sessions replay with their original relative timing.
    replace : bool
        Label the session with ``label`` and the marks only, leaving out the labels the driver
        carries (default False: a driver's own labels are kept, and marks are the caller's to refuse).

    Nothing is created until the first frames arrive: a node that fails to start leaves
    neither the folder nor a raw file behind. The graph gives a recorder to a source with its
    ``recorder`` argument (not among its ``taps``: the summary says what was recorded under
    ``recorded``).
    """

    #: The recorder takes marks and times from the source itself (:meth:`note`, :meth:`arrival`),
    #: not from its feed: the feed keeps neither, so nothing piles up unread.
    track = False

    def __init__(self, folder: str | os.PathLike[str], name: str, source: str, label: str | None = None,
                 overwrite: bool = False, keep_arrivals: bool = False, replace: bool = False) -> None:
        self.folder = Path(folder)
        if self.folder.exists() and not self.folder.is_dir():
            raise InputError(f"{self.folder} is a file; give a folder for the session")
        for path in session_paths(self.folder / name):
            if path.exists() and not overwrite:
                raise InputError(f"a session {name!r} exists in {self.folder} ({path.name}); pass --force "
                                 "to replace it, or choose another name")
        self.name = name
        self.source = source
        self.clock_rate: float | None = None
        self.rate: float | None = None
        self.channels: int | None = None
        self._raw_path = self.folder / f".{name}.raw"
        self._raw: io.BufferedWriter | None = None
        self._driver_labels: list[tuple[float, float, str]] = []
        self._label_period: float | None = None
        self._frames = 0
        self._filled: list[tuple[int, int]] = []
        self._lock = threading.Lock()
        self._marks: list[tuple[int, str | None]] = [(0, label)] if label else []
        self._timed_marks: list[tuple[float, str | None]] = []   # (seconds of common time, label)
        self.replace = replace
        self._source: Source | None = None
        self._board_marks: list[tuple[int, str]] = []      # (stream index, "restart" | "overrun")
        self._position: Callable[[], int] = lambda: self._frames
        self.paths: tuple[Path, Path] | None = None
        self.keep_arrivals = keep_arrivals
        self._arrival_frames = array.array("q")
        self._arrival_seconds = array.array("d")
        #: Arrivals left out to keep the sidecar loadable (see ARRIVALS_BUDGET).
        self.arrivals_thinned = 0

    def attach(self, rate: float, channels: int, position: Callable[[], int],
               labels: Iterable[tuple[float, float, str]] = (), clock_rate: float | None = None,
               label_period: float | None = None) -> None:
        """Take what the recorder needs of the stream (called by the node).

        The stream's rate, channels, a callable giving the current frame, the driver's own labels ``(start_s,
        end_s, name)``, kept in the session (repeating every ``label_period`` seconds for a looped source),
        and the nominal rate of the source's clock model (samples per second of common time; default
        ``rate``).
        """
        self.rate, self.channels, self._position = float(rate), int(channels), position
        self.clock_rate = self.rate if clock_rate is None else float(clock_rate)
        self._driver_labels = [(float(a), float(b), str(n)) for a, b, n in labels]
        self._label_period = label_period

    def start(self, source: Source, epoch: float) -> None:
        """Take the source this recorder records (:class:`~supramodal.node.runtime.sources.Source`), before any frame.

        :meth:`attach` to it (its rate, channels, position, truth labels and clock rate) and become its
        ``recorder``, which the source thread tells each block's marks and time. The caller's thread.
        ``epoch`` is not needed: the source's times are on common time already.
        """
        labels = source.labels
        self.attach(source.rate, source.driver.channels, lambda: source.ring.written,
                    labels=labels.ranges if labels is not None else (), clock_rate=source.time_rate,
                    label_period=labels.period if labels is not None else None)
        source.recorder = self
        self._source = source

    def newest_time(self) -> float:
        """Return the common time of the newest sample the source has delivered, seconds (-inf before the first).

        That is where a label typed now starts. Any thread.
        """
        source = self._source
        if source is None or not source.ring.written:
            return -math.inf
        return float(source.time_of(source.ring.written - 1))

    def mark_at(self, seconds: float, label: str | None) -> None:
        """Start a label at ``seconds`` of the node's common time (``None`` ends the current one).

        It is mapped to this source's frames through its recorded block times when the session is written
        (:func:`supramodal.node.runtime.clock.frames_at`). Needs ``keep_arrivals``. Thread-safe.
        """
        if not self.keep_arrivals:
            raise InputError("a mark on common time needs the blocks' times: make the recorder with keep_arrivals")
        with self._lock:
            self._timed_marks.append((float(seconds), label or None))

    def mark(self, label: str | None) -> float | None:
        """Start a label at the current stream position; ``None`` ends the current one.

        Returns its time, seconds of the stream (None before the recorder is attached: no position yet).
        Thread-safe.
        """
        with self._lock:
            at = int(self._position())
            self._marks.append((at, label or None))
        return None if self.rate is None else at / self.rate

    def note(self, index: int, kind: str) -> None:
        """Keep a driver's mark (``"restart"`` or ``"overrun"``) at stream ``index`` in the session.

        So that its replay flags the same windows. Called by the node's driver thread; thread-safe.
        """
        with self._lock:
            self._board_marks.append((int(index), kind))

    def arrival(self, end: int, seconds: float) -> None:
        """Note that a block ending at stream frame ``end`` was complete at ``seconds`` of the node's common time.

        Called by the source thread, in stream order; kept only with ``keep_arrivals``.
        """
        if self.keep_arrivals:
            self._arrival_frames.append(int(end))
            self._arrival_seconds.append(float(seconds))

    def run(self, feed: Feed | Reader) -> None:
        """Drain ``feed`` until the ring closes; then write the session (:attr:`paths`).

        ``feed``: a :class:`~supramodal.node.runtime.sources.Feed`, or a ring reader itself. The recorder's thread.
        """
        reader = feed.reader if isinstance(feed, Feed) else feed
        try:
            expected = 0
            while True:
                try:
                    chunk = reader.read(timeout=0.1)
                except RingClosed:
                    break
                if chunk is None:
                    continue
                start, data, filled = chunk
                if start > expected:
                    # The recorder fell behind the ring: keep time exact, mark the hole as filled.
                    self._append(np.zeros((start - expected, data.shape[1])), None, missing=True)
                self._append(data, filled)
                expected = start + data.shape[0]
        finally:
            if self._raw is not None:
                self._raw.close()
            self.paths = self._finish()

    def summary(self) -> dict[str, JsonValue]:
        """``{"session": name, "paths": [wav, json] or None}`` (None: no frame came)."""
        return {"session": self.name, "paths": None if self.paths is None else [str(p) for p in self.paths]}

    def _append(self, data: np.ndarray, filled: np.ndarray | None, missing: bool = False) -> None:
        if self._raw is None:
            self.folder.mkdir(parents=True, exist_ok=True)
            self._raw = open(self._raw_path, "wb")
        a = self._frames
        self._raw.write(np.ascontiguousarray(data, dtype=np.float64).tobytes())
        self._frames += data.shape[0]
        if missing:
            self._filled.append((a, self._frames))
        elif filled is not None and filled.any():
            self._filled += [(a + s, a + e) for s, e in flag_runs(filled)]

    def _labels(self, rate: float, clock_rate: float) -> list[tuple[float, float, str]]:
        """Return the session's labels, in seconds of a stream of ``rate`` Hz.

        ``clock_rate``: the source's clock model's nominal rate, for the marks on common time.
        """
        if self._driver_labels and not self.replace:
            # The driver's truth on every pass, clipped to what was recorded (a recording stopped early).
            end = self._frames / rate
            p = self._label_period
            passes = 1 if p is None else math.ceil(end / p)
            shifted = [(a + k * p if p else a, b + k * p if p else b, n)
                       for k in range(passes) for a, b, n in self._driver_labels]
            return [(a, min(b, end), n) for a, b, n in shifted if a < end]
        with self._lock:
            marks = list(self._marks) + self._timed_frames(clock_rate)
        marks = sorted(marks, key=lambda m: m[0]) + [(self._frames, None)]
        out = []
        for (a, name), (b, _) in zip(marks, marks[1:]):
            if name is not None and b > a:
                out.append((a / rate, b / rate, name))
        return out

    def _timed_frames(self, clock_rate: float) -> list[tuple[int, str | None]]:
        """Return the marks on common time as frame marks, through the clock fed this session's block times.

        All of the block times, before any thinning. Called with the lock held.
        """
        if not self._timed_marks or not len(self._arrival_frames):
            return []
        at = frames_at((self._arrival_frames, self._arrival_seconds, clock_rate), [t for t, _ in self._timed_marks],
                       self._board_marks)
        return [(int(round(min(max(float(f), 0.0), float(self._frames)))), label)
                for f, (_, label) in zip(at, self._timed_marks)]

    def _finish(self) -> tuple[Path, Path] | None:
        rate, channels, clock_rate = self.rate, self.channels, self.clock_rate   # set together, by attach
        if self._frames == 0 or rate is None or channels is None or clock_rate is None:
            if self._raw is not None:
                os.unlink(self._raw_path)
            return None
        raw = np.memmap(self._raw_path, dtype=np.float64, mode="r", shape=(self._frames, channels))
        exact32 = all(np.array_equal(raw[i : i + _CHUNK].astype(np.float32).astype(np.float64), raw[i : i + _CHUNK])
                      for i in range(0, self._frames, _CHUNK))
        with self._lock:
            marks = [(i, kind) for i, kind in self._board_marks if i < self._frames]
        paths = save_session(self.folder / self.name, raw, int(round(rate)), self.source,
                             labels=self._labels(rate, clock_rate), filled=self._merged_filled(),
                             dtype="float32" if exact32 else "float64", marks=marks,
                             arrivals=self._arrivals(clock_rate))
        del raw
        os.unlink(self._raw_path)
        return paths

    def _arrivals(self, clock_rate: float) -> tuple[np.ndarray, np.ndarray, float] | None:
        """Return the kept arrivals within what was recorded, thinned to :data:`ARRIVALS_BUDGET`.

        With the clock model's nominal rate ``clock_rate``.
        """
        if not self.keep_arrivals or not len(self._arrival_frames):
            return None
        frames = np.frombuffer(self._arrival_frames, dtype=np.int64)
        seconds = np.frombuffer(self._arrival_seconds, dtype=np.float64)
        keep = frames <= self._frames
        frames, seconds = frames[keep], seconds[keep]
        n = len(frames)
        while len(frames) * 24 > ARRIVALS_BUDGET:
            # every other block end, and always the last: two blocks replay as one
            pick = np.r_[np.arange(0, len(frames) - 1, 2), len(frames) - 1]
            frames, seconds = frames[pick], seconds[pick]
        self.arrivals_thinned = n - len(frames)
        return (frames, seconds, clock_rate) if len(frames) else None

    def _merged_filled(self) -> list[tuple[int, int]]:
        merged: list[list[int]] = []
        for a, b in sorted(self._filled):
            if merged and a <= merged[-1][1]:
                merged[-1][1] = max(merged[-1][1], b)
            else:
                merged.append([a, b])
        return [(a, b) for a, b in merged]
