"""``supramodal view REC.toml | SESSION`` (node/workflows/view_replay.py): a recording played back into the
view's page, paused and sped up from the page (with the run's token), in headless chromium."""

from __future__ import annotations

import http.client
import json
import threading
import time

import pytest
from view_browser import Browser, chromium_path

from supramodal.errors import InputError
from supramodal.node.scene.build import build_node
from supramodal.node.runtime.taps.recorder import SessionRecorder
from supramodal.node.scene.schema import scene_from_dict
from supramodal.node.runtime.sinks.view import TOKEN_HEADER
from supramodal.node.workflows.view_replay import ViewReplay

PANEL = "document.querySelector('[data-stream=\"main\"]')"


@pytest.fixture
def session(tmp_path):
    """3 s of the synthesised whisker textures, recorded as a session (no model: feature windows)."""
    sc = scene_from_dict({"driver": {"type": "synth", "textures": "reference", "seconds": 1.0, "speed": "max"},
                          "bank": {"kind": "whisker"}, "features": {"names": ["A", "f", "Af"]},
                          "sink": [{"type": "text", "path": str(tmp_path / "out.txt")}]}, "s.toml", tmp_path)
    recorder = SessionRecorder(tmp_path, "rec", "{}")
    build_node(sc, recorder=recorder).run(max_seconds=3.0)
    return tmp_path / "rec"


def _post(replay, body, token=True):
    view = replay.view
    headers = {"Origin": f"http://127.0.0.1:{view.port}", "Content-Type": "application/json"}
    if token:
        headers[TOKEN_HEADER] = view.token
    conn = http.client.HTTPConnection("127.0.0.1", view.port, timeout=30)
    try:
        conn.request("POST", "/control", body=json.dumps(body).encode(), headers=headers)
        r = conn.getresponse()
        return r.status, r.read().decode()
    finally:
        conn.close()


def test_a_session_plays_into_the_page_which_pauses_and_changes_speed(session):
    if chromium_path() is None:
        pytest.skip("Debian's chromium is not installed (apt-get install -y chromium; .ci/run installs it)")
    replay = ViewReplay(session, speed=1.0, quiet=True)
    replay.load()
    assert len(replay.items) == 30                      # 3 s of 100 ms windows
    serving = threading.Thread(target=replay.serve, daemon=True)
    serving.start()
    browser = Browser()
    try:
        browser.open(f"{replay.view.url}#token={replay.view.token}")
        browser.wait_for(f"{PANEL} && Number({PANEL}.dataset.window) >= 2", timeout=60)
        assert browser.eval(f"{PANEL}.querySelector('.decision').textContent") == "(no model)"
        assert browser.eval(f"{PANEL}.querySelector('.imgfeature').textContent") == "A"
        # pause from the page: the readout stops
        browser.eval("document.querySelector('#pause').click()")
        browser.wait_for("document.querySelector('#pause').textContent == 'play'")
        held = browser.eval(f"{PANEL}.dataset.window")
        time.sleep(1.0)
        assert browser.eval(f"{PANEL}.dataset.window") == held
        assert replay.state()["paused"] is True
        # ten times faster, and on: the rest of the 3 s comes in well under 3 s
        browser.eval("const s = document.querySelector('#speed'); s.value = '10'; s.dispatchEvent(new Event('change'))")
        deadline = time.monotonic() + 30
        while replay.state()["speed"] != 10 and time.monotonic() < deadline:
            time.sleep(0.05)
        browser.eval("document.querySelector('#pause').click()")
        browser.wait_for(f"Number({PANEL}.dataset.window) == 29", timeout=30)
        browser.wait_for("document.querySelector('#mode').textContent.endsWith('ended')", timeout=30)
    finally:
        browser.close()
        replay.stop()
        serving.join(30)
    assert not serving.is_alive()
    assert not [t.name for t in threading.enumerate() if t.name.startswith("view-")]


def test_the_controls_need_the_token_and_refuse_bad_values(session):
    replay = ViewReplay(session, quiet=True)
    serving = threading.Thread(target=replay.serve, daemon=True)
    serving.start()
    try:
        deadline = time.monotonic() + 60
        while not replay.view._started and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _post(replay, {"paused": True}, token=False)[0] == 403
        assert replay.state()["paused"] is False
        # a 900-digit speed (issue 35, item 17) raised OverflowError and got no answer
        for bad in ({"speed": 0}, {"speed": "fast"}, {"speed": 1e9}, {"speed": int("9" * 900)}, {"paused": 1},
                    {"rewind": True}):
            status, why = _post(replay, bad)
            assert status == 422, (bad, status, why)
        assert replay.state() == {**replay.state(), "paused": False, "speed": 1.0}
        status, state = _post(replay, {"paused": True, "speed": 4})
        assert status == 200 and json.loads(state)["paused"] is True and json.loads(state)["speed"] == 4.0
    finally:
        replay.stop()
        serving.join(30)
    assert not serving.is_alive()


def test_what_is_neither_a_recording_nor_a_session_is_refused_naming_the_fix(tmp_path):
    with pytest.raises(InputError, match="neither a recording's REC.toml nor a session"):
        ViewReplay(tmp_path / "nothing")
    with pytest.raises(InputError, match="playback speed"):
        ViewReplay(tmp_path / "nothing", speed=0)


def test_a_replay_plays_each_driver_event_among_the_windows_it_came_with_on_the_recordings_time():
    """A driver event is stamped on the wall clock, which a replay at full speed does not follow: kept for
    the page, it is placed (and shown, ``common_time``) at the recording's time the node had reached, so
    that it plays between the windows it came among, and not after the whole recording."""
    import numpy as np

    from supramodal.drivers.base import DriverEvent
    from supramodal.node.runtime.events import WindowEvent
    from supramodal.node.workflows.view_replay import _Keep

    keep = _Keep()
    for i in range(3):
        keep.emit(WindowEvent("main", i, 0.1 * i, 0.1 * i + 0.1, 0.1 * i + 0.1, decision="a", confidence=0.9,
                              posteriors=np.array([0.9, 0.1]), classes=("a", "b")))
    keep.event(DriverEvent("gap", "12 frames lost", time.time()))
    for i in range(3, 6):
        keep.emit(WindowEvent("main", i, 0.1 * i, 0.1 * i + 0.1, 0.1 * i + 0.1, decision="a", confidence=0.9,
                              posteriors=np.array([0.9, 0.1]), classes=("a", "b")))
    played = [m.get("event") or m["window"] for _, m in sorted(keep.items, key=lambda item: item[0])]
    assert played == [0, 1, 2, "gap", 3, 4, 5]
    gap = next(m for _, m in keep.items if m.get("event") == "gap")
    assert gap["common_time"] == 0.3 and gap["severity"] == "alarm"
