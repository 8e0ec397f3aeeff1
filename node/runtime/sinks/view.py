"""Watch it live: a page in the browser that shows what the node decides, hears and how healthy it is.

``[[sink]] type = "view"`` (or ``supramodal run SCENE --view [PORT]``) serves a page on
127.0.0.1: per stream the posteriors over time, the decision, its confidence, the truth, the
pooled decision, the current feature window and a scrolling channels x time image of one of
its features; the fused decisions and their pairing; the health (frame fates, clocks, latency,
sinks' drops) and driver events as banners coloured by how grave they are
(:data:`~supramodal.node.runtime.events.SEVERITY`), on the
node's common time. docs/view.md.

Transport: the standard library's :class:`http.server.ThreadingHTTPServer` and Server-Sent
Events (``text/event-stream``, one JSON object per message): no new dependency, a browser
reconnects by itself, and the page only reads (the few requests that change something, marks
and the replay's pause and speed, are plain POSTs that need the run's token).

Threading rules
---------------
The view is a sink like every other: behind a :class:`~supramodal.node.runtime.sinks.QueuedSink`, so
``emit`` and ``event`` run on that queue's thread, never on the processing thread. Each
message is serialised once and put in every open page's own bounded queue (:class:`Hub`);
a page that does not read (a paused tab, a killed client) loses its oldest messages, counted
(``client_dropped`` in the sink's stats), and its request thread ends when a write times out.
The server runs on a thread of its own (``view-server``, started by :meth:`ViewSink.prepare`),
one daemon thread per open request, and a health thread (``view-health``, once a second,
reading the graph's counters, ``Graph.health``, which the graph gives every sink: :meth:`Sink.watch`);
:meth:`ViewSink.close` ends them all.
"""

from __future__ import annotations

import errno
import hmac
import ipaddress
import json
import math
import secrets
import socket
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import TYPE_CHECKING, Protocol, TypedDict

import numpy as np

from supramodal.checks import Key, flag, integer, is_name, text
from supramodal.drivers.base import DriverEvent
from supramodal.drivers.spec import OptionError
from supramodal.errors import InputError
from supramodal.logs import get_logger
from supramodal.node.runtime.events import WindowEvent, severity
from supramodal.node.runtime.fields import bool_of, int_of, optional_str_of, optional_strs_of, str_of, strs_of
from supramodal.node.runtime.sinks import QueuedSink, Sink
from supramodal.node.runtime.sinks.spec import Options, SinkContext, SinkSpec
from supramodal.node.runtime.summaries import Health, RunSummary
from supramodal.records import JsonValue

if TYPE_CHECKING:   # the annotations' names only
    from supramodal.banks import Bank

_LOG = get_logger("sinks.view")

__all__ = ["SPEC", "Action", "ChannelLabels", "Hub", "SinkHolder", "ViewError", "ViewSink", "attach",
           "channel_labels", "event_message", "view_sinks", "window_message"]

#: A change a page may POST (:meth:`ViewSink.actions`): the request's JSON body in, the answer's out.
Action = Callable[[dict[str, JsonValue]], dict[str, JsonValue]]


class ChannelLabels(TypedDict):
    """A stream's channels as the page labels its feature bars (:func:`channel_labels`), in channel order."""

    names: list[str]
    centre_hz: list[float]


class SinkHolder(Protocol):
    """What the view reads of a graph (:class:`~supramodal.node.runtime.graph.Graph`, which it may not import).

    The graph imports the sinks: an import of it here, even for the type checker only, would close a cycle.
    """

    @property
    def sinks(self) -> Sequence[Sink]:
        """The graph's sinks, each as the graph holds it (a view behind its :class:`QueuedSink`)."""
        ...

