"""Training manifests: what is accepted, and every refusal naming the manifest, the line and the cause."""

from __future__ import annotations

import csv
import io
import os

import numpy as np
import pytest
from hypothesis import given, settings, HealthCheck, strategies as st

from supramodal.node.workflows.manifest import ManifestError, read_manifest
from supramodal.node.workflows.training import evaluate_manifest, train_from_manifest
from supramodal.replay.wavio import write_wav
from supramodal.banks import whisker_bank
from supramodal.errors import InputError

RATE = 5000
BANK = whisker_bank(rows="A")          # 4 channels: cheap


@pytest.fixture()
def folder(tmp_path):
    """A folder with a.wav (1 s of noise) and b.wav (2 s), both mono at 5 kHz."""
    rng = np.random.default_rng(0)
    write_wav(tmp_path / "a.wav", 0.1 * rng.standard_normal((RATE, 1)), RATE)
    write_wav(tmp_path / "b.wav", 0.1 * rng.standard_normal((2 * RATE, 1)), RATE)
    return tmp_path


def write(folder, text, name="m.csv", encoding="utf-8"):
    path = folder / name
    path.write_bytes(text.encode(encoding))
    return path


# -- accepted ---------------------------------------------------------------------------------

def test_a_spreadsheet_csv_utf8_with_bom_is_read(folder):
    m = write(folder, "\ufeffpath,label,start,end\r\na.wav,rough,0,1\r\nb.wav,smooth,,\r\n")
    recs = read_manifest(m)
    assert [(r.path, r.label, r.start, r.end, r.line) for r in recs] == [
        (folder / "a.wav", "rough", 0.0, 1.0, 2), (folder / "b.wav", "smooth", 0.0, None, 3)]


def test_quoted_label_with_a_comma_is_kept_whole(folder):
    recs = read_manifest(write(folder, 'path,label\na.wav,"rough, wet"\nb.wav,smooth\n'))
    assert [r.label for r in recs] == ["rough, wet", "smooth"]


def test_paths_are_taken_from_the_manifests_folder_not_the_working_directory(folder, tmp_path_factory, monkeypatch):
    monkeypatch.chdir(tmp_path_factory.mktemp("elsewhere"))
    recs = read_manifest(write(folder, "path,label\na.wav,rough\n"))
    assert recs[0].path == folder / "a.wav"


def test_blank_lines_are_skipped_and_lines_still_counted(folder):
    recs = read_manifest(write(folder, "path,label\n\n,\nb.wav,smooth\n"))
    assert [(r.label, r.line) for r in recs] == [("smooth", 4)]


# -- refused, each naming the line and the cause ------------------------------------------------

BAD = [
    # (manifest text, line named, words of the cause)
    ("path,label,start,end\na.wav,rough,0,1\nb.wav,smooth,5,\n", 3, ["start 5 s", "past the end", "2 s long"]),
    ("path,label,start,end\na.wav,rough,0,1.5\n", 2, ["end 1.5 s", "past the end", "1 s long"]),
    ("path,label\na.wav,rough\nb.wav,rough, wet\n", 3, ["3 fields", "quote labels"]),
    ("path,label\na.wav,rough, wet\n", 2, ["3 fields", "quote labels"]),
    ("path,label,start,end\na.wav,rough,0,inf\n", 2, ["end is 'inf'", "finite"]),
    ("path,label,start,end\na.wav,rough,-inf,\n", 2, ["start is '-inf'", "finite"]),
    ("path,label,start,end\na.wav,rough,nan,\n", 2, ["start is 'nan'", "finite"]),
    ("path,label,start,end\na.wav,rough,0,NaN\n", 2, ["end is 'NaN'", "finite"]),
    ("path,label,start,end\na.wav,rough,zero,\n", 2, ["'zero' is not a number"]),
    ("path,label,start,end\na.wav,rough,0.8,0.2\n", 2, ["0 <= start < end"]),
    ("path,label,start,end\na.wav,rough,-1,\n", 2, ["negative"]),
    ("path,label\na.wav,\n", 2, ["label is empty"]),
    ("path,label\n,rough\n", 2, ["path is empty"]),
    ("path,label\nsub/c.wav,rough\n", 2, ["no recording at", os.path.join("sub", "c.wav"), "manifest's folder"]),
    ("a.wav,rough\nb.wav,smooth\n", 1, ["header", "columns must be path,label"]),
    ("file,label\na.wav,rough\n", 1, ["header", "columns must be path,label"]),
    ("path,label,label\na.wav,rough,x\n", 1, ["each named once"]),
    ("path,label\na.wav,\"rough\n", 2, ["not valid CSV", "quote"]),
    ("", 1, ["empty"]),
    ("path,label\n", 2, ["no recording"]),
    ("path,label\nnot_a_wav.wav,rough\n", 2, ["not a WAV file"]),
    # issue 35 item 5: a label becomes a model's class, printed raw (a terminal escape, a forged line)
    ("path,label\na.wav,felt\x1b[31mRED\n", 2, ["label 'felt\\x1b[31mRED' is not printable text", "plain text"]),
    ('path,label\na.wav,"x\ny"\n', 2, ["label 'x\\ny' is not printable text"]),
]


