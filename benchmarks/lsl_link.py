"""Two processes, one LSL stream: 20 whisker channels at 5 kHz sent by one, classified by a node in another.

The two processes work as two machines would.

    python3 -m supramodal.benchmarks.lsl_link --seconds 60 --out DIR

Needs the ``lsl`` extra. The traffic stays on this machine: both processes read the
:func:`loopback_config` file (``LSLAPICFG``: IPv6 off, resolution scoped to the machine, the only
known peer 127.0.0.1, a session id of its own), and :func:`check_loopback_config` refuses to run
with any other.

The signal is the whisker reference textures, each 7.5 s (the first 60 s; fanned out to 20
channels with a gain per whisker), written once as a float32 WAV. The sender plays it in real
time in 10 ms chunks, each stamped with its last sample's time: by default a relay node
(``supramodal run`` of :func:`relay_scene`: a replay source sent on by ``[[sink]] type =
"lsl-signal"``, what machine A runs), or with ``--sender plain`` this module's own pylsl loop
(``python3 -m supramodal.benchmarks.lsl_link send``, stamping from its sample clock; the
kill-and-restart run always uses it, since it can go on where its sample clock had got to). The
node (its scene: :func:`inlet_scene`) classifies it per window. Then the same WAV is replayed locally, through the
same scene with a replay source, and the decisions are compared window by window.

Reported: samples sent and received, filled and lost; the node's decisions against the local
ones; the transport lag (a block's arrival minus its last sample's timestamp); the node's own
decision latency (from the arrival of the block that completes a window); and the end-to-end
latency (the decision minus the sender's time of the window's last sample). Writes
``lsl_link.md`` and ``lsl_link.json`` to ``--out``; exit status 0 when no sample was lost and
every decision equals the local one.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import numpy as np

#: The LSL configuration that keeps every packet on this machine (TESTING-WITHOUT-HARDWARE.md).
LOOPBACK_CONFIG = """[ports]
IPv6 = disable

[multicast]
ResolveScope = machine
ListenAddress = 127.0.0.1
Interfaces = {{127.0.0.1}}

[lab]
KnownPeers = {{127.0.0.1}}
SessionID = {session}

