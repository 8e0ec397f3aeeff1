"""Make docs/view.md's screenshots: the page on the default scene and on the two-sense world.

    python3 tests/view_screenshots.py [default|twosense ...]

Each scene runs in this process with a view sink (the two-sense world trains its two models and
its fusion first: minutes), the page is loaded in headless chromium in a 1280 x 800 window (the
width the page is made to fit, tests/test_view.py) and photographed whole near the end of the run.
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

from supramodal.node.scene.build import build_node
from supramodal.node.scene.schema import default_scene, load_scene
from supramodal.node.runtime.sinks.view import attach, view_sinks
from supramodal.node.scene.variants import with_view

sys.path.insert(0, str(Path(__file__).parent))
from view_browser import Browser  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: The window the page is photographed in, CSS px (the whole page's height is taken).
WIDTH, HEIGHT = 1280, 800


def shoot(name: str, scene, seconds: float, after_windows: int) -> None:
    graph = build_node(with_view(replace(scene, sinks=[]), 0))
    (view,) = view_sinks(graph)
    attach(graph)
    thread = threading.Thread(target=graph.run, kwargs={"max_seconds": seconds}, daemon=True)
    thread.start()
    browser = Browser(width=WIDTH, height=HEIGHT)
    try:
        browser.open(view.url, width=WIDTH, height=HEIGHT)
        browser.wait_for(f"!!document.body && Number(document.body.dataset.received || 0) > {after_windows}",
                         timeout=600)
        time.sleep(1.5)
        png = browser.screenshot(full=True)
    finally:
        browser.close()
    thread.join(600)
    out = ROOT / "docs" / "img" / f"view_{name}.png"
    out.write_bytes(png)
    print(f"wrote {out} ({len(png)} bytes)")


if __name__ == "__main__":
    which = sys.argv[1:] or ["default", "twosense"]
    if "default" in which:
        shoot("default", default_scene(), 30.0, 200)
    if "twosense" in which:
        shoot("twosense", load_scene(str(ROOT / "examples" / "two_sense_world.toml")), None, 90)
