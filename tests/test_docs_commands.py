"""The command blocks of README.md and docs/*.md, run as a reader types them: the walkthroughs stay true.

A newcomer who typed every walkthrough as written met a missing ``mkdir``, a mock board of the wrong channel
count and a raw file of the wrong sample format; each doc looked right to the person who wrote it. Here every
fenced block tagged ``sh`` is run with bash (``set -euo pipefail``), exactly as written, a document's blocks in
order in one fresh folder (a copy of the checkout's ``examples/``), as one shell session (a variable exported
and a folder changed to carry over to the next block; a process started with ``&`` lives until the document
ends). The convention the documents follow is in docs/development.md ("The documents' commands"):

* a fence says what it holds: ``sh`` is commands to run; ``text`` is output, a listing or anything else not
  run; ``toml``, ``json``, ``python``, ... are files of that kind. An untagged fence fails
  :func:`test_every_fence_says_what_it_holds`;
* comment lines right above a fence, ``<!-- docs-test: ... -->``, say how it is run:
  ``skip, REASON`` (not run: it needs hardware, a peer or a person this machine does not have),
  ``slow, COST`` (run only where ``SUPRAMODAL_DOCS_SLOW=1``; the cost as measured),
  ``needs command:NAME | module:NAME | library:NAME | file:GLOB ... (WHY)`` (not run where the program,
  Python module, shared library or file is missing, the test then skipped saying so once the rest passed),
  ``file PATH`` (the block's text is written to PATH in the folder when it is reached: the doc says
  "write this to PATH").

A document's blocks run in a process group of their own, killed (SIGTERM, then SIGKILL) when the document ends,
passed or not, with every process that left the group (found by a token in its environment): a mock board or a
JACK server started with ``&`` never outlives it. Each block has
:data:`BLOCK_SECONDS` (:data:`SLOW_BLOCK_SECONDS` when slow); a block that fails or runs over fails the test
naming the document, the block's line and the tail of its output. The folder's shell sees the variables of the
test process (so the run's model cache, ``SUPRAMODAL_CACHE``, tests/harness/shared_trainings.py), ``REPO`` (the checkout, as
own-sensor.md asks), the test's Python first on ``PATH`` (its ``supramodal``, ``python`` and ``python3``) and a
JACK server name of its own (``JACK_DEFAULT_SERVER``: a doc's ``jackd`` never meets another test's server).
"""

from __future__ import annotations

import ctypes.util
import glob
import importlib.util
import os
import re
import secrets
import shlex
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

#: The fence tags whose blocks are commands to run.
RUN_TAGS = frozenset({"sh"})
#: The environment variable under which the blocks marked slow run too ("1").
SLOW_ENV = "SUPRAMODAL_DOCS_SLOW"
#: Seconds a block may take (a first run trains models; the suite's other workers share the cores).
BLOCK_SECONDS = 420.0
#: Seconds a block marked slow may take (own-sensor.md's fit_sensors took 76 min at a load of 4 to 15).
SLOW_BLOCK_SECONDS = 5400.0

_FENCE = re.compile(r"^ {0,3}(`{3,}|~{3,})(.*)$")
_DIRECTIVE = re.compile(r"^<!--\s*docs-test:\s*(.*?)\s*-->\s*$")
_NEEDS = re.compile(r"^(command|module|library|file):(\S+)$")


@dataclass
class Block:
    """A fenced block of a document: its tag, text, the fence's line and the docs-test comments above it."""

    doc: Path
    line: int
    tag: str
    text: str
    skip: str | None = None
    slow: str | None = None
    file: str | None = None
    needs: list[str] = field(default_factory=list)

    @property
    def where(self) -> str:
        return f"{_name(self.doc)}:{self.line}"


def _name(doc: Path) -> str:
    """``doc`` as the failures name it: its path in the checkout."""
    return str(doc.relative_to(ROOT)) if doc.is_relative_to(ROOT) else str(doc)