[log]
level = -1
"""
#: The lines :func:`check_loopback_config` insists on.
_REQUIRED_LINES = ("IPv6 = disable", "ResolveScope = machine", "KnownPeers = {127.0.0.1}")

RATE = 5000
CHANNELS = 20
SECONDS_PER_TEXTURE = 7.5
STREAM_NAME = "supramodal-bench-whiskers"


def loopback_config(folder: str | os.PathLike, session: str | None = None) -> Path:
    """Write an LSL config file that keeps traffic on this machine; return its path.

    ``session``: the LSL session id (default: a fresh one, so no other run's streams are seen).
    """
    path = Path(folder) / "lsl_loopback.cfg"
    path.write_text(LOOPBACK_CONFIG.format(session=session or f"supramodal-{uuid.uuid4().hex}"))
    return path


def check_loopback_config(environ=os.environ) -> Path:
    """Return the ``LSLAPICFG`` file, checked to keep LSL on this machine; RuntimeError otherwise."""
    name = environ.get("LSLAPICFG")
    if not name or not Path(name).is_file():
        raise RuntimeError("LSLAPICFG must name a loopback config file (loopback_config()) before LSL is used")
    text = Path(name).read_text()
    missing = [line for line in _REQUIRED_LINES if line not in text]
    if missing:
        raise RuntimeError(f"{name} would let LSL reach other machines: it lacks {missing}")
    return Path(name)


def whisker_signal(seconds: float) -> np.ndarray:
    """Return the whisker reference textures in turn (7.5 s each) for ``seconds``, on 20 whiskers.

    Fanned out to 20 whiskers with gains 0.6..1.0; float32, shape (samples, 20).
    """
    from supramodal.textures import reference_texture_set

    ts = reference_texture_set("whisker")
    n = int(round(seconds * RATE))
    per = int(round(SECONDS_PER_TEXTURE * RATE))
    parts, have, k = [], 0, 0
    while have < n:
        parts.append(ts.synthesize(k % len(ts.names), duration=SECONDS_PER_TEXTURE)[:per])
        have += per
        k += 1
    mono = np.concatenate(parts)[:n]
    gains = np.linspace(0.6, 1.0, CHANNELS)
    return (mono[:, None] * gains[None, :]).astype(np.float32)


# -- the sender (its own process) --------------------------------------------------------------

def send(wav: str, name: str, source_id: str, chunk: float = 0.01, t0: float | None = None,
         wait: float = 10.0) -> int:
    """Play ``wav`` as an LSL stream in real time, in ``chunk``-second chunks stamped on the sample clock.

    Sample ``i`` is stamped ``t0 + i / rate`` on the LSL clock. With ``t0`` given (a restarted
    sender), the samples start where that clock has got to; without, when a consumer connects.
    """
    from supramodal.drivers.lsl import import_pylsl
    from supramodal.replay.wavio import read_wav

    check_loopback_config()
    pylsl = import_pylsl()
    data, rate = read_wav(wav)
    data = np.ascontiguousarray(data, dtype=np.float32)
    info = pylsl.StreamInfo(name, "Whiskers", data.shape[1], float(rate), "float32", source_id)
    outlet = pylsl.StreamOutlet(info, chunk_size=0, max_buffered=30)
    if t0 is None:
        if not outlet.wait_for_consumers(wait):
            print("send: no consumer came", file=sys.stderr)
            return 1
        time.sleep(0.2)                  # the consumer's data connection settles
        t0, i = pylsl.local_clock(), 0
    else:                                # restarted: go on where the sample clock has got to
        i = max(0, int(np.ceil((pylsl.local_clock() - t0) * rate)))
    step = max(1, int(round(chunk * rate)))
    # The sample it starts from, the schedule's t0, and when it starts, on the LSL clock (a
    # restarted sender's listener reads these).
    print(f"send: from sample {i} t0 {t0!r} at {pylsl.local_clock()!r}", file=sys.stderr, flush=True)
    while i < len(data):
        j = min(len(data), i + step)
        due = t0 + j / rate
        delay = due - pylsl.local_clock()
        if delay > 0:
            time.sleep(delay)
        outlet.push_chunk(data[i:j], timestamp=t0 + (j - 1) / rate)
        i = j
    time.sleep(0.5)                      # the last chunk reaches the consumer before the outlet goes
    return 0


def start_sender(wav, name, source_id, t0=None, env=None, stderr=None) -> subprocess.Popen:
    """Start the sender as a child process (as another machine would be); ``stderr`` as for Popen."""
    cmd = [sys.executable, "-m", "supramodal.benchmarks.lsl_link", "send", str(wav), "--name", name,
           "--source-id", source_id]
    if t0 is not None:
        cmd += ["--t0", repr(t0)]
    return subprocess.Popen(cmd, env=env or os.environ.copy(), stderr=stderr, text=True)


def relay_scene(wav, prefix: str, wait: float = 30.0) -> str:
    """Return the sending machine's scene: the WAV replayed in real time as a source that no stream reads.

    The source is sent on as ``PREFIX-whiskers-signal`` in 10 ms chunks once a consumer has come.
    """
    return (f'[[source]]\nname = "whiskers"\ntype = "replay"\npath = {json.dumps(str(wav))}\nspeed = 1.0\n\n'
            f'[[sink]]\ntype = "lsl-signal"\nprefix = "{prefix}"\nchunk = 0.01\nwait_for_consumer = {wait!r}\n')


def start_relay(scene, stderr=None) -> subprocess.Popen:
    """Start a relay node (``supramodal run SCENE``) as a child process, as the robot's computer would run it."""
    return subprocess.Popen([sys.executable, "-m", "supramodal", "run", str(scene), "--quiet"],
                            env=os.environ.copy(), stderr=stderr, text=True)


# -- the receiving node ------------------------------------------------------------------------

def inlet_scene(name: str | None, model: str, **driver) -> dict:
    """Return the node's scene on the receiving machine: the whisker bank per channel, a model file.

    The stream is found by ``name`` (or None) and whatever else ``driver`` names
    (``source_id``, ...).
    """
    named = {} if name is None else {"stream": name}
    return {"driver": {"type": "lsl", **named, "mapping": "per-channel", **driver},
            "bank": {"kind": "whisker"}, "features": {"names": ["Af"]},
            "model": {"path": model}, "decision": {"scope": "window"}}


def local_scene(wav: str, model: str, train: bool = False) -> dict:
    """Return the same scene with the WAV replayed locally at full speed."""
    return {"driver": {"type": "replay", "path": wav, "speed": "max", "mapping": "per-channel"},
            "bank": {"kind": "whisker"}, "features": {"names": ["Af"]},
            "model": {"path": model, "train_on_start": train}, "decision": {"scope": "window"}}


def _stamped_sink():
    """Return a sink that keeps each window event (``windows``) and driver event, with its host time.

    The host time is when the event reached the sinks. Made here: this module loads no part of
    the node until it runs one.
    """
    from supramodal.node.runtime.sinks import Sink

    class Stamped(Sink):
        def __init__(self):
            self.windows, self.times, self.driver_events = [], [], []

        def emit(self, event):
            self.times.append(time.monotonic())
            self.windows.append(event)

        def event(self, ev):
            self.driver_events.append(ev)

    return Stamped()


def _prepare(seconds: float, out: Path, progress):
    """Return the signal's WAV, the model trained on the whisker reference textures, and the local windows.

    The local windows are those of the WAV replayed locally through the same scene.
    """
    from supramodal.node.runtime.sinks import ListSink
    from supramodal.node.scene.build import build_node
    from supramodal.node.scene.schema import scene_from_dict
    from supramodal.replay.wavio import write_wav

    out.mkdir(parents=True, exist_ok=True)
    wav, model = out / "signal.wav", out / "model.npz"
    write_wav(wav, whisker_signal(seconds), RATE)
    local = ListSink()
    build_node(scene_from_dict(local_scene(str(wav), str(model), train=True)), sinks_override=[local]).run()
    progress(f"local replay: {len(local.windows)} windows")
    return wav, model, local.windows


def _inlet_node(name: str, model, **driver):
    """Return the inlet node, its sink, and the list its driver's reads fill.

    The list gets (end frame, timestamp, arrival) per block.
    """
    from supramodal.node.scene.build import build_node
    from supramodal.node.scene.schema import scene_from_dict

    sink = _stamped_sink()
    # The sender is another process starting up (a relay node imports, builds and opens its outlet
    # first): on a busy machine that takes longer than the default 5 s; resolving returns when it
    # answers.
    driver = {"resolve_timeout": 60.0, **driver}
    node = build_node(scene_from_dict(inlet_scene(name, str(model), **driver)), sinks_override=[sink])
    driver_ = node.sources[0].driver
    read, blocks = driver_.read, []

    def timed_read(timeout=None):
        block = read(timeout)
        if block is not None and block.frames:
            blocks.append((block.start + block.frames, block.timestamp, block.arrival))
        return block

    driver_.read = timed_read  # type: ignore[method-assign]  # the benchmark times each block the node reads
    return node, sink, blocks


def _run_for(node, seconds: float, slack: float = 30.0) -> dict:
    # Samples lost without a trace (within the gap tolerance) would leave the node short of its
    # length for ever: stop it a while after the sender must have finished.
    watchdog = threading.Timer(seconds + slack, node.stop, args=("the sender stopped short",))
    watchdog.start()
    try:
        return node.run(max_seconds=seconds)
    finally:
        watchdog.cancel()


#: Who sends: a relay node (``supramodal run`` of :func:`relay_scene`), or the plain pylsl
#: sender (:func:`send`), which stamps from its own sample clock.
SENDERS = ("node", "plain")


def run(seconds: float, out: Path, progress=print, sender: str = SENDERS[0]) -> dict:
    """Send ``seconds`` of the whisker signal from another process to an inlet node; compare with the WAV fed locally.

    ``sender``: one of :data:`SENDERS`.
    """
    if sender not in SENDERS:
        raise ValueError(f"sender is one of {SENDERS}, got {sender!r}")
    wav, model, local = _prepare(seconds, out, progress)
    progress(f"sending {seconds:g} s over LSL from another process ({sender} sender)")
    if sender == "node":
        prefix = f"bench{uuid.uuid4().hex[:8]}"
        scene = out / "relay.toml"
        scene.write_text(relay_scene(wav, prefix))
        name, proc = f"{prefix}-whiskers-signal", start_relay(scene)
    else:
        name = STREAM_NAME
        proc = start_sender(wav, name, f"supramodal-bench-{uuid.uuid4().hex[:8]}")
    try:
        node, sink, blocks = _inlet_node(name, model)
        summary = _run_for(node, seconds)
    finally:
        _end(proc)
    return {"sender": sender, **_report(local, sink.windows, sink.times, blocks, summary, seconds)}


def _end(proc) -> None:
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=10)


