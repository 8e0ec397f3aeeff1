"""Throughput of drivers.frames.FrameDecoder on the whisker array's stream, MB/s.

A 20-channel x 32-sample frame stream fed in chunks of the whole stream, 4096 B and 512 B,
each for ``--seconds``; then the worst case: garbage with a sync word every 97 bytes, where
every byte is looked at.

    python -m supramodal.benchmarks.frame_decoding [--seconds 2]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from supramodal.drivers.frames import SYNC, FrameDecoder, encode_frame


def main(argv=None) -> int:
    """Decode a stream of frames in chunks of three sizes and print the throughput of each; return 0."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=2.0, help="seconds of decoding per chunk size (default 2)")
    seconds = p.parse_args(argv).seconds
    rng = np.random.default_rng(0)
    frames = [encode_frame(k, rng.integers(-32768, 32768, (32, 20), dtype=np.int16)) for k in range(2000)]
    stream = b"".join(frames)
    for chunk in (len(stream), 4096, 512):
        dec = FrameDecoder()
        total = 0
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            for j in range(0, len(stream), chunk):
                dec.feed(stream[j:j + chunk])
            total += len(stream)
        dt = time.perf_counter() - t0
        if dec.crc_errors or dec.bytes_skipped:
            raise SystemExit(f"the decoder refused a clean stream: {dec.crc_errors} CRC errors, "
                             f"{dec.bytes_skipped} bytes skipped")
        print(f"chunks of {chunk:>7} B: {total / dt / 1e6:7.1f} MB/s, "
              f"{dec.frames_ok / dt:9.0f} frames/s ({len(frames[0])} B frames)")
    noise = bytearray(rng.integers(0, 256, 1 << 20, dtype=np.uint8).tobytes())
    for j in range(0, len(noise) - 12, 97):
        noise[j:j + 2] = SYNC
    data = bytes(noise)
    dec = FrameDecoder()
    t0 = time.perf_counter()
    for j in range(0, len(data), 4096):
        dec.feed(data[j:j + 4096])
    dt = time.perf_counter() - t0
    print(f"garbage with a sync every 97 B: {len(noise) / dt / 1e6:7.1f} MB/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
