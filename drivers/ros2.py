"""ROS 2, as the node meets it.

rclpy imported from wherever it is, one rclpy node on a context of its own, ROS names checked
before anything starts, and the command line's ``--ros-args``.

Needs the optional extra ``ros2`` (rclpy and the stock message packages as wheels) or a sourced ROS 2
installation (``source /opt/ros/<distro>/setup.bash``): rclpy is imported from wherever Python finds
it, so the robot's own ROS 2 is used as it is. :func:`import_rclpy` says what to install when it is
missing.

The node's ROS 2 parts (the ``ros2`` sink, the ``ros2`` driver) each run a :class:`RosNode`: an rclpy node on a
``rclpy.Context`` of its own, spun by an executor on a thread of its own, so that a program that
uses rclpy itself (a launch file's other nodes, a test's subscriber) is not touched, and so that
rclpy installs no signal handler: SIGINT and SIGTERM stay the node's (a clean stop with a summary).

ROS arguments
-------------
``supramodal run SCENE --ros-args -r __ns:=/robot -p use_sim_time:=true`` works as for any ROS 2
node: :func:`split_ros_arguments` takes the ``--ros-args ... [--]`` sections off the command line
before the command's own options are read, and :func:`use_ros_arguments` keeps them for every
:class:`RosNode` of the process (ROS 2's *global* arguments: remappings, parameters, log level), so
that a launch file can start the node as a process and remap it.

The sensor topic as a driver
----------------------------
:class:`Ros2TopicDriver` subscribes to a topic of samples x channels: ``std_msgs/Float32MultiArray``,
``Float64MultiArray`` or ``Int16MultiArray`` (``layout.dim`` ``[samples, channels]``, or none), or the
stamped form, ``sensor_msgs/Image`` (``height`` samples by ``width`` channels, ``encoding`` ``32FC1``,
``64FC1`` or ``16SC1``, ``header.stamp`` the time of the block's last sample on the publisher's
sample clock). Each message is a block. Its time for the node's clock model is the header's stamp, put
on this host's monotonic clock by an offset measured at open, else the message's arrival. Gaps are
judged on the sample clock as for an LSL inlet (:class:`~supramodal.drivers.timestamps.ClockSteps`): a
publisher that died and came back leaves samples missing, filled with zeros (exactly, with stamps on
its sample clock; to the arrival jitter without); one stalled that then flushes its backlog leaves
none, and nothing is filled. A topic silent for ``stall_timeout`` is said (``unplug``; ``waiting``
before its first message), and so is its return (``reconnect``). The topic's type is read from the
ROS graph (``message = "auto"``) or checked against it; a message of another layout is refused and
counted, a non-finite value set to 0 and counted, and the samples' rate checked after
:data:`RATE_CHECK_SECONDS` against the scene's. The subscription's callback runs on the driver's
node's executor thread and queues the samples (``queue_seconds``; beyond, a message is dropped and
counted); :meth:`Ros2TopicDriver.read` takes them on the node's source thread.

Threading rules: a :class:`RosNode` is made and closed on one thread; its executor runs timers and
subscriptions on its own thread; publishing is safe from any thread (rmw's publish is thread-safe).
"""

from __future__ import annotations

import collections
import math
import os
import re
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from supramodal.checks import REQUIRED, Key, integer, one_of, positive
from supramodal.drivers.base import Block, DeviceUnavailable, DriverBase, DriverClosed, DriverError
from supramodal.drivers.spec import BuildContext, Built, DriverSpec, OptionError, given
from supramodal.drivers.timestamps import ClockSteps, StampedBlocks, Step
from supramodal.errors import InputError
from supramodal.interrupts import held_interrupts

__all__ = ["INSTALL_HINT", "Ros2Unavailable", "RosNode", "check_namespace", "check_node_name", "check_shared_memory",
           "check_token", "import_rclpy", "ros_arguments", "split_ros_arguments", "stale_port_segments",
           "use_ros_arguments"]

INSTALL_HINT = ('install the optional extra: pip install "supramodal[ros2]" (rclpy and the stock messages as '
                "wheels, no ROS installation needed), or source your ROS 2 installation "
                "(source /opt/ros/<distro>/setup.bash) before starting the node")

#: Seconds a closing node waits for its executor thread.
CLOSE_TIMEOUT = 2.0

_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


class Ros2Unavailable(DeviceUnavailable):
    """rclpy (or a stock message package the node needs) cannot be imported on this machine."""