def _start_line(proc) -> tuple[float, float]:
    """``(t0, started)`` from a sender's first line.

    Its schedule's t0 and when it began to push, both on the LSL clock.
    """
    said = []
    for line in proc.stderr:             # liblsl's own log lines come first
        if line.startswith("send: from sample"):
            break
        said.append(line.strip())
    else:
        raise RuntimeError(f"the sender ended before it sent; it said {said[-5:]}")
    threading.Thread(target=proc.stderr.read, daemon=True).start()    # never let its pipe fill
    words = line.split()
    return float(words[words.index("t0") + 1]), float(words[words.index("at") + 1])


def run_restart(seconds: float, out: Path, kill_at: float = 3.0, down: float = 1.0, progress=print) -> dict:
    """Kill the sender ``kill_at`` s into the stream and start it again ``down`` s later.

    The new sender goes on from where its sample clock has got to. Measures the gap the node
    counts and fills, and how soon after the new sender's first push the node decides again on
    measured samples.
    """
    from supramodal.drivers.lsl import import_pylsl, lsl_clock_offset

    pylsl = import_pylsl()
    wav, model, _ = _prepare(seconds + kill_at + down + 2.0, out, progress)
    name, source_id = f"{STREAM_NAME}-restart", f"supramodal-bench-{uuid.uuid4().hex[:8]}"
    first = start_sender(wav, name, source_id, stderr=subprocess.PIPE)
    second = None
    node, sink, _ = _inlet_node(name, model, stall_timeout=0.3)
    summary: dict = {}
    runner = threading.Thread(target=lambda: summary.update(_run_for(node, seconds)), name="inlet node")
    runner.start()
    try:
        t0, _ = _start_line(first)
        time.sleep(kill_at)
        first.kill()
        first.wait(timeout=10)
        killed = time.monotonic()
        progress(f"sender killed at {kill_at:g} s; starting it again in {down:g} s")
        time.sleep(down)
        second = start_sender(wav, name, source_id, t0=t0, stderr=subprocess.PIPE)
        _, began = _start_line(second)
        began += lsl_clock_offset(pylsl)                         # one machine, one offset
        runner.join(timeout=seconds + 60.0)
    finally:
        for proc in (first, second):
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait(timeout=10)
    if runner.is_alive():
        node.stop("the benchmark gave up")
        runner.join(timeout=10)
        raise RuntimeError("the inlet node did not reach the end of its stream")
    again = next((t for w, t in zip(sink.windows, sink.times) if t > began and "gap" not in w.flags), None)
    driver = summary["driver"]
    return {"seconds": seconds, "kill_at": kill_at, "down": down, "outage_s": round(began - killed, 3),
            "windows": len(sink.windows), "window_numbers_contiguous":
                [w.window for w in sink.windows] == list(range(len(sink.windows))),
            "gap_windows": sum("gap" in w.flags for w in sink.windows), "driver": driver,
            "filled_s": driver["filled"] / RATE, "events": sorted({e.kind for e in sink.driver_events}),
            "decides_again_after_s": None if again is None else round(again - began, 3)}


