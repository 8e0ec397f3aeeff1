"""What lies between one block of a stream and the next, judged from their stamps on the sender's sample clock.

It is nothing, jitter, lost samples to fill, a backlog pushed late, or a restart.

Pure functions of the blocks' sizes and stamps (no device, no clock of their own), so that they are
tested alone: :class:`ClockSteps` for a live stream (the LSL inlet, the ROS 2 subscriber), whose stamps
may be late by a delay but never early; :class:`TimestampSteps` for a recording's stamps (XDF). The
drivers' module notes say how each uses them (``supramodal.drivers.lsl``, ``supramodal.drivers.ros2``).
:class:`StampedBlocks` makes a live stream's blocks with what :class:`ClockSteps` judged.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from supramodal.drivers.base import Block
from supramodal.errors import InputError

__all__ = ["ENVELOPE_SECONDS", "ClockSteps", "StampedBlocks", "Step", "TimestampSteps"]


@dataclass(frozen=True)
class Step:
    """What lies between one block and the next, judged from their timestamps.

    ``kind``: ``"first"`` (no block before), ``"ok"`` (within half the tolerance), ``"slip"``
    (between half the tolerance and the tolerance: jitter, or a loss too short to tell),
    ``"gap"`` (``samples`` lost, to fill), ``"long"`` (a gap beyond ``max_gap``) or
    ``"back"`` (the timestamps stepped back beyond the tolerance); from :class:`ClockSteps` also
    ``"backlog"`` (stamps late by ``seconds`` that came back onto the sample clock: a held and
    flushed backlog, nothing missing). ``seconds``: the time missing between the blocks
    (negative: overlapping).
    """

    kind: str
    seconds: float = 0.0
    samples: int = 0
    #: The block's last sample's time on the sender's sample clock (the clock model's line), for
    #: a block whose stamps are known late (a backlog's): its stamps say when it was pushed, not
    #: when it was sampled. None: the stamps stand.
    on_line: float | None = None


class TimestampSteps:
    """Judges the step between consecutive blocks of a stream from their first and last timestamps.

    The timestamps are seconds, on any clock: a pure function of the stamps, so that it is
    tested alone.

    Parameters
    ----------
    rate : float
        Nominal rate, Hz: the next block's first sample is due one period after the last one.
    tolerance, max_gap : float
        Seconds; see the module notes.
    """

    def __init__(self, rate: float, tolerance: float, max_gap: float) -> None:
        self.rate, self.tolerance, self.max_gap = float(rate), float(tolerance), float(max_gap)
        self.last: float | None = None

    def step(self, first: float, last: float) -> Step:
        """Return the step before a block whose samples are stamped ``first`` .. ``last``."""
        before, self.last = self.last, last
        if before is None:
            return Step("first")
        missing = first - before - 1.0 / self.rate
        if missing > self.max_gap:
            return Step("long", missing)
        if missing > self.tolerance:
            return Step("gap", missing, int(round(missing * self.rate)))
        if missing < -self.tolerance:
            return Step("back", missing)
        return Step("slip" if abs(missing) > self.tolerance / 2 else "ok", missing)


#: Seconds of stream over which the clock model keeps its lower envelope (the earliest stamp
#: relative to the sample count): long enough to hold a quick block, short enough that a sender's
#: rate error (100 ppm: 0.2 ms over 2 s) does not count.
ENVELOPE_SECONDS = 2.0


class ClockSteps:
    """Judges, on the sender's sample clock, what lies before each block of a stream.

    A pure function of the blocks' sizes and stamps, so that it is tested alone.

    The clock model is the line ``t = E + index / rate``: ``E`` the lower envelope of the
    accepted blocks' ``last stamp - last index / rate`` over the last :data:`ENVELOPE_SECONDS`
    (stamps are late by a delay >= 0, never early: the earliest is the sample clock). A block
    whose last stamp lies within ``tolerance`` of the line follows on (``"ok"``, or ``"slip"``
    beyond half the tolerance). A block stamped later than that is held, with those after it,
    until the stamps say what happened:

    - they come back onto the line (within the tolerance): the sender held its samples and
      flushed its backlog, stamped at push time (overlapping stamps, 3 s of samples in
      milliseconds): nothing was lost, nothing is filled (``"backlog"``);
    - they run on at the sample rate, off the line by the same amount, for ``confirm`` seconds
      of samples: samples are missing, as many as the smallest offset says (``"gap"``; beyond
      ``max_gap`` seconds: ``"long"``, a restart).

    A block stamped earlier than the line by more than the tolerance is a restart (``"back"``).
    The first block, and the first after a restart, is ``"first"``.

    Parameters
    ----------
    rate : float
        Nominal rate, Hz.
    tolerance, max_gap : float
        Seconds (see the drivers that use it).
    confirm : float, optional
        Seconds of samples after a step whose stamps must run at the rate before it is filled
        (default twice the tolerance).
    """

    def __init__(self, rate: float, tolerance: float, max_gap: float, confirm: float | None = None) -> None:
        self.rate, self.tolerance, self.max_gap = float(rate), float(tolerance), float(max_gap)
        self.confirm = 2 * self.tolerance if confirm is None else float(confirm)
        self.index = 0                      # the stream index of the next sample (fills included)
        self._envelope: list[tuple[int, float]] = []     # (last index, intercept) of accepted blocks
        self._held: list[tuple[int, float, float, float]] = []   # (samples, first, last, residual)

    @property
    def held(self) -> int:
        """Blocks held, awaiting a verdict."""
        return len(self._held)

    def _intercept(self) -> float | None:
        horizon = self.index - ENVELOPE_SECONDS * self.rate
        self._envelope = [e for e in self._envelope if e[0] >= horizon] or self._envelope[-1:]
        return min(e[1] for e in self._envelope) if self._envelope else None

    def _accept(self, n: int, last: float, fill: int = 0) -> None:
        self.index += fill + n
        self._envelope.append((self.index - 1, last - (self.index - 1) / self.rate))

    def add(self, n: int, first: float, last: float) -> list[Step]:
        """Take a block of ``n`` samples stamped ``first`` .. ``last`` (seconds).

        Returns the steps of the blocks judged now, oldest first: one per block, in the order
        they came (none while a step is being judged).
        """
        if n < 1:
            raise InputError(f"a block has at least one sample, got {n!r}")
        e = self._intercept()
        if e is None:
            self._accept(n, last)
            return [Step("first")]
        held_n = sum(h[0] for h in self._held)
        residual = last - (self.index + held_n + n - 1) / self.rate - e
        if not self._held:
            if residual < -self.tolerance or residual > self.max_gap:
                return [self._restart(n, last, residual)]
            if residual <= self.tolerance:
                self._accept(n, last)
                return [Step("slip" if residual > self.tolerance / 2 else "ok", residual)]
        self._held.append((n, first, last, residual))
        if residual <= self.tolerance:      # back on the line: a backlog, flushed
            return self._release(0)
        # Do the last stamps run at the rate over the last `confirm` seconds of samples held? (A
        # backlog's are all about the flush's instant; liblsl dates a chunk's samples back from
        # its stamp, so only the blocks' last stamps are compared.)
        k, span = len(self._held) - 1, 0
        while k > 0 and span < self.confirm * self.rate:
            span += self._held[k][0]
            k -= 1
        if span < self.confirm * self.rate:
            return []
        if last - self._held[k][2] >= span / self.rate - self.tolerance:
            return self._release(min(h[3] for h in self._held))
        return []

    def flush(self) -> list[Step]:
        """Return a verdict on every held block now (the stream went silent, or ended).

        The verdict is a gap of their smallest offset where it exceeds the tolerance, else a
        backlog.
        """
        steps: list[Step] = []
        while self._held:
            steps += self._release(min(h[3] for h in self._held))
        return steps

    def _release(self, offset: float) -> list[Step]:
        """Release the held blocks: return the first one's step (``offset``: seconds missing before it).

        The blocks held after it are judged again, on the line it leaves, and their steps
        returned too.
        """
        held, self._held = self._held, []
        fill = int(round(offset * self.rate)) if offset > self.tolerance else 0
        if fill and offset > self.max_gap:
            steps = [self._restart(held[0][0], held[0][2], offset)]
        elif fill:
            self._accept(held[0][0], held[0][2], fill)
            steps = [Step("gap", fill / self.rate, fill)]
        else:                               # a backlog: its blocks dated by the sample clock
            e = self._intercept()
            assert e is not None            # a block was accepted before any is held
            steps = []
            for k, (n, _, last, residual) in enumerate(held):
                on_line = e + (self.index + n - 1) / self.rate
                self._accept(n, min(last, on_line))
                steps.append(Step("backlog" if k == 0 else "ok", residual if k == 0 else 0.0, on_line=on_line))
            return steps
        for n, first, last, _ in held[1:]:
            steps += self.add(n, first, last)
        return steps

    def _restart(self, n: int, last: float, residual: float) -> Step:
        """Return a step that cannot be filled: the clock model starts again with this block."""
        self._envelope = []
        self._accept(n, last)
        return Step("back" if residual < 0 else "long", residual)


class StampedBlocks:
    """A live stream's samples as :class:`~supramodal.drivers.base.Block`, each with the step before it.

    The steps are :class:`ClockSteps`': a gap filled with zeros, a restart marked, a backlog
    dated on the sample clock, each counted and said. What the LSL inlet and the ROS 2
    subscriber share.

    Parameters
    ----------
    channels : int
        Columns of each block.
    where : callable
        How a message names the stream, asked at each message, e.g. ``"LSL: name='x' ..."`` (the ROS 2
        topic's name says its type once it is known).
    sender : str
        What sends it, for a person: ``"sender"``, ``"publisher"``.
    max_gap : float
        The driver's longest filled gap, seconds (for the message of a longer one).
    say : callable ``(kind, message, frame)``
        Records a driver event (``"gap"``, ``"restart"``, ``"backlog"``) at a stream frame.

    Attributes
    ----------
    frames, filled, gaps, restarts, backlogs, slips : int
        Frames made (filled ones included), frames filled, gaps filled, restarts, backlogs, steps
        between half the tolerance and the tolerance (jitter, or a loss too short to tell).
    last_stamp : float
        The last block's :attr:`~supramodal.drivers.base.Block.timestamp` (-inf before the first).

    One thread (the driver's reader) calls :meth:`block`; the counts may be read from any.
    """

    def __init__(self, channels: int, where: Callable[[], str], sender: str, max_gap: float,
                 say: Callable[[str, str, int], object]) -> None:
        self.channels, self.where, self.sender, self.max_gap, self._say = channels, where, sender, max_gap, say
        self.frames = self.filled = self.gaps = self.restarts = self.backlogs = self.slips = 0
        self.last_stamp = -math.inf

    def block(self, data: np.ndarray, last: float, arrival: float, step: Step) -> Block:
        """Return the block of ``data`` (samples x channels), after the step ``step``.

        Its last sample is stamped ``last`` (host seconds), and it came at ``arrival``.
        """
        start, fill = self.frames, 0
        restarts: tuple[int, ...] = ()
        if step.kind == "gap":
            fill = step.samples
            self.gaps += 1
            self.filled += fill
            self._say("gap", f"{self.where()}: {fill} samples ({step.seconds * 1e3:.1f} ms) missing; filled with zeros",
                      start)
        elif step.kind in ("long", "back"):
            restarts = (0,)
            self.restarts += 1
            what = (f"{step.seconds:.2f} s without samples, more than max_gap ({self.max_gap:g} s): not filled"
                    if step.kind == "long" else
                    f"timestamps stepped back {-step.seconds * 1e3:.1f} ms (the {self.sender} restarted?)")
            self._say("restart", f"{self.where()}: {what}; stream time jumps here", start)
        elif step.kind == "slip":
            self.slips += 1
        elif step.kind == "backlog":
            self.backlogs += 1
            self._say("backlog", f"{self.where()}: samples stamped up to {step.seconds:.2f} s late came back onto the "
                                 f"{self.sender}'s sample clock (a backlog sent at once); nothing missing, nothing "
                                 "filled", start)
        n = data.shape[0]
        filled = None
        if fill:
            data = np.concatenate([np.zeros((fill, self.channels)), data])
            filled = np.zeros(fill + n, dtype=bool)
            filled[:fill] = True
        self.frames += fill + n
        stamp = last if step.on_line is None else step.on_line
        if not restarts:                    # one clock, never backwards (a backlog's dates meet the stamps)
            stamp = max(stamp, self.last_stamp)
        self.last_stamp = stamp
        return Block(data, start, arrival, filled, restarts=restarts, timestamp=stamp)