def import_rclpy() -> ModuleType:
    """Return the rclpy module, with the stock message packages the node uses.

    Raises :class:`Ros2Unavailable` saying what to install.
    """
    try:
        with held_interrupts():         # a Ctrl-C inside a C extension's import reads as ImportError
            import diagnostic_msgs.msg  # noqa: F401  (the messages are checked here, once, with their fix)
            import rclpy
            import sensor_msgs.msg  # noqa: F401
            import std_msgs.msg  # noqa: F401
    except ImportError as exc:
        raise Ros2Unavailable(f"ROS 2 needs {exc.name or 'rclpy'}, which is not installed: {INSTALL_HINT}") from None
    except (OSError, RuntimeError) as exc:
        # rclpy is there but a native library of it is not (a wheel for another Python, a half-sourced ROS)
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise Ros2Unavailable(f"rclpy is installed but cannot load ({first}): {INSTALL_HINT}") from None
    module: ModuleType = rclpy      # a module, untyped (Any) to mypy
    return module


# -- names ----------------------------------------------------------------------------------------------

def check_token(value: object) -> bool:
    """Whether ``value`` is one token of a ROS name.

    A token is a letter or ``_``, then letters, digits and ``_``, no ``__`` (ROS 2's rule;
    e.g. a stream's name, which becomes a topic's part).
    """
    return isinstance(value, str) and bool(_TOKEN.fullmatch(value)) and "__" not in value


def check_node_name(value: object) -> bool:
    """Whether ``value`` may name a ROS 2 node (one token)."""
    return check_token(value)


def check_namespace(value: object) -> bool:
    """Whether ``value`` may be a node's namespace.

    A namespace is ``""`` (the root, or what ``-r __ns:=`` says) or ``/``-separated tokens,
    e.g. ``"/robot/left_arm"`` (a leading ``/`` is added if missing).
    """
    if not isinstance(value, str):
        return False
    if value in ("", "/"):
        return True
    parts = value.removeprefix("/").split("/")   # a trailing "/" leaves an empty part: refused
    return all(check_token(p) for p in parts)


# -- the command line's ROS arguments --------------------------------------------------------------------

_ros_arguments: list[str] = []


