"""Soak and faults: the node on the serial driver against the mock whisker board, for a long time.

    python3 -m supramodal.benchmarks.soak --minutes 60 --unplugs 100 --out DIR

Runs a :class:`supramodal.node.runtime.graph.Node` (serial driver -> ring -> 20-channel whisker pipeline -> a
counting sink) against :class:`supramodal.drivers.mock_whisker.MockWhiskerDevice` on a real pty at full
rate (20 channels x 5 kHz, 32 samples per frame: about 200 kB/s), with every fault the mock
can inject (garbage, altered bytes, truncated, left-out, wrong-channel-count and
wrong-version frames) and ``--unplugs`` unplug/replug cycles spread over the run. Every
block the driver hands the node is checked against what the mock sent: measured rows
bit-exact, filled rows zero, and each filled frame looked up in the mock's ledger (why it was
lost). At the end the mock stops injecting faults, the node runs on for a few seconds (so
every fault is judged), and the driver's counters are compared with the mock's ledger.

Prints a report (ledger vs driver, RSS start/max/end and slope, windows, blocks, uptime,
stalls) and writes ``soak.md``, ``soak.json`` and, with matplotlib, ``rss.png`` to ``--out``.
Exit status 0 when every count matches exactly, nothing stalled and the node never stopped.

What cannot be exact, and is reported as such: ``header_errors`` counts the wrong-version
frames plus sync words occurring by chance in skipped bytes (garbage, damaged frames).
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
import threading
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from supramodal.banks import whisker_bank
from supramodal.drivers.base import DriverBase
from supramodal.drivers.mock_whisker import FaultSpec, MockWhiskerDevice
from supramodal.drivers.serial_whisker import SerialWhiskerDriver
from supramodal.node.runtime.graph import Node
from supramodal.node.runtime.sinks import Sink
from supramodal.node.runtime.summaries import RunSummary
from supramodal.pipeline import FeaturePipeline

RATE, CHANNELS, SPF = 5000.0, 20, 32
#: Fault probabilities per frame (156 frames/s): about 4 faulted frames a second.
FAULT_RATES = {"garbage_rate": 0.01, "drop_rate": 0.005, "crc_rate": 0.005, "omit_rate": 0.005,
               "channels_rate": 0.005, "version_rate": 0.005}
UNPLUG_FOR = 0.5  #: s unplugged per cycle
STALL = 5.0  #: s without a window (board plugged or not): a stall
DRAIN = 2.0  #: s of clean frames after the faults end, before the node is stopped


def rss_kib() -> int:
    """Resident set size of this process, KiB (VmRSS of /proc/self/status)."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return 0


def source_signal(seconds: float = 6.0) -> np.ndarray:
    """Return what the board loops: three reference whisker textures in turn, shape (n, 20), full scale +-1.

    The 20 channels have different gains (a channel swap would show).
    """
    from supramodal.textures import reference_texture_set

    ts = reference_texture_set("whisker")
    x = np.concatenate([ts.synthesize(i, duration=seconds / 3) for i in range(3)])
    x = x / max(1e-12, float(np.abs(x).max())) * 0.9
    return x[:, None] * np.linspace(0.5, 1.0, CHANNELS)[None, :]


