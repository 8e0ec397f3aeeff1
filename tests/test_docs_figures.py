"""The figures of README.md and docs/*.md come from a command the docs name, and the cheap ones are what that
command prints today.

A newcomer ran the commands beside the figures and got others: README's late fusion 0.775 where the command
printed 0.919, docs/node.md's weight 0.50 where it printed 0.30. The text had been true once. Here a comment
right above a paragraph, table, list, fenced block or heading says where its figures come from (the
convention is in docs/development.md, "The documents' figures"):

* ``<!-- figures: COMMAND -->``: cheap. The test runs COMMAND with bash in a fresh folder (a copy of the
  checkout's ``examples/``, as tests/test_docs_commands.py runs the walkthroughs) and fails naming every figure
  of the element that COMMAND did not print. COMMAND (each of its parts joined by ``&&``) must also appear in
  the document's text, where a reader sees it. ``<!-- figures: COMMAND; except WORD, ... -->``: a line of the
  element that holds one of the WORDs keeps its figures out of the check (a wall time, which no two runs
  share).
* ``<!-- figures: walkthrough -->``: the figures are what the document's own command blocks above the element
  printed: tests/test_docs_commands.py, which runs them, checks the element against their output (so a
  walkthrough's figures need no command of their own, and its commands run once).
* ``<!-- figures: measured -->``: too costly to run here (minutes to hours). The element must show the command
  that printed its figures (in backticks: ``supramodal ...``, ``python -m supramodal....``) and the date it was
  run (YYYY-MM-DD), and the command must exist (a subcommand of ``supramodal``, a module that imports).

A *figure* is a number with a decimal point (0.811, 2.41, 27.5): counts and settings are integers or live in
the scene's key tables. The element a comment covers is the paragraph, table or list item that follows (up
to a blank line), the fenced block, or, below a heading, that heading's whole section (below the title: the
whole document); or, where a ``<!-- figures: end -->`` comment follows, everything up to it (a caption, its
table and the paragraph after it). :func:`test_every_measured_figure_says_where_it_comes_from` holds every
number of three decimals or more (what a measurement prints: 0.811, 0.0252) to a comment, outside the documents' files
(``toml``, ``json``, ``python`` fences) and the generated key tables.
"""

from __future__ import annotations

import importlib.util
import re
import subprocess
from dataclasses import dataclass
from datetime import date
from pathlib import Path

import pytest
from test_docs_commands import DOCUMENTS, _environment, _fresh_folder, _name

_COMMENT = re.compile(r"^\s*<!--\s*figures:\s*(.*?)\s*-->\s*$")
_FENCE = re.compile(r"^ {0,3}(`{3,}|~{3,})(.*)$")
_HEADING = re.compile(r"^(#{1,6})\s")
#: A figure: a number with a decimal point, not part of a version, a date or a word (3.11.7, T8, 1e-12).
FIGURE = re.compile(r"(?<![\w.\-+])[-+]?\d+\.\d+(?![\w.]*\d)(?!\.\d)")
#: A measured figure, held to a comment: three decimals or more.
MEASURED = re.compile(r"(?<![\w.\-+])[-+]?\d+\.\d{3,}(?![\w.]*\d)(?!\.\d)")
#: A command as the text shows it: in backticks, the CLI or one of its modules.
_SHOWN_COMMAND = re.compile(r"`((?:supramodal|python3? -m supramodal[\w.]*)(?: [^`]*)?)`")
_DATE = re.compile(r"\b(20\d\d)-(\d\d)-(\d\d)\b")
#: Fences whose text is a file of the documents (a scene, a bank), not output: their numbers are settings.
_FILE_TAGS = frozenset({"toml", "json", "python", "yaml", "csv"})
_GENERATED = re.compile(r"^<!-- (BEGIN|END) generated: ")


@dataclass
class Element:
    """What one figures comment covers: the document, the comment's line, the covered lines (1-based, end
    exclusive) and the comment's text."""

    doc: Path
    line: int
    start: int
    end: int
    says: str

    @property
    def where(self) -> str:
        return f"{_name(self.doc)}:{self.line}"

    def text(self) -> str:
        return "\n".join(self.doc.read_text().splitlines()[self.start - 1:self.end - 1])