def split_ros_arguments(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """Split ``argv`` into the command's own arguments and ROS 2's.

    ROS 2's are every ``--ros-args`` section, up to a ``--`` that ends it or the end (as
    rclpy's ``remove_ros_args`` does, without rclpy).

    Returns
    -------
    own : list of str
    ros : list of str
        Each section with its ``--ros-args`` flag, ready for ``rclpy.init(args=...)``.
    """
    own: list[str] = []
    ros: list[str] = []
    inside = False
    for arg in argv:
        if arg == "--ros-args":
            inside = True
            ros.append(arg)
        elif inside and arg == "--":
            inside = False
        elif inside:
            ros.append(arg)
        else:
            own.append(arg)
    return own, ros


def use_ros_arguments(ros: Sequence[str]) -> None:
    """Keep ``ros`` (``--ros-args`` sections) as the global ROS arguments of every later :class:`RosNode`.

    They apply to every one made after this call in this process (the command line sets them).
    """
    global _ros_arguments
    _ros_arguments = list(ros)


def ros_arguments() -> list[str]:
    """Return the global ROS arguments :func:`use_ros_arguments` kept (empty by default)."""
    return list(_ros_arguments)


# -- a node of the node's own -----------------------------------------------------------------------------

#: Where Fast DDS (ROS 2's default middleware) keeps its shared-memory segments.
SHARED_MEMORY_DIR = Path("/dev/shm")
#: Seconds after which an empty Fast DDS port segment is a dead process's: its maker sizes it at once.
STALE_SEGMENT_SECONDS = 5.0
_PORT_SEGMENT = re.compile(r"fastdds_port\d+")


def stale_port_segments(folder: Path | None = None, now: float | None = None) -> list[Path]:
    """Fast DDS shared-memory port segments left empty by a process killed while it made them.

    Fast DDS makes a port's segment (``/dev/shm/fastdds_portN``) as a file and sizes it at once; a
    process killed between the two leaves it empty, and every later ROS 2 participant that opens the
    port waits for it to be sized, for ever, in native code that no signal interrupts (seen here:
    a test run hung in ``rclpy.create_node``). An empty port segment older than
    :data:`STALE_SEGMENT_SECONDS` is such a one.

    Parameters
    ----------
    folder : Path, optional
        Where the segments are (default :data:`SHARED_MEMORY_DIR`; absent: none).
    now : float, optional
        The time, s since the epoch (default: now).

    Returns
    -------
    list of Path
        The stale segments, sorted; removing them is safe (no process can use an empty segment).
    """
    now = time.time() if now is None else now
    out = []
    try:
        names = sorted((SHARED_MEMORY_DIR if folder is None else folder).iterdir())
    except OSError:
        return []
    for path in names:
        if not _PORT_SEGMENT.fullmatch(path.name):
            continue
        try:
            st = path.stat()
        except OSError:            # gone meanwhile
            continue
        if st.st_size == 0 and now - st.st_mtime > STALE_SEGMENT_SECONDS:
            out.append(path)
    return out


def check_shared_memory() -> None:
    """Refuse to start a ROS 2 node that would hang on a stale Fast DDS segment, saying what to remove.

    The segments are those of :func:`stale_port_segments`; nothing to check under another
    middleware (``RMW_IMPLEMENTATION``).
    """
    if not os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp").startswith("rmw_fastrtps"):
        return
    stale = stale_port_segments()
    if stale:
        paths = " ".join(str(p) for p in stale)
        raise Ros2Unavailable(f"ROS 2 may hang on start: Fast DDS's shared-memory segment(s) {paths} were left "
                              "empty by a process killed while making them, and a ROS 2 node that opens one waits "
                              f"on it for ever; remove them (rm {paths}: no process can use an empty segment) and "
                              "start again")


class RosNode:
    """An rclpy node on a context of its own, spun on a thread of its own.

    Parameters
    ----------
    name : str
        The node's name (:func:`check_node_name`); ``-r __node:=`` on the command line renames it.
    namespace : str
        Default ``""``: the root, or what ``-r __ns:=`` says.

    Raises
    ------
    Ros2Unavailable
        No rclpy here, or a stale Fast DDS segment that would hang it (:func:`check_shared_memory`).
    InputError
        rclpy refused the name, the namespace or the ROS arguments (its reason in the message).

    Use :meth:`start` to spin it (timers, subscriptions, parameter services, ``/clock`` under
    ``use_sim_time``) and :meth:`close` once, last.
    """

    def __init__(self, name: str, namespace: str = "") -> None:
        rclpy = import_rclpy()
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        check_shared_memory()
        self.context = rclpy.Context()
        try:
            rclpy.init(args=["supramodal", *ros_arguments()], context=self.context,
                       signal_handler_options=SignalHandlerOptions.NO)
        except Exception as exc:   # rcl's own errors (a malformed remapping) are no SupramodalError
            raise InputError(f"ROS 2 refused the arguments {ros_arguments()}: {exc}") from None
        try:
            self.node: Any = rclpy.create_node(name, namespace=namespace or None, context=self.context)
        except Exception as exc:
            self.context.try_shutdown()
            raise InputError(f"ROS 2 refused node name {name!r} in namespace {namespace!r}: {exc}") from None
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, name=f"ros2-{name}", daemon=True)
        self._closed = False

    @property
    def name(self) -> str:
        """The node's fully qualified name (``/robot/supramodal``), after any remapping."""
        name: str = self.node.get_fully_qualified_name()
        return name

    def start(self) -> None:
        """Spin the node's executor on its thread (idempotent)."""
        if not self._thread.is_alive() and not self._closed:
            self._thread.start()

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            self.executor.spin()
        except ExternalShutdownException:
            pass

    def close(self) -> None:
        """Stop spinning, destroy the node and shut its context down (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self.executor.shutdown(timeout_sec=CLOSE_TIMEOUT)
        self.node.destroy_node()
        self.context.try_shutdown()
        if self._thread.is_alive():
            self._thread.join(CLOSE_TIMEOUT)


# -- common time on the ROS clock ---------------------------------------------------------------------------

class RosClock:
    """The node's common time on a ROS node's clock, in integer nanoseconds.

    Parameters
    ----------
    clock : rclpy.clock.Clock
        The ROS node's clock (``node.get_clock()``): system time, or the ``/clock`` topic where
        the node runs with ``use_sim_time`` (a bag played with ``--clock``).
    epoch : float
        The graph's start on ``time.monotonic()``: common time 0.

    On system time the offset between the host's monotonic clock and the ROS clock is measured
    once, here (the tightest of a few brackets, as for LSL): every window of a run is then mapped by
    the same line. On simulated time no such line exists (the bag's clock may pause, jump or run at
    another rate): a window is stamped with the ROS clock's *now* less the window's age on the
    host's clock.
    """

    def __init__(self, clock: Any, epoch: float) -> None:
        self._clock = clock
        self.epoch = epoch
        best = (math.inf, 0)
        for _ in range(9):
            a = time.monotonic_ns()
            ros = int(clock.now().nanoseconds)
            b = time.monotonic_ns()
            best = min(best, (b - a, (a + b) // 2 - ros))
        #: ``monotonic - ROS`` time, ns (meaningful on system time).
        self.offset_ns = best[1]

    @property
    def simulated(self) -> bool:
        """Whether the ROS clock follows ``/clock`` (``use_sim_time``)."""
        return bool(getattr(self._clock, "ros_time_is_active", False))

    def stamp_ns(self, common: float) -> int:
        """Return a time on the node's common clock, seconds, as nanoseconds on the ROS clock."""
        host_ns = round((self.epoch + common) * 1e9)
        if self.simulated:
            return int(self._clock.now().nanoseconds) - (time.monotonic_ns() - host_ns)
        return host_ns - self.offset_ns


