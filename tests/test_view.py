"""The view (node/runtime/sinks/view.py): a page served by a running node, checked in a real headless browser
(Debian's chromium over the DevTools protocol, tests/view_browser.py), and its server's rules
(the token, the Origin, bounded messages, a page that stops reading never slows the node)."""

from __future__ import annotations

import http.client
import json
import socket
import threading
import time
from dataclasses import replace
from pathlib import Path

import pytest
from view_browser import Browser, chromium_path, png_colours, png_size

from supramodal.banks import cochlea_bank, whisker_bank
from supramodal.decisions import PooledDecision
from supramodal.drivers.base import DriverEvent
from supramodal.drivers.spec import OptionError
from supramodal.node.runtime.events import SEVERITY, WindowEvent, severity
from supramodal.node.runtime.sinks import QueuedSink
from supramodal.node.runtime.sinks.spec import SinkContext
from supramodal.node.runtime.sinks.view import (
    CLIENT_QUEUE,
    MAX_BODY,
    SPEC,
    TOKEN_HEADER,
    ViewError,
    ViewSink,
    attach,
    channel_labels,
    event_message,
    view_sinks,
)
from supramodal.node.runtime.taps.recorder import SessionRecorder
from supramodal.node.scene.build import build_node
from supramodal.node.scene.schema import SceneError, scene_from_dict

NO_CHROMIUM = "Debian's chromium is not installed (apt-get install -y chromium; .ci/run installs it)"

# The default scene's model, trained once per test process (node/scene/build.py keeps it), at twice real time.
DEFAULT = {"driver": {"type": "synth", "textures": "reference", "seconds": 10.0, "held_out": True, "block": 50,
                      "speed": 2.0},
           "bank": {"kind": "whisker"}, "features": {"names": ["Af"]}, "model": {"train_on_start": True},
           "decision": {"scope": "window"}}


def scene(tmp_path: Path, *sinks: dict, **driver):
    d = {**DEFAULT, "driver": {**DEFAULT["driver"], **driver}, "sink": list(sinks)}
    return scene_from_dict(d, str(tmp_path / "scene.toml"), tmp_path)


class Running:
    """A graph run on a thread (the test's thread drives the browser meanwhile)."""

    def __init__(self, graph, seconds: float | None) -> None:
        self.graph, self.summary, self.error = graph, None, None
        self.thread = threading.Thread(target=self._run, args=(seconds,), daemon=True)
        self.thread.start()

    def _run(self, seconds):
        try:
            self.summary = self.graph.run(max_seconds=seconds)
        except BaseException as exc:     # surfaced by join()
            self.error = exc

    def join(self, timeout: float = 120.0):
        self.thread.join(timeout)
        assert not self.thread.is_alive(), "the node did not end"
        if self.error is not None:
            raise self.error
        return self.summary


@pytest.fixture(scope="module")
def browser():
    if chromium_path() is None:
        pytest.skip(NO_CHROMIUM)
    b = Browser()
    yield b
    b.close()


def _view(graph) -> ViewSink:
    (view,) = view_sinks(graph)
    return view


def _request(view: ViewSink, method: str, path: str, body: bytes = b"", headers: dict | None = None):
    conn = http.client.HTTPConnection("127.0.0.1", view.port, timeout=30)
    try:
        conn.request(method, path, body=body, headers=headers or {})
        r = conn.getresponse()
        return r.status, r.read().decode()
    finally:
        conn.close()


def _own(view: ViewSink) -> dict:
    """The headers of the view's own page with the token."""
    return {TOKEN_HEADER: view.token, "Origin": f"http://127.0.0.1:{view.port}", "Content-Type": "application/json"}


# -- in a real browser -----------------------------------------------------------------------------

@pytest.mark.slow   # a long run: a model trained on the spot, 6 s of stream in the browser
def test_the_page_shows_the_running_nodes_decisions_as_its_jsonl_sink_has_them(tmp_path, browser):
    jsonl = tmp_path / "decisions.jsonl"
    graph = build_node(scene(tmp_path, {"type": "jsonl", "path": str(jsonl)}, {"type": "view"}))
    view = _view(graph)
    attach(graph)
    run = Running(graph, 14.0)                    # 14 s of stream at twice real time
    browser.open(view.url)
    panel = "document.querySelector('[data-stream=\"main\"]')"
    browser.wait_for(f"{panel} && {panel}.dataset.window", timeout=60)
    seen = {}
    deadline = time.monotonic() + 60
    while len(seen) < 4 and time.monotonic() < deadline:
        w, predicted, conf = browser.eval(f"[{panel}.dataset.window, {panel}.querySelector('.decision').textContent,"
                                          f" {panel}.querySelector('.confidence').textContent]")
        seen[int(w)] = (predicted, conf)
        time.sleep(0.4)
    summary = run.join()
    assert len(seen) >= 4, f"the readout changed only {len(seen)} times: {seen}"
    lines = [json.loads(line) for line in jsonl.read_text().splitlines()]
    windows = {d["window"]: d for d in lines if d.get("stream") == "main" and "window" in d}
    for w, (predicted, conf) in seen.items():
        assert windows[w]["predicted"] == predicted, (w, windows[w], predicted)
        assert f"{windows[w]['confidence']:.3f}" == conf, (w, windows[w], conf)
    # the health panel shows the graph's counters, and the run's end
    browser.wait_for("!!document.querySelector('#frames tbody tr[data-stream=\"main\"]')")
    browser.wait_for("document.querySelector('#mode').textContent.endsWith('ended')")
    shown = browser.eval("document.querySelector('#frames tbody tr[data-stream=\"main\"]').children[2].textContent")
    assert int(shown) == summary["frames"]["delivered"]
    assert not [t.name for t in threading.enumerate() if t.name.startswith("view-")]


