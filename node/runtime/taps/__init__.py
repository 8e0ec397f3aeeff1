"""Taps: readers of a source's raw frames, each on a thread of its own (the recorder, the LSL signal outlet).

A tap sees a source's samples before any processing, with their ``filled`` marks, through a
:class:`~supramodal.node.runtime.sources.Feed` of the source's ring. The graph
(:class:`supramodal.node.runtime.graph.Graph`) drives every tap through the calls of :class:`Tap`, in
this order: :meth:`~Tap.prepare`, :meth:`~Tap.start`, :meth:`~Tap.run` on the tap's thread,
:meth:`~Tap.close` (at least once: again when the run ends, whatever happened), then
:meth:`~Tap.summary`.

Threading rules
---------------
``prepare``, ``start``, ``summary`` and ``close`` are called from the caller's thread (the one
that runs the graph); ``run`` from the tap's own thread, between ``start`` and the ``close``
after it. A tap never makes a source or a stream wait, except as its ring's policy says: a file
source's ring (policy "block") waits for every reader, a tap included; a live source's ring
drops the frames a tap falls behind on, and counts them in the tap's ``frames`` (see
:meth:`~supramodal.node.runtime.sources.Source.frame_fates`).
"""

from __future__ import annotations

import abc
from typing import TYPE_CHECKING

from supramodal.records import JsonValue

if TYPE_CHECKING:   # the sources import the taps: names for the annotations only
    from supramodal.node.runtime.sources import Feed, Source

__all__ = ["Tap"]


class Tap(abc.ABC):
    """The base of a graph's taps: every call the graph makes, with no-op defaults but :meth:`run`.

    Attributes
    ----------
    name : str
        What the tap is called in the summary's ``taps`` and in its thread's name (unique among
        a graph's taps). Set by the subclass.
    track : bool
        Whether the tap's feed keeps each block's arrival and the driver's marks
        (``Feed.arrivals``, ``Feed.marks``; default True). A tap that does not read them says
        False, so that nothing piles up unread.
    """

    name: str = "tap"
    track: bool = True

    def prepare(self) -> None:
        """Prepare before the graph's start, on the caller's thread; may wait (e.g. for a consumer).

        Default: nothing.
        """

    def start(self, source: Source, epoch: float) -> None:
        """Take the source this tap reads and the graph's start on ``time.monotonic()`` (common time 0).

        ``source``: a :class:`~supramodal.node.runtime.sources.Source`. The caller's thread, before any
        frame and before the tap's thread starts. Default: nothing.
        """

    @abc.abstractmethod
    def run(self, feed: Feed) -> None:
        """Read ``feed`` (a :class:`~supramodal.node.runtime.sources.Feed`) until its ring closes.

        That is, ``feed.reader.read`` until it raises :class:`~supramodal.node.runtime.ringbuffer.RingClosed`.
        The tap's thread; an exception stops the graph, which raises it from :meth:`Graph.run`.
        """

    def summary(self) -> dict[str, JsonValue]:
        """Return the tap's own counts, for the graph's summary (``taps``; the graph adds ``frames``).

        The caller's thread, after :meth:`close`. Default: ``{}``.
        """
        return {}

    def close(self) -> None:
        """Release what the tap holds (an outlet, a file).

        Called after the tap's thread has ended, and again when the graph's run ends, whatever happened: a
        second call is a no-op. The caller's thread. Default: nothing.
        """