class CheckedDriver(DriverBase):
    """The serial driver as the node sees it, checking each block against the mock as it passes.

    Keeps counts only (memory stays flat): filled frames by the ledger's reason, frames whose
    samples differ from what the mock sent, and the index of the last frame received. Its
    events are the serial driver's.
    """

    def __init__(self, inner: SerialWhiskerDriver, dev: MockWhiskerDevice) -> None:
        self.inner, self.dev = inner, dev
        self.rate, self.channels = inner.rate, inner.channels
        self.filled_by_kind: collections.Counter[str] = collections.Counter()
        self.mismatched_frames = 0
        self.unaligned_blocks = 0
        self.blocks = 0
        self.last_frame = -1
        self._started = False

    def open(self) -> None:
        """Open the serial driver, and start the board the first time."""
        self.inner.open()
        if not self._started:  # the board streams once the port is open (nothing flushed)
            self.dev.start()
            self._started = True

    def close(self) -> None:
        """Close the serial driver."""
        self.inner.close()

    def stats(self) -> dict[str, int]:
        """Return the serial driver's counters."""
        return self.inner.stats()

    def take_events(self):
        """Return the serial driver's new events and dropped counts."""
        return self.inner.take_events()

    def read(self, timeout: float | None = None):
        """Return the serial driver's next block (None if none came within ``timeout`` s), checked against the mock."""
        block = self.inner.read(timeout)
        if block is not None:
            self._check(block)
        return block

    def _check(self, block) -> None:
        self.blocks += 1
        if block.start % SPF or block.frames % SPF:
            self.unaligned_blocks += 1
            return
        assert self.inner.first_sequence is not None, "a block came: the driver has seen a frame"
        k0 = (self.inner.first_sequence - self.dev.first_seq) % 65536
        first = k0 + block.start // SPF
        n = block.frames // SPF
        filled = np.zeros(n, bool) if block.filled is None else block.filled[::SPF]
        got = (block.data * 32768).astype(np.int16)  # exact: the driver scales by a power of two
        for i in range(n):
            k = first + i
            rows = got[i * SPF:(i + 1) * SPF]
            if filled[i]:
                self.filled_by_kind[self.dev.lost_kind(k) or "not in the ledger"] += 1
                self.mismatched_frames += bool(rows.any())
            elif not np.array_equal(rows, self.dev.frame_rows(k)):
                self.mismatched_frames += 1
        self.last_frame = first + n - 1  # a block always ends with a received frame


class CountingSink(Sink):
    """Counts windows and gap windows, and the longest wall time between two windows."""

    def __init__(self) -> None:
        self.windows = self.gap_windows = 0
        self.longest_gap = 0.0
        self.stalls = 0
        self._last: float | None = None
        self.result: dict | None = None

    def emit(self, event) -> None:
        """Count a window (and a gap window), and the wall time since the last."""
        now = time.monotonic()
        if self._last is not None:
            gap = now - self._last
            self.longest_gap = max(self.longest_gap, gap)
            self.stalls += gap > STALL
        self._last = now
        self.windows += 1
        self.gap_windows += "gap" in event.flags

    def summary(self, summary: RunSummary) -> None:
        """Keep the run's summary as ``result``, as JSON (the report is JSON)."""
        self.result = summary.to_dict()

    def close(self) -> None:
        """Do nothing: the sink holds nothing to release."""
        pass