@pytest.mark.slow   # a browser's screenshot, 10 s; the quick command keeps the token-and-mark browser test
def test_a_screenshot_of_the_page_is_not_blank(tmp_path, browser):
    graph = build_node(scene(tmp_path, {"type": "view"}))
    view = _view(graph)
    attach(graph)
    run = Running(graph, 6.0)
    browser.open(view.url)
    browser.wait_for("document.querySelectorAll('[data-stream=\"main\"] .legend span').length == 8", timeout=60)
    width, height, colours = png_colours(browser.screenshot(scale=0.5))
    run.join()
    assert width > 300 and height > 300
    assert colours > 20, f"{colours} colours: the page looks blank"


def test_a_mark_from_the_page_needs_the_token_and_lands_in_the_recording(tmp_path, browser):
    sc = scene(tmp_path, {"type": "view", "labels": ["smooth", "rough"]}, seconds=3.0, speed=1.0)
    recorder = SessionRecorder(tmp_path, "rec", "{}", replace=True)
    graph = build_node(sc, recorder=recorder)
    view = _view(graph)
    attach(graph, on_mark=recorder.mark)
    run = Running(graph, 6.0)
    # read-only without the token: the buttons are there, but disabled
    browser.open(view.url)
    browser.wait_for("document.querySelectorAll('#markbuttons button').length == 2", timeout=60)
    assert browser.eval("document.querySelector('#markbuttons button').disabled") is True
    # with it, a click marks
    browser.open(f"{view.url}#token={view.token}")
    browser.wait_for("document.querySelector('[data-stream=\"main\"]') && "
                     "Number(document.querySelector('[data-stream=\"main\"]').dataset.window) > 3", timeout=60)
    browser.eval("document.querySelector('#markbuttons button[data-label=\"rough\"]').click()")
    browser.wait_for("document.querySelector('#markstatus').textContent.startsWith('marking rough')")
    # the mark's time, the recording's seconds (issue 35: "marking rough since - s" in a one-source recording)
    said = browser.eval("document.querySelector('#markstatus').textContent")
    since = float(said.split(" since ")[1].split(" s")[0])
    run.join()
    labels = json.loads((tmp_path / "rec.json").read_text())["labels"]
    assert [lab["label"] for lab in labels] == ["rough"], labels
    assert abs(labels[0]["start"] - since) < 0.011, (labels, said)


# -- the server's rules, over plain HTTP ----------------------------------------------------------

@pytest.fixture
def marking_view():
    view = ViewSink(labels=["smooth", "rough"], quiet=True)
    marks = []
    view.on_mark = lambda label: marks.append(label) or 1.5
    view.prepare()
    yield view, marks
    view.close()


def test_a_change_without_the_token_or_from_another_origin_is_refused_and_changes_nothing(marking_view):
    view, marks = marking_view
    body = json.dumps({"label": "rough"}).encode()
    own = _own(view)
    assert _request(view, "POST", "/mark", body, {**own, TOKEN_HEADER: ""})[0] == 403
    # one character off (always another: a token that ended in "x" made the "x" of before the token itself)
    wrong = view.token[:-1] + ("x" if view.token[-1] != "x" else "y")
    assert _request(view, "POST", "/mark", body, {**own, TOKEN_HEADER: wrong})[0] == 403
    status, why = _request(view, "POST", "/mark", body, {**own, "Origin": "http://evil.example"})
    assert status == 403 and "Origin" in why
    assert _request(view, "POST", "/mark", body, {k: v for k, v in own.items() if k != "Origin"})[0] == 403
    status, why = _request(view, "POST", "/mark", json.dumps({"label": "wet"}).encode(), own)
    assert status == 422 and "'wet'" in why
    assert _request(view, "POST", "/mark", b"x" * (MAX_BODY + 1), own)[0] == 413
    assert _request(view, "POST", "/mark", b"[1]", own)[0] == 400
    assert _request(view, "POST", "/nothing", body, own)[0] == 404
    assert _request(view, "GET", "/../etc/passwd")[0] == 404
    assert marks == [] and view.marks == []
    status, done = _request(view, "POST", "/mark", body, own)
    assert status == 200 and json.loads(done) == {"type": "mark", "label": "rough", "time": 1.5}
    assert marks == ["rough"]
    status, _ = _request(view, "POST", "/mark", json.dumps({"label": None}).encode(), own)
    assert status == 200 and marks == ["rough", None]


def test_without_marks_the_view_is_read_only():
    view = ViewSink(quiet=True)
    view.prepare()
    try:
        status, why = _request(view, "POST", "/mark", b"{}", _own(view))
        assert status == 404 and "read-only" in why
        assert _request(view, "GET", "/")[0] == 200
        assert json.loads(_request(view, "GET", "/state")[1])["marks"] is False
    finally:
        view.close()


