"""CPU cost of drivers.serial_whisker.SerialWhiskerDriver streaming from the mock board on a pty.

CPU seconds per second of stream, for the reading thread alone (``time.thread_time``) and for
the whole process (the mock's writer thread included).

    python -m supramodal.benchmarks.serial_whisker_cpu [--seconds 5] [--channels 20] [--rate 5000]
        [--samples-per-frame 32]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from supramodal.drivers.mock_whisker import MockWhiskerDevice
from supramodal.drivers.serial_whisker import SerialWhiskerDriver


def measure(seconds: float = 5.0, channels: int = 20, rate: float = 5000.0, samples_per_frame: int = 32) -> dict:
    """Stream ``seconds`` of sines through the mock board and the driver; the CPU and wall times."""
    n = int(seconds * rate)
    t = np.arange(n)[:, None] / rate
    src = 0.5 * np.sin(2 * np.pi * (50 + 10 * np.arange(channels)) * t)
    with MockWhiskerDevice(src, rate, samples_per_frame=samples_per_frame) as dev, \
            SerialWhiskerDriver(dev.port, rate, channels) as drv:
        reads = rows = 0
        cpu0, proc0, wall0 = time.thread_time(), time.process_time(), time.monotonic()
        dev.start()
        while rows < n:
            block = drv.read(1.0)
            reads += 1
            if block is None and dev.finished.is_set():
                break
            rows += 0 if block is None else block.frames
        cpu, proc, wall = (time.thread_time() - cpu0, time.process_time() - proc0, time.monotonic() - wall0)
        stats = drv.stats()
    return {"stream_seconds": rows / rate, "wall": wall, "reads": reads, "driver_cpu": cpu, "process_cpu": proc,
            "stats": stats}


def main(argv=None) -> int:
    """Measure the serial driver with the command line's settings and print its CPU; return 0."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=5.0, help="seconds of stream (default 5)")
    p.add_argument("--channels", type=int, default=20)
    p.add_argument("--rate", type=float, default=5000.0, help="samples per second per channel (default 5000)")
    p.add_argument("--samples-per-frame", type=int, default=32)
    a = p.parse_args(argv)
    r = measure(a.seconds, a.channels, a.rate, a.samples_per_frame)
    s = r["stream_seconds"]
    print(f"{a.channels} channels x {a.rate:g} Hz, {a.samples_per_frame} samples/frame, "
          f"{s:.2f} s of stream in {r['wall']:.2f} s, {r['reads']} reads, {r['stats']['frames_ok']} frames")
    print(f"driver thread: {r['driver_cpu'] / s * 1000:.1f} ms CPU per s of stream "
          f"({r['driver_cpu'] / s * 100:.2f} % of a core); whole process incl. mock writer: "
          f"{r['process_cpu'] / s * 100:.2f} %")
    print({k: v for k, v in r["stats"].items() if v})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
