"""Measurements of the model and the node: the one home of benchmark and soak code.

Nothing here is a product path; the model (``supramodal``), the drivers and the node never
import it. Each module is runnable with ``python -m supramodal.benchmarks.NAME`` and prints its report.
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Callable
from pathlib import Path

from supramodal.parallel import THREAD_VARS

#: Environment that pins numerical libraries to one thread; set before numpy is imported.
PINNED_THREADS = dict.fromkeys(THREAD_VARS, "1")


def run_pinned(module: str) -> None:
    """Re-execute ``python -m module`` with the same arguments and BLAS and OpenMP held to one thread.

    Nothing happens if this process already is: a thread count is read when numpy loads, so it
    cannot be set later. Call it first thing under ``if __name__ == "__main__":``.
    """
    if any(os.environ.get(k) != v for k, v in PINNED_THREADS.items()):
        os.execve(sys.executable, [sys.executable, "-m", module, *sys.argv[1:]], {**os.environ, **PINNED_THREADS})


def write_result(result: dict, out, name: str, as_json: bool, report: Callable[[dict], str]) -> int:
    """Write ``result`` as ``out/name.json`` and print it: as JSON with ``as_json``, else ``report(result)``.

    Returns the exit status (0).
    """
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{name}.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2) if as_json else report(result))
    return 0