def test_the_page_learns_the_scenes_stream_order_before_any_window_whatever_window_comes_first(tmp_path):
    """The page lays out its panels in the order hello lists the streams. They once came in the order
    the first windows arrived, so a fused graph's right stream could be shown before its left one."""
    from supramodal.node.scene.variants import with_view

    d = {"source": [{"name": n, "type": "synth", "seconds": 1.0} for n in ("zeta", "alpha")],
         "stream": [{"name": n, "source": n} for n in ("zeta", "alpha")]}           # features only: no model
    (view,) = view_sinks(build_node(with_view(scene_from_dict(d, str(tmp_path / "s.toml")), 0)))
    try:
        assert view.hello()["streams"] == ["zeta", "alpha"]                          # the scene's order
    finally:
        view.close()
    fused = ViewSink(quiet=True, streams=("left", "right", "fused"))                # as a fused scene names them
    loose = ViewSink(quiet=True)                                                     # no scene: first window first
    try:
        for name in ("fused", "right", "b", "right"):
            fused.emit(WindowEvent(name, 0, 0.0, 0.1, 0.1))
        assert fused.hello()["streams"] == ["left", "right", "fused", "b"]
        for name in ("b", "a", "b"):
            loose.emit(WindowEvent(name, 0, 0.0, 0.1, 0.1))
        assert loose.hello()["streams"] == ["b", "a"]
    finally:
        fused.close()
        loose.close()


def _page_that_never_reads(view: ViewSink) -> socket.socket:
    """A page's connection to ``view``'s events with a small receive buffer, which never reads; returned once
    the view has it among its pages."""
    page = socket.create_connection(("127.0.0.1", view.port), timeout=10)
    page.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    page.sendall(b"GET /events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    deadline = time.monotonic() + 30
    while view.hub.clients() == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    return page


def test_a_page_that_stops_reading_loses_messages_counted_and_never_blocks_the_sink():
    view = ViewSink(quiet=True)
    view.prepare()
    stalled = _page_that_never_reads(view)
    try:
        features = {"Af": [float(i) for i in range(200)]}
        t0 = time.monotonic()
        n = 20 * CLIENT_QUEUE
        for w in range(n):
            view.emit(WindowEvent("main", w, w * 0.1, w * 0.1 + 0.1, w * 0.1 + 0.1, features=features))
        took = time.monotonic() - t0
        assert view.hub.dropped > n // 2, view.hub.dropped     # most were dropped, and counted
        assert took < 30, f"{n} emits took {took:.1f} s"        # each is a few microseconds; never a wait
        assert view.stats()["client_dropped"] == view.hub.dropped
    finally:
        stalled.close()
        view.close()
    assert not [t.name for t in threading.enumerate() if t.name.startswith("view-")]


def test_a_page_given_up_counts_what_it_never_took_and_the_summary_says_so(monkeypatch):
    """Issue 35 (the view, with a browser): a page reading slowly (a small receive buffer) got windows 0-130 of
    600 and its connection was given up; the summary said ``pages: 1`` and nothing else. What it had not taken
    is counted as dropped, and the page as given up."""
    from supramodal.node.runtime.sinks import view as view_module

    monkeypatch.setattr(view_module, "WRITE_TIMEOUT", 1.0)
    view = ViewSink(quiet=True)
    view.prepare()
    slow = _page_that_never_reads(view)
    try:
        deadline = time.monotonic() + 30
        features = {"Af": [float(i) for i in range(400)]}
        n = CLIENT_QUEUE // 2                        # its queue never overflows: only the give-up loses them
        for w in range(n):
            view.emit(WindowEvent("main", w, w * 0.1, w * 0.1 + 0.1, w * 0.1 + 0.1, features=features))
        while view.hub.clients() and time.monotonic() < deadline:
            time.sleep(0.05)
        stats = view.stats()
        assert stats["pages"] == 1 and stats["pages_given_up"] == 1, stats
        assert 0 < stats["client_dropped"] <= n + 1, stats   # those still queued, and the one on its way
    finally:
        slow.close()
        view.close()


def test_mark_buttons_come_with_the_model_s_classes_once_the_first_window_names_them():
    """Issue 35 (the view, with a browser): ``record --marks --view`` with the labels left to the model's classes
    showed no mark buttons: the first hello (``labels: []``, before any window) was the page's last word. A
    window that first names a stream's classes sends a new hello with them."""
    view = ViewSink(quiet=True, streams=["main"])
    view.prepare()
    try:
        client = view.hub.open()
        first = [json.loads(m[len(b"data: "):]) for m in client.items]
        assert [m["labels"] for m in first if m["type"] == "hello"] == [[]]
        view.emit(WindowEvent("main", 0, 0.0, 0.1, 0.1, posteriors=__import__("numpy").array([0.7, 0.3]),
                              decision="silk", confidence=0.7, classes=("silk", "cork")))
        said = [json.loads(m[len(b"data: "):]) for m in client.items]
        hellos = [m for m in said if m["type"] == "hello"]
        assert hellos[-1]["labels"] == ["cork", "silk"] and hellos[-1]["classes"] == {"main": ["silk", "cork"]}
        assert [m["type"] for m in said].index("window") > said.index(hellos[-1])     # the buttons, then the window
        late = view.hub.open()                                                      # a page opened later: the new
        assert json.loads(late.items[0][len(b"data: "):])["labels"] == ["cork", "silk"]    # hello first
    finally:
        view.close()


def test_a_node_with_a_page_that_never_reads_runs_as_fast_and_counts_the_drops(tmp_path):
    sc = scene(tmp_path, {"type": "view"}, speed="max")
    graph = build_node(sc)
    view = _view(graph)
    attach(graph)
    graph.sinks[0].prepare()
    stalled = socket.create_connection(("127.0.0.1", view.port), timeout=10)
    stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    stalled.sendall(b"GET /events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    try:
        summary = Running(graph, None).join()
    finally:
        stalled.close()
    assert summary["windows"] == 8 * 100                         # every window processed
    (stats,) = summary["sinks"]
    assert stats["client_dropped"] > 0                           # the page's loss, counted in the view's stats
    assert stats["written"] + stats["dropped_windows"] + stats["dropped_events"] >= summary["windows"]


# -- bad input -------------------------------------------------------------------------------------

def test_binding_beyond_loopback_needs_remote_and_a_token(tmp_path):
    context = SinkContext("s.toml: [[sink]] #1")
    base = {"port": 0, "host": "0.0.0.0", "remote": False, "token": None, "labels": None}
    with pytest.raises(OptionError, match="remote = true and a token"):
        SPEC.build(base, context)
    with pytest.raises(OptionError, match="remote = true and a token"):
        SPEC.build({**base, "remote": True}, context)
    with pytest.raises(SceneError, match="token: expected .* at least 16"):
        scene(tmp_path, {"type": "view", "host": "0.0.0.0", "remote": True, "token": "short"})
    sink = SPEC.build({**base, "remote": True, "token": "a-long-enough-token-0123"}, context)
    try:
        assert isinstance(sink, QueuedSink) and sink.sink.token == "a-long-enough-token-0123"
    finally:
        sink.close()


def test_a_request_for_another_host_is_refused_even_a_read_dns_rebinding(marking_view):
    """Issue 35, item 6: a page of another site whose name resolves to this machine (DNS rebinding) sends
    its own name as Host: it may not read the stream (``/state``, ``/events``, the page) nor change it;
    the view's own names (with or without the port) are served."""
    view, marks = marking_view
    for path in ("/state", "/events", "/"):
        status, why = _request(view, "GET", path, headers={"Host": f"evil.example:{view.port}"})
        assert status == 403 and "Host" in why, (path, status)
    body = json.dumps({"label": "rough"}).encode()
    status, _ = _request(view, "POST", "/mark", body, {**_own(view), "Host": f"evil.example:{view.port}",
                                                        "Origin": f"http://evil.example:{view.port}"})
    assert status == 403 and marks == []
    for host in (f"127.0.0.1:{view.port}", f"localhost:{view.port}", "127.0.0.1"):
        assert _request(view, "GET", "/state", headers={"Host": host})[0] == 200, host


def test_a_remote_view_takes_changes_from_the_page_it_served_at_the_address_it_was_reached_by():
    """Issue 35, item 26: served on every address (host 0.0.0.0, remote, a token), the page reached as
    http://ADDRESS:PORT sends that Origin with that Host: its marks are taken; another origin is refused."""
    got = []
    view = ViewSink(0, "0.0.0.0", remote=True, token="a-long-enough-token-0123", labels=["rough"], quiet=True)
    view.on_mark = lambda label: got.append(label) or 1.0
    view.prepare()
    try:
        body = json.dumps({"label": "rough"}).encode()
        own = {TOKEN_HEADER: view.token, "Content-Type": "application/json"}
        page = f"192.0.2.2:{view.port}"          # the machine's address on the robot's network, say
        assert _request(view, "POST", "/mark", body, {**own, "Host": page, "Origin": f"http://{page}"})[0] == 200
        assert _request(view, "POST", "/mark", body, {**own, "Host": page,
                                                     "Origin": "http://evil.example"})[0] == 403
        assert got == ["rough"]
    finally:
        view.close()


def test_a_page_that_resets_its_connection_prints_no_traceback(marking_view, capfd):
    """Issue 35, item 18: a client that resets its connection mid-request made the view print a server
    traceback (11 of 12 requests, no token needed). A reset is no error of the node's: nothing is said,
    and the view goes on answering."""
    import struct

    view, _ = marking_view
    for _ in range(12):
        s = socket.create_connection(("127.0.0.1", view.port), timeout=10)
        s.sendall(b"POST /mark HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 100000\r\n\r\nabc")
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))    # RST on close
        s.close()
    time.sleep(0.5)
    assert _request(view, "GET", "/state")[0] == 200
    err = capfd.readouterr().err
    assert "Traceback" not in err, err


