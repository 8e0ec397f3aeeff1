"""What the view costs the node: decision latency p99 and CPU with a page open, against the same run without.

    python3 -m supramodal.benchmarks.view_cost [--seconds S] [--scene default|twosense]

Runs the scene twice in real time, once with only a counting sink and once with a view sink too and
a page reading it (a Server-Sent Events client on a thread of its own, as a browser's EventSource
reads: every message taken as it comes), and prints per stream the decision latency p50 and p99 and
the processing's real-time factor (CPU s per s of stream), and the process's CPU seconds, for both
runs side by side (medians of ``--repeats`` runs of each, alternated). The issue's bar (issue 28):
p99 within +0.5 ms, CPU within +10%.
"""

from __future__ import annotations

import argparse
import socket
import threading
import time
from dataclasses import replace
from pathlib import Path

from supramodal.node.runtime.sinks import ListSink
from supramodal.node.runtime.sinks.view import attach, view_sinks
from supramodal.node.scene.build import build_node
from supramodal.node.scene.schema import default_scene, load_scene
from supramodal.node.scene.variants import with_view

ROOT = Path(__file__).resolve().parents[1]


def _reader(port: int, stop: threading.Event, counted: list[int]) -> None:
    """Read /events as a page does, until ``stop``, counting the messages in ``counted[0]``."""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(b"GET /events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        s.settimeout(0.5)
        while not stop.is_set():
            try:
                chunk = s.recv(1 << 16)
            except TimeoutError:
                continue
            if not chunk:
                break
            counted[0] += chunk.count(b"\n\ndata:") + chunk.startswith(b"data:")


def run(scene, seconds: float | None, view: bool) -> dict:
    """Run ``scene`` for ``seconds`` (None: to its end), with the view and a reader or without.

    Returns the process's CPU seconds, the messages the reader got, and each stream's latency
    p50 and p99 (ms) and real-time factor.
    """
    scene = replace(scene, sinks=[])
    if view:
        scene = with_view(scene, 0)
    graph = build_node(scene, sinks_override=None if view else [ListSink()])
    stop, counted = threading.Event(), [0]
    reader = None
    if view:
        (v,) = view_sinks(graph)
        attach(graph)
        v.prepare()
        reader = threading.Thread(target=_reader, args=(v.port, stop, counted), daemon=True)
        reader.start()
    cpu = time.process_time()
    summary = graph.run(max_seconds=seconds)
    cpu = time.process_time() - cpu
    stop.set()
    if reader is not None:
        reader.join(5)
    return {"cpu_s": cpu, "messages": counted[0],
            "streams": {k: {"p50": (s.latency_ms or {}).get("p50"), "p99": (s.latency_ms or {}).get("p99"),
                            "rtf": s.real_time_factor} for k, s in summary.streams.items()}}


def _median(runs: list[dict]) -> dict:
    """Per number, the median over runs."""
    import statistics

    return {"cpu_s": statistics.median(r["cpu_s"] for r in runs),
            "messages": statistics.median(r["messages"] for r in runs),
            "streams": {k: {m: statistics.median(r["streams"][k][m] for r in runs) for m in ("p50", "p99", "rtf")}
                        for k in runs[0]["streams"]}}


def main(argv=None) -> int:
    """Run the scene with and without the view, alternated, and print the medians; return 0."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=20.0, help="seconds of stream per run (default 20)")
    p.add_argument("--scene", choices=["default", "twosense"], default="default")
    p.add_argument("--repeats", type=int, default=3, help="runs of each, alternated; medians printed (default 3)")
    args = p.parse_args(argv)
    scene = default_scene() if args.scene == "default" else load_scene(
        str(ROOT / "examples" / "two_sense_world.toml"))
    seconds = None if args.scene == "twosense" else args.seconds
    runs: dict[bool, list[dict]] = {False: [], True: []}
    for _ in range(args.repeats):              # alternated, so that a busy spell of the machine hits both
        for view in (False, True):
            runs[view].append(run(scene, seconds, view))
    without, with_page = _median(runs[False]), _median(runs[True])
    print(f"scene {args.scene}: medians of {args.repeats} runs each; {with_page['messages']} messages read by the page")
    print(f"{'stream':<10} {'p50 ms':>14} {'p99 ms':>16} {'real-time factor':>22}")
    for name in without["streams"]:
        a, b = without["streams"][name], with_page["streams"][name]
        print(f"{name:<10} {a['p50']:6.2f} -> {b['p50']:5.2f} {a['p99']:7.2f} -> {b['p99']:6.2f} "
              f"{a['rtf']:9.4f} -> {b['rtf']:.4f}   (p99 {b['p99'] - a['p99']:+.2f} ms)")
    print(f"process CPU {without['cpu_s']:.2f} s -> {with_page['cpu_s']:.2f} s "
          f"({100 * (with_page['cpu_s'] / without['cpu_s'] - 1):+.1f}%)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
