"""A node whose contacts come from a bus (``[decision] contact_from``), fed edges at known host times.

:func:`run_with_edges` runs the two-sense world's whiskers, paced at 2x real time, through a model and
the contact-pooled decision, while a thread says the robot's contact states on the bus: each edge of
:data:`EDGES` (seconds of host time after the bus is matched), and, between edges, the current state
again every 0.1 s (a touch sensor that publishes its state, not only its changes). It returns what the
node decided and the edges on the node's common time, as the test's own clock measured them.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from supramodal.node.runtime.sinks import ListSink
from supramodal.node.scene.build import build_node
from supramodal.node.scene.schema import scene_from_dict

#: (host seconds after the bus is matched, in contact) of the robot's signal; the run stops 0.5 s after.
EDGES = ((0.5, True), (1.5, False), (2.0, True), (2.8, False))
#: Seconds between two repeats of the current state.
REPEAT = 0.1


def scene(contact_from: str) -> dict:
    """The whiskers of the two-sense world at 2x (16 s of stream: room for discovery), a model trained
    on start (the run's cache shares it with test_graph's), decisions pooled per contact."""
    return {"source": [{"name": "whiskers", "type": "twosense", "sense": "whiskers", "seconds": 2.0, "block": 50}],
            "stream": [{"name": "whiskers", "source": "whiskers", "bank": {"kind": "whisker"},
                        "model": {"train_on_start": True},
                        "decision": {"scope": "contact", "n": 0, "contact_from": contact_from}}]}


def run_with_edges(contact_from: str, say: Callable[[bool], float], matched: Callable[[], bool],
                   repeat: bool = True) -> tuple[ListSink, dict, list[tuple[float, bool]]]:
    """Run :func:`scene` while a thread says :data:`EDGES` with ``say(state) -> host time it said it``, once
    ``matched()``; return the sink, the summary and the edges on common time."""
    sink = ListSink()
    graph = build_node(scene_from_dict(scene(contact_from), "contacts.toml"), speed=2.0, sinks_override=[sink])
    said: list[tuple[float, bool]] = []
    failed: list[BaseException] = []

    def edges() -> None:
        try:
            deadline = time.monotonic() + 30
            listener = graph.contacts[0][0]
            while not (listener.listening and matched()):
                if time.monotonic() > deadline:
                    raise TimeoutError("the node's contact listener never matched the test's publisher")
                time.sleep(0.01)
            start, state = time.monotonic(), False
            for at, new in (*EDGES, (EDGES[-1][0] + 0.5, None)):
                while repeat and time.monotonic() < start + at - REPEAT:
                    time.sleep(REPEAT)
                    say(state)
                time.sleep(max(0.0, start + at - time.monotonic()))
                if new is None:
                    break
                said.append((say(new), new))
                state = new
        except BaseException as exc:  # surfaced by the test
            failed.append(exc)
        finally:
            graph.stop("the test's edges are said")

    thread = threading.Thread(target=edges, daemon=True)
    summary = graph.run(on_running=thread.start)
    thread.join(5)
    if failed:
        raise failed[0]
    epoch = graph.sources[0].epoch
    return sink, summary, [(t - epoch, state) for t, state in said]


def expected(edges: list[tuple[float, bool]], t: float) -> bool:
    """The state at common time ``t`` by the edges said: the last one at or before it (none: not in contact)."""
    state = False
    for at, new in edges:
        if at <= t:
            state = new
    return state
