"""Contacts from the robot's own signal, without a bus: the timeline, the markers, the scene's rules."""

from __future__ import annotations

import random

import pytest

from supramodal.drivers.contact import CONTACT_MARKERS, check_contact_from, marker_state
from supramodal.errors import InputError
from supramodal.node.runtime.contacts import ContactTimeline
from supramodal.node.scene.build import build_node
from supramodal.node.scene.schema import SceneError, scene_from_dict

from contact_edges import scene


def _state_at(states: list[tuple[float, bool]], t: float) -> bool:
    """The plain reference: the last state said at or before ``t`` (ties: the later said), else False."""
    best = None
    for k, (at, state) in enumerate(states):
        if at <= t and (best is None or (at, k) >= best[:2]):
            best = (at, k, state)
    return best[2] if best is not None else False


def test_the_timeline_is_the_last_state_said_before_each_time_whatever_order_the_states_come_in():
    """Repeats, out-of-order states (two buses' delays) and a state at an edge's own time: the timeline
    says, at every time, the state of the latest sample at or before it, as a plain scan of every
    state said does; touches count the rising edges of that signal."""
    rng = random.Random(7)
    for _ in range(200):
        times = sorted(rng.sample(range(1000), rng.randint(1, 40)))
        states = [(t / 10, rng.random() < 0.5) for t in times]
        shuffled = states[:]
        # a few swaps of neighbours: a state comes a little late
        for _ in range(rng.randint(0, 5)):
            i = rng.randrange(len(shuffled))
            j = min(len(shuffled) - 1, i + 1)
            shuffled[i], shuffled[j] = shuffled[j], shuffled[i]
        timeline = ContactTimeline("x")
        for k in range(0, len(shuffled), 3):           # in batches, as a poll returns them
            timeline.add(shuffled[k:k + 3])
        for t in [s / 10 + d for s in range(-5, 1010, 7) for d in (0.0, 0.05)]:
            assert timeline.at(t) == _state_at(states, t), (t, states, shuffled)
        ref = [_state_at(states, t / 10) for t in range(-1, 1001)]
        assert timeline.touches == sum(b and not a for a, b in zip(ref, ref[1:]))
        assert timeline.states == len(states)
        edges = timeline.edges()
        assert all(a[1] != b[1] for a, b in zip(edges, edges[1:])) and (not edges or edges[0][1])


def test_a_window_is_in_the_contact_that_holds_at_its_centre():
    timeline = ContactTimeline("x")
    timeline.add([(1.0, True), (1.2, True), (2.0, False)])
    assert timeline.edges() == [(1.0, True), (2.0, False)]
    assert not timeline.in_window(0.9, 1.05)          # centre 0.975: before the touch
    assert timeline.in_window(0.95, 1.1)              # centre 1.025: in it
    assert timeline.in_window(1.9, 2.05) and not timeline.in_window(1.95, 2.1)
    assert timeline.summary() == {"from": "x", "states": 3, "touches": 1}


def test_markers_say_a_state_in_any_case_and_anything_else_says_none():
    for word, state in CONTACT_MARKERS.items():
        assert marker_state(word) is state and marker_state(f" {word.upper()} ") is state
    assert marker_state(1.0) is True and marker_state(0) is False and marker_state(-3) is True
    for other in ("hello", "", "truee", float("nan"), float("inf"), None, True, [1]):
        assert marker_state(other) is None, other


@pytest.mark.parametrize("value, says", [
    ("/robot/touch", "BUS:ADDRESS"),
    ("can:/robot/touch", "no bus 'can'"),
    ("ros2:", "no ROS 2 topic name"),
    ("ros2:/robot//touch", "no ROS 2 topic name"),
    ("ros2:/robot/9touch", "no ROS 2 topic name"),
    ("lsl:", "an LSL stream's name"),
    ("lsl:it's", "an LSL stream's name"),
    (3, "BUS:ADDRESS"),
])
def test_a_contact_from_that_names_no_signal_is_refused_saying_what_is_accepted(value, says):
    with pytest.raises(InputError, match=says):
        check_contact_from(value)


def test_good_contact_from_values_name_their_bus_and_address():
    assert check_contact_from("ros2:/robot/in_contact") == ("ros2", "/robot/in_contact")
    assert check_contact_from("ros2:in_contact") == ("ros2", "in_contact")
    assert check_contact_from("lsl:Robot contacts") == ("lsl", "Robot contacts")


