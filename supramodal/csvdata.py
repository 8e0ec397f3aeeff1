"""Bounded reading of the CSV files a user gives (manifests, spans, timestamps).

A file is data, and a "CSV" with no line break (a binary file, ``/dev/zero``) must be refused
before it is read whole.

:func:`bounded_lines` feeds :func:`csv.reader` one line at a time, each at most :data:`MAX_CSV_LINE`
characters; a longer one is refused with the caller's error, naming the file and the line. Files may be
as long as they need (a per-sample timestamp file of an hour at 44.1 kHz is gigabytes): memory is bounded
by the line, not the file.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import TextIO

__all__ = ["MAX_CSV_LINE", "bounded_lines"]

#: Longest line of a CSV file read here, characters (a manifest's paths and labels, a timestamp row).
MAX_CSV_LINE = 64 * 1024


def bounded_lines(f: TextIO, where: str, error: type[Exception]) -> Iterator[str]:
    """Yield the lines of ``f``, each at most :data:`MAX_CSV_LINE` characters besides its line break.

    ``f`` is opened with ``newline=""``, as :mod:`csv` wants; a longer line raises ``error``
    naming ``where`` and the line.
    """
    number = 0
    while True:
        line = f.readline(MAX_CSV_LINE + 2)        # the line and its terminator (\r\n at most)
        if not line:
            return
        number += 1
        if len(line.rstrip("\r\n")) > MAX_CSV_LINE:
            raise error(f"{where}, line {number}: longer than {MAX_CSV_LINE} characters without a line break; this "
                        "is not a CSV file of text lines (a binary file?): give the CSV file")
        yield line