def run_soak(seconds: float, unplugs: int, seed: int = 1, sample_every: float = 2.0,
             faults: dict | None = None, progress=None) -> dict:
    """Run the soak; return the report as a dict (see :func:`format_report`).

    Parameters
    ----------
    seconds : float
        Seconds of faults and unplugs, > 0; the run lasts ``DRAIN`` s longer.
    unplugs : int
        Unplug/replug cycles, spread evenly over ``seconds``.
    seed : int
        Seed of the mock's fault schedule.
    sample_every : float
        Seconds between RSS samples.
    faults : dict, optional
        FaultSpec rates; default :data:`FAULT_RATES`.
    progress : callable, optional
        Called with a line of text at each RSS sample.
    """
    rates = dict(FAULT_RATES if faults is None else faults)
    every = None
    if unplugs > 0:
        # Each cycle is `every` connected + UNPLUG_FOR + the driver's reopen (< 0.6 s).
        every = max(0.5, seconds / (unplugs + 0.5) - UNPLUG_FOR - 0.6)
    spec = FaultSpec(**rates, unplug_every=every, unplug_for=UNPLUG_FOR,
                     unplug_limit=unplugs if unplugs > 0 else None)
    dev = MockWhiskerDevice(source_signal(), RATE, samples_per_frame=SPF, loop=True, faults=spec,
                            seed=seed)
    driver = CheckedDriver(SerialWhiskerDriver(dev.port, RATE, CHANNELS), dev)
    sink = CountingSink()
    node = Node(driver, FeaturePipeline(whisker_bank(), ("Af",)), [sink], overrun="drop-oldest")
    samples: list[tuple[float, int, int, int]] = []  # (s since start, RSS KiB, windows, frames)
    t0 = time.monotonic()

    def sample() -> None:
        st = driver.inner.stats()
        samples.append((time.monotonic() - t0, rss_kib(), sink.windows, st["frames"]))
        if progress:
            t, r, w, f = samples[-1]
            progress(f"{t:7.0f} s  RSS {r / 1024:6.1f} MiB  windows {w}  stream {f / RATE:.0f} s  "
                     f"unplugs {st['unplugs']}  frames lost {st['frames_lost']}")

    def control() -> None:
        try:
            while not node._stop.wait(min(sample_every, max(0.0, t0 + seconds - time.monotonic()))):
                if time.monotonic() >= t0 + seconds:
                    break
                sample()
            dev.end_faults()
            node._stop.wait(DRAIN)
            sample()
        finally:
            node.stop("soak finished")

    controller = threading.Thread(target=control, name="soak-control", daemon=True)
    error = None
    with dev:
        controller.start()
        try:
            summary = node.run().to_dict()
        except Exception as exc:  # the report says so; the exit status too
            summary, error = sink.result or {}, f"{type(exc).__name__}: {exc}"
        controller.join(10)
        ledger = dev.ledger
        mock_error = None if dev.error is None else repr(dev.error)
    uptime = time.monotonic() - t0
    rep = _compare(ledger, driver, sink, summary, samples, uptime, error, mock_error,
                   seconds=seconds, unplugs=unplugs, seed=seed, spec=spec)
    rep["growth_kib"] = {"mock_ledger": _size_kib(ledger.lost)}
    return rep


def _size_kib(container) -> float:
    """Memory held by a dict or list and the numbers in it, KiB (what grows by design)."""
    items = container.items() if isinstance(container, dict) else ((x,) for x in container)
    return (sys.getsizeof(container) + sum(sys.getsizeof(v) for item in items for v in item
                                           if not isinstance(v, str))) / 1024


def rss_slope(samples, skip: float = 0.25) -> float | None:
    """Least-squares RSS slope, KiB per minute, after the first ``skip`` of the run.

    ``samples`` are ``(seconds, RSS KiB, ...)``.
    """
    if len(samples) < 4:
        return None
    t = np.array([s[0] for s in samples])
    r = np.array([s[1] for s in samples], float)
    keep = t >= t[0] + skip * (t[-1] - t[0])
    if keep.sum() < 3:
        return None
    return float(np.polyfit(t[keep] / 60.0, r[keep], 1)[0])