#: Messages each open page's queue holds; beyond it the oldest are dropped and counted.
CLIENT_QUEUE = 256
#: Window messages kept for a page opened later (the last 60 s of 100 ms windows).
HISTORY = 600
#: Channels of a feature a window message carries at the most (a message stays small).
MAX_CHANNELS = 256
#: Bytes of a request body at the most (a mark is a label name).
MAX_BODY = 1024
#: Bytes of a page's socket send buffer (the kernel doubles it).
SEND_BUFFER = 64 * 1024
#: Seconds a write to a page may take before that page is given up.
WRITE_TIMEOUT = 5.0
#: Seconds the view's close waits for the open pages to take what is queued (the summary).
CLOSE_FLUSH = 1.0
#: Seconds between two health messages.
HEALTH_PERIOD = 1.0
#: The shortest token a non-loopback view accepts.
MIN_TOKEN = 16
#: The header that carries the token.
TOKEN_HEADER = "X-Supramodal-Token"
#: The page's files, inside the package.
_HTML = "text/html; charset=utf-8"
STATIC = {"/": ("index.html", _HTML), "/index.html": ("index.html", _HTML),
          "/view.js": ("view.js", "text/javascript; charset=utf-8"),
          "/view.css": ("view.css", "text/css; charset=utf-8")}


class ViewError(InputError):
    """A view that cannot be served as asked (a port in use, a bind without a token)."""


def _port(v: object) -> bool:
    return integer(0, 65535)(v)


def _token(v: object) -> bool:
    return text(v) and len(v) >= MIN_TOKEN and v.isascii() and v.isprintable() and " " not in v


def _labels(v: object) -> bool:
    return isinstance(v, list) and bool(v) and len(v) <= 64 and all(is_name(x) for x in v) and len(set(v)) == len(v)


KEYS = {
    "port": Key(_port, "a TCP port 0..65535 (0: any free one, printed at start)", 0),
    "host": Key(text, 'the address to serve on; anything but loopback needs remote = true and a token',
                "127.0.0.1"),
    "remote": Key(flag, "true to allow a host other than loopback (with a token)", False),
    "token": Key(_token, f"the token that requests changing something must carry, at least {MIN_TOKEN} printable "
                         "characters (default: a new one each run, printed at start)", None),
    "labels": Key(_labels, "the mark buttons' labels, names (default: the streams' classes)", None),
}


