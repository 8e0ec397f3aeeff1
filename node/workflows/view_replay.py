"""``supramodal view REC.toml | SESSION``: a recording played back into the view's page, with pause and speed.

So that a user can look back at what the robot felt.

The recording is first run through the node at once (``--speed max``: the same windows, decisions
and driver events a live run of it gives, node/runtime/graph.py), kept in memory, then played to the page
on the recording's own time (each window at its end on common time) by a player thread, which
the page's pause, speed and restart buttons steer (POST ``/control``, with the run's token, as
every change). The health the page shows is the recording's whole run (its summary's counters).

Threading rules
---------------
:meth:`ViewReplay.serve` runs the node (its own threads, joined), then the player on the
caller's thread until :meth:`ViewReplay.stop` (from a signal handler or another thread); the
page's requests come on the view's server threads and only change the player's state under its
condition.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

from supramodal.drivers.base import DriverEvent
from supramodal.errors import InputError
from supramodal.node.runtime.events import WindowEvent
from supramodal.node.runtime.sinks import Sink
from supramodal.node.runtime.sinks.view import ViewSink, event_message, window_message
from supramodal.node.runtime.summaries import RunSummary

__all__ = ["BANKS_BY_RATE", "MAX_SPEED", "ViewReplay", "replay_scene"]

#: A session alone (no REC.toml) is seen through the paper's bank for its rate.
BANKS_BY_RATE = {5000: "whisker", 44100: "cochlea"}
#: The fastest playback the page may ask for.
MAX_SPEED = 100.0


class _Keep(Sink):
    """Keeps what the node sends, as the page will get it, with each item's time."""

    def __init__(self) -> None:
        self.items: list[tuple[float, dict[str, Any]]] = []
        self.summary_: RunSummary | None = None
        self._lock = threading.Lock()
        self._latest = 0.0          # the latest window's end kept, on common time

    def emit(self, event: WindowEvent) -> None:
        with self._lock:
            self._latest = max(self._latest, float(event.end))
            self.items.append((float(event.end), window_message(event)))

    def event(self, ev: DriverEvent) -> None:
        # An event is stamped on the wall clock, which a replay at full speed does not follow: it is
        # played, and shown, at the recording's time the node had reached when it was said (the latest
        # window's end), beside the windows it came among.
        with self._lock:
            message = {**event_message(ev), "common_time": round(self._latest, 3)}
            self.items.append((self._latest, message))

    def summary(self, summary: RunSummary) -> None:
        self.summary_ = summary


def replay_scene(path: str | Path) -> Any:
    """Return the scene that replays ``path``.

    A recorded graph's ``REC.toml`` as it is, or a session (``NAME``, ``NAME.wav`` or ``NAME.json``) through
    the paper's bank for its rate, no model.
    """
    from supramodal.node.scene.schema import load_scene, scene_from_dict
    from supramodal.replay.session import load_session, session_paths

    p = Path(path)
    if p.suffix.lower() == ".toml":
        return load_scene(str(p))
    wav, sidecar = session_paths(p)
    if not sidecar.exists():
        raise InputError(f"{path}: neither a recording's REC.toml nor a session ({sidecar} is missing); give "
                         "the .toml that supramodal record wrote, or a session NAME.wav with its NAME.json")
    session = load_session(p)
    kind = BANKS_BY_RATE.get(int(session.rate)) if float(session.rate).is_integer() else None
    if kind is None:
        raise InputError(f"{path}: a session at {session.rate:g} Hz has no default bank (whisker: 5000 Hz, cochlea: "
                         "44100 Hz); view it through a scene of yours: supramodal run SCENE --view, with [driver] "
                         f"type = \"replay\" and path = \"{wav}\"")
    return scene_from_dict({"driver": {"type": "replay", "path": str(wav)}, "bank": {"kind": kind},
                            "features": {"names": ["A", "f", "Af"]}, "sink": [{"type": "text"}]}, str(p))


def _health(summary: RunSummary | None) -> dict[str, Any]:
    """Return the page's health message from a run's summary (the recording's totals; None: nothing run)."""
    if summary is None:
        return {"type": "health", "streams": {"main": {"windows": 0, "frames": {}, "latency_ms": None}}, "clocks": {},
                "fusion": None, "sinks": [], "replay": True}
    one = summary.one_stream
    # a one-stream node's stream and clock are the page's "main", as the JSON form has them at the top level
    named = {"main": one} if one is not None else summary.streams
    streams = {name: {"windows": s.windows, "frames": dict(s.frames),
                      "latency_ms": None if s.latency_ms is None else dict(s.latency_ms)} for name, s in named.items()}
    if one is not None:
        clock = summary.clocks.get(one.source)
        clocks = {"main": dict(clock)} if clock else {}
    else:
        clocks = {name: dict(c) for name, c in summary.clocks.items()}
    f = summary.fusion
    fusion = None if f is None else {"windows": f.windows, "paired": f.paired, "alone": f.alone, "late": dict(f.late),
                                     "dropouts": dict(f.dropouts),
                                     "latency_ms": None if f.latency_ms is None else dict(f.latency_ms)}
    return {"type": "health", "streams": streams, "clocks": clocks, "fusion": fusion, "sinks": [], "replay": True}