def _fence_end(lines: list[str], i: int) -> int:
    """The index after the fence opened at ``lines[i]``."""
    fence = _FENCE.match(lines[i]).group(1)
    j = i + 1
    while j < len(lines) and not re.match(rf"^ {{0,3}}{fence[0]}{{{len(fence)},}}\s*$", lines[j]):
        j += 1
    return j + 1


def _covered(lines: list[str], i: int) -> tuple[int, int]:
    """The lines (0-based, end exclusive) the element starting at ``lines[i]`` spans (see the module docstring)."""
    heading = _HEADING.match(lines[i])
    if heading:
        level = len(heading.group(1))
        j = i + 1
        while j < len(lines):
            if _FENCE.match(lines[j]):
                j = _fence_end(lines, j)
                continue
            h = _HEADING.match(lines[j])
            if h and len(h.group(1)) <= level:
                break
            j += 1
        return i, j
    if _FENCE.match(lines[i]):
        return i, _fence_end(lines, i)
    j = i
    while j < len(lines) and lines[j].strip():
        j += 1
    return i, j


def elements(doc: Path) -> tuple[list[Element], list[str]]:
    """The figures comments of ``doc`` with what each covers, and what is wrong with them (a comment with
    nothing under it)."""
    lines = doc.read_text().splitlines()
    found, problems = [], []
    comments = [(i, m.group(1)) for i, line in enumerate(lines) if (m := _COMMENT.match(line))]
    for k, (i, says) in enumerate(comments):
        if says == "end":
            if k == 0 or comments[k - 1][1] == "end":
                problems.append(f"{_name(doc)}:{i + 1}: a 'figures: end' comment without a figures comment above")
            continue
        j = i + 1
        while j < len(lines) and (not lines[j].strip() or lines[j].lstrip().startswith("<!--")):
            j += 1
        if j == len(lines) or not says:
            problems.append(f"{_name(doc)}:{i + 1}: a figures comment needs what it says (a command or "
                            "'measured') and an element below it")
            continue
        if k + 1 < len(comments) and comments[k + 1][1] == "end":
            start, end = j, comments[k + 1][0]          # up to its end comment
        else:
            start, end = _covered(lines, j)
        found.append(Element(doc, i + 1, start + 1, end + 1, says))
    return found, problems


def _checked_lines(doc: Path) -> list[tuple[int, str]]:
    """``doc``'s lines (1-based) that hold prose, tables and output: not a file's fence, a generated key table
    or a comment."""
    lines = doc.read_text().splitlines()
    kept, i, generated = [], 0, False
    while i < len(lines):
        if _GENERATED.match(lines[i]):
            generated = lines[i].startswith("<!-- BEGIN")
            i += 1
            continue
        fence = _FENCE.match(lines[i])
        if fence:
            end = _fence_end(lines, i)
            tag = fence.group(2).strip().split()[0] if fence.group(2).strip() else ""
            if tag not in _FILE_TAGS and not generated:
                kept.extend((n + 1, lines[n]) for n in range(i + 1, end - 1))
            i = end
            continue
        if not generated and not lines[i].lstrip().startswith("<!--"):
            kept.append((i + 1, lines[i]))
        i += 1
    return kept


def test_every_measured_figure_says_where_it_comes_from():
    """Every number of three decimals or more in README.md and docs/*.md (outside files and the generated key
    tables) lies under a figures comment, and every figures comment covers something."""
    problems = []
    for doc in DOCUMENTS:
        found, wrong = elements(doc)
        problems.extend(wrong)
        covered = {n for e in found for n in range(e.start, e.end)}
        for n, line in _checked_lines(doc):
            if n not in covered and MEASURED.search(line):
                problems.append(f"{_name(doc)}:{n}: {', '.join(MEASURED.findall(line))} without a figures comment "
                                f"above its paragraph, table or section: {line.strip()[:100]}")
    assert not problems, "\n".join(problems)


#: The comments that name no command of their own.
KINDS = ("measured", "walkthrough")


def _all_elements(kind: str) -> list[Element]:
    """The elements of every document whose comment is ``kind``: "measured", "walkthrough" or "cheap" (a
    command)."""
    return [e for doc in DOCUMENTS for e in elements(doc)[0] if e.says == kind or (kind == "cheap" and e.says
                                                                                   not in KINDS)]


