"""A base for drivers that tests stand in for a device."""

from supramodal.drivers.base import DriverBase


class StandInDriver(DriverBase):
    """Nothing to open or close, no labels, no events unless it logs some (``self._record``):
    :class:`~supramodal.drivers.base.DriverBase` as it is; subclasses set ``rate``,
    ``channels`` and give ``read`` and ``stats``."""
