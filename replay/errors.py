"""Exceptions and warnings of the replay package.

Every error the replay package raises on purpose derives from
:class:`ReplayError`, which is both a :class:`ValueError` (the input was
bad: a file, a sidecar, an argument) and a :class:`supramodal.drivers.base.DriverError`
(so the node's ``except DriverError`` around any driver catches it too).
"""

from __future__ import annotations

from supramodal.drivers.base import DriverError
from supramodal.errors import SupramodalWarning


class ReplayError(DriverError, ValueError):
    """Base class of the replay package's errors: bad input, refused clearly."""


class WavFormatError(ReplayError):
    """A WAV file is unsupported (24-bit, compressed, ...), truncated or corrupt.

    The message names the file and the problem, and says what to do instead.
    """


class SessionError(ReplayError):
    """A session sidecar (``NAME.json``) is invalid or disagrees with its WAV.

    The message names the file, the offending key and the fix.
    """


class MissingSidecarError(SessionError, FileNotFoundError):
    """A session's sidecar (``NAME.json``) is not beside its WAV. Also a FileNotFoundError.

    The message names the missing file, says what it holds and how to get it back.
    """


class XdfDamageWarning(SupramodalWarning):
    """pyxdf read an XDF file only by skipping damaged chunks: their samples are missing."""


class ClippingWarning(SupramodalWarning):
    """Samples were clipped when writing an integer WAV file."""
