"""The docs' tables of scene keys, made from the schema itself, so that they cannot drift.

``python -m supramodal.node.scene.docs`` rewrites the generated blocks of README.md and
docs/node.md (between ``<!-- BEGIN generated: NAME -->`` and ``<!-- END generated: NAME -->``);
``--check`` exits 1 when the committed files differ from the schema (a test runs it too). The README's
command table is made the same way from the command modules (``python -m supramodal.node.cli.docs``: the
command line sits above the scene, which may not import it).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

from supramodal.node.runtime.sinks.spec import sink_keys
from supramodal.node.scene.registry import driver_spec, driver_types, sink_spec, sink_types, source_keys
from supramodal.node.scene.schema import FUSION_KEYS, ONE_SOURCE_KEYS, SECTIONS, SOURCE_KEYS, STREAM_KEYS

__all__ = ["BLOCKS", "blocks", "check", "command_line", "main", "rewrite"]

#: File (relative to the repository root) -> the generated blocks it holds.
BLOCKS = {"docs/node.md": ("driver-keys", "section-keys", "sink-keys", "graph-keys"), "README.md": ("driver-types",)}


def _value(v) -> str:
    if v is None:
        return "—"          # the driver's or the bank's own default, as "expected" says
    return "`" + (json.dumps(v) if not isinstance(v, float) else f"{v:g}") + "`"


def _keys_table(keys: dict) -> list[str]:
    rows = ["| key | expected | default |", "|---|---|---|"]
    for key, k in keys.items():
        default = "**required**" if k.required else _value(k.default)
        expected = k.expected.replace("|", "\\|")
        rows.append(f"| `{key}` | {expected} | {default} |")
    return rows


def blocks() -> dict[str, str]:
    """Every generated block, by name, as Markdown."""
    out = {}
    lines = []
    for kind in driver_types():
        spec = driver_spec(kind)
        lines += [f"#### `type = \"{kind}\"`: {spec.summary}", "",
                  f"{'Live' if spec.live else 'A file'}: `overrun = \"auto\"` is `\"{spec.overrun}\"`.", ""]
        lines += _keys_table(source_keys(spec)) + [""]
    out["driver-keys"] = "\n".join(lines).rstrip()
    lines = []
    lines += ["#### `[driver]` of a one-source scene: its driver's keys (above) and", ""]
    lines += _keys_table(ONE_SOURCE_KEYS) + [""]
    for section, keys in SECTIONS.items():
        lines += [f"#### `[{section}]`", ""] + _keys_table(keys) + [""]
    out["section-keys"] = "\n".join(lines).rstrip()
    lines = []
    for kind in sink_types():
        sink = sink_spec(kind)
        lines += [f"#### `[[sink]] type = \"{kind}\"`: {sink.summary}", ""] + _keys_table(sink_keys(sink)) + [""]
    out["sink-keys"] = "\n".join(lines).rstrip()
    lines = ["#### `[[source]]`: a driver's keys (above) and", ""] + _keys_table(SOURCE_KEYS) + [""]
    lines += ["#### `[[stream]]`: `[stream.bank]`, `[stream.features]`, `[stream.model]`, `[stream.decision]` "
              "(the sections above) and", ""] + _keys_table(STREAM_KEYS) + [""]
    lines += ["#### `[fusion]`: `[fusion.decision]` (a `[decision]`) and", ""] + _keys_table(FUSION_KEYS)
    out["graph-keys"] = "\n".join(lines).rstrip()
    out["driver-types"] = "\n".join(f"- `{kind}`: {driver_spec(kind).summary}" for kind in driver_types())
    return out


def _pattern(name: str) -> re.Pattern:
    return re.compile(rf"(<!-- BEGIN generated: {re.escape(name)} -->\n)(?:.*?\n)?(<!-- END generated: "
                      rf"{re.escape(name)} -->)", re.S)


def rewrite(text: str, names, made: Mapping[str, str], where: str = "the file") -> str:
    """``text`` with each named block replaced by ``made[name]``; a missing block is an error."""
    for name in names:
        pattern = _pattern(name)
        if not pattern.search(text):
            raise ValueError(f"{where} has no generated block {name!r} (<!-- BEGIN generated: {name} --> ...)")
        # sub() calls the lambda before the loop moves on: it sees this name's block
        text = pattern.sub(lambda m: m.group(1) + made[name] + "\n" + m.group(2), text)  # noqa: B023
    return text


def check(root: Path, files: Mapping[str, Sequence[str]] = BLOCKS, made: Mapping[str, str] | None = None) -> list[str]:
    """Return the files under ``root`` whose generated blocks differ from what the code makes of them.

    Parameters
    ----------
    root : Path
        The repository's root.
    files : mapping of str to sequence of str
        File (relative to ``root``) -> the names of the blocks it holds (default: :data:`BLOCKS`).
    made : mapping of str to str, optional
        Block name -> its Markdown (default: :func:`blocks`).
    """
    made = blocks() if made is None else made
    return [f for f, names in files.items()
            if (root / f).read_text() != rewrite((root / f).read_text(), names, made, f)]


def command_line(argv: Sequence[str] | None, prog: str, description: str, files: Mapping[str, Sequence[str]],
                 make: Callable[[], Mapping[str, str]], stale: str) -> int:
    """Run the command line of a writer of generated blocks: rewrite ``files``' blocks from ``make()``.

    Or, with ``--check``, say which files differ (``"FILE: STALE; run PROG"``) and exit 1. This module's and the
    command table's (``supramodal.node.cli.docs``) share it, so that both are run and fail alike.
    """
    parser = argparse.ArgumentParser(prog=prog, description=description)
    parser.add_argument("--root", type=Path, default=Path.cwd(), help="the repository's root (default: here)")
    parser.add_argument("--check", action="store_true", help="only say whether the files are up to date")
    args = parser.parse_args(argv)
    made = make()
    if args.check:
        differ = check(args.root, files, made)
        for f in differ:
            print(f"{f}: {stale}; run {prog}", file=sys.stderr)
        return 1 if differ else 0
    for f, names in files.items():
        path = args.root / f
        path.write_text(rewrite(path.read_text(), names, made, f))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Rewrite the scene key tables of README.md and docs/node.md, or with ``--check`` say which differ.

    ``python -m supramodal.node.scene.docs [--check]``; returns the exit status (1: a file differs).
    """
    assert __doc__ is not None
    return command_line(argv, "python -m supramodal.node.scene.docs", __doc__.splitlines()[0], BLOCKS, blocks,
                        "its scene key tables differ from the schema")


if __name__ == "__main__":
    sys.exit(main())
