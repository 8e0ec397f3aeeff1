"""What a scene needs to know of a kind of driver, in one object: :class:`DriverSpec`.

Each driver module defines its spec as the module attribute ``SPEC``: the ``type`` a scene names
it by, its keys (:class:`supramodal.checks.Key`: the check, the words, the default), how to build
the driver from validated options, whether it is live, its timebase and what its samples are. The
node's registry (``supramodal.node.scene.registry``) maps each type to the module holding its spec and
imports that module only when a scene names the type; so a new driver is one module plus one
line there (or one :func:`~supramodal.node.scene.registry.register_driver` call for a driver defined
outside the package).

A spec's ``build`` never imports the node: it is given a :class:`BuildContext` (the rate a bank
reads the source at, the scene's folder, a shared cache) and returns a :class:`Built`. It raises
:class:`OptionError` for an option that cannot be honoured (the node says which table it was in),
and its driver's own errors otherwise.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from supramodal.checks import Key
from supramodal.errors import InputError

__all__ = ["BuildContext", "Built", "DriverSpec", "OptionError", "ReplayedSession", "TIMEBASES", "given"]

#: How a source's samples are put on the graph's common time (see ``supramodal.node.runtime.sources.Source``):
#: ``stream`` (a file's own time, from its first sample), ``recorded`` (a recording's clock as it was
#: recorded) or ``host`` (a live device's arrivals, fitted by a clock model).
TIMEBASES = ("stream", "recorded", "host")


class OptionError(InputError):
    """A driver option that cannot be honoured.

    The message starts with the key, and the node puts the table it came from in front of it.
    """


@dataclass(frozen=True)
class BuildContext:
    """What a spec's ``build`` may use besides its options.

    Attributes
    ----------
    rate : float or None
        The rate, Hz, at which a bank reads the source: a file is resampled to it, a stream at
        another rate refused. None: no bank reads the source (a relay's), it keeps its own rate.
    resolve : callable
        ``resolve(path) -> Path``: a path of the scene, relative to the scene file's folder.
    speed : float, str or None
        The command line's ``--speed`` (None: the scene's own).
    shared : dict
        One dict for all the sources of one scene: a spec may keep what several of its sources
        share (an XDF file read once).
    channels : int or None
        The channels of the bank that reads the source (None: no bank), the default of a device
        whose channel count is a setting.
    bank : object or None
        The bank that reads the source (``supramodal.banks.Bank``), for sources the model itself
        makes (synthesised textures); a device or file driver needs only ``rate``.
    """

    rate: float | None
    resolve: Callable[[str], Path] = Path
    speed: Any = None
    shared: dict[str, Any] = field(default_factory=dict)
    channels: int | None = None
    bank: Any = None


@dataclass(frozen=True)
class Built:
    """A driver built from a scene's options.

    Attributes
    ----------
    driver : Driver
    labels : tuple of (float, float, str)
        Truth labels the build made, as ``(start_s, end_s, name)`` on the stream's time (a
        synthesised source's). Empty: the driver's own (``driver.labels``, ``passes``,
        ``period``: a replayed session's) are read.
    label_period : float or None
        Seconds after which ``labels`` repeat (a looped source), or None.
    training_set : object or None
        The textures a model trained on the spot learns for this source (a synthesised one's
        own); None: the bank's reference set.
    source_rate : float or None
        A file's own rate where it was resampled to the bank's: the node warns when the bank has
        channels above its band.
    """

    driver: Any
    labels: tuple[tuple[float, float, str], ...] = ()
    label_period: float | None = None
    training_set: Any = None
    source_rate: float | None = None


@dataclass(frozen=True)
class ReplayedSession:
    """A recorded session a source replays (:attr:`DriverSpec.replays`).

    Attributes
    ----------
    path : str
        The session (``NAME.wav`` and its ``NAME.json``), as the scene names it: relative to the
        scene's folder.
    in_step : bool
        Replayed at its recorded times, in step with the graph's other recorded sources
        (``timing = "recorded"``), rather than on its rate's schedule.
    """

    path: str
    in_step: bool


def _default_timebase(live: bool) -> Callable[[Mapping[str, Any], Any], tuple[str, float, float]]:
    def timebase(options: Mapping[str, Any], driver: Any) -> tuple[str, float, float]:
        return ("host" if live else "stream"), 0.0, float(driver.rate)
    return timebase


@dataclass(frozen=True)
class DriverSpec:
    """A kind of driver as a scene sees it.

    Attributes
    ----------
    type : str
        The name a scene gives it (``[driver] type`` / ``[[source]] type``).
    keys : mapping of str to Key
        Its options besides ``type`` (and a graph source's ``name`` and ``buffer``).
    build : callable
        ``build(options, context) -> Built``, with ``options`` validated and filled in.
    live : bool
        A device whose samples arrive whether or not the node keeps up: its ring drops the oldest
        when full (``overrun = "auto"``) and its samples are put on host time. A file (False)
        waits: the ring blocks it.
    summary : str
        One line for the docs' table of driver types.
    timebase : callable, optional
        ``timebase(options, driver) -> (timebase, time_offset, time_rate)`` (:data:`TIMEBASES`);
        by default host time at the driver's rate for a live driver, stream time otherwise.
    signal_type : callable, optional
        ``signal_type(options) -> str or None``: what the samples are as an LSL content type
        (``"Whiskers"``, ``"Audio"``), when no bank says so; None: unknown.
    check : callable, optional
        ``check(options) -> None``: a check across keys, raising :class:`OptionError`; run when
        the scene is loaded, before anything is built.
    buffered : bool
        A live driver that holds what arrives in a buffer of its own (an LSL inlet: liblsl keeps
        ``buffer_seconds``), so that the node may wait for it: its ring blocks it (``overrun =
        "auto"``) instead of dropping, and a backlog its sender flushes at once waits there.
        Default False.
    replays : callable, optional
        ``replays(options) -> ReplayedSession or None``: the recorded session the source replays, which
        the workflows train on, label and evaluate (``supramodal train --scene``, ``label``); None
        (the default) for a source that replays none.
    """

    type: str
    keys: Mapping[str, Key]
    build: Callable[[Mapping[str, Any], BuildContext], Built]
    live: bool
    summary: str
    timebase: Callable[[Mapping[str, Any], Any], tuple[str, float, float]] | None = None
    signal_type: Callable[[Mapping[str, Any]], str | None] = field(default=lambda options: None)
    check: Callable[[Mapping[str, Any]], None] = field(default=lambda options: None)
    buffered: bool = False
    replays: Callable[[Mapping[str, Any]], ReplayedSession | None] = field(default=lambda options: None)

    def timebase_of(self, options: Mapping[str, Any], driver: Any) -> tuple[str, float, float]:
        """``(timebase, time_offset, time_rate)`` of a built driver."""
        tb = (self.timebase or _default_timebase(self.live))(options, driver)
        if tb[0] not in TIMEBASES or not (math.isfinite(tb[2]) and tb[2] > 0):
            raise InputError(f"driver {self.type!r}: timebase {tb!r} is not one of {TIMEBASES} at a positive rate")
        return tb

    @property
    def overrun(self) -> str:
        """The ring's policy for ``overrun = "auto"``.

        Lossless back-pressure for a file (and a live driver with a buffer of its own), the
        oldest frames dropped for a live device (it cannot wait).
        """
        return "drop-oldest" if self.live and not self.buffered else "block"


def given(options: Mapping[str, Any], names: Mapping[str, str]) -> dict[str, Any]:
    """Return the options a scene sets, renamed to a driver's keyword arguments.

    ``names`` maps ``{scene key: argument}``. An option left at None is not passed, so that the
    driver's own default applies (its one home).
    """
    return {arg: options[key] for key, arg in names.items() if options.get(key) is not None}