def _compare(led, driver: CheckedDriver, sink: CountingSink, summary: dict, samples, uptime: float,
             error, mock_error, **params) -> dict:
    st = driver.stats()
    k_last = driver.last_frame
    lost = collections.Counter(v for k, v in led.lost.items() if k <= k_last)
    n_lost = sum(lost.values())
    by = driver.filled_by_kind

    rows = []

    def row(name, ledger, counted, checked=None, exact=True):
        seen = [c for c in (counted, checked) if c is not None]
        # Not exact: the driver's count may exceed the ledger's, the checked one may not.
        ok = all(c == ledger for c in seen) if exact else (
            counted >= ledger and (checked is None or checked == ledger))
        rows.append({"count": name, "ledger": ledger, "driver": counted, "checked": checked,
                     "exact": exact, "ok": bool(ok)})

    row("frames produced up to the last received", k_last + 1, st["frames_ok"] + st["frames_lost"])
    row("frames delivered intact", k_last + 1 - n_lost, st["frames_ok"])
    row("truncated frames", led.truncated, st["truncated"], by["truncated"])
    row("altered frames (CRC)", led.crc, st["crc_errors"], by["crc"])
    row("frames left out", led.omitted, None, by["omitted"])
    row("wrong channel count", led.wrong_channels, st["channel_mismatch"], by["channels"])
    row("wrong version (header errors >=)", led.wrong_version, st["header_errors"], by["version"],
        exact=False)
    row("frames not written (pty full)", lost["overflow"], None, by["overflow"])
    row("frames while unplugged", lost["unplugged"], None, by["unplugged"])
    row("frames lost in the port at unplug", lost["unplug"], None, by["unplug"])
    row("unplugs", led.unplugs, st["unplugs"])
    row("reconnects", led.unplugs, st["reconnects"])
    row("frames lost (all reasons)", n_lost, st["frames_lost"], sum(by.values()))
    row("samples filled", SPF * n_lost, st["filled"], SPF * sum(by.values()))
    row("bytes skipped (garbage + damaged + cut)", led.garbage_bytes + led.damaged_bytes + led.cut_bytes,
        st["bytes_skipped"])
    row("filled frames not in the ledger", 0, None, by["not in the ledger"])
    row("frames differing from the mock's", 0, None, driver.mismatched_frames)
    row("discontinuities", 0, st["discontinuities"])
    row("unplugs forced (ledger not exact)", 0, led.unplugs_forced)
    # The node's summary: every row of the stream has one fate (docs/node.md); the filled ones
    # are exactly the ledger's lost frames, and no measured row was lost in the ring.
    fates = summary.get("frames") or {}
    row("node summary: rows filled", SPF * n_lost, fates.get("filled", -1))
    row("node summary: rows dropped", 0, fates.get("dropped", -1))
    row("node summary: delivered + filled + dropped - stream", 0,
        sum(fates.get(k, 0) for k in ("delivered", "filled", "dropped")) - fates.get("stream", -1))

    rss = [s[1] for s in samples]
    report = {
        "params": {**{k: v for k, v in params.items() if k != "spec"}, "spec": asdict(params["spec"])},
        "rows": rows,
        "exact": all(r["ok"] for r in rows),
        "rss_kib": {"start": rss[0] if rss else None, "max": max(rss) if rss else None,
                    "end": rss[-1] if rss else None, "slope_kib_per_min": rss_slope(samples)},
        "uptime_s": uptime,
        "stream_s": st["frames"] / RATE,
        "windows": sink.windows,
        "gap_windows": sink.gap_windows,
        "blocks": driver.blocks,
        "unaligned_blocks": driver.unaligned_blocks,
        "longest_s_between_windows": sink.longest_gap,
        "stalls": sink.stalls,
        "stopped_by": summary.get("stopped_by"),
        "node_error": error,
        "mock_error": mock_error,
        "ledger_garbage": {"insertions": led.garbage, "bytes": led.garbage_bytes},
        "header_errors_by_chance": st["header_errors"] - led.wrong_version,
        "driver": st,
        "node_summary": {k: v for k, v in summary.items() if k != "driver"},
        "samples": samples,
    }
    report["passed"] = bool(report["exact"] and not sink.stalls and error is None and mock_error is None
                            and report["stopped_by"] == "soak finished")
    return report