def test_a_scene_refuses_contact_from_without_contact_scope_or_with_a_bad_address():
    d = scene("ros2:/robot/in_contact")
    d["stream"][0]["decision"]["scope"] = "window"
    with pytest.raises(SceneError, match=r'\[decision\] contact_from .* needs scope = "contact"'):
        scene_from_dict(d, "c.toml")
    d = scene("ros2:/robot//in_contact")
    with pytest.raises(SceneError, match=r"c.toml: .*\[decision\] contact_from .*no ROS 2 topic name"):
        scene_from_dict(d, "c.toml")
    d = {"source": [{"name": "a", "type": "twosense", "sense": "whiskers"},
                    {"name": "b", "type": "twosense", "sense": "microphone"}],
         "stream": [{"name": "a", "source": "a", "bank": {"kind": "whisker"}, "model": {"train_on_start": True}},
                    {"name": "b", "source": "b", "bank": {"kind": "cochlea"}, "model": {"train_on_start": True}}],
         "fusion": {"streams": ["a", "b"], "decision": {"scope": "window", "contact_from": "lsl:touch"}}}
    with pytest.raises(SceneError, match=r'\[fusion.decision\] contact_from .* needs scope = "contact"'):
        scene_from_dict(d, "c.toml")


def test_a_file_replayed_at_its_own_time_cannot_take_contacts_from_the_robot_s_clock():
    """A source at max speed keeps its own time; the robot's contacts are on the host's clock: refused at
    build, naming the source and the two ways out."""
    d = scene("lsl:touch")
    d["stream"][0]["model"] = {}                        # feature windows: contacts, and no decision to pool
    del d["stream"][0]["decision"]["n"]
    with pytest.raises(SceneError, match=r"source 'whiskers' keeps its own time .*--speed 1.*contact_threshold"):
        build_node(scene_from_dict(d, "c.toml"), speed="max")


def test_a_long_run_keeps_a_bounded_number_of_states_and_still_counts_every_touch(monkeypatch):
    from supramodal.node.runtime import contacts

    monkeypatch.setattr(contacts, "MAX_STATES", 10)
    timeline = ContactTimeline("x")
    for k in range(60):                                 # 30 touches, one state at a time
        timeline.add([(k * 0.5, k % 2 == 0)])
    assert len(timeline.edges()) <= 10 and timeline.touches == 30 and timeline.states == 60
    assert timeline.at(29.6) is False and timeline.at(29.0) is True


def test_contact_from_is_written_back_in_its_decision_tables(tmp_path):
    from supramodal.node.scene.schema import load_scene, scene_to_toml

    d = {"source": [{"name": "a", "type": "twosense", "sense": "whiskers"},
                    {"name": "b", "type": "twosense", "sense": "microphone"}],
         "stream": [{"name": "a", "source": "a", "bank": {"kind": "whisker"}, "model": {"train_on_start": True},
                     "decision": {"scope": "contact", "contact_from": "ros2:/robot/in_contact"}},
                    {"name": "b", "source": "b", "bank": {"kind": "cochlea"}, "model": {"train_on_start": True}}],
         "fusion": {"streams": ["a", "b"], "decision": {"scope": "contact", "contact_from": "lsl:touch"}}}
    first = scene_from_dict(d, str(tmp_path / "c.toml"), tmp_path)
    (tmp_path / "c.toml").write_text(scene_to_toml(first))
    again = load_scene(tmp_path / "c.toml")
    assert [s.contact_from for s in again.streams] == ["ros2:/robot/in_contact", None]
    assert again.fusion.contact_from == "lsl:touch"
    assert again.streams == first.streams and again.fusion == first.fusion


@pytest.mark.parametrize("key, value", [("scope", "contact"), ("confidence", 0.9), ("unknown", 0.05), ("n", 3),
                                        ("method", "vote"), ("unknown_below", 0.5), ("contact_threshold", 0.2)])
def test_decision_rules_on_a_stream_without_a_model_are_refused_not_ignored(key, value):
    """Issue 35, item 25: ``[decision]`` keys on a stream without a model were silently ignored, in the
    one-source and the graph form alike. Refused, naming the key and the two ways out; the contacts of
    ``contact_from`` (with scope = "contact") stay, and a scene written back, every default stated, loads."""
    import tomllib

    from supramodal.node.scene.schema import scene_to_toml

    decision = {"scope": "contact", key: value} if key in ("confidence",) else {key: value}
    one = {"driver": {"type": "synth"}, "decision": decision}
    with pytest.raises(SceneError, match=rf"c.toml: \[decision\] {key} = .*no model, so it decides nothing.*"
                                         rf"\[model\] \(path or train_on_start\), or remove {key}"):
        scene_from_dict(one, "c.toml")
    graph = {"source": [{"name": "w", "type": "synth"}],
             "stream": [{"name": "w", "source": "w", "decision": decision}]}
    with pytest.raises(SceneError, match=rf"c.toml: \[\[stream\]\] w \[decision\] {key} = .*no model"):
        scene_from_dict(graph, "c.toml")
    with_model = {"driver": {"type": "synth"}, "model": {"train_on_start": True}, "decision": decision}
    scene_from_dict(with_model, "c.toml")                               # a model decides by them
    contacts = {"driver": {"type": "synth"}, "decision": {"scope": "contact", "contact_from": "lsl:touch"}}
    kept = scene_from_dict(contacts, "c.toml")
    assert kept.only_stream().contact_from == "lsl:touch"
    scene_from_dict(tomllib.loads(scene_to_toml(kept)), "back.toml")
