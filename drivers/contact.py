"""A robot's own contact signal, read from its bus: when the whiskers or the microphone touch.

The robot often knows when it touches a surface better than the input's level can tell (a
force/torque sensor, a joint's effort, a touch switch). A scene names that signal with
``[decision] contact_from = "BUS:ADDRESS"``:

================  =======================================================================================
``ros2:TOPIC``    a ``std_msgs/msg/Bool`` topic: ``true`` in contact, ``false`` not. Each message is
                  stamped when it arrives (Bool has no header). The subscription follows the publishers'
                  QoS (reliable where every publisher is; transient local, so that the last state is
                  there at once, where every publisher keeps it). Needs the extra ``ros2``.
``lsl:NAME``      an LSL stream of one channel, by its name: strings (a marker stream) from
                  :data:`CONTACT_MARKERS`, or numbers (non-zero: in contact). Each sample is stamped with
                  its LSL timestamp, on this host's clock. Needs the extra ``lsl``.
================  =======================================================================================

A listener only reads: :meth:`ContactListener.poll` returns the states that came, each with its time on
the host's monotonic clock (``time.monotonic()``, seconds); the node puts them on its common time and
assigns windows to contacts (:mod:`supramodal.node.runtime.contacts`). A new bus is one class here
and one line of :data:`CONTACT_BUSES`.

Threading rules
---------------
:meth:`ContactListener.open`, :meth:`~ContactListener.poll` and :meth:`~ContactListener.close` are
called from one thread (the node's contact thread); ``poll`` blocks at most ``timeout`` seconds.
:meth:`~ContactListener.take_events` and :meth:`~ContactListener.stats` may be called from any thread.
"""

from __future__ import annotations

import math
import queue
import time
from typing import Any, ClassVar, Self

from supramodal.drivers.base import DeviceUnavailable, DriverError, DriverEvent, EventLog
from supramodal.errors import InputError

__all__ = ["CONTACT_BUSES", "CONTACT_MARKERS", "ContactListener", "LslContactListener", "Ros2ContactListener",
           "check_contact_from", "contact_listener", "marker_state"]

#: A marker's string (stripped, any case) -> in contact or not.
CONTACT_MARKERS: dict[str, bool] = {
    **dict.fromkeys(("1", "true", "on", "contact", "touch", "down"), True),
    **dict.fromkeys(("0", "false", "off", "release", "lift", "up", "none"), False),
}

#: Seconds between two looks at a ROS 2 topic's publishers before the listener has subscribed.
LOOK_INTERVAL = 0.25
#: Seconds the LSL resolver waits for the contact stream at open.
LSL_RESOLVE_TIMEOUT = 5.0


def marker_state(value: object) -> bool | None:
    """Return the contact state a sample says, or None for no state.

    A sample says a state as a string of :data:`CONTACT_MARKERS`, or as a finite number
    (non-zero: in contact); anything else gives None (refused and counted by the listener).
    """
    if isinstance(value, str):
        return CONTACT_MARKERS.get(value.strip().lower())
    if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
        return value != 0
    return None


def check_contact_from(value: object) -> tuple[str, str]:
    """Return ``(bus, address)`` of a ``contact_from`` value, or raise :class:`InputError` saying what is accepted.

    Checks the text only (no bus is reached).
    """
    from supramodal.drivers.ros2 import check_topic

    buses = ", ".join(f'"{bus}:..."' for bus in CONTACT_BUSES)
    if not isinstance(value, str) or ":" not in value:
        raise InputError(f"contact_from must be BUS:ADDRESS ({buses}, e.g. \"ros2:/robot/in_contact\"), "
                         f"got {value!r}")
    bus, address = value.split(":", 1)
    if bus not in CONTACT_BUSES:
        raise InputError(f"contact_from {value!r}: no bus {bus!r}; the buses are {buses}")
    if bus == "ros2" and not check_topic(address):
        raise InputError(f"contact_from {value!r}: {address!r} is no ROS 2 topic name (/-separated tokens of "
                         "letters, digits and _, e.g. /robot/in_contact)")
    if bus == "lsl" and (not address or "'" in address or address != address.strip()):
        raise InputError(f"contact_from {value!r}: an LSL stream's name, non-empty, without quotes or "
                         "surrounding spaces")
    return bus, address