def format_report(rep: dict) -> str:
    """Return the report as Markdown (also what is printed)."""
    p = rep["params"]
    out = [f"# Soak: {p['seconds']:g} s of faults, {p['unplugs']} unplugs, seed {p['seed']}", "",
           f"20 channels x 5 kHz, {SPF} samples/frame; `python3 -m supramodal.benchmarks.soak --minutes "
           f"{p['seconds'] / 60:g} --unplugs {p['unplugs']} --seed {p['seed']}`", "",
           "| count | mock's ledger | driver | checked blocks | match |", "|---|---:|---:|---:|---|"]
    for r in rep["rows"]:
        drv = "" if r["driver"] is None else r["driver"]
        chk = "" if r["checked"] is None else r["checked"]
        mark = ("exact" if r["ok"] else "**MISMATCH**") if r["exact"] else ("ok (>=)" if r["ok"] else "**LOW**")
        out.append(f"| {r['count']} | {r['ledger']} | {drv} | {chk} | {mark} |")
    r = rep["rss_kib"]
    slope = "n/a" if r["slope_kib_per_min"] is None else f"{r['slope_kib_per_min']:+.1f} KiB/min"
    g = rep["ledger_garbage"]
    out += ["",
            f"- garbage insertions: {g['insertions']} ({g['bytes']} bytes); header errors from sync words "
            f"by chance in skipped bytes: {rep['header_errors_by_chance']}",
            f"- RSS: start {r['start']} KiB, max {r['max']} KiB, end {r['end']} KiB, slope {slope} "
            "(least squares after the first quarter)",
            *([f"- what grows by design: the mock's ledger of lost frames {g2['mock_ledger']:.0f} KiB at the end "
               "(the node keeps its latencies in a fixed histogram)"]
              if (g2 := rep.get("growth_kib")) else []),
            f"- uptime {rep['uptime_s']:.1f} s, stream {rep['stream_s']:.1f} s, {rep['blocks']} blocks "
            f"({rep['unaligned_blocks']} not frame-aligned), {rep['windows']} windows "
            f"({rep['gap_windows']} flagged gap)",
            f"- longest time between two windows {rep['longest_s_between_windows']:.2f} s; stalls "
            f"(> {STALL:g} s) {rep['stalls']}; stopped by: {rep['stopped_by']}; node error: "
            f"{rep['node_error']}; mock error: {rep['mock_error']}",
            f"- **{'PASSED' if rep['passed'] else 'FAILED'}**: every count exact, no stall, the node ran "
            "until stopped" if rep["passed"] else "- **FAILED**"]
    return "\n".join(out) + "\n"


def write_report(rep: dict, out: Path) -> list[Path]:
    """Write soak.md, soak.json and (with matplotlib) rss.png into ``out``; the paths written."""
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / "soak.md", out / "soak.json"]
    paths[0].write_text(format_report(rep))
    paths[1].write_text(json.dumps(rep, indent=1))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return paths
    t = np.array([s[0] for s in rep["samples"]]) / 60
    r = np.array([s[1] for s in rep["samples"]]) / 1024
    fig, ax = plt.subplots(figsize=(7, 3))
    ax.plot(t, r)
    ax.set_xlabel("minutes")
    ax.set_ylabel("RSS, MiB")
    ax.set_ylim(0, max(r.max() * 1.1, 1) if r.size else 1)
    ax.set_title("node RSS during the soak")
    fig.tight_layout()
    fig.savefig(out / "rss.png", dpi=100)
    plt.close(fig)
    return paths + [out / "rss.png"]


def main(argv=None) -> int:
    """Run the soak from the command line and write its report; return 0 if it passed, else 1."""
    ap = argparse.ArgumentParser(prog="python3 -m supramodal.benchmarks.soak", description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=60.0, help="minutes of faults and unplugs (default 60)")
    ap.add_argument("--unplugs", type=int, default=100, help="unplug/replug cycles (default 100)")
    ap.add_argument("--seed", type=int, default=1, help="seed of the fault schedule (default 1)")
    ap.add_argument("--sample-every", type=float, default=None, metavar="S",
                    help="seconds between RSS samples (default: the run / 600, at least 1)")
    ap.add_argument("--out", default="soak-report", help="folder for soak.md, soak.json, rss.png")
    args = ap.parse_args(argv)
    if not args.minutes > 0 or args.unplugs < 0:
        ap.error("--minutes must be > 0 and --unplugs >= 0")
    seconds = args.minutes * 60
    every = args.sample_every or max(1.0, seconds / 600)
    rep = run_soak(seconds, args.unplugs, args.seed, every,
                   progress=lambda m: print(m, file=sys.stderr, flush=True))
    text = format_report(rep)
    print(text)
    for p in write_report(rep, Path(args.out)):
        print(f"wrote {p}", file=sys.stderr)
    return 0 if rep["passed"] else 1


if __name__ == "__main__":
    sys.exit(main())