class ViewReplay:
    """A recording run through the node once, then played to the view's page.

    Parameters
    ----------
    path : str or Path
        A recorded graph's ``REC.toml`` or a session.
    port : int
        The view's port (0: any free one).
    speed : float
        Playback speed at the start (1: the recording's own pace).
    progress : callable, optional
        ``progress(message)`` for start-up lines.
    quiet : bool
        The view prints no URL.
    """

    def __init__(self, path: str | Path, port: int = 0, speed: float = 1.0,
                 progress: Callable[[str], None] | None = None, quiet: bool = False) -> None:
        if not (isinstance(speed, (int, float)) and math.isfinite(speed) and 0 < speed <= MAX_SPEED):
            raise InputError(f"--speed {speed!r}: expected a playback speed > 0 and at most {MAX_SPEED:g}")
        self.scene = replay_scene(path)
        self.path = str(path)
        self.progress = progress
        self.view = ViewSink(port, mode="replay", quiet=quiet, streams=self.scene.window_names)
        self.view.control = self._control
        self._cond = threading.Condition()
        self._paused = False
        self._speed = float(speed)
        self._position = 0.0          # seconds of the recording
        self._restart = False
        self._stopped = threading.Event()
        self.items: list[tuple[float, dict[str, Any]]] = []
        self.summary: RunSummary | None = None
        self.played = 0               # items sent to the page, over every pass

    # -- the page's controls --

    def _control(self, asked: dict[str, Any]) -> dict[str, Any]:
        unknown = sorted(set(asked) - {"paused", "speed", "restart"})
        if unknown:
            raise InputError(f"unknown control(s) {unknown}; the controls are paused, speed and restart")
        paused, speed = asked.get("paused"), asked.get("speed")
        if paused is not None and not isinstance(paused, bool):
            raise InputError(f"paused: expected true or false, got {paused!r}")
        # an int is compared as it is (math.isfinite of a 900-digit int raised OverflowError, unanswered)
        if speed is not None and not (isinstance(speed, (int, float)) and not isinstance(speed, bool)
                                      and (isinstance(speed, int) or math.isfinite(speed))
                                      and 0 < speed <= MAX_SPEED):
            raise InputError(f"speed: expected a number > 0 and at most {MAX_SPEED:g}, got {str(speed)[:40]}")
        with self._cond:
            if paused is not None:
                self._paused = paused
            if speed is not None:
                self._speed = float(speed)
            if asked.get("restart") is True:
                self._restart = True
            self._cond.notify_all()
            return self.state()

    def state(self) -> dict[str, Any]:
        """``{"paused", "speed", "position"}`` (position: seconds of the recording)."""
        return {"paused": self._paused, "speed": self._speed, "position": round(self._position, 3)}

    def stop(self, reason: str = "stop requested") -> None:
        """End :meth:`serve` (thread-safe, also from a signal handler)."""
        self._stopped.set()
        if self._cond.acquire(blocking=False):       # a signal handler never waits for the lock
            try:
                self._cond.notify_all()
            finally:
                self._cond.release()

    # -- running --

    def load(self) -> None:
        """Run the recording through the node at once and keep what it sends."""
        from supramodal.node.scene.build import build_node

        keep = _Keep()
        graph = build_node(replace(self.scene, sinks=[]), speed="max", sinks_override=[keep], progress=self.progress)
        self.summary = graph.run()
        self.items = sorted(keep.items, key=lambda item: item[0])

    def serve(self, on_running: Callable[[], None] | None = None, loop: bool = False) -> None:
        """Load (if not yet), then play to the page until :meth:`stop`.

        At the end of the recording the page keeps what it has (``loop``: it starts again).
        """
        try:
            if self.summary is None:
                self.load()
            self.view.prepare()
            if on_running is not None:
                on_running()
            if self.progress:
                self.progress(f"{self.path}: {len(self.items)} windows and events, "
                              f"{self.items[-1][0] if self.items else 0:.1f} s; Ctrl-C ends the view")
            while not self._stopped.is_set():
                self._play()
                if not loop:
                    with self._cond:
                        while not (self._stopped.is_set() or self._restart):
                            self._cond.wait(0.5)
        finally:
            self.view.close()

    def _play(self) -> None:
        """One pass over the recording, paced by the player's speed, paused while asked."""
        hub = self.view.hub
        hub.reset()
        hub.publish({"type": "reset"}, keep="none")
        with self._cond:
            self._restart = False
            self._position = 0.0
        hub.publish(_health(self.summary), keep="latest")
        wall = time.monotonic()
        for t, message in self.items:
            with self._cond:
                while True:
                    if self._stopped.is_set() or self._restart:
                        return
                    now = time.monotonic()
                    if not self._paused:
                        self._position += (now - wall) * self._speed
                    wall = now
                    if not self._paused and self._position >= t:
                        break
                    wait = 0.1 if self._paused else min(0.1, (t - self._position) / self._speed)
                    self._cond.wait(max(wait, 0.001))
            if message["type"] == "window":
                self.view.emit_message(message)
            else:
                hub.publish(message)
            self.played += 1
        summary = None if self.summary is None else self.summary.to_dict()
        hub.publish({"type": "summary", "summary": summary}, keep="latest")