def test_a_port_in_use_or_out_of_range_is_refused_naming_the_fix(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(ViewError, match=f"127.0.0.1:{port}.*give another port, or 0"):
            ViewSink(port, quiet=True)
    with pytest.raises(SceneError, match="port: expected a TCP port 0..65535"):
        scene(tmp_path, {"type": "view", "port": 70000})


def test_a_view_serves_on_ipv6_loopback_and_a_host_that_is_no_address_here_names_that_fix():
    """Issue 35 item 30: ``host = "::1"`` serves the page (it said "Address family for hostname not
    supported; give another port"); a host that does not resolve, or is no address of this machine,
    asks for an address of this machine, not another port."""
    try:
        with socket.socket(socket.AF_INET6) as probe:
            probe.bind(("::1", 0))
    except OSError:
        pytest.skip("this machine has no IPv6 loopback")
    view = ViewSink(0, host="::1", quiet=True)
    view.prepare()
    try:
        assert view.url.startswith("http://[::1]:")
        conn = http.client.HTTPConnection("::1", view.port, timeout=10)
        conn.request("GET", "/state", headers={"Host": f"[::1]:{view.port}"})
        assert conn.getresponse().status == 200
        conn.close()
    finally:
        view.close()
    for host in ("no-such-host.invalid", "192.0.2.1"):       # unresolvable; TEST-NET, no address of ours
        with pytest.raises(ViewError, match=f"{host}.*give an address of this machine") as refused:
            ViewSink(0, host=host, remote=True, token="a-token-of-twenty-chars", quiet=True)
        assert "another port" not in str(refused.value)


def test_events_are_coloured_by_how_grave_they_are_and_shown_on_common_time(browser):
    """Issue 36, item 8: "opened" and "reconnected" showed as red alarms like "unplugged" (every event did, then
    every kind not on the page's own list was news); the event list showed Unix epoch seconds, then the host's
    clock time, beside the windows' common time. An event's severity comes with it, from the sink's one
    mapping (:data:`SEVERITY`): a loss is a red alarm, a warning amber, news blue; its time is on common time."""
    view = ViewSink(quiet=True)
    view.start(time.monotonic() - 100.0)              # the graph started 100 s ago: common time 100 now
    zero = time.time() - 100.0                        # common time 0 on the wall clock the events are stamped on
    try:
        browser.open(view.url)
        browser.wait_for("!!document.querySelector('#conn.live')", timeout=60)
        view.event(DriverEvent("unplug", "lost /dev/ttyACM0: [Errno 5] Input/output error", zero + 42.5))
        view.event(DriverEvent("reconnect", "reconnected to /dev/ttyACM0 after 1.20 s", zero + 45.0))
        view.event(DriverEvent("sense_lost", "fusion: no window from 'mic' within 0.5 s", zero + 60.0, source="fused"))
        view.event(DriverEvent("brand_new_kind", "a driver of tomorrow says something", zero + 70.0))
        browser.wait_for("!!document.querySelector('#banners .event-brand_new_kind')", timeout=30)
        shown = browser.eval("Object.fromEntries([...document.querySelectorAll('#banners .banner')].map("
                             "b => [b.dataset.kind, [b.dataset.severity, getComputedStyle(b).color]]))")
        severities = {kind: sev for kind, (sev, _) in shown.items()}
        assert severities == {"event-unplug": "alarm", "event-reconnect": "info", "event-sense_lost": "warning",
                              "event-brand_new_kind": "warning"}, shown
        colours = {sev: colour for sev, colour in shown.values()}
        assert len(set(colours.values())) == 3, f"three severities, three colours: {shown}"
        assert colours["alarm"] == "rgb(180, 35, 24)", shown          # var(--bad): the red of a wrong decision
        items = browser.eval("[...document.querySelectorAll('#eventlog li')].map(li => [li.dataset.severity, "
                             "li.querySelector('.when').textContent])")
        assert [sev for sev, _ in items] == ["warning", "warning", "info", "alarm"], items
        when = [float(w.removesuffix(" s")) for _, w in items]         # common time, s: never a clock or epoch
        for got, want in zip(when, [70.0, 60.0, 45.0, 42.5]):
            assert abs(got - want) < 0.5, items                         # the host's clocks, read a moment apart
    finally:
        view.close()


def test_every_kind_of_event_the_node_says_has_a_severity():
    """The severity mapping is the one place a kind's gravity is said (the page has no list of its own): every
    kind a driver, the fusion or the decisions record is in it, so that none falls to the default by oversight."""
    import re

    root = Path(__file__).resolve().parents[1]
    said = re.compile(r'(?:_record|\.record|_say|DriverEvent)\(\s*f?"([a-z_]+)"|_notice\([^()]*,\s*"([a-z_]+)"')
    kinds = {a or b for folder in ("drivers", "node", "replay") for path in (root / folder).rglob("*.py")
             for a, b in said.findall(path.read_text())}
    assert {"unplug", "reconnect", "open", "gap", "silence", "sense_lost", "change"} <= kinds, kinds  # the scan works
    assert kinds <= set(SEVERITY), f"kinds without a severity: {sorted(kinds - set(SEVERITY))}"
    assert set(SEVERITY.values()) == {"alarm", "warning", "info"}
    lossy = {"unplug", "gap", "overrun", "overflow", "dropped", "restart", "channels", "silence", "error"}
    assert {k for k in lossy if severity(k) != "alarm"} == set()
    assert {k for k in ("open", "close", "reconnect", "sense_back", "change") if severity(k) != "info"} == set()
    ev = DriverEvent("reconnect", "back", 1_800_000_012.25)
    assert event_message(ev)["severity"] == "info" and "common_time" not in event_message(ev)
    assert event_message(ev, 1_800_000_000.0)["common_time"] == 12.25    # beside time, the wall clock's, unchanged
    assert event_message(ev, 1_800_000_000.0)["time"] == 1_800_000_012.25


#: A fused two-stream page as a long run shows it: the two-sense world's streams (the whisker array's 20
#: channels, the cochlea's 50, with two features), their fusion, an hour's counts, long names, the events.
WHISKERS, MIC = "whiskers", "mic"
CLASSES = ("H1a", "H1b", "H2a", "H2b", "F1a", "F1b", "F2a", "F2b")


def _a_long_runs_page(view: ViewSink, windows: int = 40) -> None:
    """Send ``view`` what a fused two-sense graph sends its page (windows, health, events), at once."""
    import numpy as np

    rng = np.random.default_rng(36)
    channels = {WHISKERS: 20, MIC: 50}
    for w in range(windows):
        end = 3600.0 + 0.1 * (w + 1)
        for stream, n in channels.items():
            p = rng.dirichlet(np.ones(len(CLASSES)))
            features = {"Af": rng.gamma(1.0, 1e-3, n)} | ({"A": rng.gamma(1.0, 1e-2, n)} if stream == MIC else {})
            k = int(np.argmax(p))
            view.emit(WindowEvent(stream, 36000 + w, end - 0.1, end, end, features=features, posteriors=p,
                                  decision=CLASSES[k], confidence=float(p[k]), truth="H1b", classes=CLASSES,
                                  flags=frozenset({"gap"} if w == 7 else ()), latency_ms=1.5,
                                  pooled=PooledDecision("H1b", 0.98765, 123, decided=True)))
        p = rng.dirichlet(np.ones(len(CLASSES)))
        k = int(np.argmax(p))
        view.emit(WindowEvent("fused", 36000 + w, end - 0.1, end, end, posteriors=p, decision=CLASSES[k],
                              confidence=float(p[k]), truth="H1b", classes=CLASSES, senses=(WHISKERS, MIC),
                              flags=frozenset({"alone"} if w % 9 == 0 else ())))
    hour = {"windows": 36040, "frames": {"delivered": 158_760_000, "filled": 12_345, "dropped": 678},
            "latency_ms": {"p50": 1.43, "p99": 117.96, "max": 250.0}}
    view.hub.publish({"type": "health", "clients": 2, "client_dropped": 1234,
                      "streams": {WHISKERS: {**hour, "frames": {**hour["frames"], "delivered": 18_000_000}},
                                  MIC: hour},
                      "clocks": {WHISKERS: {"ppm": 37.4, "delay_ms": 1.27, "jitter_ms": 5.22},
                                 MIC: {"ppm": -67.5, "delay_ms": 1.57, "jitter_ms": 6.2}},
                      "fusion": {"windows": 36040, "paired": 35_912, "alone": 128, "late": {WHISKERS: 3, MIC: 12},
                                 "dropouts": {WHISKERS: 0, MIC: 2}, "latency_ms": {"p50": 1.5, "p99": 17.96}},
                      "sinks": [{"sink": "JsonLinesSink /home/robot/runs/2026-11-29-whiskers-and-microphone/"
                                         "decisions_of_the_whole_afternoon.jsonl",
                                 "written": 1_234_567_890, "dropped_windows": 12, "dropped_events": 3, "errors": 0},
                                {"sink": f"ViewSink {view.url}", "written": 108_120, "dropped_windows": 0,
                                 "dropped_events": 0, "errors": 0}]}, keep="latest")
    now = time.time()
    for kind, message in [
            ("open", "opened /dev/serial/by-id/usb-Supramodal_Whisker_Board_v2_0123456789ABCDEF-if00"),
            ("silence", "no valid frame from /dev/serial/by-id/usb-Supramodal_Whisker_Board_v2_0123456789ABCDEF-if00 "
                        "for 2.0 s: 4096 bytes arrived but no valid frame (12 CRC errors, 3 bad headers, 77 bytes "
                        "skipped): a wrong baud rate (set the board's; USB boards ignore it), another device on this "
                        "port, or firmware sending another format (docs/serial-frames.md)"),
            ("unplug", "lost /dev/ttyACM0: [Errno 5] Input/output error; reopening with backoff"),
            ("reconnect", "reconnected to /dev/ttyACM0 after 1.20 s"),
            ("sense_lost", "fusion: no window from 'mic' within 0.5 s; deciding on 'whiskers' alone until it "
                           "comes back")]:
        view.event(DriverEvent(kind, message, now, source=WHISKERS if kind != "sense_lost" else "fused"))


#: Every element that reaches past the window's right edge, and every one that clips what it holds
#: (a table cell, or a box that scrolls or hides what overflows it): described, none expected.
OVERFLOWS = """(() => {
  const width = Math.min(innerWidth, document.documentElement.clientWidth), out = [];
  const name = e => e.tagName.toLowerCase() + (e.id ? "#" + e.id : "") +
    (typeof e.className === "string" && e.className.trim() ? "." + e.className.trim().split(/\\s+/).join(".") : "") +
    (e.dataset.stream ? "[" + e.dataset.stream + "]" : "") + " '" + (e.textContent || "").trim().slice(0, 30) + "'";
  for (const e of document.querySelectorAll("body *")) {
    const r = e.getBoundingClientRect();
    if (r.width > 0 && r.right > width + 0.5) out.push(name(e) + " ends at " + r.right.toFixed(1));
    const clips = e.matches("td, th") || getComputedStyle(e).overflowX !== "visible";
    if (clips && r.width > 0 && e.scrollWidth > e.clientWidth + 1)
      out.push(name(e) + " clips " + e.scrollWidth + " > " + e.clientWidth);
  }
  const page = document.documentElement.scrollWidth;
  if (page > innerWidth) out.push("the page is " + page + " wide");
  return out;
})()"""


@pytest.mark.parametrize("width, height", [(1280, 800), (1024, 768)])
def test_a_fused_two_stream_page_fits_a_1280_px_window_with_nothing_cut(browser, width, height):
    """Issue 36, item 8: in a 1400 px window the health column overflowed (its p99 and errors columns cut; the
    page's screenshots in docs/img too). A fused two-stream page with an hour's counts, long names and paths,
    the events and the feature bars' labels fits a 1280 x 800 window, and a narrower one (the health under the
    streams): no element reaches past the right edge, none clips its content, the screenshot is the window's
    width."""
    view = ViewSink(quiet=True, streams=(WHISKERS, MIC, "fused"),
                    channels={WHISKERS: channel_labels(whisker_bank()), MIC: channel_labels(cochlea_bank(50))})
    view.start(time.monotonic() - 3600.0)
    try:
        _a_long_runs_page(view)
        browser.open(view.url, width=width, height=height)
        browser.wait_for("document.querySelectorAll('#streams .stream[data-window]').length === 3 && "
                         "document.querySelectorAll('#frames tbody tr').length === 3 && "
                         "document.querySelectorAll('#eventlog li').length === 5", timeout=60)
        assert browser.eval("innerWidth") == width
        assert browser.eval(OVERFLOWS) == []
        png = browser.screenshot(full=True)
        assert png_size(png)[0] == width, png_size(png)
        # every column of the health's tables shown, p99 and errors among them
        for table, last in (("frames", "117.96"), ("sinks", "0")):
            cells = browser.eval(f"[...document.querySelectorAll('#{table} tbody tr:first-child td')].map(td => "
                                 "[td.textContent, td.getBoundingClientRect().width])")
            assert cells[-1][0] == last and all(w > 10 for _, w in cells), cells
    finally:
        view.close()


def test_the_feature_bars_are_labelled_with_the_bank_s_channels(browser, tmp_path):
    """Issue 36, item 8: the Af bars had no channel labels. Under the bars, each channel's name and centre
    frequency as the stream's bank gives them (every k-th where they would overlap: the cochlea's 50); a stream
    the view knows no bank of has its bars numbered. The view learns the banks from the scene."""
    whiskers, cochlea = whisker_bank(), cochlea_bank(50)
    view = ViewSink(quiet=True, streams=(WHISKERS, MIC, "other"),
                    channels={WHISKERS: channel_labels(whiskers), MIC: channel_labels(cochlea)})
    view.start(time.monotonic())
    try:
        _a_long_runs_page(view, windows=3)
        view.emit(WindowEvent("other", 0, 0.0, 0.1, 0.1, features={"Af": [float(i) for i in range(6)]}))
        browser.open(view.url, width=1280, height=800)
        browser.wait_for("document.querySelectorAll('.chaxis span').length > 30", timeout=60)
        labels = browser.eval("""Object.fromEntries([...document.querySelectorAll('#streams .stream')].map(s => [
            s.dataset.stream, {what: s.querySelector('.chwhat').textContent,
                               spans: [...s.querySelectorAll('.chaxis span')].map(sp => [Number(sp.dataset.channel),
                                       sp.innerText.split('\\n'), sp.getBoundingClientRect().left,
                                       sp.getBoundingClientRect().right])}]))""")
    finally:
        view.close()
    w = labels[WHISKERS]
    assert w["what"] == "name, centre frequency in Hz"
    assert [name for _, (name, _), _, _ in w["spans"]] == list(whiskers.names)            # 20 fit: every one
    assert [hz for _, (_, hz), _, _ in w["spans"]][:1] == [f"{whiskers.cf[0]:.0f}"]
    m = labels[MIC]
    shown = [k for k, _, _, _ in m["spans"]]
    assert 5 < len(shown) < 50 and shown[0] == 0 and len({b - a for a, b in zip(shown, shown[1:])}) == 1, shown
    assert [name for _, (name, _), _, _ in m["spans"]] == [cochlea.names[k] for k in shown]
    assert m["spans"][-1][1][1].endswith("k")                                              # kHz at the top
    for panel in (w, m):                                                                   # side by side, never
        assert all(a[3] <= b[2] for a, b in zip(panel["spans"], panel["spans"][1:])), panel  # overlapping
    o = labels["other"]
    assert o["what"] == "index" and [t for _, t, _, _ in o["spans"]] == [[str(i)] for i in range(6)]
    # from a scene: each stream's bank, before any window
    d = {"source": [{"name": n, "type": "synth", "seconds": 1.0} for n in ("a", "b")],
         "stream": [{"name": "a", "source": "a"}, {"name": "b", "source": "b", "bank": {"kind": "cochlea"}}]}
    from supramodal.node.scene.variants import with_view

    (built,) = view_sinks(build_node(with_view(scene_from_dict(d, str(tmp_path / "s.toml")), 0)))
    try:
        channels = built.hello()["channels"]
        assert channels["a"]["names"] == list(whiskers.names)
        assert channels["b"]["names"][:2] == ["ch00", "ch01"] and len(channels["b"]["centre_hz"]) == 50
    finally:
        built.close()


def test_a_driver_event_shows_as_a_banner_within_a_second(browser):
    view = ViewSink(quiet=True)
    view.prepare()
    try:
        browser.open(view.url)
        browser.wait_for("!!document.querySelector('#conn.live')", timeout=60)
        sent = time.monotonic()
        view.event(DriverEvent("unplug", "the whisker board is unplugged; waiting for it", 12.5))
        browser.wait_for("!!document.querySelector('#banners .event-unplug')", timeout=30, interval=0.02)
        assert time.monotonic() - sent < 1.0 + 2.0        # within 1 s, plus the test's own polling on a busy machine
        assert "unplugged" in browser.eval("document.querySelector('#banners .event-unplug').textContent")
        assert "unplug" in browser.eval("document.querySelector('#eventlog li').textContent")
    finally:
        view.close()


@pytest.mark.hardware
def test_an_unplug_of_the_mock_board_shows_a_banner_within_a_second(tmp_path, browser):
    """The whisker board on a pty unplugs once, 1.5 s into its stream: the page shows the unplug
    banner, and then the reconnect, driven by the serial driver's own events through the sink queue
    and the event stream (measured from the moment the board closed its port)."""
    import numpy as np

    from supramodal.drivers.mock_whisker import FaultSpec, MockWhiskerDevice

    rate = 5000
    samples = 0.3 * np.random.default_rng(3).standard_normal((4 * rate, 20))
    faults = FaultSpec(unplug_every=1.5, unplug_for=0.5, unplug_limit=1)
    with MockWhiskerDevice(samples, float(rate), samples_per_frame=32, faults=faults, seed=4) as dev:
        d = {"driver": {"type": "serial", "port": dev.port, "rate": float(rate), "channels": 20,
                        "mapping": "per-channel"},
             "bank": {"kind": "whisker"}, "features": {"names": ["Af"]}, "sink": [{"type": "view"}]}
        graph = build_node(scene_from_dict(d, str(tmp_path / "board.toml"), tmp_path))
        view = _view(graph)
        attach(graph)
        run = Running(graph, None)
        try:
            browser.open(view.url)
            browser.wait_for("!!document.querySelector('#conn.live')", timeout=60)
            assert dev.wait_for_reader(60), "the node never opened the port"
            dev.start()
            browser.wait_for("!!document.querySelector('#banners .event-unplug')", timeout=30, interval=0.02)
            shown = time.monotonic()
            (unplugged,) = dev.ledger.unplug_times
            # within 1 s; the slack is the test's polling of the browser on a busy machine
            assert shown - unplugged < 1.0 + 1.0, shown - unplugged
            browser.wait_for("!!document.querySelector('#banners .event-reconnect, #eventlog .event-reconnect')"
                             " || [...document.querySelectorAll('#eventlog li')].some(li => "
                             "li.textContent.includes('reconnect'))", timeout=30)
            dev.finished.wait(30)
        finally:
            graph.stop()
            run.join()


@pytest.mark.slow   # a long run: two models trained on the spot and fused, in the browser
def test_a_fused_graph_shows_both_streams_the_fused_one_and_the_pairing(tmp_path, browser):
    from supramodal.node.scene.schema import load_scene
    from supramodal.node.scene.variants import with_view

    sc = load_scene(str(Path(__file__).resolve().parents[1] / "examples" / "two_streams_fused.toml"))
    graph = build_node(with_view(replace(sc, sinks=[]), 0))
    view = _view(graph)
    attach(graph)
    run = Running(graph, 6.0)
    browser.open(view.url)
    shown = ("[...document.querySelectorAll('#streams .stream')]"
             ".map(s => s.dataset.stream + ':' + (s.dataset.window || ''))")
    browser.wait_for(f"{shown}.every(s => !s.endsWith(':')) && {shown}.length == 3", timeout=120)
    assert [s.split(":")[0] for s in browser.eval(shown)] == ["left", "right", "fused"]
    fused = "document.querySelector('[data-stream=\"fused\"]')"
    assert set(browser.eval(f"{fused}.dataset.senses").split(",")) <= {"left", "right"}
    browser.wait_for(f"{fused}.querySelector('.pairing').textContent.startsWith('paired ')", timeout=30)
    # the real page fits the browser's 1280 px too, its bars labelled with the left stream's bank
    assert browser.eval(OVERFLOWS) == []
    label = browser.eval("document.querySelector('[data-stream=\"left\"] .chaxis span').innerText")
    assert label.split("\n")[0] == view.hello()["channels"]["left"]["names"][0], label
    summary = run.join()
    assert summary["fusion"]["windows"] > 0


def test_run_view_serves_the_page_beside_the_json_lines_and_refuses_a_bad_port(tmp_path):
    import subprocess
    import sys
    import urllib.request

    (tmp_path / "s.toml").write_text('[driver]\ntype = "synth"\ntextures = "reference"\nseconds = 1.0\n'
                                     '[bank]\nkind = "whisker"\n[features]\nnames = ["Af"]\n')
    cmd = [sys.executable, "-m", "supramodal", "run", str(tmp_path / "s.toml"), "--json", "--seconds", "4",
           "--quiet", "--view"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stderr.readline()
        assert line.startswith("supramodal: view at http://127.0.0.1:") and "#token=" in line, line
        url = line.split()[3]
        with urllib.request.urlopen(url, timeout=30) as r:
            assert r.status == 200 and b"<canvas" in r.read()
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    lines = [json.loads(x) for x in out.splitlines()]
    assert sum("window" in d for d in lines) == 40
    sinks = lines[-1]["sinks"]
    assert [s["sink"].split()[0] for s in sinks] == ["JsonLinesSink", "ViewSink"]
    assert sinks[1]["dropped_windows"] == 0 and sinks[1]["url"] == url
    bad = subprocess.run(cmd[:-1] + ["--view", "70000"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--view 70000: expected a TCP port 0..65535 (0: any free one)" in bad.stderr


def test_a_summary_with_numbers_json_cannot_carry_reaches_the_page_as_null():
    view = ViewSink(quiet=True)
    try:
        view.summary({"window_accuracy": float("nan"), "ppm": float("inf"), "windows": 3})
        page = view.hub.open()
        messages = [json.loads(m.decode()[len("data: "):]) for m in page.items]
        (summary,) = [m["summary"] for m in messages if m["type"] == "summary"]
        assert summary == {"window_accuracy": None, "ppm": None, "windows": 3}
    finally:
        view.close()