# -- the robot's sensor topic as a driver ---------------------------------------------------------------

def check_topic(value: object) -> bool:
    """Whether ``value`` may name a topic.

    A topic is ``/``-separated tokens, absolute (``/robot/whiskers``) or relative to the node's
    namespace (``whiskers``).
    """
    return isinstance(value, str) and value not in ("", "/") and check_namespace(value) and not value.endswith("/")


#: The message types the driver reads (ROS's full names) -> (module, class, numpy dtype, full scale).
#: ``sensor_msgs/msg/Image`` is the stamped form: ``header.stamp`` the time of the block's last sample,
#: ``height`` samples by ``width`` channels, ``encoding`` ``32FC1``, ``64FC1`` or ``16SC1``.
MESSAGES: dict[str, tuple[str, str]] = {
    "std_msgs/msg/Float32MultiArray": ("std_msgs.msg", "Float32MultiArray"),
    "std_msgs/msg/Float64MultiArray": ("std_msgs.msg", "Float64MultiArray"),
    "std_msgs/msg/Int16MultiArray": ("std_msgs.msg", "Int16MultiArray"),
    "sensor_msgs/msg/Image": ("sensor_msgs.msg", "Image"),
}
_ARRAY_DTYPES = {"std_msgs/msg/Float32MultiArray": (np.float32, 1.0),
                 "std_msgs/msg/Float64MultiArray": (np.float64, 1.0),
                 "std_msgs/msg/Int16MultiArray": (np.int16, 2.0 ** 15)}
_IMAGE_ENCODINGS = {"32FC1": (np.float32, 1.0), "64FC1": (np.float64, 1.0), "16SC1": (np.int16, 2.0 ** 15)}


def samples_of(kind: str, msg: Any, channels: int) -> tuple[np.ndarray | None, str]:
    """Return one message's samples, shape (samples, channels), float64 at full scale +-1.

    Or None and why it is refused (the reason names the layout the driver reads).

    A ``*MultiArray`` holds samples x channels row by row: ``layout.dim`` either two dimensions
    (``[samples, channels]``; ``data_offset`` honoured) or none (the data's length a multiple of
    ``channels``). An ``Image`` holds ``height`` samples of ``width`` channels (``encoding``
    ``32FC1``, ``64FC1``, ``16SC1``; ``is_bigendian`` honoured; rows of ``step`` bytes).
    """
    if kind == "sensor_msgs/msg/Image":
        if msg.encoding not in _IMAGE_ENCODINGS:
            return None, (f"encoding {msg.encoding!r}; the driver reads {sorted(_IMAGE_ENCODINGS)} (height: samples, "
                          "width: channels)")
        dtype, scale = _IMAGE_ENCODINGS[msg.encoding]
        item = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
        if msg.width != channels:
            return None, f"{msg.width} channels (width), not the {channels} the scene reads"
        if msg.step < msg.width * item.itemsize or len(msg.data) < msg.height * msg.step:
            return None, f"{len(msg.data)} bytes for {msg.height} rows of step {msg.step}: a truncated image"
        rows = np.frombuffer(bytes(msg.data), dtype=np.uint8)[:msg.height * msg.step].reshape(msg.height, msg.step)
        data = rows[:, :msg.width * item.itemsize].copy().view(item).reshape(msg.height, msg.width)
    else:
        dtype, scale = _ARRAY_DTYPES[kind]
        flat = np.frombuffer(msg.data, dtype=dtype) if len(msg.data) else np.zeros(0, dtype)
        dims = msg.layout.dim
        if len(dims) == 2:
            n, c = int(dims[0].size), int(dims[1].size)
            if c != channels:
                return None, f"{c} channels (layout.dim[1]), not the {channels} the scene reads"
            flat = flat[msg.layout.data_offset:]
            if len(flat) < n * c:
                return None, f"{len(flat)} values for a layout of {n} samples x {c} channels: a truncated message"
            data = flat[:n * c].reshape(n, c)
        elif not dims:
            if len(flat) % channels:
                return None, (f"{len(flat)} values, not a whole number of samples of {channels} channels (give "
                              "layout.dim [samples, channels])")
            data = flat.reshape(-1, channels)
        else:
            return None, f"a layout of {len(dims)} dimensions; the driver reads [samples, channels] (or none)"
    if data.shape[0] == 0:
        return None, "no sample"
    out = data.astype(np.float64)
    if scale != 1.0:
        out /= scale
    return out, ""