def is_loopback(host: str) -> bool:
    """Whether ``host`` is this machine only (127.0.0.0/8, ::1, localhost)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


# -- messages ------------------------------------------------------------------------------------------

def _json(obj: object) -> str:
    return json.dumps(obj, separators=(",", ":"), default=_plain, allow_nan=False)


def _plain(o: object) -> JsonValue:
    """Convert numpy scalars and arrays, and sets, to what JSON has for them."""
    if isinstance(o, np.ndarray):
        nested: list[JsonValue] = o.tolist()     # numbers, in lists as deep as the array
        return nested
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, (set, frozenset, tuple)):
        return sorted(o) if isinstance(o, (set, frozenset)) else list(o)
    raise TypeError(f"{type(o).__name__} is not JSON")


def _clean(o: JsonValue) -> JsonValue:
    """``o`` with every number JSON can carry (NaN and infinities as None; numpy as Python)."""
    if isinstance(o, dict):
        return {str(k): _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple, set, frozenset, np.ndarray)):
        return [_clean(v) for v in (sorted(o) if isinstance(o, (set, frozenset)) else o)]
    if isinstance(o, (float, np.floating)):
        return float(o) if math.isfinite(o) else None
    if isinstance(o, (np.integer, np.bool_)):
        return o.item()
    return o


def _finite(x: float, digits: int) -> float | None:
    x = float(x)
    return round(x, digits) if math.isfinite(x) else None


def window_message(event: WindowEvent) -> dict[str, JsonValue]:
    """Return a window event as the page gets it.

    That is :meth:`WindowEvent.as_dict` (the JSONL sink's object, unchanged in meaning) and what the page
    draws besides: ``posteriors`` with their ``classes``, ``features`` per channel (rounded, at most
    :data:`MAX_CHANNELS`), ``in_contact``, ``flags``.
    """
    out = event.as_dict()
    out["type"] = "window"
    if event.posteriors is not None:
        out["posteriors"] = [_finite(p, 5) for p in np.asarray(event.posteriors, dtype=float).ravel()]
        out["classes"] = list(event.classes)
    if event.features is not None:
        out["features"] = {name: [_finite(x, 6) for x in np.asarray(v, dtype=float).ravel()[:MAX_CHANNELS]]
                           for name, v in event.features.items()}
    out["in_contact"] = bool(event.in_contact)
    out["flags"] = list(sorted(event.flags))   # a list of JSON values (sorted's own is a list of str)
    if event.decision is not None and event.novelty is not None:      # where as_dict says it
        out["novelty"] = _finite(event.novelty, 5)
    return out


def event_message(ev: DriverEvent, wall_at_zero: float | None = None) -> dict[str, JsonValue]:
    """Return a driver event as the page gets it (a banner and a line in its list).

    That is :meth:`DriverEvent.as_dict`, its ``severity`` (:func:`~supramodal.node.runtime.events.severity`) and,
    given ``wall_at_zero`` (the host's ``time.time()`` at common time 0), ``common_time``: when it happened on the
    node's common time, seconds, as the windows' times are (the event's ``time`` is the host's wall clock, seconds
    since 1970).
    """
    out: dict[str, JsonValue] = {"type": "event", **ev.as_dict(), "severity": severity(ev.kind)}
    if wall_at_zero is not None:
        out["common_time"] = _finite(ev.time - wall_at_zero, 3)
    return out


# -- the open pages ------------------------------------------------------------------------------------

class _Client:
    """One open page's queue: bounded; when full, the oldest message goes (counted)."""

    def __init__(self, capacity: int) -> None:
        self.items: deque[bytes] = deque()
        self.capacity = capacity
        self.ready = threading.Condition()
        self.dropped = 0
        self.gone = False


class Hub:
    """Every open page's queue, and the recent messages a page opened later gets first.

    :meth:`publish` never blocks (it is called on the sink's thread); what a page does not take
    in time is dropped from its own queue and counted in :attr:`dropped`.
    """

    def __init__(self, capacity: int = CLIENT_QUEUE, history: int = HISTORY) -> None:
        self.capacity = capacity
        self._clients: set[_Client] = set()
        self._lock = threading.Lock()
        self._history: deque[bytes] = deque(maxlen=history)
        self._latest: dict[str, bytes] = {}   # the last message of each other kind (hello, health, summary)
        self.dropped = 0                       # messages dropped by pages that did not read
        self.opened = 0                        # pages that ever connected
        self.given_up = 0                      # pages whose connection was given up (stalled or gone)
        self.closed = False

    @staticmethod
    def encode(message: Mapping[str, JsonValue]) -> bytes:
        """Return ``message`` as one server-sent event: ``data: JSON`` and a blank line, UTF-8."""
        return f"data: {_json(message)}\n\n".encode()

    def publish(self, message: Mapping[str, JsonValue], keep: str = "history") -> None:
        """Send ``message`` to every open page, and keep it for pages opened later as ``keep`` says.

        ``keep``: ``"history"`` (a window or an event, kept for a page opened later among the last :data:`HISTORY`),
        ``"latest"`` (only the last of its ``type`` is kept) or ``"none"``.
        """
        data = self.encode(message)
        with self._lock:
            if keep == "history":
                self._history.append(data)
            elif keep == "latest":
                self._latest[str(message.get("type"))] = data
            clients = list(self._clients)
        for c in clients:
            self._put(c, data)

    def reset(self) -> None:
        """Forget the history (a replay that starts again)."""
        with self._lock:
            self._history.clear()

    def _put(self, c: _Client, data: bytes) -> None:
        with c.ready:
            if len(c.items) >= c.capacity:
                c.items.popleft()
                c.dropped += 1
                with self._lock:
                    self.dropped += 1
            c.items.append(data)
            c.ready.notify()

    def open(self) -> _Client:
        """Open a new page's queue and return it.

        Its queue starts with the latest hello, health and summary and the history (the newest
        :attr:`capacity` of them).
        """
        c = _Client(self.capacity)
        with self._lock:
            first = [self._latest[k] for k in ("hello", "health", "summary") if k in self._latest]
            c.items.extend((first + list(self._history))[-self.capacity:])
            self._clients.add(c)
            self.opened += 1
        return c

    def leave(self, c: _Client, given_up: bool = False, in_flight: int = 0) -> None:
        """End a page's connection.

        ``given_up``: it failed (the page stalled or went away); what it had not taken (its queue, and
        ``in_flight``, a message being written) is counted as dropped, and the page as given up.
        """
        with c.ready:
            left = len(c.items) + in_flight
        with self._lock:
            self._clients.discard(c)
            if given_up:
                self.dropped += left
                self.given_up += 1

    def take(self, c: _Client, timeout: float) -> bytes | None:
        """Return the page's next message, or None after ``timeout`` seconds or once closed."""
        with c.ready:
            if not c.items and not self.closed:
                c.ready.wait(timeout)
            return c.items.popleft() if c.items else None

    def close(self) -> None:
        """Wake every page's thread: they end."""
        with self._lock:
            self.closed = True
            clients = list(self._clients)
        for c in clients:
            with c.ready:
                c.ready.notify_all()

    def clients(self) -> int:
        """Return the number of pages connected now."""
        with self._lock:
            return len(self._clients)


# -- the server ----------------------------------------------------------------------------------------

class _Server(ThreadingHTTPServer):
    daemon_threads = True          # a page's request thread never keeps the process alive
    block_on_close = False
    view: ViewSink

    # The base's request (typeshed's own type); its client_address is typeshed's Any, which this server's two
    # families make an (host, port) or (host, port, flowinfo, scope_id) tuple.
    def handle_error(self, request: socket.socket | tuple[bytes, socket.socket],
                     client_address: tuple[str, int] | tuple[str, int, int, int]) -> None:
        """Say a request's error in one line, never as a traceback on the node's stderr (socketserver's default).

        A page that went away mid-request (a reset, a closed tab) is no error of the node's, and is not said.
        """
        exc = sys.exc_info()[1]
        if isinstance(exc, (ConnectionError, TimeoutError)):
            return
        _LOG.warning(f"view: a request from {client_address[0]} failed: {type(exc).__name__}: {exc}")


class _Server6(_Server):
    """The view's server on an IPv6 address (``::1``, ``::``)."""

    address_family = socket.AF_INET6


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    protocol_version = "HTTP/1.1"

    def log_message(self, format: str, *args: object) -> None:   # noqa: A002 (the base's name)
        pass                                                     # no access log on the node's stderr

    def setup(self) -> None:
        super().setup()
        self.connection.settimeout(WRITE_TIMEOUT)                # a stalled page is given up

    # -- replies --

    def _reply(self, status: int, body: bytes, kind: str = "text/plain; charset=utf-8") -> None:
        self.send_response(status)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _refuse(self, status: int, why: str) -> None:
        self._reply(status, (why + "\n").encode())

    # -- GET --

    def do_GET(self) -> None:
        view = self.server.view
        path = self.path.split("?", 1)[0]
        if not view.host_ok(self.headers.get("Host")):
            self._refuse(HTTPStatus.FORBIDDEN, "this view answers requests for its own address only (Host)")
        elif path in STATIC:
            name, kind = STATIC[path]
            self._reply(HTTPStatus.OK, _static(name), kind)
        elif path == "/state":
            self._reply(HTTPStatus.OK, _json(view.hello()).encode(), "application/json")
        elif path == "/events":
            self._events()
        else:
            self._refuse(HTTPStatus.NOT_FOUND, f"no {path} here; the page is at /")

    do_HEAD = do_GET

    def _events(self) -> None:
        hub = self.server.view.hub
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.send_header("Connection", "close")
        self.end_headers()
        self.close_connection = True
        # A small send buffer: a page that stops reading falls behind in its own bounded queue,
        # where its loss is counted, rather than in megabytes of the kernel's buffers.
        self.connection.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
        client = hub.open()
        on_its_way = 0                      # a message being written when the connection failed
        try:
            self.wfile.write(b"retry: 1000\n\n")
            while True:
                data = hub.take(client, 1.0)
                if data is None and hub.closed:      # what was queued before the end is sent first
                    break
                on_its_way = data is not None
                self.wfile.write(data if data is not None else b": keep-alive\n\n")
                self.wfile.flush()
                on_its_way = False
            hub.leave(client)
        except OSError:                     # the page went away, or stopped reading for WRITE_TIMEOUT: what it
            hub.leave(client, given_up=True, in_flight=int(on_its_way))    # had not taken is lost, counted
        except BaseException:
            hub.leave(client)
            raise

    # -- POST: changes need the token and the page's own origin --

    def do_POST(self) -> None:
        view = self.server.view
        path = self.path.split("?", 1)[0]
        actions = view.actions()
        if not view.host_ok(self.headers.get("Host")):
            return self._refuse(HTTPStatus.FORBIDDEN, "this view answers requests for its own address only (Host)")
        if path not in actions:
            return self._refuse(HTTPStatus.NOT_FOUND, f"no {path} here" + (
                f"; this view takes {sorted(actions)}" if actions else "; this view is read-only"))
        try:
            length = int(self.headers.get("Content-Length") or 0)
        except ValueError:
            length = -1
        if length < 0 or length > MAX_BODY:
            self.close_connection = True
            return self._refuse(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, f"a body of at most {MAX_BODY} bytes")
        body = self.rfile.read(length)
        given = self.headers.get(TOKEN_HEADER) or ""
        if not hmac.compare_digest(given.encode(), view.token.encode()):
            return self._refuse(HTTPStatus.FORBIDDEN, f"a change needs the run's token in {TOKEN_HEADER} (printed "
                                "on the terminal at start; open the page with #token=... to send it)")
        if not view.origin_ok(self.headers.get("Origin"), self.headers.get("Host")):
            return self._refuse(HTTPStatus.FORBIDDEN, "a change must come from the view's own page (Origin)")
        try:
            asked = json.loads(body or b"{}")
            if not isinstance(asked, dict):
                raise ValueError("not an object")
        except ValueError as exc:
            return self._refuse(HTTPStatus.BAD_REQUEST, f"the body must be a JSON object: {exc}")
        try:
            done = actions[path](asked)
        except InputError as exc:
            return self._refuse(HTTPStatus.UNPROCESSABLE_ENTITY, str(exc))
        self._reply(HTTPStatus.OK, _json(done).encode(), "application/json")


def _static(name: str) -> bytes:
    return (resources.files("supramodal.node.runtime.sinks") / "view_static" / name).read_bytes()


# -- the sink ------------------------------------------------------------------------------------------

class ViewSink(Sink):
    """Serves the page and sends it each window, driver event, health and the summary.

    Parameters
    ----------
    port : int
        0: any free one (:attr:`url` says which).
    host : str
        Loopback unless ``remote``; a non-loopback host needs ``remote`` and ``token``.
    remote : bool
    token : str or None
        What a request that changes something must carry; None: a new random one.
    labels : list of str or None
        The mark buttons' labels (default: the streams' classes, as the windows name them).
    mode : {"live", "replay"}
    quiet : bool
        Do not print the URL on stderr.
    streams : sequence of str
        The streams the page shows, in order (a scene's: its streams, then ``"fused"``); a stream
        not named here is added when its first window comes.
    channels : mapping of str to mapping, optional
        Per stream, its bank's channels as the page labels its feature bars: ``{"names": [...],
        "centre_hz": [...]}`` in channel order (:func:`channel_labels`); a stream not named here has its
        bars numbered.

    Raises
    ------
    ViewError
        For a non-loopback host without ``remote`` and a token, or a port that cannot be bound;
        the message names the fix.
    """

    def __init__(self, port: int = 0, host: str = "127.0.0.1", remote: bool = False, token: str | None = None,
                 labels: list[str] | None = None, mode: str = "live", quiet: bool = False,
                 streams: Sequence[str] = (),
                 channels: Mapping[str, ChannelLabels] | None = None) -> None:
        if not is_loopback(host) and not (remote and token):
            raise ViewError(f"serving the view on {host!r} (not loopback) lets other machines see it: it needs "
                            "remote = true and a token of your own (token = \"...\", at least "
                            f"{MIN_TOKEN} characters); or leave host at 127.0.0.1")
        if token is not None and not _token(token):
            raise ViewError(f"the view's token must be at least {MIN_TOKEN} printable characters without spaces")
        self.token = token or secrets.token_urlsafe(18)
        self.labels = list(labels) if labels else None
        self.mode = mode
        self.hub = Hub()
        self.health: Callable[[], Health] | None = None
        self.on_mark: Callable[[str | None], object] | None = None   # its answer, a number: the mark's time
        self.control: Action | None = None
        self.marks: list[dict[str, JsonValue]] = []
        self._classes: dict[str, list[str]] = {}
        self._streams: list[str] = list(streams)   # in the scene's order; others as their first window comes
        self._channels: dict[str, JsonValue] = {name: {"names": [str(n) for n in c["names"]],
                                 "centre_hz": [_finite(f, 1) for f in c["centre_hz"]]}
                          for name, c in (channels or {}).items()}
        self._wall_at_zero: float | None = None     # the host's time.time() at common time 0, once started
        self._lock = threading.Lock()
        self._closing = threading.Event()
        self._threads: list[threading.Thread] = []
        try:
            self._server = (_Server6 if ":" in host else _Server)((host, port), _Handler, bind_and_activate=True)
        except OverflowError as exc:
            raise ViewError(f"port {port}: {exc}; give a port 0..65535 (0: any free one)") from None
        except socket.gaierror as exc:     # a host that is no address of this machine's, or not one at all
            raise ViewError(f"cannot serve the view on host {host!r}: {exc.strerror or exc}; give an address of "
                            "this machine (127.0.0.1, ::1, or 0.0.0.0 for every one)") from None
        except OSError as exc:
            fix = ("give another port, or 0 for any free one" if exc.errno in (errno.EADDRINUSE, errno.EACCES)
                   else "give an address of this machine (127.0.0.1, ::1, or 0.0.0.0 for every one)")
            raise ViewError(f"cannot serve the view on {host}:{port}: {exc.strerror or exc}; {fix}") from None
        self._server.view = self
        self.host, self.port = host, int(self._server.server_address[1])
        shown = f"[{host}]" if ":" in host else host
        self.url = f"http://{shown}:{self.port}/"
        self.path = self.url
        self._origins = {f"http://{shown}:{self.port}"} | (
            {f"http://localhost:{self.port}", f"http://127.0.0.1:{self.port}"} if is_loopback(host) else set())
        # the names a request may give as its Host (a page of another site whose name resolves to this
        # machine, DNS rebinding, gives its own); a remote view answers any name it is reached by
        self.remote = bool(remote)
        self._names = {shown} | ({"localhost", "127.0.0.1", "[::1]"} if is_loopback(host) else set())
        self._started = False
        if not quiet:
            # the address the user opens: said whatever the log level (a result of starting the view)
            print(f"supramodal: view at {self.url} (read-only); to mark or control it open "  # noqa: T201
                  f"{self.url}#token={self.token}", file=sys.stderr, flush=True)

    # -- what the page asks --

    def hello(self) -> dict[str, JsonValue]:
        """Return what the page needs first, the ``hello`` message.

        The mode, the streams and their classes, their channels (the feature bars' labels), the mark
        labels, whether marks and controls are open.
        """
        with self._lock:
            classes: dict[str, JsonValue] = {k: list(v) for k, v in self._classes.items()}
            streams: list[JsonValue] = list(self._streams)
        labels: list[JsonValue] = list(self._mark_labels())
        return {"type": "hello", "mode": self.mode, "streams": streams, "classes": classes, "channels": self._channels,
                "labels": labels, "marks": self.on_mark is not None, "control": self.control is not None}

    def _mark_labels(self) -> list[str]:
        """Return the mark buttons' labels: those given, else every stream's classes (sorted)."""
        with self._lock:
            classes = [c for cs in self._classes.values() for c in cs]
        return self.labels or sorted(set(classes))

    def actions(self) -> dict[str, Action]:
        """Return the changes a page may POST, by path: ``/mark`` while marks are taken, ``/control`` with a control.

        Each handler takes the request's JSON body and returns the answer's. None open: a read-only view.
        """
        out: dict[str, Action] = {}
        if self.on_mark is not None:
            out["/mark"] = self._mark
        if self.control is not None:
            out["/control"] = self.control
        return out

    def host_ok(self, host: str | None) -> bool:
        """Return whether a request (any: reads too) names this view as its Host.

        On a view not ``remote``, one of the names it serves on (a page of another site whose name resolves to this
        machine, DNS rebinding, names its own, and may not read the stream). A remote view answers any name it is
        reached by.
        """
        if host is None:
            return False
        if self.remote:
            return True
        name = host if host.endswith("]") else host.rsplit(":", 1)[0]
        return name in self._names

    def origin_ok(self, origin: str | None, host: str | None) -> bool:
        """Return whether a change comes from the view's own page: its Origin is the view's, and so is its Host.

        A page of another site that resolves its name to this machine has another Host. A remote view's page is the
        one served as the Host it was reached by (any address of the machine).
        """
        if self.remote:
            return host is not None and origin == f"http://{host}"
        return origin in self._origins and host is not None and f"http://{host}" in self._origins

    def _mark(self, asked: dict[str, JsonValue]) -> dict[str, JsonValue]:
        label = asked.get("label")
        allowed = self._mark_labels()
        if set(asked) - {"label"}:
            raise InputError(f"a mark is {{\"label\": NAME or null}}; unknown keys {sorted(set(asked) - {'label'})}")
        if label is not None and not (isinstance(label, str) and label in allowed):
            raise InputError(f"the label {label!r} is not one of this view's: {allowed}")
        label = label if isinstance(label, str) else None
        mark = self.on_mark
        if mark is None:
            raise InputError("marks are closed")
        when = mark(label)
        done: dict[str, JsonValue] = {"type": "mark", "label": label,
                                      "time": round(float(when), 3) if isinstance(when, (int, float)) else None}
        with self._lock:
            self.marks.append(done)
        self.hub.publish(done)
        return done

    # -- the Sink calls --

    def prepare(self) -> None:
        """Start serving (the URL was printed when the sink was made)."""
        if not self._started:
            self._started = True
            self._spawn("view-server", self._server.serve_forever, 0.2)
            self.hub.publish(self.hello(), keep="latest")

    def start(self, epoch: float) -> None:
        """Serve, and put the driver events on common time from now on.

        ``epoch``, common time 0 on ``time.monotonic()``, is this far back on the wall clock the events are stamped
        with.
        """
        self._wall_at_zero = time.time() - (time.monotonic() - epoch)
        self.prepare()
        self._spawn("view-health", self._health_loop)

    def _spawn(self, name: str, target: Callable[..., object], *args: object) -> None:
        t = threading.Thread(target=target, args=args, name=name, daemon=True)
        t.start()
        self._threads.append(t)

    def _health_loop(self) -> None:
        while not self._closing.wait(HEALTH_PERIOD):
            self.publish_health()

    def publish_health(self) -> None:
        """Send the graph's counters now (``Graph.health``), if the view is in a graph."""
        if self.health is not None:
            try:
                self.hub.publish({"type": "health", "clients": self.hub.clients(),
                                  "client_dropped": self.hub.dropped, **self.health()}, keep="latest")
            except Exception:       # a counter read mid-update: the next tick has it
                pass

    def emit(self, event: WindowEvent) -> None:
        """Send a window to every page, as :func:`window_message` makes it (see :meth:`emit_message`)."""
        self.emit_message(window_message(event))

    def emit_message(self, message: Mapping[str, JsonValue]) -> None:
        """Send a window as :func:`window_message` made it (a replay plays those it kept).

        A new stream, or a stream's first classes, sends the page a new hello first.
        """
        stream = str_of(message, "stream")
        classes = message.get("classes")
        news = False                        # the page's hello changes: a stream, or classes (the mark labels)
        if stream not in self._classes and classes:
            with self._lock:
                self._classes[stream] = strs_of(message, "classes")
            news = True
        if stream not in self._streams:
            with self._lock:
                self._streams.append(stream)
            news = True
        if news:
            self.hub.publish(self.hello(), keep="latest")
        self.hub.publish(message)

    def event(self, ev: DriverEvent) -> None:
        """Send a driver event to every page, as :func:`event_message` makes it (kept in the history)."""
        self.hub.publish(event_message(ev, self._wall_at_zero))

    def summary(self, summary: RunSummary) -> None:
        """Send the last health and the run's summary to every page (None where JSON has no form for it)."""
        self.publish_health()
        try:
            self.hub.publish({"type": "summary", "summary": _clean(dict(summary))}, keep="latest")
        except (TypeError, ValueError):     # a value JSON has no form for: the page still learns of the end
            self.hub.publish({"type": "summary", "summary": None}, keep="latest")

    def stats(self) -> dict[str, JsonValue]:
        """Return the view's address, the pages opened and given up, what they dropped and the marks taken."""
        return {"url": self.url, "pages": self.hub.opened, "pages_given_up": self.hub.given_up,
                "client_dropped": self.hub.dropped, "marks": len(self.marks)}

    def close(self) -> None:
        """Stop serving: the server's, the health and every page's thread end."""
        self._closing.set()
        self.hub.close()
        deadline = time.monotonic() + CLOSE_FLUSH
        while self.hub.clients() and time.monotonic() < deadline:   # the pages get the summary
            time.sleep(0.02)
        if self._started:
            self._server.shutdown()
        self._server.server_close()
        for t in self._threads:
            t.join(2 * WRITE_TIMEOUT)


# -- a graph's views ----------------------------------------------------------------------------------

def view_sinks(graph: SinkHolder) -> list[ViewSink]:
    """Return the graph's view sinks (each behind its queue)."""
    return [s.sink for s in graph.sinks if isinstance(s, QueuedSink) and isinstance(s.sink, ViewSink)]


def attach(graph: SinkHolder, on_mark: Callable[[str | None], object] | None = None) -> list[ViewSink]:
    """Return the graph's view sinks, given the marks' handler while recording (``on_mark``).

    Their counters (health) the graph gives every sink itself
    (:meth:`Sink.watch <supramodal.node.runtime.sinks.Sink.watch>`).
    """
    views = view_sinks(graph)
    for v in views:
        if on_mark is not None:
            v.on_mark = on_mark
    return views


# -- as a scene names it -------------------------------------------------------------------------------

def channel_labels(bank: Bank) -> ChannelLabels:
    """Return a bank's channels as the page labels a stream's feature bars: ``{"names", "centre_hz"}``.

    In channel order (the order of every feature's values in a window); :class:`ViewSink` makes them JSON.
    """
    return {"names": list(bank.names), "centre_hz": [float(f) for f in bank.cf]}


def _build(options: Options, context: SinkContext) -> Sink:
    # Made from the streams' plans (their banks: the bars' labels), still before any model is trained.
    channels = {name: channel_labels(p.pipeline.bank) for name, p in context.plans.items()}
    try:
        view = ViewSink(int_of(options, "port"), str_of(options, "host"), bool_of(options, "remote"),
                        optional_str_of(options, "token"), optional_strs_of(options, "labels"),
                        streams=context.stream_names, channels=channels)
    except ViewError as exc:
        raise OptionError(str(exc)) from None
    # Behind its own queue, as every sink: a slow or absent page never slows processing.
    return QueuedSink(view)


SPEC = SinkSpec(type="view", keys=KEYS, build=_build, needs="plans",
                summary="a page in the browser (127.0.0.1): decisions, posteriors, features, health, marks")

