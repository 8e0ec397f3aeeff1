"""Truth labels of a source's samples, as time ranges: what a stream scores its decisions against.

They are known where the truth is (a replayed, labelled session). Its own module: the sources hold them
and the streams read them, so that neither imports the other for it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from supramodal.drivers.base import Driver

__all__ = ["Labels"]


@dataclass
class Labels:
    """Truth labels as time ranges ``(start_s, end_s, name)``, for accuracy where they are known.

    With a ``period`` (seconds) they repeat, as a looped source's do.
    """

    ranges: list[tuple[float, float, str]] = field(default_factory=list)
    period: float | None = None

    @classmethod
    def of(cls, driver: Driver) -> Labels:
        """Return the labels a driver carries (a replayed session's, repeating with its loop), or none.

        None means no ranges (a :class:`~supramodal.drivers.base.DriverBase`'s ``labels`` are empty).
        """
        ranges = [(lab.start, lab.end, lab.label) for lab in driver.labels]
        looped = ranges and driver.passes != 1
        return cls(ranges, driver.period if looped else None)

    def at(self, t: float) -> str | None:
        """Return the label whose range holds time ``t`` (seconds; wrapped by ``period`` if any), or None."""
        if self.period is not None:
            t = t % self.period
        for start, end, name in self.ranges:
            if start <= t < end:
                return name
        return None
