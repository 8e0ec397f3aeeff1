"""A recording's band against a bank's channels: say so when channels can see nothing.

A recording sampled at ``r`` Hz holds nothing above ``r / 2``. Resampled to a bank's higher
rate, it still holds nothing there, and the bank's channels centred above ``r / 2`` answer
only to the resampler's residue: a cochlea model fed 5 kHz recordings has half its channels
empty and scores near chance with no error. The node and the training commands warn instead
of staying quiet.
"""

from __future__ import annotations

import warnings

import numpy as np

from supramodal.banks import Bank
from supramodal.errors import SupramodalWarning

__all__ = ["BandWarning", "channels_beyond_band", "warn_if_beyond_band"]


class BandWarning(SupramodalWarning):
    """Channels of the bank lie above the band of the recording fed to it."""


def channels_beyond_band(bank: Bank, source_rate: float) -> np.ndarray:
    """Return the indices of the channels whose centre frequency is at or above ``source_rate / 2`` (Hz)."""
    return np.flatnonzero(bank.cf >= source_rate / 2)


def warn_if_beyond_band(bank: Bank, source_rate: float, what: str) -> int:
    """Warn when ``what``, sampled at ``source_rate`` Hz, leaves channels of ``bank`` above its band.

    The warning is a :class:`BandWarning`. Returns how many channels that is (0: nothing said).
    """
    empty = channels_beyond_band(bank, source_rate)
    if empty.size:
        warnings.warn(BandWarning(
            f"{what} was sampled at {source_rate:g} Hz, so it holds nothing above {source_rate / 2:g} Hz: "
            f"{empty.size} of the {bank.kind} bank's {bank.channels} channels (centre frequencies from "
            f"{bank.cf[empty].min():g} Hz) see nothing of it, and results will be poor; record at "
            f"{bank.fs:g} Hz, or use a bank that fits the recording"), stacklevel=2)
    return int(empty.size)