class Ros2TopicDriver(DriverBase):
    """Samples of a ROS 2 topic, as blocks: the robot's sensor driver publishes, the node subscribes.

    Parameters
    ----------
    topic : str
        The topic (:func:`check_topic`; relative names are in ``namespace``).
    rate : float
        The samples' rate, Hz (the bank's): checked against what arrives.
    channels : int
        Channels per sample: a message of another layout is refused, counted and said (``channels``).
    message : str
        ``"auto"`` (default: the type the topic's publishers advertise) or one of :data:`MESSAGES`; a
        topic of another type is refused, naming both.
    reliability : {"reliable", "best_effort"}
        The subscription's (default reliable: nothing lost between the publisher and the node; a
        best-effort publisher, e.g. one with ROS's sensor-data QoS, needs ``"best_effort"``, and the
        driver says so).
    node_name, namespace : str
        The driver's ROS 2 node: default ``supramodal_`` and the topic's tokens (``/robot/whiskers``:
        ``supramodal_robot_whiskers``), in the root.
    gap_tolerance, max_gap, stall_timeout, queue_seconds, rate_tolerance : float
        Seconds (the last a fraction); see the module notes.
    block : int or None
        Samples per message the publisher is said to send (the scene's ``block``): a message of another
        size is kept (nothing is lost) but counted (``odd_blocks``) and said (``block``), since the node's
        latency and the windows' timing follow the publisher's blocks. None (default): any size.

    Events (:meth:`take_events`): ``waiting`` (no first message yet, after ``stall_timeout``),
    ``unplug`` (no message for ``stall_timeout`` after the first), ``reconnect``, ``gap`` (samples
    filled), ``restart``, ``backlog``, ``channels`` (a message refused), ``nan`` (non-finite samples
    set to 0), ``overflow`` (the queue was full), ``block`` (a message of another size than ``block``).
    """

    def __init__(self, topic: str, rate: float, channels: int, *, message: str = "auto",
                 reliability: str = "reliable", node_name: str | None = None, namespace: str = "",
                 gap_tolerance: float = 0.05, max_gap: float = 10.0, stall_timeout: float = 0.5,
                 queue_seconds: float = 30.0, rate_tolerance: float = 0.05, block: int | None = None) -> None:
        if not check_topic(topic):
            raise InputError(f"topic {topic!r} is not a ROS topic name (tokens of letters, digits and '_' "
                             "separated by '/')")
        if message != "auto" and message not in MESSAGES:
            raise InputError(f"message {message!r}: expected \"auto\" or one of {sorted(MESSAGES)}")
        if reliability not in ("reliable", "best_effort"):
            raise InputError(f"reliability {reliability!r}: expected \"reliable\" or \"best_effort\"")
        for key, v in (("rate", rate), ("gap_tolerance", gap_tolerance), ("max_gap", max_gap),
                       ("stall_timeout", stall_timeout), ("queue_seconds", queue_seconds),
                       ("rate_tolerance", rate_tolerance)):
            if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0):
                raise InputError(f"{key} must be a positive number, got {v!r}")
        if isinstance(channels, bool) or not isinstance(channels, int) or channels < 1:
            raise InputError(f"channels must be a positive integer, got {channels!r}")
        if block is not None and (isinstance(block, bool) or not isinstance(block, int) or block < 1):
            raise InputError(f"block must be a positive integer (samples per message), got {block!r}")
        self.block = block
        self.topic, self.rate, self.channels = topic, float(rate), int(channels)
        self.message, self.reliability = message, reliability
        # one node per topic read: two sources of a scene (and a ros2 sink) never share a node's name
        self.node_name = node_name or "supramodal_" + "_".join(t for t in topic.split("/") if t)
        self.namespace = namespace
        self.gap_tolerance, self.max_gap = float(gap_tolerance), float(max_gap)
        self.stall_timeout = float(stall_timeout)
        self.queue_seconds, self.rate_tolerance = float(queue_seconds), float(rate_tolerance)
        import_rclpy()          # says what to install, when the scene is built
        self._ros: RosNode | None = None
        self._sub: Any = None
        self._kind: str | None = None
        self._lock = threading.Lock()
        self._arrived = threading.Event()
        super().__init__()
        self._reset()

    @property
    def info(self) -> str:
        """The topic, as messages name it."""
        full = self._sub.topic_name if self._sub is not None else self.topic
        return f"ROS 2 topic {full}" + (f" ({self._kind})" if self._kind else "")

    def _reset(self) -> None:
        self._inbox: collections.deque[tuple[np.ndarray, float | None, float]] = collections.deque()
        self._queued = 0
        self._messages = self._stalls = 0
        self._refused = self._nan = self._dropped_messages = self._dropped_samples = 0
        self._incompatible = False                              # a publisher's QoS the subscription cannot meet
        self._odd_blocks = 0                                    # messages of another size than `block`
        self._steps = ClockSteps(self.rate, self.gap_tolerance, self.max_gap)
        self._blocks = StampedBlocks(self.channels, lambda: f"ROS 2: {self.info}", "publisher", self.max_gap,
                                     self._record)
        self._held: collections.deque[tuple[np.ndarray, float, float]] = collections.deque()
        self._ready: collections.deque[Block] = collections.deque()
        self._last_data = time.monotonic()
        self._stalled = False
        self._next_look = 0.0
        self._rate_since: tuple[int, float] | None = None       # (frame, stamp) the rate is measured from
        self._rate_checked = False

    # -- life cycle -----------------------------------------------------------------------------------

    def open(self) -> None:
        """Start the driver's ROS 2 node; the subscription is made as soon as the topic's type is known.

        That is at once with ``message`` given, else when a publisher advertises it.
        """
        self._reset()
        self.event_log.clear()
        self._ros = RosNode(self.node_name, self.namespace)
        self._ros.start()
        self._clock = RosClock(self._ros.node.get_clock(), 0.0)   # ROS time -> monotonic, measured once
        if self.message != "auto":
            self._subscribe(self.message)
        self._last_data = time.monotonic()

    def close(self) -> None:
        ros, self._ros, self._sub = self._ros, None, None
        if ros is not None:
            ros.close()

    def _subscribe(self, kind: str) -> None:
        """Subscribe with the type ``kind``, on the node's executor thread from then on."""
        import importlib

        from rclpy.event_handler import SubscriptionEventCallbacks
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

        assert self._ros is not None, "open() first"
        module, name = MESSAGES[kind]
        msg_type = getattr(importlib.import_module(module), name)
        qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, durability=DurabilityPolicy.VOLATILE,
                         reliability=ReliabilityPolicy.RELIABLE if self.reliability == "reliable"
                         else ReliabilityPolicy.BEST_EFFORT)
        self._kind = kind
        events = SubscriptionEventCallbacks(incompatible_qos=self._on_incompatible_qos)
        self._sub = self._ros.node.create_subscription(msg_type, self.topic, self._on_message, qos,
                                                       event_callbacks=events)

    def _on_incompatible_qos(self, info: Any) -> None:
        self._incompatible = True

    def _on_message(self, msg: Any) -> None:
        """Queue one message's samples for :meth:`read`, or refuse and count it (the executor's thread).

        Never blocks but on a short lock.
        """
        now = time.monotonic()
        assert self._kind is not None
        data, why = samples_of(self._kind, msg, self.channels)
        stamp = None
        if data is not None and self._kind == "sensor_msgs/msg/Image":
            ros_ns = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
            stamp = (ros_ns + self._clock.offset_ns) / 1e9          # on this host's monotonic clock
        if data is not None and self.block is not None and data.shape[0] != self.block:
            with self._lock:
                self._odd_blocks += 1
            self._record("block", f"ROS 2: a message of {self.info} holds {data.shape[0]} samples, not the "
                                  f"{self.block} the scene says (block); kept. Set block to the publisher's, or "
                                  "leave it out", self._blocks.frames)
        if data is not None and not np.isfinite(data).all():
            bad = ~np.isfinite(data)
            data[bad] = 0.0
            with self._lock:
                self._nan += int(np.count_nonzero(bad))
            self._record("nan", f"ROS 2: {int(np.count_nonzero(bad))} non-finite values from {self.info} set to 0; "
                                "check the publisher", self._blocks.frames)
        with self._lock:
            if data is None:
                self._refused += 1
            elif self._queued + data.shape[0] > self.queue_seconds * self.rate:
                self._dropped_messages += 1
                self._dropped_samples += data.shape[0]
            else:
                self._inbox.append((data, stamp, now))
                self._queued += data.shape[0]
                data = None
                why = ""
        if why:
            self._record("channels", f"ROS 2: a message of {self.info} refused: {why}", self._blocks.frames)
        elif data is not None:
            self._record("overflow", f"ROS 2: {data.shape[0]} samples of {self.info} dropped: the node is "
                                     f"{self.queue_seconds:g} s behind", self._blocks.frames)
        self._arrived.set()

    # -- reading (the source thread) -----------------------------------------------------------------

    def read(self, timeout: float | None = None) -> Block | None:
        """Return the next message's samples as a block, with any gap before them filled or marked.

        Waits at most ``timeout`` s; None if none came.
        """
        if self._ready:
            return self._ready.popleft()
        if self._ros is None:
            raise DriverClosed("the ROS 2 driver is closed")
        with self._lock:
            item = self._inbox.popleft() if self._inbox else None
            if item is not None:
                self._queued -= item[0].shape[0]
            else:
                self._arrived.clear()
        if item is None:
            self._arrived.wait(0.0 if timeout is None else max(0.0, float(timeout)))
            with self._lock:
                item = self._inbox.popleft() if self._inbox else None
                if item is not None:
                    self._queued -= item[0].shape[0]
        now = time.monotonic()
        if item is None:
            return self._silent(now)
        data, stamp, arrival = item
        if self._stalled:
            self._stalled = False
            if self._messages:
                self._record("reconnect", f"ROS 2: messages from {self.info} again after "
                                          f"{now - self._last_data:.2f} s", self._blocks.frames)
        self._last_data = now
        self._messages += 1
        last = arrival if stamp is None else stamp
        n = data.shape[0]
        self._held.append((data, last, arrival))
        self._judged(self._steps.add(n, last - (n - 1) / self.rate, last))
        return self._ready.popleft() if self._ready else None

    def _silent(self, now: float) -> Block | None:
        """Handle a read that found no message.

        Judge what is held once the topic is silent, say it is (``unplug``), and look for the
        topic's type (``message = "auto"``), a type that does not match, or a QoS that cannot.
        """
        if self._incompatible:
            raise DriverError(f"ROS 2: the publisher of {self.info} offers a QoS the {self.reliability} subscription "
                              "cannot match (a best-effort publisher, e.g. sensor-data QoS): set reliability = "
                              "\"best_effort\" in the scene")
        if self._held and now - self._last_data > self.stall_timeout:
            self._judged(self._steps.flush())
            return self._ready.popleft() if self._ready else None
        if now >= self._next_look:
            self._next_look = now + 0.25
            self._look_at_the_graph()
        if not self._stalled and now - self._last_data > self.stall_timeout:
            self._stalled = True
            publishers = self._sub.get_publisher_count() if self._sub is not None else 0
            who = "" if publishers else " (no publisher)"
            if self._messages == 0:         # nothing lost yet: the robot's driver has not started
                self._record("waiting", f"ROS 2: waiting for the first message on {self.info}{who}",
                             self._blocks.frames)
            else:
                self._stalls += 1
                self._record("unplug", f"ROS 2: no message on {self.info} for {self.stall_timeout:g} s{who}; "
                                       "waiting for it to come back", self._blocks.frames)
        return None

    def _look_at_the_graph(self) -> None:
        """Read the types the topic's publishers advertise, and subscribe (``auto``) or refuse a mismatch."""
        assert self._ros is not None
        node = self._ros.node
        full = node.resolve_topic_name(self.topic)
        # the publishers' types only: the driver's own subscription advertises the type it expects
        types = sorted({info.topic_type for info in node.get_publishers_info_by_topic(full)})
        if not types:
            return
        if self._kind is None:
            readable = [t for t in types if t in MESSAGES]
            if not readable:
                raise DriverError(f"ROS 2: the topic {full} carries {types}; the driver reads {sorted(MESSAGES)} "
                                  "(samples x channels): publish one of those, or convert")
            self._subscribe(readable[0])
        elif self._kind not in types:
            raise DriverError(f"ROS 2: the topic {full} carries {types}, not the {self._kind} the scene says "
                              "(message = ...); name its type, or \"auto\"")

    def _judged(self, steps: list[Step]) -> None:
        for step in steps:
            data, last, arrival = self._held.popleft()
            block = self._blocks.block(data, last, arrival, step)
            if block.restarts:
                self._rate_since = None         # the rate is measured again from the restart
            self._check_rate(self._blocks.last_stamp)
            self._ready.append(block)

    def _check_rate(self, stamp: float) -> None:
        """Check the samples' rate against the scene's, after :data:`RATE_CHECK_SECONDS` of samples.

        A publisher at another rate is refused (every window would be wrong).
        """
        if self._rate_checked:
            return
        if self._rate_since is None:
            self._rate_since = (self._blocks.frames, stamp)
            return
        frames, since = self._blocks.frames - self._rate_since[0], stamp - self._rate_since[1]
        if since < RATE_CHECK_SECONDS:
            return
        measured = frames / since
        if abs(measured / self.rate - 1) > self.rate_tolerance:
            raise DriverError(f"ROS 2: {self.info} brings {measured:.0f} samples a second, not the {self.rate:g} Hz "
                              "the scene reads; set the source's rate (and its bank) to the publisher's, or fix it")
        self._rate_checked = True

    # -- counters -------------------------------------------------------------------------------------

    def stats(self) -> dict[str, int]:
        """Return the driver's counters since ``open()``.

        ``frames`` (delivered, filled ones included), ``filled``, ``messages``, ``gaps``, ``restarts``,
        ``stalls``, ``backlogs``, ``refused`` (messages of another layout), ``nan`` (values set to 0),
        ``odd_blocks`` (messages of another size than ``block``, kept),
        ``dropped_messages`` and ``dropped_samples`` (the queue was full).
        """
        with self._lock:
            b = self._blocks
            return {"frames": b.frames, "filled": b.filled, "messages": self._messages, "gaps": b.gaps,
                    "restarts": b.restarts, "stalls": self._stalls, "backlogs": b.backlogs,
                    "refused": self._refused, "nan": self._nan, "odd_blocks": self._odd_blocks,
                    "dropped_messages": self._dropped_messages,
                    "dropped_samples": self._dropped_samples}

    def __repr__(self) -> str:
        return f"Ros2TopicDriver({self.topic!r}, {self.rate:g} Hz, {self.channels} channels)"