def contact_listener(value: str) -> ContactListener:
    """Return the listener of a ``contact_from`` value (:func:`check_contact_from`); nothing is opened yet."""
    bus, address = check_contact_from(value)
    return CONTACT_BUSES[bus](address)


class ContactListener:
    """The states of one contact signal, as they come (see the module notes).

    Parameters
    ----------
    address : str
        The bus's name of the signal (a topic, a stream's name).
    """

    #: The bus, as ``contact_from`` names it.
    bus: ClassVar[str] = ""

    def __init__(self, address: str) -> None:
        self.address = address
        self.event_log = EventLog()
        self.messages = 0               # states that came, refused ones included
        self.refused = 0                # samples that said no state (counted, said)
        #: True from the end of :meth:`open` (a resolve, a subscription) to :meth:`close`.
        self.listening = False

    @property
    def name(self) -> str:
        """The ``contact_from`` value: ``BUS:ADDRESS``."""
        return f"{self.bus}:{self.address}"

    def open(self) -> None:
        """Reach the bus (may block: a resolve)."""

    def close(self) -> None:
        """Leave the bus (idempotent)."""

    def poll(self, timeout: float) -> list[tuple[float, bool]]:
        """Return the states that came, ``(time on time.monotonic(), in contact)``.

        Waits at most ``timeout`` seconds for the first.
        """
        raise NotImplementedError

    def take_events(self) -> tuple[list[DriverEvent], dict[str, int]]:
        """Return the new events and the counts dropped (:meth:`EventLog.take`)."""
        return self.event_log.take()

    def stats(self) -> dict[str, int]:
        """``messages`` and ``refused``."""
        return {"messages": self.messages, "refused": self.refused}

    def _refuse(self, value: object) -> None:
        self.refused += 1
        self.event_log.record("contact", f"contact: {self.name} said {value!r}, which is no contact state "
                                         f"(markers: {sorted(CONTACT_MARKERS)}, or a number); left out")

    def __enter__(self) -> Self:
        self.open()
        self.listening = True
        return self

    def __exit__(self, *exc: object) -> None:
        self.listening = False
        self.close()


class Ros2ContactListener(ContactListener):
    """A ``std_msgs/msg/Bool`` topic (see the module notes).

    It runs its own rclpy node, named ``supramodal_contact``
    (``-r supramodal_contact:__node:=...`` renames it).
    """

    bus = "ros2"
    TYPE = "std_msgs/msg/Bool"
    NODE_NAME = "supramodal_contact"

    def __init__(self, address: str) -> None:
        from supramodal.drivers.ros2 import import_rclpy

        import_rclpy()                  # no rclpy: said at build, not at start
        super().__init__(address)
        self._ros: Any = None
        self._sub: Any = None
        self._inbox: queue.SimpleQueue[tuple[float, bool]] = queue.SimpleQueue()
        self._looked = -math.inf

    def open(self) -> None:
        """Start the listener's ROS 2 node; the topic is subscribed to once a publisher advertises it."""
        from supramodal.drivers.ros2 import RosNode

        self._ros = RosNode(self.NODE_NAME)
        self._ros.start()
        self._looked = -math.inf

    def close(self) -> None:
        """Close the ROS 2 node and its subscription (idempotent)."""
        ros, self._ros, self._sub = self._ros, None, None
        if ros is not None:
            ros.close()

    def poll(self, timeout: float) -> list[tuple[float, bool]]:
        """Return the states queued since the last call, waiting at most ``timeout`` seconds for the first.

        Until subscribed, looks for the topic's publishers every :data:`LOOK_INTERVAL` seconds and
        subscribes once one advertises it (a topic of another type is refused). Each state is
        ``(time.monotonic() at arrival, in contact)``.
        """
        if self._sub is None and time.monotonic() - self._looked >= LOOK_INTERVAL:
            self._looked = time.monotonic()
            self._subscribe_when_published()
        out = []
        try:
            out.append(self._inbox.get(timeout=max(0.0, timeout)))
            while True:
                out.append(self._inbox.get_nowait())
        except queue.Empty:
            pass
        return out

    def _subscribe_when_published(self) -> None:
        """Subscribe once the topic has publishers, with QoS they all offer; refuse another type."""
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
        from std_msgs.msg import Bool

        node = self._ros.node
        full = node.resolve_topic_name(self.address)
        publishers = node.get_publishers_info_by_topic(full)
        if not publishers:
            return
        types = sorted({p.topic_type for p in publishers})
        if types != [self.TYPE]:
            raise DriverError(f"ROS 2: contact_from {self.name}: the topic carries {types}; contacts are read from "
                              f"{self.TYPE} (true: in contact)")
        reliable = all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in publishers)
        latched = all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in publishers)
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                         reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)
        self._sub = node.create_subscription(Bool, full, self._on_message, qos)

    def _on_message(self, msg: Any) -> None:
        # the executor's thread: a put on a queue, nothing more
        self.messages += 1
        self._inbox.put((time.monotonic(), bool(msg.data)))


