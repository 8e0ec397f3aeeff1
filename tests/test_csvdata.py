"""supramodal/csvdata.py: every CSV file a user gives (a manifest, spans, timestamps) is read a bounded line
at a time; a file with no line break is refused before it is read whole (issue 35, item 10: a CSV of 3 GB
of NULs took 6.4 GB, /dev/zero grew 300 MB/s)."""

from __future__ import annotations

import io
import os
import resource

import pytest

from supramodal.csvdata import MAX_CSV_LINE, bounded_lines
from supramodal.errors import InputError
from supramodal.node.workflows.import_recording import ImportRecordingError, read_times
from supramodal.node.workflows.labels import LabelError, read_spans
from supramodal.node.workflows.manifest import ManifestError, read_manifest

READERS = [(read_manifest, ManifestError), (read_spans, LabelError),
           (lambda p: read_times(p, 1000), ImportRecordingError)]


def test_lines_come_whole_and_a_line_longer_than_the_bound_is_refused_naming_it():
    text = "a,b\r\n" + "x" * MAX_CSV_LINE + "\n" + "c,d"
    assert list(bounded_lines(io.StringIO("a,b\r\nc,d\n", newline=""), "f", InputError)) == ["a,b\r\n", "c,d\n"]
    lines = bounded_lines(io.StringIO(text, newline=""), "f.csv", InputError)
    assert next(lines) == "a,b\r\n" and next(lines) == "x" * MAX_CSV_LINE + "\n"
    assert next(lines) == "c,d"
    with pytest.raises(InputError, match=rf"f.csv, line 2: longer than {MAX_CSV_LINE} characters"):
        list(bounded_lines(io.StringIO("a,b\n" + "y" * (MAX_CSV_LINE + 1), newline=""), "f.csv", InputError))


@pytest.mark.parametrize("read, error", READERS)
def test_a_csv_without_line_breaks_is_refused_in_bounded_memory(tmp_path, read, error):
    path = tmp_path / "nuls.csv"
    with path.open("wb") as f:
        f.write(b"\0" * (64 * 2**20))                 # 64 MB of NULs, no line break
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(error, match="line 1: longer than .* without a line break"):
        read(path)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 32_000     # KB: far from 64 MB


@pytest.mark.skipif(not os.path.exists("/dev/zero"), reason="no /dev/zero here")
@pytest.mark.parametrize("read, error", READERS)
def test_dev_zero_given_as_a_csv_is_refused_at_once(read, error):
    with pytest.raises(error, match="line 1: longer than"):
        read("/dev/zero")