#: Seconds of samples after a (re)start over which the rate is measured against the scene's.
RATE_CHECK_SECONDS = 2.0


# -- as a scene names it ---------------------------------------------------------------------------------

#: Bounds of the driver's times a scene may set, seconds (``rate_tolerance``: a fraction).
LIMITS = {"gap_tolerance": 10.0, "max_gap": 60.0, "stall_timeout": 60.0, "queue_seconds": 600.0,
          "rate_tolerance": 0.5}
#: Highest rate a scene may give a topic's samples, Hz.
MAX_RATE = 1e6
#: Most samples per message a scene may say a publisher sends (10 s at 100 kHz).
MAX_BLOCK = 1_000_000


def _build(options: Mapping[str, Any], context: BuildContext) -> Built:
    rate = options["rate"] if options["rate"] is not None else context.rate
    channels = options["channels"] if options["channels"] is not None else context.channels
    if rate is None or channels is None:
        raise OptionError("rate and channels: a topic read by no bank needs both (the samples' rate, Hz, and the "
                          "channels per sample)")
    if context.rate is not None and abs(rate - context.rate) > 1e-9 * context.rate:
        raise OptionError(f"rate: {rate:g} Hz, but the bank reads {context.rate:g} Hz; give the stream a bank at "
                          "the topic's rate")
    try:
        driver = Ros2TopicDriver(options["topic"], float(rate), int(channels), message=options["message"],
                                 reliability=options["reliability"], namespace=options["namespace"],
                                 block=options["block"],
                                 **given(options, {"node_name": "node_name", **{k: k for k in LIMITS}}))
    except DriverError:
        raise
    except InputError as exc:
        raise OptionError(str(exc)) from None
    return Built(driver)