@pytest.mark.parametrize("text, line, causes", BAD)
def test_bad_manifests_name_the_line_and_the_cause(folder, text, line, causes):
    (folder / "not_a_wav.wav").write_text("hello, this is text\n")
    m = write(folder, text)
    with pytest.raises(ManifestError) as info:
        read_manifest(m)
    message = str(info.value)
    assert f"{m}, line {line}:" in message
    for cause in causes:
        assert cause in message
    assert isinstance(info.value, InputError)


def test_a_manifest_that_is_not_utf8_is_refused_with_the_fix(folder):
    m = write(folder, "path,label\na.wav,rauh\u00e9\n", encoding="latin-1")
    with pytest.raises(ManifestError, match="not UTF-8.*CSV UTF-8"):
        read_manifest(m)


def test_a_missing_manifest(folder):
    with pytest.raises(ManifestError, match="no manifest at"):
        read_manifest(folder / "none.csv")


LABEL = st.text(st.characters(codec="utf-8", exclude_categories=("Cs", "Cc", "Cf", "Zl", "Zp")), min_size=1,
                max_size=12).map(str.strip).filter(bool)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(labels=st.lists(LABEL, min_size=1, max_size=6))
def test_labels_written_by_a_csv_writer_come_back_whole(folder, labels):
    out = io.StringIO()
    w = csv.writer(out)
    w.writerow(["path", "label"])
    for i, label in enumerate(labels):
        w.writerow(["ab"[i % 2] + ".wav", label])
    recs = read_manifest(write(folder, out.getvalue()))
    assert [r.label for r in recs] == labels
    assert [r.line for r in recs] == list(range(2, 2 + len(labels)))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(labels=st.lists(st.sampled_from(["rough", "smooth", "felt"]), min_size=1, max_size=6), data=st.data())
def test_an_unquoted_comma_in_any_line_is_refused_at_that_line(folder, labels, data):
    k = data.draw(st.integers(0, len(labels) - 1))
    labels[k] = labels[k] + ", wet"
    text = "path,label\n" + "".join(f"a.wav,{label}\n" for label in labels)
    with pytest.raises(ManifestError) as info:
        read_manifest(write(folder, text))
    assert f"line {k + 2}: the line has 3 fields" in str(info.value)


# -- training and evaluation refuse before they work ----------------------------------------------

def test_training_refuses_a_start_past_the_file_instead_of_a_class_with_no_window(folder):
    m = write(folder, "path,label,start,end\na.wav,rough,0,\nb.wav,smooth,3,\n")
    with pytest.raises(ManifestError, match=r"line 3: start 3 s lies past the end of b\.wav, which is 2 s long"):
        train_from_manifest(m, BANK, epochs=2)


def test_training_refuses_a_line_shorter_than_one_window(folder):
    m = write(folder, "path,label,start,end\na.wav,rough,0,\nb.wav,smooth,1.95,\n")
    with pytest.raises(ManifestError, match=r"line 3: b\.wav \[1\.95, end\) s holds no complete window of 0\.1 s"):
        train_from_manifest(m, BANK, epochs=2)


def test_training_and_evaluation_name_the_line_when_a_file_does_not_fit_the_mapping(folder):
    write_wav(folder / "st.wav", np.zeros((RATE, 2)), RATE)
    m = write(folder, "path,label\na.wav,rough\nst.wav,smooth\n")
    with pytest.raises(ManifestError, match=r"line 3: .*mono"):
        train_from_manifest(m, BANK, epochs=2, mapping="mono")


def test_evaluation_names_the_line_of_an_unknown_label(folder):
    model = train_from_manifest(write(folder, "path,label\na.wav,rough\nb.wav,smooth\n"), BANK, epochs=2)
    m = write(folder, "path,label\na.wav,rough\nb.wav,silk\n", name="t.csv")
    with pytest.raises(ManifestError, match=r"t\.csv, line 3: label 'silk' is not a class of the model"):
        evaluate_manifest(model, m)
    m = write(folder, "path,label,start\na.wav,rough,0.95\n", name="t.csv")
    with pytest.raises(ManifestError, match=r"t\.csv, line 2: a\.wav \[0\.95, end\) s holds no complete window"):
        evaluate_manifest(model, m)