def _percentiles(values) -> dict:
    v = np.asarray(values, dtype=float)
    if not v.size:
        return {"n": 0}
    return {"n": int(v.size), "p50": round(float(np.percentile(v, 50)), 3),
            "p99": round(float(np.percentile(v, 99)), 3), "max": round(float(v.max()), 3)}


def _report(local, remote, times, blocks, summary, seconds) -> dict:
    """Return the counts, the decisions compared window by window, and the three latencies, ms."""
    mine = {e.window: e.decision for e in local}
    theirs = {e.window: e.decision for e in remote}
    common = sorted(set(mine) & set(theirs))
    ends = np.array([b[0] for b in blocks])
    lag = [(arrival - stamp) * 1e3 for _, stamp, arrival in blocks if stamp is not None]
    W = int(round(0.1 * RATE))
    e2e = []
    for event, emitted in zip(remote, times):
        end = (event.window + 1) * W
        k = int(np.searchsorted(ends, end))          # the block holding the window's last sample
        if k < len(blocks) and blocks[k][1] is not None:
            taken = blocks[k][1] - (blocks[k][0] - end) / RATE
            e2e.append((emitted - taken) * 1e3)
    driver = summary["driver"]
    return {
        "seconds": seconds,
        "samples_sent": int(round(seconds * RATE)),
        "samples_received": driver["frames"] - driver["filled"],
        "driver": driver,
        "windows_local": len(mine), "windows_remote": len(theirs),
        "decisions_compared": len(common), "decisions_equal": sum(mine[w] == theirs[w] for w in common),
        "transport_lag_ms": _percentiles(lag),
        "decision_latency_ms": summary["latency_ms"],
        "end_to_end_ms": _percentiles(e2e),
    }


