"""The contract every driver follows, and the package's exceptions.

Threading and real-time rules
-----------------------------
* :meth:`Driver.read` is called from one thread only (the node's driver thread).
  It may block for at most ``timeout`` seconds and returns ``None`` when no block
  arrived in that time; it raises :class:`DriverClosed` once the stream has ended
  for good (end of file, ``close()`` called).
* A driver never drops, repairs or skips a sample without counting it in
  :meth:`Driver.stats`: ``frames`` (delivered, including filled ones), ``filled``
  (frames synthesised to fill a gap, never measured), and driver-specific counters
  (CRC errors, skipped bytes, overflows, reconnects, ...).
* A driver whose filled frames all stand for samples the host received and lost
  itself (a buffer overflow, not a loss on the line or at the source) says so
  with a true ``fills_are_drops`` attribute; the node then reports them as
  *dropped*, not *filled* (docs/node.md, "Every frame has one fate"). Absent
  means False.
* Drivers are context managers: ``with driver: ...`` opens and closes the device.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from supramodal.errors import SupramodalError


class DriverError(SupramodalError):
    """Base class of every error a driver raises."""


class DeviceUnavailable(DriverError):
    """The device (port, sound card, file) is missing or cannot be opened."""


class DriverClosed(DriverError):
    """The stream has ended: end of file, or the driver was closed."""


@dataclass(frozen=True)
class Block:
    """A block of samples from a driver.

    Attributes
    ----------
    data : ndarray, shape (frames, channels)
        Samples, float32 or float64, scaled so that full scale is +-1.0.
    start : int
        Index of the first frame in the driver's stream (0-based). Filled frames
        count: blocks tile the stream with no holes, so ``start`` of a block is
        ``start + frames`` of the previous one.
    filled : ndarray of bool, shape (frames,), or None
        True where a frame was synthesised by the driver to fill a gap (lost
        bytes, dropped frames) rather than measured. ``None`` means none was.
    arrival : float
        ``time.monotonic()`` when the driver received the block's last frame;
        the node measures decision latency from it.
    """

    data: np.ndarray
    start: int
    arrival: float
    filled: np.ndarray | None = field(default=None)

    @property
    def frames(self) -> int:
        return int(self.data.shape[0])

    @property
    def n_filled(self) -> int:
        return 0 if self.filled is None else int(np.count_nonzero(self.filled))


@runtime_checkable
class Driver(Protocol):
    """What the node needs of a source of blocks.

    Attributes
    ----------
    rate : float
        Frames per second, Hz.
    channels : int
        Channels per frame.
    fills_are_drops : bool, optional
        True if every filled frame stands for a sample the host lost (see the
        module documentation); absent means False.
    """

    rate: float
    channels: int

    def open(self) -> None: ...

    def close(self) -> None: ...

    def read(self, timeout: float | None = None) -> Block | None:
        """Return the next block, ``None`` if none arrived within ``timeout`` s.

        Raises :class:`DriverClosed` at the end of the stream.
        """
        ...

    def stats(self) -> dict[str, int]:
        """Counters since ``open()``: at least ``frames`` and ``filled``."""
        ...

    def __enter__(self) -> "Driver": ...

    def __exit__(self, *exc) -> None: ...
