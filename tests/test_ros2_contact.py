"""``[decision] contact_from = "ros2:TOPIC"``: the robot's std_msgs/Bool contact topic, against real rclpy."""

from __future__ import annotations

import pytest

from contact_edges import EDGES, expected, run_with_edges
from ros2_only import localhost_only, require_ros2, unique_namespace  # noqa: F401  (the fixture applies itself)

require_ros2()

from std_msgs.msg import Bool  # noqa: E402  (after the skip)


class _Publisher:
    """A plain rclpy publisher of the robot's contact state (reliable, volatile: rclpy's default)."""

    def __init__(self, topic: str) -> None:
        import rclpy
        from rclpy.signals import SignalHandlerOptions

        self.context = rclpy.Context()
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node("touch_sensor", context=self.context)
        self.pub = self.node.create_publisher(Bool, topic, 10)

    def say(self, state: bool) -> float:
        import time

        at = time.monotonic()
        self.pub.publish(Bool(data=state))
        return at

    def close(self) -> None:
        self.node.destroy_node()
        self.context.try_shutdown()


@pytest.mark.slow   # paced in real time, with a model trained on start (or the run's cache)
def test_contacts_and_contact_decisions_follow_the_topic_s_edges():
    """Done when (issue 33): with a Bool contact topic, contacts and the contact-pooled decisions follow
    the topic's edges: every window is in contact as the topic said at its centre (within one window
    of an edge either way), the pooled decision starts again at each touch, and nothing is pooled out
    of contact; repeats of a state are no edges."""
    topic = f"{unique_namespace()}/in_contact"
    pub = _Publisher(topic)
    try:
        sink, summary, edges = run_with_edges(f"ros2:{topic}", pub.say, lambda: pub.pub.get_subscription_count() > 0)
    finally:
        pub.close()
    assert [s for _, s in edges] == [s for _, s in EDGES]
    windows = sink.windows
    span = windows[0].end - windows[0].start                # one window, on common time
    checked = 0
    for w in windows:
        centre = 0.5 * (w.start + w.end)
        if min(abs(centre - t) for t, _ in edges) > span:
            assert w.in_contact == expected(edges, centre), (w.window, centre, edges)
            checked += 1
        else:   # at an edge: either side, but at most one window off
            assert w.in_contact in (expected(edges, centre - span), expected(edges, centre + span))
    assert checked >= 0.8 * len(windows)
    # The pooled decision: restarted at each touch (1, 2, 3, ... windows), nothing pooled out of contact.
    touches, run = 0, 0
    for w in windows:
        if w.in_contact:
            touches += run == 0
            run += 1
            assert w.pooled.windows == run and w.pooled.label is not None
        else:
            run = 0
            assert w.pooled.to_dict() == {"label": None, "confidence": 0.0, "windows": 0}
    assert touches == 2
    contacts = summary["contacts"]
    assert contacts == [{"from": f"ros2:{topic}", "states": contacts[0]["states"], "touches": 2,
                         "messages": contacts[0]["messages"], "refused": 0}]
    assert contacts[0]["states"] >= 20     # the repeats came, and made no edge


def test_a_contact_topic_of_another_type_stops_the_node_naming_the_type_it_found():
    """Bad input (issue 33): the contact topic carries std_msgs/String: the node stops, within seconds,
    with one error that names the type found and the type it reads; nothing hangs."""
    import time

    from std_msgs.msg import String

    from contact_edges import scene
    from supramodal.node.runtime.graph import NodeError
    from supramodal.node.runtime.sinks import ListSink
    from supramodal.node.scene.build import build_node
    from supramodal.node.scene.schema import scene_from_dict

    topic = f"{unique_namespace()}/in_contact"
    pub = _Publisher(topic)
    strings = pub.node.create_publisher(String, topic + "_s", 10)
    try:
        d = scene(f"ros2:{topic}_s")
        d["stream"][0]["model"] = {}                    # feature windows: contacts, and no decision to pool
        del d["stream"][0]["decision"]["n"]
        graph = build_node(scene_from_dict(d, "c.toml"), speed=2.0, sinks_override=[ListSink()])
        t = time.monotonic()
        with pytest.raises(NodeError, match=r"contacts ros2:.*carries \['std_msgs/msg/String'\].*std_msgs/msg/Bool"):
            graph.run()
        assert time.monotonic() - t < 15
        assert strings.get_subscription_count() == 0
    finally:
        pub.close()