def parse(doc: Path) -> tuple[list[Block], list[str]]:
    """The fenced blocks of ``doc`` with their docs-test comments, and what is wrong with them (an untagged
    fence, an unknown or incomplete comment, a comment that is not right above a fence)."""
    lines = doc.read_text().splitlines()
    blocks: list[Block] = []
    problems: list[str] = []
    pending: list[tuple[int, str]] = []          # the docs-test comments of the lines right above
    i = 0
    while i < len(lines):
        m = _FENCE.match(lines[i])
        directive = _DIRECTIVE.match(lines[i])
        if directive:
            pending.append((i + 1, directive.group(1)))
            i += 1
            continue
        if m is None:
            for n, _ in pending:
                problems.append(f"{_name(doc)}:{n}: a docs-test comment must be right above a fence")
            pending = []
            i += 1
            continue
        fence, info = m.group(1), m.group(2).strip()
        end = i + 1
        while end < len(lines) and not re.match(rf"^ {{0,3}}{fence[0]}{{{len(fence)},}}\s*$", lines[end]):
            end += 1
        block = Block(doc, i + 1, info.split()[0] if info else "", "\n".join(lines[i + 1:end]) + "\n")
        if not block.tag:
            problems.append(f"{block.where}: an untagged fence: tag it sh (commands to run), text (output, "
                            "anything not run) or its file's kind (toml, json, python, ...)")
        for n, text in pending:
            problem = _apply(block, text)
            if problem:
                problems.append(f"{_name(doc)}:{n}: {problem}")
        pending = []
        blocks.append(block)
        i = end + 1
    for n, _ in pending:
        problems.append(f"{_name(doc)}:{n}: a docs-test comment must be right above a fence")
    return blocks, problems


def _apply(block: Block, directive: str) -> str | None:
    """Set ``block``'s field from one docs-test comment; what is wrong with the comment, or None."""
    word, _, rest = directive.partition(" ")
    word = word.rstrip(",")
    rest = rest.strip()
    if word in ("skip", "slow"):
        if block.tag not in RUN_TAGS:
            return f"'{word}' is for a block of commands (sh), not {block.tag or 'an untagged one'}"
        if not rest:
            return f"'{word}' needs its reason: <!-- docs-test: {word}, WHY -->"
        setattr(block, word, rest)
    elif word == "needs":
        if block.tag not in RUN_TAGS:
            return f"'needs' is for a block of commands (sh), not {block.tag or 'an untagged one'}"
        needs = re.sub(r"\(.*\)$", "", rest).replace(",", " ").split()    # a last (...) says why
        bad = [n for n in needs if not _NEEDS.match(n)]
        if not needs or bad:
            return f"'needs' takes command:NAME, module:NAME, library:NAME or file:GLOB, not {bad or 'nothing'}"
        block.needs.extend(needs)
    elif word == "file":
        if not rest or Path(rest).is_absolute() or ".." in Path(rest).parts:
            return f"'file' needs a path in the document's folder, not {rest!r}"
        block.file = rest
    else:
        return f"unknown docs-test comment {directive!r}: skip, slow, needs or file"
    return None


def _missing(needs: list[str]) -> list[str]:
    """The needs of a block this machine does not meet."""
    finds = {"command": shutil.which, "module": importlib.util.find_spec, "library": ctypes.util.find_library,
             "file": lambda pattern: glob.glob(pattern) or None}
    return [need for need in needs if finds[need.split(":", 1)[0]](need.split(":", 1)[1]) is None]


def _runnable_documents() -> list[Path]:
    """The documents with a block to run (in the default run or under :data:`SLOW_ENV`)."""
    return [doc for doc in DOCUMENTS
            if any(b.tag in RUN_TAGS and b.skip is None for b in parse(doc)[0])]


def test_every_fence_says_what_it_holds():
    """Every fenced block of README.md and docs/*.md is tagged, and every docs-test comment is one the test
    knows, complete and right above a fence, so that no command block escapes the test unseen."""
    problems = [p for doc in DOCUMENTS for p in parse(doc)[1]]
    assert not problems, "\n".join(problems)


# -- running a document's blocks ----------------------------------------------------------------------------

def _fresh_folder(path: Path) -> Path:
    """An empty folder holding a copy of the checkout's examples/ as a fresh clone has them (examples/out/
    holds only its .gitignore: an earlier run's outputs there would be refused without --force)."""
    def leave_out(folder: str, names: list[str]) -> list[str]:
        if Path(folder).name == "out":
            return [n for n in names if n != ".gitignore"]
        return [n for n in names if n == "__pycache__"]

    path.mkdir()
    shutil.copytree(ROOT / "examples", path / "examples", ignore=leave_out)
    return path


#: The variable whose value marks the processes of one document's run (:func:`_members`).
_TOKEN = "SUPRAMODAL_DOCS_TEST"