def report_markdown(link: dict, restart: dict | None) -> str:
    """Return the two runs as the report's tables."""
    d = link["driver"]
    lines = ["# 20 whisker channels at 5 kHz over LSL, between two processes", "",
             f"{link['seconds']:g} s sent in 10 ms chunks by one process ("
             + ("a relay node, `supramodal run relay.toml`: a replay source sent on by `[[sink]] type = "
                "\"lsl-signal\"`, each chunk stamped with its last sample's time on the node's common clock"
                if link.get("sender", "plain") == "node" else "the plain pylsl sender, its sample clock stamping "
                "each chunk")
             + "), classified by a node in another (LSL on loopback only; LSLAPICFG: machine scope, known peer "
             "127.0.0.1).", "",
             "| measure | value |", "|---|---|",
             f"| samples sent / received | {link['samples_sent']} / {link['samples_received']} |",
             f"| filled, gaps, restarts, timing slips | {d['filled']}, {d['gaps']}, {d['restarts']}, "
             f"{d['timing_slips']} |",
             f"| windows decided (inlet / local replay) | {link['windows_remote']} / {link['windows_local']} |",
             f"| decisions equal to the local replay's | {link['decisions_equal']} of {link['decisions_compared']} |"]
    for key, what in (("transport_lag_ms", "transport lag (block arrival - its last sample's time)"),
                      ("decision_latency_ms", "node decision latency (from the completing block's arrival)"),
                      ("end_to_end_ms", "end to end (decision - the sender's time of the window's last sample)")):
        v = link[key]
        cells = " / ".join("-" if v.get(k) is None else f"{v[k]:.3f}" for k in ("p50", "p99", "max"))
        lines.append(f"| {what}, p50 / p99 / max ms | {cells} |")
    if restart is not None:
        r = restart
        lines += ["", f"## The sender killed {r['kill_at']:g} s in, started again {r['down']:g} s later", "",
                  "The plain pylsl sender, started again on the same sample clock (so that the outage is known to "
                  "the sample).", "",
                  "| measure | value |", "|---|---|",
                  f"| outage (kill to the new sender's first push) | {r['outage_s']} s |",
                  f"| node kept running: windows, contiguous | {r['windows']}, {r['window_numbers_contiguous']} |",
                  f"| gap counted and filled | {r['driver']['gaps']} gap, {r['filled_s']:.3f} s "
                  f"({r['driver']['filled']} samples), {r['gap_windows']} windows flagged |",
                  f"| events | {', '.join(r['events'])} |",
                  f"| decides again on measured samples after the new sender's first push | "
                  f"{r['decides_again_after_s']} s |"]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    """Run the link (and the kill-and-restart run), or with ``send`` be the sender; return the exit status.

    The exit status is 0 when no sample was lost and every decision equals the local one.
    """
    parser = argparse.ArgumentParser(prog="python -m supramodal.benchmarks.lsl_link", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command")
    s = sub.add_parser("send", help="play a WAV as an LSL stream (the sending process)")
    s.add_argument("wav")
    s.add_argument("--name", default=STREAM_NAME)
    s.add_argument("--source-id", required=True)
    s.add_argument("--t0", type=float, default=None)
    parser.add_argument("--seconds", type=float, default=60.0, help="stream sent, seconds (default 60)")
    parser.add_argument("--restart-seconds", type=float, default=20.0,
                        help="stream of the kill-and-restart run, seconds (0: leave it out; default 20)")
    parser.add_argument("--sender", choices=SENDERS, default=SENDERS[0],
                        help="who sends: a relay node (supramodal run, [[sink]] type = \"lsl-signal\"; default) or "
                             "the plain pylsl sender of this module")
    parser.add_argument("--out", default="lsl-link")
    args = parser.parse_args(argv)
    if args.command == "send":
        return send(args.wav, args.name, args.source_id, t0=args.t0)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    # This benchmark stays on this machine whatever the environment says.
    os.environ["LSLAPICFG"] = str(loopback_config(out))
    check_loopback_config()
    progress = lambda m: print(m, file=sys.stderr, flush=True)   # noqa: E731
    link = run(args.seconds, out / "link", progress, sender=args.sender)
    restart = run_restart(args.restart_seconds, out / "restart", progress=progress) if args.restart_seconds else None
    (out / "lsl_link.json").write_text(json.dumps({"link": link, "restart": restart}, indent=1))
    text = report_markdown(link, restart)
    (out / "lsl_link.md").write_text(text)
    print(text)
    ok = (link["samples_received"] == link["samples_sent"] and link["driver"]["filled"] == 0
          and link["decisions_equal"] == link["decisions_compared"] == link["windows_local"])
    if restart is not None:
        ok = ok and restart["driver"]["gaps"] >= 1 and (restart["decides_again_after_s"] or 99) <= 2.0
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
