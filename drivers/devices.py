"""What is plugged in: audio input devices and serial ports, as plain dicts and as text.

For a ``supramodal devices`` command: the names and indices printed here are
what :class:`~drivers.microphone.MicrophoneDriver` accepts as ``device``, and the
paths what the whisker driver accepts as its port.

sounddevice and pyserial are imported inside the functions, so importing this
module loads neither. All functions may be called from any thread, but not
while a PortAudio stream is being opened or closed on another (PortAudio's
device queries are not thread-safe against that).
"""

from __future__ import annotations

from typing import Any

from supramodal.drivers.base import DeviceUnavailable, DriverError
from supramodal.drivers.microphone import import_sounddevice, portaudio_errors

__all__ = ["list_audio_inputs", "list_serial_ports", "format_devices"]


def list_audio_inputs() -> list[dict[str, Any]]:
    """List PortAudio's input devices.

    Returns
    -------
    list of dict
        One per device with at least one input channel, in PortAudio's order:
        ``index`` (int, what ``device=`` takes), ``name`` (str), ``hostapi``
        (str, e.g. 'ALSA'), ``channels`` (int, most input channels),
        ``default_rate`` (float, Hz), ``low_latency`` and ``high_latency``
        (float, s, PortAudio's default input latencies), ``default`` (bool,
        the system's default input device).

    Raises
    ------
    DeviceUnavailable
        PortAudio is missing (the message says which package to install) or
        fails to list its devices.
    """
    sd = import_sounddevice()
    with portaudio_errors("cannot list the audio devices"):
        hostapis = sd.query_hostapis()
        devices = sd.query_devices()
    # PortAudio's default input (what device=None opens), -1 when there is none.
    default = sd.default.device["input"]
    return [
        {
            "index": int(d["index"]),
            "name": str(d["name"]),
            "hostapi": str(hostapis[d["hostapi"]]["name"]),
            "channels": int(d["max_input_channels"]),
            "default_rate": float(d["default_samplerate"]),
            "low_latency": float(d["default_low_input_latency"]),
            "high_latency": float(d["default_high_input_latency"]),
            "default": int(d["index"]) == default,
        }
        for d in devices
        if d["max_input_channels"] > 0
    ]


def list_serial_ports() -> list[dict[str, Any]]:
    """List the serial ports the operating system reports.

    Returns
    -------
    list of dict
        One per port, sorted by path: ``device`` (str, the path to open),
        ``description`` (str), ``hwid`` (str), ``vid`` and ``pid`` (int or None,
        USB vendor and product ids), ``serial_number``, ``manufacturer``,
        ``product`` (str or None).

    Raises
    ------
    DeviceUnavailable
        pyserial is not installed.

    Notes
    -----
    Pseudo-terminals (``os.openpty()``, used by tests and mock devices) are not
    listed: they are not serial hardware.
    """
    try:
        from serial.tools import list_ports
    except ImportError as exc:
        raise DeviceUnavailable(
            f"cannot list serial ports: {exc}. Install pyserial: `pip install pyserial`"
        ) from exc
    return [
        {
            "device": p.device,
            "description": p.description,
            "hwid": p.hwid,
            "vid": p.vid,
            "pid": p.pid,
            "serial_number": p.serial_number,
            "manufacturer": p.manufacturer,
            "product": p.product,
        }
        for p in sorted(list_ports.comports(), key=lambda p: p.device)
    ]


def format_devices() -> str:
    """Describe the audio inputs and serial ports as text, for people.

    Returns
    -------
    str
        Two sections, ``Audio inputs`` and ``Serial ports``, one line per
        device; the default audio input is marked ``*``. A section that cannot
        be listed (PortAudio or pyserial missing) shows why and how to fix it
        instead, so the other section is still printed.
    """
    def audio_line(d: dict[str, Any]) -> str:
        mark = "*" if d["default"] else " "
        return f"{mark} {d['index']:3d}  {d['name']}  ({d['hostapi']}, {d['channels']} in, {d['default_rate']:g} Hz)"

    def serial_line(p: dict[str, Any]) -> str:
        desc = p["description"] if p["description"] not in (None, "", "n/a") else ""
        usb = f"  USB {p['vid']:04x}:{p['pid']:04x}" if p["vid"] is not None and p["pid"] is not None else ""
        return f"  {p['device']}  {desc}{usb}".rstrip()

    lines = []
    for title, lister, line in (
            ("Audio inputs (MicrophoneDriver device= takes the index or part of the name):", list_audio_inputs,
             audio_line),
            ("Serial ports:", list_serial_ports, serial_line)):
        lines.append(title)
        try:
            found = lister()
        except DriverError as exc:
            lines.append(f"  unavailable: {exc}")
            continue
        lines += [line(item) for item in found] or ["  none found"]
    return "\n".join(lines) + "\n"
