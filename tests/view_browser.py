"""A real headless browser for the view's tests: Debian's chromium, driven over the DevTools protocol
through a pipe (``--remote-debugging-pipe``: JSON messages ending in NUL on file descriptors 3 and 4).

The pipe needs nothing beyond the standard library (no WebSocket client, no Selenium or Playwright
and their own browser downloads); :func:`chromium_path` is None where chromium is not installed,
and the tests skip, saying so.
"""

from __future__ import annotations

import base64
import itertools
import json
import os
import shutil
import struct
import subprocess
import tempfile
import time
import zlib
from typing import Any

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome")


def chromium_path() -> str | None:
    return next((p for p in map(shutil.which, CHROMIUM_NAMES) if p), None)


class Browser:
    """One headless chromium; :meth:`open` a page, :meth:`eval` JavaScript in it, :meth:`screenshot`."""

    def __init__(self, width: int = 1280, height: int = 1400, timeout: float = 60.0) -> None:
        path = chromium_path()
        if path is None:
            raise RuntimeError("chromium is not installed")
        self.timeout = timeout
        self._profile = tempfile.mkdtemp(prefix="view-chromium-")
        to_chrome_r, self._to_chrome = os.pipe()
        self._from_chrome, from_chrome_w = os.pipe()
        # fds 3 and 4 in the child, whatever the parent's numbers are (moved above 4 first)
        hi_r = os.dup(to_chrome_r) if to_chrome_r > 4 else _above(to_chrome_r)
        hi_w = os.dup(from_chrome_w) if from_chrome_w > 4 else _above(from_chrome_w)

        def child() -> None:
            os.dup2(hi_r, 3)
            os.dup2(hi_w, 4)

        args = [path, "--headless", "--remote-debugging-pipe", f"--user-data-dir={self._profile}",
                "--no-first-run", "--no-default-browser-check", "--disable-gpu", "--disable-extensions",
                "--disable-background-networking", "--disable-sync", "--mute-audio", "--hide-scrollbars",
                f"--window-size={width},{height}", "about:blank"]
        if os.geteuid() == 0:
            args.insert(1, "--no-sandbox")      # chromium refuses to run as root with its sandbox
        self.proc = subprocess.Popen(args, preexec_fn=child, close_fds=False, stdin=subprocess.DEVNULL,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        for fd in (to_chrome_r, from_chrome_w, hi_r, hi_w):
            os.close(fd)
        self._ids = itertools.count(1)
        self._buffer = b""
        self.session: str | None = None

    # -- the protocol --

    def send(self, method: str, params: dict | None = None, session: str | None = None) -> dict[str, Any]:
        """One command; its result (raises on a protocol error)."""
        msg_id = next(self._ids)
        msg: dict[str, Any] = {"id": msg_id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        os.write(self._to_chrome, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + self.timeout
        while True:
            reply = self._read(deadline)
            if reply.get("id") == msg_id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})

    def _read(self, deadline: float) -> dict[str, Any]:
        import select

        while b"\0" not in self._buffer:
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError("chromium did not answer in time")
            ready, _, _ = select.select([self._from_chrome], [], [], left)
            if ready:
                chunk = os.read(self._from_chrome, 1 << 20)
                if not chunk:
                    raise RuntimeError("chromium closed its pipe")
                self._buffer += chunk
        raw, self._buffer = self._buffer.split(b"\0", 1)
        return json.loads(raw)

    # -- pages --

    def open(self, url: str, width: int | None = None, height: int | None = None) -> None:
        """A new tab on ``url``; ``width`` x ``height``: its window (CSS px) instead of the browser's."""
        sized = width is not None and height is not None
        target = self.send("Target.createTarget", {"url": "about:blank" if sized else url})["targetId"]
        self.session = self.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        if sized:
            # set before the page loads, so that it is laid out at that size from the start
            self.send("Emulation.setDeviceMetricsOverride", {"width": width, "height": height, "deviceScaleFactor": 1,
                                                              "mobile": False}, self.session)
            self.send("Page.navigate", {"url": url}, self.session)

    def eval(self, expression: str) -> Any:
        """The value of ``expression`` in the page (awaited when it is a promise)."""
        r = self.send("Runtime.evaluate", {"expression": expression, "returnByValue": True, "awaitPromise": True},
                      self.session)
        if "exceptionDetails" in r:
            raise RuntimeError(f"{expression}: {r['exceptionDetails']}")
        return r["result"].get("value")

    def wait_for(self, expression: str, timeout: float = 30.0, interval: float = 0.1) -> Any:
        """Poll ``expression`` until it is truthy; its value (fails after ``timeout`` s)."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                value = self.eval(expression)
            except RuntimeError as exc:
                # A page just opened (or reloading) has no JavaScript context for a moment: not yet true.
                if "execution context" not in str(exc) or time.monotonic() > deadline:
                    raise
                value = None
            if value:
                return value
            if time.monotonic() > deadline:
                raise AssertionError(f"not true within {timeout} s: {expression}")
            time.sleep(interval)

    def screenshot(self, scale: float = 1.0, full: bool = False) -> bytes:
        """The page as PNG (``full``: the whole page, not only the window), scaled by ``scale``."""
        params: dict[str, Any] = {"format": "png", "captureBeyondViewport": full}
        if scale != 1.0 or full:
            size = self.eval("[document.documentElement.scrollWidth, document.documentElement.scrollHeight,"
                             " innerWidth, innerHeight]")
            w, h = (size[0], size[1]) if full else (size[2], size[3])
            params["clip"] = {"x": 0, "y": 0, "width": w, "height": h, "scale": scale}
        return base64.b64decode(self.send("Page.captureScreenshot", params, self.session)["data"])

    def close(self) -> None:
        try:
            self.send("Browser.close")
        except Exception:
            pass
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(10)
        for fd in (self._to_chrome, self._from_chrome):
            try:
                os.close(fd)
            except OSError:
                pass
        shutil.rmtree(self._profile, ignore_errors=True)


def _above(fd: int) -> int:
    import fcntl

    return fcntl.fcntl(fd, fcntl.F_DUPFD, 5)


def png_size(png: bytes) -> tuple[int, int]:
    """``(width, height)`` of a PNG, from its header."""
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and png[12:16] == b"IHDR", "not a PNG"
    width, height = struct.unpack(">II", png[16:24])
    return width, height


def png_colours(png: bytes) -> tuple[int, int, int]:
    """``(width, height, distinct RGB colours)`` of an 8-bit RGB or RGBA PNG (chromium's screenshots)."""
    assert png[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG"
    pos, idat, width = 8, b"", 0
    height = depth = colour = 0
    while pos < len(png):
        length, kind = struct.unpack(">I4s", png[pos:pos + 8])
        data = png[pos + 8:pos + 8 + length]
        if kind == b"IHDR":
            width, height, depth, colour = struct.unpack(">IIBB", data[:10])
        elif kind == b"IDAT":
            idat += data
        pos += 12 + length
    assert depth == 8 and colour in (2, 6), (depth, colour)
    bpp = 3 if colour == 2 else 4
    raw = zlib.decompress(idat)
    stride = width * bpp
    prev = bytearray(stride)
    colours = set()
    for y in range(height):
        f = raw[y * (stride + 1)]
        row = bytearray(raw[y * (stride + 1) + 1:(y + 1) * (stride + 1)])
        for i in range(stride):
            a = row[i - bpp] if i >= bpp else 0
            b = prev[i]
            c = prev[i - bpp] if i >= bpp else 0
            if f == 1:
                row[i] = (row[i] + a) & 255
            elif f == 2:
                row[i] = (row[i] + b) & 255
            elif f == 3:
                row[i] = (row[i] + (a + b) // 2) & 255
            elif f == 4:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                row[i] = (row[i] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 255
        if y % 8 == 0:
            colours.update(bytes(row[i:i + 3]) for i in range(0, stride, bpp * 4))
        prev = row
    return width, height, len(colours)
