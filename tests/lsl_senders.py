"""A plain pylsl sender for the LSL tests, run as a child process (as another machine would be):
``python tests/lsl_senders.py --name N [options]``.

It sends ``--channels`` channels of a deterministic signal at ``--rate`` Hz in chunks of
``--chunk`` seconds, paced in real time, for ``--seconds`` seconds, and writes one JSON line to
stdout at the start: ``{"t0": LSL time of sample 0 on the sender's sample clock}``.

``--stamp push``: each chunk is stamped when it is pushed (pylsl's default, ``local_clock()``);
``--stamp sample``: with its last sample's time on the sender's sample clock (``t0 + i / rate``).
``--hold-at A --hold-for B``: from A seconds of samples on, nothing is pushed for B seconds (the
samples are kept), then the backlog is pushed at once, chunk by chunk, and sending goes on.
``--source-id ""`` gives the stream no source id. ``--wait``: sample 0 is sent once a consumer has
connected (so that it gets every sample; ``t0`` is printed then).
"""

import argparse
import json
import sys
import time

import numpy as np


def signal(start: int, n: int, rate: float, channels: int) -> np.ndarray:
    """Samples ``start`` .. ``start + n`` of the test signal: a sine per channel, full scale 0.5."""
    t = (start + np.arange(n)) / rate
    return (0.5 * np.sin(2 * np.pi * (100.0 + 37.0 * np.arange(channels))[None, :] * t[:, None])).astype(np.float32)


def main(argv=None) -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--name", required=True)
    p.add_argument("--type", default="Whiskers")
    p.add_argument("--source-id", default="")
    p.add_argument("--rate", type=float, default=5000.0)
    p.add_argument("--channels", type=int, default=20)
    p.add_argument("--chunk", type=float, default=0.01)
    p.add_argument("--seconds", type=float, default=30.0)
    p.add_argument("--stamp", choices=["push", "sample"], default="push")
    p.add_argument("--hold-at", type=float, default=None)
    p.add_argument("--hold-for", type=float, default=0.0)
    p.add_argument("--wait", action="store_true", help="send nothing before a consumer has connected")
    a = p.parse_args(argv)

    import pylsl

    info = pylsl.StreamInfo(a.name, a.type, a.channels, a.rate, "float32", a.source_id)
    size = max(1, int(round(a.chunk * a.rate)))
    outlet = pylsl.StreamOutlet(info, chunk_size=size)
    total = int(round(a.seconds * a.rate))
    hold_from = None if a.hold_at is None else int(round(a.hold_at * a.rate))
    if a.wait:                                      # every sample to a consumer connected first
        if not outlet.wait_for_consumers(60.0):
            sys.exit("no consumer came")
        time.sleep(0.3)
    t0 = pylsl.local_clock() + 0.05
    print(json.dumps({"t0": t0}), flush=True)
    i, held = 0, hold_from is None
    while i < total:
        j = min(total, i + size)
        if not held and j > hold_from:           # the hold: nothing pushed until it ends
            while pylsl.local_clock() < t0 + hold_from / a.rate + a.hold_for:
                time.sleep(0.005)
            held = True
        delay = t0 + j / a.rate - pylsl.local_clock()   # a chunk goes once its last sample is taken
        if delay > 0:                               # (the backlog after a hold: at once)
            time.sleep(delay)
        x = signal(i, j - i, a.rate, a.channels)
        if a.stamp == "sample":
            outlet.push_chunk(x, t0 + (j - 1) / a.rate)
        else:
            outlet.push_chunk(x)
        i = j
    time.sleep(0.5)                                 # let the last chunk go
    sys.exit(0)


if __name__ == "__main__":
    main()
