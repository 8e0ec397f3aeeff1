"""Sources of sample blocks: the whisker array on a serial port and the microphone.

A driver produces :class:`~drivers.base.Block` objects and knows nothing of the
signal processing that follows. Every driver follows :class:`~drivers.base.Driver`;
the replay driver (package ``replay``) is just another one.

Hardware modules (``drivers.serial_whisker``, ``drivers.microphone``) import
pyserial and sounddevice themselves, so ``import drivers`` alone imports neither.
"""

from supramodal.drivers.base import Block, DeviceUnavailable, Driver, DriverClosed, DriverError

__all__ = ["Block", "Driver", "DriverError", "DriverClosed", "DeviceUnavailable"]
