"""What the ``ros2`` sink costs the node: decision latency and throughput with the sink off, on, and stalled.

The three cases are the sink off, on with a live subscriber, and on with a subscriber stopped by
SIGSTOP, side by side in one run.

    python3 -m supramodal.benchmarks.ros2_sink --seconds 2 --rounds 3

Needs the ``ros2`` extra (or a sourced ROS 2). DDS stays on this machine
(``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``) in a domain drawn for the run (``ROS_DOMAIN_ID`` 1-100,
unless set).

The scene: two synthesised whisker sources in real time (``--seconds`` of each of the eight reference
textures; their own block sizes), a model per stream (trained on start once, then read from the model
cache), late fusion, a ``jsonl`` sink to a file; with the sink on, a ``ros2`` sink publishing every
stream's and the fusion's decisions, posteriors and features. Each round runs the three cases one after
the other (round ``r`` starting with case ``r``: no case always runs first, or after the same one), each a
node process of its own (``supramodal run``); the subscriber is a plain rclpy
process (reliable, keep last 10 on every decision and posteriors topic), matched before the node
starts (``wait_for_subscribers``), stopped with SIGSTOP once the first window is written in the third
case. Reported per case, pooled over rounds: the node's decision latency per stream (p50, p99, max, from
the arrival of the block that completes a window to its event), windows written by the jsonl sink and
dropped by each sink, the run's wall time; and the p99's difference to the case without the sink, with
its 95 % interval (a bootstrap over the windows of both cases: a p99 rests on its few slowest windows,
and the interval says how far apart two runs of the same case fall). Exit status 0 when no case lost a
window of the jsonl sink.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
import uuid
from pathlib import Path

import numpy as np

#: Two synthesised whisker sources in real time on their own block sizes (``seconds`` of each of the
#: eight reference textures), a model trained on start for each (the model cache makes it once), late
#: fusion, a jsonl sink to ``out.jsonl``: the node's outputs of every kind.
SCENE = """
[[source]]
name = "left"
type = "synth"
seconds = {seconds}

[[source]]
name = "right"
type = "synth"
seconds = {seconds}
block = 37

[[stream]]
name = "left"
source = "left"
[stream.model]
train_on_start = true

[[stream]]
name = "right"
source = "right"
[stream.model]
train_on_start = true

[fusion]
streams = ["left", "right"]
method = "late"
weight = 0.5
max_wait = 0.5

[[sink]]
type = "jsonl"
path = "out.jsonl"
"""


def scene(seconds: float, namespace: str | None = None, ros2: str = "wait_for_subscribers = 60") -> str:
    """:data:`SCENE` of ``seconds`` per texture, with a ros2 sink in ``namespace``, or without one (None).

    The sink's other keys are ``ros2``, TOML lines.
    """
    sink = "" if namespace is None else f'\n[[sink]]\ntype = "ros2"\nnamespace = "{namespace}"\n{ros2}\n'
    return SCENE.format(seconds=seconds) + sink


SUBSCRIBER = textwrap.dedent("""
    import sys, rclpy
    from std_msgs.msg import String
    from sensor_msgs.msg import JointState
    rclpy.init()
    node = rclpy.create_node("bench_listener")
    got = [0]
    def keep(m):
        got[0] += 1
    for s in ("left", "right", "fused"):
        node.create_subscription(String, f"{sys.argv[1]}/supramodal/{s}/decision", keep, 10)
        node.create_subscription(JointState, f"{sys.argv[1]}/supramodal/{s}/posteriors", keep, 10)
    print("up", flush=True)
    try:
        rclpy.spin(node)
    except BaseException:
        pass
