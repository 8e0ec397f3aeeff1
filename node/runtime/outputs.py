"""Files the node and the command line write: never replace one by accident.

Every writer of a user's file (file sinks, recorded sessions, trained models, synthesised
textures) goes through :func:`check_new_file` before it starts its work, so that an existing
file is replaced only when the user said so (``--force``), and a path that cannot be written
is refused before anything is lost.
"""

from __future__ import annotations

import os
from pathlib import Path

from supramodal.errors import InputError

__all__ = ["check_new_file"]


def check_new_file(path: Path, overwrite: bool, what: str) -> None:
    """Refuse to write ``path`` where that would replace a file, unless ``overwrite``.

    Refuse a folder, a missing parent folder or one that cannot be written, naming the fix. A named pipe
    (FIFO) is not replaced by writing to it: it needs no ``overwrite``.
    """
    if path.is_dir():
        raise InputError(f"{what} {path} is a folder; give a file name")
    if path.exists() and not overwrite and not path.is_fifo():    # a named pipe is written to, not replaced
        raise InputError(f"{what} {path} exists; pass --force to replace it, or choose another path")
    if not path.parent.is_dir():
        raise InputError(f"{what} {path}: the folder {path.parent} does not exist; create it first")
    if not os.access(path.parent, os.W_OK | os.X_OK):
        raise InputError(f"{what} {path}: cannot write in {path.parent} (permission denied)")