def _environment() -> dict[str, str]:
    """The shell's environment: the test's, with its Python first on PATH, REPO, a JACK server name of its own
    and the run's token (:data:`_TOKEN`)."""
    env = dict(os.environ)
    env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])
    env["REPO"] = str(ROOT)
    env["JACK_DEFAULT_SERVER"] = f"supramodal-docs-{os.getpid()}-{secrets.token_hex(4)}"
    env[_TOKEN] = secrets.token_hex(8)
    env.pop("PYTHONPATH", None)              # the installed package, as a reader has it
    return env


def _script(block: Block, state: Path) -> str:
    """``block`` as a bash script that starts where the document's last block left off (its exported
    variables and its folder) and leaves the same for the next."""
    env, cwd = shlex.quote(str(state / "env")), shlex.quote(str(state / "cwd"))
    return (f"set -euo pipefail\n"
            f"if [ -f {env} ]; then source {env}; fi\n"
            f"if [ -f {cwd} ]; then cd \"$(cat {cwd})\"; fi\n"
            f"trap '{{ export -p > {env}; pwd > {cwd}; }} 2>/dev/null || true' EXIT\n"
            f"{block.text}")


def _tail(path: Path, chars: int = 4000) -> str:
    text = path.read_text(errors="replace")
    return text if len(text) <= chars else "...\n" + text[-chars:]


def _members(token: str) -> list[int]:
    """The live processes whose environment holds the document's token (:data:`_TOKEN`): every process its
    blocks started, also one that left the group for a session of its own (jackd does)."""
    marker = f"{_TOKEN}={token}".encode()
    found = []
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            if marker not in (Path(entry.path) / "environ").read_bytes().split(b"\0"):
                continue
            if (Path(entry.path) / "stat").read_text().rsplit(")", 1)[1].split()[0] == "Z":
                continue                     # ended, waiting to be reaped by its parent
        except OSError:                      # gone meanwhile, or another user's
            continue
        found.append(int(entry.name))
    return found


