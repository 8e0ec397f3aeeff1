"""JSON a user may receive, read within bounds: its size checked before it is read, its nesting before it is parsed.

Python's :mod:`json` parses a deeply nested text by recursion and fails with a
``RecursionError`` (a traceback, not a refusal), and it will read a file of any
size into memory. The readers of the project's JSON files (model headers,
texture sets, session sidecars) go through :func:`read_json_file` or
:func:`parse_json_text` with their own limits, named constants in the module
that reads each format, and get a clear refusal in their own error class.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np

from supramodal.errors import SupramodalError

__all__ = ["nesting_depth", "parse_json_text", "read_json_file"]

# A JSON string (escapes included): its brackets are text, not structure.
_STRING = re.compile(r'"(?:[^"\\]|\\.)*"', re.DOTALL)
_BRACKET = re.compile(r"[\[\]{}]")


def nesting_depth(text: str) -> tuple[int, int]:
    """Deepest nesting of arrays and objects in JSON ``text``, without parsing it.

    Returns
    -------
    depth : int
        0 for a bare number or string, 1 for ``[1, 2]``, 2 for ``{"a": [1]}``, ...
    first_deepest : int
        Character offset of the first bracket that opens the deepest level (0 if none).
    """
    bare = _STRING.sub(lambda m: " " * len(m.group()), text)        # same offsets, strings blanked
    at = [m.start() for m in _BRACKET.finditer(bare)]
    if not at:
        return 0, 0
    level = np.cumsum([1 if bare[i] in "[{" else -1 for i in at])
    k = int(np.argmax(level))
    return max(int(level[k]), 0), at[k]


def _line_column(text: str, offset: int) -> str:
    line_start = text.rfind("\n", 0, offset) + 1
    return f"line {text.count(chr(10), 0, offset) + 1}, column {offset - line_start + 1}"


def parse_json_text(text: str, where: str, *, max_depth: int, error: type[Exception], limit_name: str, **json_kwargs):
    """Parse ``text`` as JSON if it nests at most ``max_depth`` levels.

    Parameters
    ----------
    text : str
        The JSON text.
    where : str
        What it is, for messages (normally the file's path).
    max_depth : int
        Most nesting levels of arrays and objects accepted.
    error : exception class
        Raised for a refusal, with a message naming ``where``, the place and the limit.
    limit_name : str
        The constant holding ``max_depth``, named in the message.
    **json_kwargs
        Passed to :func:`json.loads` (hooks); an ``error`` they raise passes through.

    Raises
    ------
    error
        If the text nests too deep or is not valid JSON.
    """
    depth, at = nesting_depth(text)
    if depth > max_depth:
        raise error(f"{where}: JSON nested {depth} levels deep (deepest at {_line_column(text, at)}); the limit is "
                    f"{max_depth} ({limit_name}): this file is damaged or not of this format")
    try:
        return json.loads(text, **json_kwargs)
    except json.JSONDecodeError as e:
        raise error(f"{where}: not valid JSON ({e}); fix or regenerate the file") from None
    except RecursionError:                    # not reached with a sane limit; never a traceback all the same
        raise error(f"{where}: JSON nested too deep to parse; the limit is {max_depth} ({limit_name})") from None
    except ValueError as e:
        if isinstance(e, SupramodalError):    # a hook's own refusal
            raise
        # Python refuses an integer of more than sys.get_int_max_str_digits() digits (4300) with a plain ValueError
        raise error(f"{where}: not valid JSON here ({str(e).split(';')[0]}); no file of this kind holds such a "
                    "value: this file is damaged or not of this format") from None


def read_json_file(path, *, max_bytes: int, max_depth: int, error: type[Exception], limits: tuple[str, str],
                   **json_kwargs):
    """Read a UTF-8 JSON file of at most ``max_bytes`` bytes (checked before reading) and parse it.

    Parameters
    ----------
    path : str or path-like
    max_bytes : int
        Largest file accepted, bytes.
    max_depth : int
        See :func:`parse_json_text`.
    error : exception class
        Raised for a refusal.
    limits : (str, str)
        Names of the constants holding ``max_bytes`` and ``max_depth``, for messages.
    **json_kwargs
        Passed to :func:`json.loads`.

    Raises
    ------
    FileNotFoundError
        If there is no such file.
    error
        If it is too large, not UTF-8, nests too deep or is not valid JSON.
    """
    path = Path(path)
    size = os.stat(path).st_size
    if size > max_bytes:
        raise error(f"{path}: {size} bytes, more than the {max_bytes} bytes a file of this kind may hold "
                    f"({limits[0]}): this file is damaged or not of this format")
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise error(f"{path}: not valid JSON: not UTF-8 text ({e.reason} at byte {e.start}); fix or regenerate "
                    "the file") from None
    return parse_json_text(text, str(path), max_depth=max_depth, error=error, limit_name=limits[1], **json_kwargs)
