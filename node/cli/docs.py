"""The README's command table, made from the command modules, so that it cannot drift.

``python -m supramodal.node.cli.docs`` rewrites README.md's generated block (between
``<!-- BEGIN generated: commands -->`` and ``<!-- END generated: commands -->``) from each command's
``README_ROWS``, in the order of :data:`~supramodal.node.cli.COMMANDS`; ``--check`` exits 1 when the
committed file differs from the commands (a test runs it too). The scene's key tables are made the same
way (``python -m supramodal.node.scene.docs``, whose rewriting this module uses): the scene sits below
the command line and may not import it, hence two writers.

A command module says what it does once, in ``SUMMARY`` (its ``--help`` line); its ``README_ROWS`` are
its forms as the README lists them, ``(synopsis, what it does)`` in Markdown, built on ``SUMMARY`` where
the row says what the whole command does.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

from supramodal.node.cli import COMMANDS, command_module
from supramodal.node.scene.docs import check as check_blocks
from supramodal.node.scene.docs import command_line

__all__ = ["BLOCKS", "blocks", "check", "command_table", "main"]

#: File (relative to the repository root) -> the generated blocks it holds.
BLOCKS = {"README.md": ("commands",)}


def _cell(text: str) -> str:
    return text.replace("|", "\\|")     # a pipe inside a cell (``S|max``) would end it, as in the key tables


def command_table() -> str:
    """Return the README's command table, as Markdown: one row per form of each command, in ``COMMANDS``' order.

    Raises
    ------
    ValueError
        A command module without ``README_ROWS`` (every command is in the README).
    """
    rows = ["| command | what it does |", "|---|---|"]
    for name in COMMANDS:
        module = command_module(name)
        forms = getattr(module, "README_ROWS", ())
        if not forms:
            raise ValueError(f"command {name!r} ({COMMANDS[name]}) has no README_ROWS: its rows in the README's "
                             "command table, (synopsis, what it does)")
        rows += [f"| `{_cell(synopsis)}` | {_cell(what)} |" for synopsis, what in forms]
    return "\n".join(rows)


def blocks() -> dict[str, str]:
    """Every generated block of this module, by name, as Markdown."""
    return {"commands": command_table()}


def check(root: Path) -> list[str]:
    """Return the files under ``root`` (the repository's root) whose command table differs from the commands'."""
    return check_blocks(root, BLOCKS, blocks())


def main(argv: Sequence[str] | None = None) -> int:
    """Rewrite README.md's command table from the command modules, or with ``--check`` say if it differs.

    ``python -m supramodal.node.cli.docs [--check]``; returns the exit status (1: the file differs).
    """
    assert __doc__ is not None
    return command_line(argv, "python -m supramodal.node.cli.docs", __doc__.splitlines()[0], BLOCKS, blocks,
                        "its command table differs from the command modules")


if __name__ == "__main__":
    sys.exit(main())
