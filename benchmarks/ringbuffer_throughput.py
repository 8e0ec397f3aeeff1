"""Throughput of node.runtime.ringbuffer.RingBuffer: one writer thread, one reader thread.

Writes ``--frames`` frames of ``--channels`` float64 channels in blocks of
``--block`` frames (default 50: 10 ms at the whisker array's 5 kHz) as fast as
the writer can, while one reader thread reads until the ring is closed. Under
the default 'block' policy nothing is lost, so frames/s is frames delivered
end to end; the clock runs from the first write to the reader's last frame.

    python -m supramodal.benchmarks.ringbuffer_throughput [--block 50] [--reads block|all] [--policy block]
"""

from __future__ import annotations

import argparse
import threading
import time

import numpy as np

from supramodal.node.runtime.ringbuffer import RingBuffer, RingClosed


def run(frames: int, channels: int, block: int, capacity: int, policy: str, reads: str) -> dict:
    """Write ``frames`` in blocks of ``block`` to a ring read by one thread; return the throughput.

    Parameters
    ----------
    frames, channels, block, capacity : int
        Frames written in all, channels per frame, frames per write, the ring's capacity in frames.
    policy : str
        The ring's ``overrun`` policy.
    reads : {"block", "all"}
        The reader asks for exactly one block per read, or for all that is available.

    Returns
    -------
    dict
        ``frames`` read, ``lost`` (the reader's), ``reads``, ``seconds``, ``frames_per_s`` and
        ``blocks_per_s``.
    """
    rb = RingBuffer(capacity, channels, overrun=policy)
    reader = rb.add_reader()
    data = np.random.default_rng(0).standard_normal((block, channels))
    mask = np.zeros(block, bool)
    n_blocks = frames // block
    got = {"frames": 0, "reads": 0}

    def consume():
        kwargs = {"max_frames": block, "min_frames": block} if reads == "block" else {}
        while True:
            try:
                chunk = reader.read(**kwargs)
            except RingClosed:
                break
            got["frames"] += len(chunk.data)
            got["reads"] += 1
        got["end"] = time.perf_counter()

    t = threading.Thread(target=consume)
    t.start()
    t0 = time.perf_counter()
    for _ in range(n_blocks):
        rb.write(data, mask)
    rb.close()
    t.join()
    s = rb.stats()["readers"]["reader0"]
    elapsed = got["end"] - t0
    return {"frames": got["frames"], "lost": s["lost"], "reads": got["reads"], "seconds": elapsed,
            "frames_per_s": got["frames"] / elapsed, "blocks_per_s": n_blocks / elapsed}


def main() -> None:
    """Run the measurement ``--repeat`` times with the command line's settings and print each."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=5_000_000)
    p.add_argument("--channels", type=int, default=20)
    p.add_argument("--block", type=int, default=50)
    p.add_argument("--capacity", type=int, default=8192)
    p.add_argument("--policy", default="block")
    p.add_argument("--reads", choices=("block", "all"), default="block",
                   help="reader asks for exactly one block per read, or for all that is available")
    p.add_argument("--repeat", type=int, default=3)
    a = p.parse_args()
    for _ in range(a.repeat):
        r = run(a.frames, a.channels, a.block, a.capacity, a.policy, a.reads)
        print(f"{a.channels} ch float64, {a.block}-frame blocks, policy={a.policy}, reads={a.reads}: "
              f"{r['frames_per_s']:.3g} frames/s ({r['blocks_per_s']:.3g} blocks/s, "
              f"{r['frames']} frames in {r['seconds']:.2f} s, {r['reads']} reads, lost {r['lost']})")


if __name__ == "__main__":
    main()