def _limit(key: str, what: str) -> Key:
    return Key(positive(LIMITS[key]), f"{what}, up to {LIMITS[key]:g}", None)


SPEC = DriverSpec(
    type="ros2",
    summary="a ROS 2 topic of sensor samples: std_msgs *MultiArray or a stamped sensor_msgs/Image (the ros2 extra)",
    keys={
        "topic": Key(check_topic, 'the topic, e.g. "/whiskers" (relative: in the namespace)', REQUIRED),
        "rate": Key(positive(MAX_RATE), f"Hz of the samples, up to {MAX_RATE:g} (default: the bank's)", None),
        "channels": Key(integer(1, 4096), "channels per sample, 1..4096 (default: the bank's)", None),
        "block": Key(integer(1, MAX_BLOCK), f"samples per message the publisher sends, 1..{MAX_BLOCK} (checked: "
                     "another size is kept, counted and said; default: any)", None),
        "message": Key(one_of("auto", *MESSAGES), f'"auto" (the type the publishers advertise) or one of '
                       f"{sorted(MESSAGES)}", "auto"),
        "reliability": Key(one_of("reliable", "best_effort"), '"reliable" or "best_effort" (for a best-effort '
                           "publisher, e.g. sensor-data QoS)", "reliable"),
        "node_name": Key(check_node_name, "the driver's ROS node's name (default: supramodal_ and the topic's "
                         "tokens, e.g. supramodal_whiskers)", None),
        "namespace": Key(check_namespace, 'the driver\'s ROS node\'s namespace ("": the root)', ""),
        "gap_tolerance": _limit("gap_tolerance", "seconds of stamp jitter before a step counts as lost samples "
                                "(default 0.05)"),
        "max_gap": _limit("max_gap", "longest gap filled with zeros, seconds (a longer one is a restart; default 10)"),
        "stall_timeout": _limit("stall_timeout", "seconds without a message before the topic is reported lost "
                                "(default 0.5)"),
        "queue_seconds": _limit("queue_seconds", "seconds of samples the driver queues for the node (default 30)"),
        "rate_tolerance": _limit("rate_tolerance", "how far the samples' measured rate may be off the scene's, a "
                                 "fraction (default 0.05)"),
    },
    build=_build, live=True, buffered=True)