class LslContactListener(ContactListener):
    """An LSL stream of one channel, by name (see the module notes)."""

    bus = "lsl"

    def __init__(self, address: str) -> None:
        from supramodal.drivers.lsl import import_pylsl

        self._pylsl = import_pylsl()    # no pylsl: said at build, not at start
        super().__init__(address)
        self._inlet: Any = None
        self._offset = 0.0

    def open(self) -> None:
        """Resolve the stream by name, open an inlet to it and measure the clock offset.

        Waits up to :data:`LSL_RESOLVE_TIMEOUT` seconds for each step; a stream of more than one
        channel, or one that cannot be opened, raises :class:`DeviceUnavailable`.
        """
        from supramodal.drivers.lsl import describe_stream, lsl_clock_offset, resolve_stream

        pylsl = self._pylsl
        info = resolve_stream(name=self.address, timeout=LSL_RESOLVE_TIMEOUT)
        if info.channel_count() != 1:
            raise DeviceUnavailable(f"LSL: contact_from {self.name}: the stream has {info.channel_count()} "
                                    f"channels ({describe_stream(info)}); contacts come from one channel")
        try:
            self._inlet = pylsl.StreamInlet(info, max_buflen=60, recover=True, processing_flags=pylsl.proc_clocksync)
            self._inlet.open_stream(timeout=LSL_RESOLVE_TIMEOUT)
            # The first clock-synced sample waits for the first time correction (0.6 s measured here): an
            # edge that late falls in the wrong windows. Take it now, before time starts.
            self._inlet.time_correction(timeout=LSL_RESOLVE_TIMEOUT)
        except Exception as exc:   # liblsl's errors, one place
            self._inlet = None
            raise DeviceUnavailable(f"LSL: contact_from {self.name}: cannot open the stream: {exc}") from None
        self._offset = lsl_clock_offset(pylsl)

    def close(self) -> None:
        """Close the inlet (idempotent)."""
        inlet, self._inlet = self._inlet, None
        if inlet is not None:
            try:
                inlet.close_stream()
            except Exception:  # closing: nothing left to tell
                pass

    def poll(self, timeout: float) -> list[tuple[float, bool]]:
        """Return the states that came, waiting at most ``timeout`` seconds for the first.

        Each state is ``(sender's stamp on this host's time.monotonic(), in contact)``. A sample
        that says no state is refused and counted; a lost sender is recorded as ``unplug``.
        """
        out: list[tuple[float, bool]] = []
        wait = max(0.0, timeout)
        while True:
            try:
                sample, stamp = self._inlet.pull_sample(timeout=wait)
            except Exception as exc:   # a lost sender without a source id: silent until it is back
                self.event_log.record("unplug", f"LSL: contact_from {self.name}: {exc}")
                time.sleep(wait)
                return out
            if sample is None:
                return out
            wait = 0.0
            self.messages += 1
            state = marker_state(sample[0])
            if state is None:
                self._refuse(sample[0])
            else:
                out.append((stamp + self._offset, state))


#: ``contact_from``'s buses -> their listener.
CONTACT_BUSES: dict[str, type[ContactListener]] = {"ros2": Ros2ContactListener, "lsl": LslContactListener}
