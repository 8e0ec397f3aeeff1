"""Child process of the microphone hardware-in-the-loop tests (tests/test_microphone.py).

Runs in its own process because ALSA_CONFIG_PATH, which the parent sets to an
asound.conf serving a raw file as the default capture device, must be in the
environment before PortAudio initialises, and the test process may already
have imported sounddevice.

Usage::

    python mic_hil_child.py capture OUT_PREFIX FRAMES DTYPE BUFFER_SECONDS [stall]
    python mic_hil_child.py errors OUT_JSON

``capture`` reads FRAMES frames from the default input device with
MicrophoneDriver (with ``stall``, only once the unpaced stream has overrun the
buffer and blocks were dropped), notes the counters, closes the driver, drains
what was buffered, and writes OUT_PREFIX.npz (every delivered block, concatenated) and
OUT_PREFIX.json (counters, block boundaries). ``errors`` writes the messages of
the driver's refusals and the device listing. The parent makes the assertions.
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from supramodal.drivers import DeviceUnavailable, DriverClosed
from supramodal.drivers.devices import format_devices, list_audio_inputs
from supramodal.drivers.microphone import MicrophoneDriver


def capture(prefix: str, n: int, dtype: str, buffer_seconds: float, stall: bool) -> None:
    blocks = []
    with MicrophoneDriver(
        device=None, rate=44100, channels=1, blocksize=441, dtype=dtype, buffer_seconds=buffer_seconds
    ) as mic:
        if stall:
            # A reader that falls behind: the unpaced stream fills the buffer, and the
            # driver must drop (never wait). It does within milliseconds; 60 s is for
            # a loaded machine.
            deadline = time.monotonic() + 60.0
            while mic.stats()["dropped"] == 0:
                if time.monotonic() > deadline:
                    raise SystemExit("the stream never overran the buffer in 60 s")
                time.sleep(0.001)
        got = 0
        while got < n:
            block = mic.read(timeout=30.0)
            if block is None:
                raise SystemExit(f"no block from the microphone in 30 s, after {got} of {n} frames; "
                                 f"driver stats {mic.stats()}")
            blocks.append(block)
            got += block.frames
        at_n = mic.stats()
        device = mic.device_info["name"]
    # Closed: what was buffered still comes, then DriverClosed.
    while True:
        try:
            block = mic.read(timeout=30.0)
        except DriverClosed:
            break
        if block is None:
            raise SystemExit("read() after close() neither delivered nor ended in 30 s")
        blocks.append(block)
    final = mic.stats()
    np.savez(
        prefix + ".npz",
        data=np.concatenate([b.data for b in blocks]),
        filled=np.concatenate(
            [b.filled if b.filled is not None else np.zeros(b.frames, bool) for b in blocks]
        ),
    )
    with open(prefix + ".json", "w") as f:
        json.dump(
            {
                "device": device,
                "at_n": at_n,
                "final": final,
                "starts": [b.start for b in blocks],
                "frames": [b.frames for b in blocks],
                "arrivals": [b.arrival for b in blocks],
                "dtypes": sorted({str(b.data.dtype) for b in blocks}),
            },
            f,
        )


def errors(out: str) -> None:
    result = {"inputs": list_audio_inputs(), "text": format_devices()}
    for key, kwargs in {
        "no_such_device": {"device": "no-such-microphone-xyz"},
        "bad_index": {"device": 999},
        "bad_rate": {"rate": 10_000_000},
    }.items():
        try:
            with MicrophoneDriver(**kwargs):
                result[key] = None
        except DeviceUnavailable as exc:
            result[key] = str(exc)
    with open(out, "w") as f:
        json.dump(result, f)


if __name__ == "__main__":
    if sys.argv[1] == "capture":
        capture(sys.argv[2], int(sys.argv[3]), sys.argv[4], float(sys.argv[5]), sys.argv[6:] == ["stall"])
    elif sys.argv[1] == "errors":
        errors(sys.argv[2])
    else:
        raise SystemExit(f"unknown mode {sys.argv[1]!r}")
