"""Replay driver: recorded sessions, WAV files and in-memory arrays, as a live driver would deliver them.

``replay`` is just another driver: it produces :class:`supramodal.drivers.base.Block`
objects and knows nothing of the signal processing (it never imports
``supramodal`` or ``node``).

Modules
-------
replay.errors
    :class:`ReplayError` and its subclasses.
replay.wavio
    WAV files to and from float64 arrays scaled to +-1 full scale.
replay.session
    Sessions: a WAV file plus a strict JSON sidecar (labels, filled ranges).
replay.driver
    :class:`ReplayDriver`, the pacing schedule and block-size policies.
"""

from supramodal.replay.driver import DeviceClock, ReplayDriver, random_block_sizes, release_time
from supramodal.replay.errors import ClippingWarning, ReplayError, SessionError, WavFormatError
from supramodal.replay.session import Label, Session, load_session, save_session, session_paths
from supramodal.replay.wavio import WavInfo, read_wav, wav_info, write_wav

__all__ = [
    "ClippingWarning",
    "Label",
    "DeviceClock",
    "ReplayDriver",
    "ReplayError",
    "Session",
    "SessionError",
    "WavFormatError",
    "WavInfo",
    "load_session",
    "random_block_sizes",
    "read_wav",
    "release_time",
    "save_session",
    "session_paths",
    "wav_info",
    "write_wav",
]
