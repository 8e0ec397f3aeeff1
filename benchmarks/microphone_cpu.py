"""Measure the microphone driver's own CPU cost per second of audio.

Runs a PortAudio input stream twice for the same amount of audio: once with a
callback that does nothing (what PortAudio, the host API and sounddevice's
callback wrapper cost anyway), once through MicrophoneDriver with this process's
main thread reading every block (what the node's driver thread does). It
reports process CPU seconds per second of audio for both and their difference;
a third run measures the thread CPU time spent inside the driver's callback and
in the reader thread.

Real-time pacing with no sound card (see docs/testing-without-hardware.md)::

    apt-get install -y --no-install-recommends jackd2
    jackd --no-realtime -d dummy -r 44100 -p 256 -C 1 -P 1 &
    python -m supramodal.benchmarks.microphone_cpu --device system --seconds 60

PortAudio's own JACK host API opens the dummy server's ports ("system")
directly. Unpaced, from ALSA's file plugin (ALSA_CONFIG_PATH set as in the
tests), the same command measures CPU per second of audio delivered as fast as
the file plugin goes.
"""

from __future__ import annotations

import argparse
import threading
import time

import supramodal.drivers.microphone as micmod
from supramodal.drivers.microphone import MicrophoneDriver, import_sounddevice

_PlainBuffer = micmod.CaptureBuffer


def baseline(device, rate: float, blocksize: int, frames: int) -> tuple[float, float]:
    """Process CPU s and wall s for ``frames`` frames through a do-nothing callback."""
    sd = import_sounddevice()
    count = [0]
    done = threading.Event()

    def callback(indata, n, time_info, status):
        count[0] += n
        if count[0] >= frames:
            done.set()

    with sd.InputStream(device=device, samplerate=rate, channels=1, dtype="float32",
                        blocksize=blocksize, callback=callback):
        cpu0, wall0 = time.process_time(), time.monotonic()
        count[0] = 0
        done.wait()
        return time.process_time() - cpu0, time.monotonic() - wall0


class _TimedBuffer(micmod.CaptureBuffer):
    """CaptureBuffer whose callback adds up its own thread CPU time."""

    spent_ns = 0
    first_adc: float | None = None  # inputBufferAdcTime of the first and last callbacks, s
    last_adc: float | None = None
    last_start = 0  # stream index the last callback's block was given

    def callback(self, indata, frames, time_info, status):
        t = time.thread_time_ns()
        super().callback(indata, frames, time_info, status)
        self.spent_ns += time.thread_time_ns() - t
        adc = time_info.inputBufferAdcTime
        if self.first_adc is None:
            self.first_adc = adc
        self.last_adc, self.last_start = adc, self._next - frames


def driver(device, rate: float, blocksize: int, frames: int, timed: bool) -> dict:
    """Measure the same through MicrophoneDriver, read block by block on this thread.

    With ``timed``, the callback's own CPU time is measured too (which costs a
    little: use the untimed run for the total).
    """
    # The driver makes its CaptureBuffer by this module-level name: swapped for one that times its callback.
    micmod.CaptureBuffer = _TimedBuffer if timed else _PlainBuffer  # type: ignore[misc]  # a class swapped in
    try:
        mic = MicrophoneDriver(device=device, rate=rate, channels=1, blocksize=blocksize)
        with mic:
            got = 0
            cpu0, wall0, reader0 = time.process_time(), time.monotonic(), time.thread_time()
            while got < frames:
                block = mic.read(timeout=5.0)
                if block is None:
                    raise SystemExit("no audio for 5 s")
                got += block.frames
            result = {
                "cpu": time.process_time() - cpu0,
                "wall": time.monotonic() - wall0,
                "reader": time.thread_time() - reader0,
                "frames": got,
                "stats": mic.stats(),
            }
            if timed:
                buf = mic._buffer  # noqa: SLF001
                assert isinstance(buf, _TimedBuffer), "made while _TimedBuffer was swapped in"
                assert buf.first_adc is not None and buf.last_adc is not None, "blocks came: callbacks ran"
                result["callback"] = buf.spent_ns / 1e9
                # Where the last block should start by the device's clock, against where
                # the driver put it: frames lost in overflows that were not accounted for.
                result["drift"] = round((buf.last_adc - buf.first_adc) * rate) - buf.last_start
        return result
    finally:
        micmod.CaptureBuffer = _PlainBuffer  # type: ignore[misc]  # the driver's own class back


def main() -> None:
    """Measure a no-op callback and the driver on the device named on the command line; print the CPU."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", default=None, help="PortAudio input device (index or name)")
    p.add_argument("--rate", type=float, default=44100)
    p.add_argument("--blocksize", type=int, default=441)
    p.add_argument("--seconds", type=float, default=30.0, help="seconds of audio per run")
    a = p.parse_args()
    device = int(a.device) if a.device is not None and a.device.isdigit() else a.device
    frames = int(a.seconds * a.rate)
    base_cpu, base_wall = baseline(device, a.rate, a.blocksize, frames)
    r = driver(device, a.rate, a.blocksize, frames, timed=False)
    rt = driver(device, a.rate, a.blocksize, frames, timed=True)
    audio = r["frames"] / a.rate
    print(f"device={device!r} rate={a.rate:g} Hz blocksize={a.blocksize} audio={audio:.1f} s")
    for name, wall, cpu in (("no-op callback: ", base_wall, base_cpu), ("driver + reader:", r["wall"], r["cpu"])):
        print(f"{name} wall {wall:7.2f} s  process CPU {1e3 * cpu / audio:7.3f} ms per s of audio")
    print(f"difference (the driver's own cost): {1e3 * (r['cpu'] - base_cpu) / audio:7.3f} ms per s of audio")
    print("timed run:")
    print(f"  inside the callback:    {1e3 * rt['callback'] / audio:7.3f} ms per s of audio "
          f"({1e6 * rt['callback'] / max(1, rt['stats']['callbacks']):.1f} us per callback)")
    print(f"  reader thread (read()): {1e3 * rt['reader'] / audio:7.3f} ms per s of audio")
    print(f"  stream index behind the device clock at the end: {rt['drift']} frames "
          "(meaningful only where the host API timestamps blocks on the device clock)")
    print(f"stats: {r['stats']}")
    print(f"stats (timed run): {rt['stats']}")


if __name__ == "__main__":
    main()