""")

CASES = ("off", "on, live subscriber", "on, stopped subscriber")


def run_case(case: str, seconds: float, folder: Path, keys: str = "") -> dict:
    """One node process of ``case``: the summary's latencies, windows and drops.

    ``keys``: TOML lines of the ros2 sink's other keys.
    """
    namespace = f"/bench{uuid.uuid4().hex[:8]}"
    text = scene(seconds, None if case == "off" else namespace, "wait_for_subscribers = 60\n" + keys)
    work = folder / f"case{CASES.index(case)}-{uuid.uuid4().hex[:6]}"
    work.mkdir()
    (work / "node.toml").write_text(text)
    listener = None
    if case != "off":
        listener = subprocess.Popen([sys.executable, "-c", SUBSCRIBER, namespace], stdout=subprocess.PIPE,
                                    text=True)
        assert listener.stdout is not None and listener.stdout.readline().strip() == "up"
    try:
        node = subprocess.Popen([sys.executable, "-m", "supramodal", "run", "node.toml", "--quiet"], cwd=work,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        if case == "on, stopped subscriber" and listener is not None:
            while not (work / "out.jsonl").exists() and node.poll() is None:
                time.sleep(0.02)
            os.kill(listener.pid, signal.SIGSTOP)
        _, err = node.communicate(timeout=900)
        if node.returncode != 0:
            raise SystemExit(f"the node failed ({case}): {err[-1500:]}")
    finally:
        if listener is not None:
            os.kill(listener.pid, signal.SIGCONT)
            listener.kill()
            listener.wait()
    lines = (work / "out.jsonl").read_text().splitlines()
    summary = json.loads(lines[-1])
    latencies = {s: [w["latency_ms"] for w in map(json.loads, lines[:-1]) if w.get("stream") == s
                     and w.get("latency_ms") is not None] for s in ("left", "right", "fused")}
    sinks = [{k: s.get(k) for k in ("sink", "written", "dropped_windows", "errors")} for s in summary["sinks"]]
    return {"latencies": latencies, "windows": len(lines) - 1, "wall": summary["wall_seconds"], "sinks": sinks}


def p99_difference_interval(on: np.ndarray, off: np.ndarray, draws: int = 2000, seed: int = 0) -> tuple[float, float]:
    """Return the 95 % bootstrap interval of ``p99(on) - p99(off)``, each case's windows resampled on their own."""
    rng = np.random.default_rng(seed)
    diffs = [np.percentile(rng.choice(on, on.size), 99) - np.percentile(rng.choice(off, off.size), 99)
             for _ in range(draws)]
    low, high = np.percentile(diffs, [2.5, 97.5])
    return float(low), float(high)


def main(argv: list[str] | None = None) -> int:
    """Run the rounds of the three cases and print the table; return 1 if a case lost a jsonl window, else 0."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=2.0, help="seconds of each of the 8 textures per run (2)")
    p.add_argument("--rounds", type=int, default=3, help="rounds of the three cases (3)")
    p.add_argument("--sink-keys", default="", metavar="TOML",
                   help='the ros2 sink\'s other keys, TOML lines (e.g. "diagnostics_period = 60"; default none)')
    args = p.parse_args(argv)
    os.environ.setdefault("ROS_DOMAIN_ID", str(random.SystemRandom().randint(1, 100)))
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    from supramodal.drivers.ros2 import import_rclpy

    import_rclpy()     # says what to install, before any run
    pooled: dict[str, dict] = {c: {"latencies": {}, "windows": [], "wall": [], "dropped": 0} for c in CASES}
    with tempfile.TemporaryDirectory(prefix="ros2-bench-") as tmp:
        for r in range(args.rounds):
            for case in CASES[r % len(CASES):] + CASES[:r % len(CASES)]:    # each case first in some round
                t = time.monotonic()
                got = run_case(case, args.seconds, Path(tmp), args.sink_keys)
                print(f"round {r + 1}/{args.rounds}, {case}: {got['windows']} windows in "
                      f"{time.monotonic() - t:.1f} s", file=sys.stderr, flush=True)
                into = pooled[case]
                for s, v in got["latencies"].items():
                    into["latencies"].setdefault(s, []).extend(v)
                into["windows"].append(got["windows"])
                into["wall"].append(got["wall"])
                into["dropped"] += sum(int(s["dropped_windows"] or 0) + int(s["errors"] or 0) for s in got["sinks"])
    print(f"ros2 sink cost: {args.rounds} rounds of {8 * args.seconds:g} s of stream per case, 2 streams + fusion, "
          f"real time; decision latency in ms (pooled over rounds)"
          + (f"; the sink's keys: {args.sink_keys!r}" if args.sink_keys else "") + "\n")
    print("| case | stream | p50 | p99 | max | windows per run | dropped or failed by sinks | wall s |")
    print("|---|---|---|---|---|---|---|---|")
    off = {s: np.asarray(v) for s, v in pooled["off"]["latencies"].items()}
    for case in CASES:
        into = pooled[case]
        for s, v in sorted(into["latencies"].items()):
            a = np.asarray(v)
            p99 = float(np.percentile(a, 99))
            if case == "off":
                delta = ""
            else:
                low, high = p99_difference_interval(a, off[s])
                delta = f" ({p99 - float(np.percentile(off[s], 99)):+.2f}, 95 % {low:+.2f} to {high:+.2f})"
            print(f"| {case} | {s} | {np.percentile(a, 50):.2f} | {p99:.2f}{delta} | {a.max():.2f} | "
                  f"{sorted(set(into['windows']))} | {into['dropped']} | {np.mean(into['wall']):.2f} |")
    lost = len({w for c in CASES for w in pooled[c]["windows"]}) != 1
    print("\n" + ("every case wrote every window" if not lost else "a case lost windows: see the table"))
    return 1 if lost else 0


if __name__ == "__main__":
    sys.exit(main())