def _end_group(leader: subprocess.Popen, token: str) -> None:
    """End every process of the document: SIGTERM (a mock board removes its port, a node prints its summary),
    then SIGKILL for what is left after 10 s; the group's, and those that left it (:func:`_members`)."""
    for signum, grace in ((signal.SIGTERM, 10.0), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(leader.pid, signum)
        except ProcessLookupError:
            pass
        for pid in _members(token):
            try:
                os.kill(pid, signum)
            except ProcessLookupError:
                pass
        leader.wait()
        deadline = time.monotonic() + grace
        while _members(token) and time.monotonic() < deadline:
            time.sleep(0.1)
        if not _members(token):
            return


def run_document(doc: Path, tmp_path: Path) -> None:
    """Run ``doc``'s blocks in order in a fresh folder (see the module's docstring); fail naming the first block
    that fails or runs over; skip afterwards naming the blocks a missing program, module, library or file kept
    from running, or when no block ran (all slow)."""
    blocks = parse(doc)[0]
    folder = _fresh_folder(tmp_path / "doc")
    state = tmp_path / "shell"
    state.mkdir()
    env = _environment()
    slow = os.environ.get(SLOW_ENV) == "1"
    ran = 0
    outputs: list[tuple[int, Path]] = []    # (the block's line, its output): what a walkthrough's figures are
    not_run: list[str] = []             # for want of a program, module, library or file
    not_slow: list[str] = []            # slow, and SLOW_ENV not set
    # The group's leader holds the group while no block runs, so that every block (and what it leaves running
    # with &) joins one group, killed whole at the end; outside the terminal's group, Ctrl-C reaches the test
    # alone, which then ends the group here.
    leader = subprocess.Popen(["sleep", "infinity"], process_group=0, stdin=subprocess.DEVNULL, env=env)
    try:
        for k, block in enumerate(blocks):
            if block.file is not None:
                target = folder / block.file
                target.parent.mkdir(parents=True, exist_ok=True)
                target.write_text(block.text)
            if block.tag not in RUN_TAGS or block.skip is not None:
                continue
            if block.slow is not None and not slow:
                not_slow.append(f"{block.where} (slow, {block.slow}: set {SLOW_ENV}=1)")
                continue
            missing = _missing(block.needs)
            if missing:
                not_run.append(f"{block.where} (missing {', '.join(missing)})")
                continue
            log = tmp_path / f"block-{k}-line-{block.line}.log"
            limit = SLOW_BLOCK_SECONDS if block.slow is not None else BLOCK_SECONDS
            started = time.monotonic()
            with open(log, "wb") as out:
                # Output to a file, not a pipe: a process left running with & would hold a pipe open after the
                # block's shell ended.
                proc = subprocess.Popen(["bash", "-c", _script(block, state)], cwd=folder, env=env,
                                        stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
                                        process_group=leader.pid)
                try:
                    code = proc.wait(timeout=limit)
                except subprocess.TimeoutExpired:
                    code = None
                finally:
                    if proc.poll() is None:
                        proc.kill()
                        proc.wait()
            took = time.monotonic() - started
            ran += 1
            outputs.append((block.line, log))
            print(f"{block.where}: {took:.1f} s")      # the cost of each block (pytest -rA or -s shows it)
            if code != 0:
                said = (f"ran over {limit:.0f} s" if code is None
                        else f"ended with exit status {code} after {took:.1f} s")
                pytest.fail(f"{block.where}: the block {said}:\n{block.text}\n--- its output, the end ---\n"
                            f"{_tail(log)}", pytrace=False)
    finally:
        _end_group(leader, env[_TOKEN])
    _check_walkthrough_figures(doc, outputs)
    if not_slow:
        print(f"not run: {'; '.join(not_slow)}")
    # A walkthrough cut short by a missing extra is said (skipped), as the suite's other tests say theirs; one whose
    # slow blocks were left out, as asked, passed on the others.
    if not_run or not ran:
        pytest.skip(f"{_name(doc)}: {'the other blocks ran; ' if ran else ''}not run: {'; '.join(not_run + not_slow)}")


def _check_walkthrough_figures(doc: Path, outputs: list[tuple[int, Path]]) -> None:
    """Fail naming each figure under a ``<!-- figures: walkthrough -->`` comment of ``doc`` that the blocks run
    above it did not print (tests/test_docs_figures.py: the documents' figures). An element with no block run
    above it (a slow one left out) is not checked."""
    from test_docs_figures import elements, unprinted

    wrong = []
    for element in elements(doc)[0]:
        if element.says != "walkthrough":
            continue
        above = [log.read_text(errors="replace") for line, log in outputs if line < element.start]
        if not above:
            continue
        missing = unprinted(element, "\n".join(above))
        if missing:
            wrong.append(f"{element.where}: the walkthrough's commands above did not print {', '.join(missing)}")
    assert not wrong, "copy what the commands print into the document:\n" + "\n".join(wrong)


#: Each document's pytest marks, by what its blocks do (docs/development.md; the times on 2 cores at a load of 2 to
#: 4): ``slow`` leaves it out of the quick command; ``hardware`` puts it in tests/harness/pacing.py's paced group of the
#: pty boards and JACK-paced microphones, ``paced`` in the other paced group (it waits on a clock, at normal
#: priority, and holds no computing worker while it waits).
_MARKS = {
    "README.md": [pytest.mark.slow, pytest.mark.paced],       # the default scene: 80 s in real time, 106 s
    "own-sensor.md": [pytest.mark.slow],                      # a whole fit and a model: 160 s (the fit 40 s idle)
    "testing-without-hardware.md": [pytest.mark.slow, pytest.mark.hardware],   # a model trained on start: 45 s
    "ros2.md": [pytest.mark.slow, pytest.mark.paced],         # ROS 2 nodes, a recording of 10 s in real time: 15 s
    "results.md": [pytest.mark.slow],                         # with SUPRAMODAL_DOCS_SLOW=1, the experiments
}


@pytest.mark.parametrize("doc", [pytest.param(doc, id=doc.name, marks=_MARKS.get(doc.name, []))
                                 for doc in _runnable_documents()])
def test_a_document_s_commands_run_as_written(doc, tmp_path):
    """Every sh block of ``doc`` not marked skip (nor slow, unless SUPRAMODAL_DOCS_SLOW=1) runs as written and
    exits 0, in order, in one fresh folder."""
    if doc.name == "ros2.md":
        # As before every ROS 2 test (tests/ros2_only.py): tests/harness/environment.py keeps DDS on this machine, in the run's own
        # domain (inherited by the blocks); a segment a killed process left empty would hang the node's start.
        from ros2_only import remove_stale_segments

        assert os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE") == "LOCALHOST", "tests/harness/environment.py keeps ROS 2 on localhost"
        assert os.environ.get("ROS_DOMAIN_ID") == os.environ.get("SUPRAMODAL_TEST_ROS_DOMAIN")
        remove_stale_segments()
    run_document(doc, tmp_path)