def unprinted(element: Element, printed_text: str, exempt: list[str] = ()) -> list[str]:
    """The figures of ``element`` that ``printed_text`` does not hold (each with its line), leaving out the
    lines that hold a word of ``exempt``."""
    printed = {f.lstrip("+-") for f in FIGURE.findall(printed_text)}
    missing = []
    for n, line in enumerate(element.text().splitlines(), element.start):
        if any(word in line for word in exempt):
            continue
        missing += [f"{f} (line {n})" for f in FIGURE.findall(line) if not _as_printed(f) & printed]
    return missing


def _command_exists(command: str) -> str | None:
    """What is wrong with a shown command (None: it exists): a ``supramodal`` subcommand, or a module of
    ``python -m``."""
    words = command.split()
    if words[0] == "supramodal":
        from supramodal.node.cli import build_parser

        subcommands = build_parser()._subparsers._group_actions[0].choices      # argparse keeps them here
        if len(words) > 1 and not words[1].startswith("-") and words[1] not in subcommands:
            return f"`{command}`: supramodal has no subcommand {words[1]!r}"
        return None
    module = words[2]
    return None if importlib.util.find_spec(module) is not None else f"`{command}`: no module {module}"


@pytest.mark.parametrize("element", [pytest.param(e, id=e.where) for e in _all_elements("measured")])
def test_a_costly_figure_shows_its_command_and_date(element):
    text = element.text()
    commands = _SHOWN_COMMAND.findall(text)
    dates = [date(*map(int, m)) for m in _DATE.findall(text)]
    assert commands, f"{element.where}: the figures below show no command (in backticks) that printed them"
    assert dates, f"{element.where}: the figures below show no date (YYYY-MM-DD) they were measured on"
    assert all(d <= date.today() for d in dates), f"{element.where}: a date in the future: {dates}"
    wrong = [w for w in map(_command_exists, commands) if w]
    assert not wrong, f"{element.where}: " + "; ".join(wrong)


#: Seconds a figures command may take: a first run trains its models (the two-sense world's early fusion took
#: 5 min at a load of 4 on 2 cores).
FIGURES_SECONDS = 2400.0
_OUTPUTS: dict[str, str] = {}


def _printed(command: str, tmp_path_factory) -> str:
    """What ``command`` printed (stdout and stderr), run once per test session in a fresh folder."""
    if command not in _OUTPUTS:
        folder = _fresh_folder(tmp_path_factory.mktemp("figures") / "doc")
        done = subprocess.run(["bash", "-c", f"set -euo pipefail\n{command}"], cwd=folder, env=_environment(),
                              stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=FIGURES_SECONDS)
        assert done.returncode == 0, f"`{command}` ended with exit status {done.returncode}:\n{done.stderr[-3000:]}"
        _OUTPUTS[command] = done.stdout + "\n" + done.stderr
    return _OUTPUTS[command]


def _as_printed(figure: str) -> set[str]:
    """The spellings of ``figure`` that count as printing it (a sign dropped: "+39.92 ppm" and "-0.002 ms" in
    prose are 39.92 and 0.002 in a column)."""
    return {figure, figure.lstrip("+-")}


@pytest.mark.slow
@pytest.mark.parametrize("element", [pytest.param(e, id=e.where) for e in _all_elements("cheap")])
def test_a_cheap_figure_is_what_its_command_prints(element, tmp_path_factory):
    command, _, rest = element.says.partition("; except ")
    command = command.strip()
    exempt = [w.strip() for w in rest.removeprefix(" ").removeprefix("except").split(",") if w.strip()]
    shown = re.sub(r"<!--\s*figures:.*?-->", "", element.doc.read_text())
    unshown = [part.strip() for part in command.split("&&") if part.strip() not in shown]
    assert not unshown, f"{element.where}: the document does not show the command {unshown} its figures come from"
    missing = unprinted(element, _printed(command, tmp_path_factory), exempt)
    assert not missing, (f"{element.where}: `{command}` did not print {', '.join(missing)}; run it and copy what it "
                         f"prints\n--- it printed ---\n{_printed(command, tmp_path_factory)[-3000:]}")
