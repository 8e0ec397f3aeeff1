"""Run mypy on the package as it installs: `python .ci/typecheck.py [mypy options]` from anywhere.

The checkout keeps node/, drivers/, replay/ and benchmarks/ beside supramodal/ and the wheel installs them as
supramodal.node, ... (pyproject's [tool.setuptools.package-dir]). mypy cannot follow that mapping: it names a
module after its folders (node/runtime/clock.py would be `node.clock`, a second copy of `supramodal.node.runtime.clock`), and
it does not see through setuptools' editable-install import hook (python/mypy#13392), so `mypy -p supramodal`
finds only the model. This script hands mypy every module of the package under its installed name, with its
real path (so messages point into the checkout), and the settings of pyproject's [tool.mypy] sections.
It reads the mapping from pyproject, so a new module or package needs no change here.
"""

from __future__ import annotations

import os
import sys
import tomllib
from pathlib import Path

from mypy import build
from mypy.errors import CompileError
from mypy.main import process_options
from mypy.modulefinder import BuildSource

ROOT = Path(__file__).resolve().parent.parent


def package_sources() -> list[BuildSource]:
    """Every module of every package pyproject installs, as (path, installed module name)."""
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    folders: dict[str, str] = setuptools["package-dir"]
    sources = []
    for package in setuptools["packages"]:
        top = max((name for name in folders if package == name or package.startswith(name + ".")), key=len)
        folder = ROOT / folders[top] / Path(*package[len(top):].split(".")[1:])
        for path in sorted(folder.glob("*.py")):
            module = package if path.stem == "__init__" else f"{package}.{path.stem}"
            sources.append(BuildSource(str(path.relative_to(ROOT)), module, None, base_dir=str(ROOT)))
    return sources


def main(argv: list[str]) -> int:
    os.chdir(ROOT)   # pyproject's [tool.mypy] is found here; paths in messages are relative to the checkout
    sources = package_sources()
    # process_options reads the config and the command line; the target it is given is replaced below.
    _, options = process_options([*argv, *(source.path for source in sources if source.path)])
    try:
        result = build.build(sources, options, stdout=sys.stdout, stderr=sys.stderr)
    except CompileError as error:
        for message in error.messages:
            print(message, file=sys.stderr)
        return 2
    for message in result.errors:
        print(message)
    files = len(sources)
    if result.errors:
        count = sum(1 for message in result.errors if ": error:" in message)
        with_errors = len({message.split(":", 1)[0] for message in result.errors if ": error:" in message})
        print(f"Found {count} errors in {with_errors} files (checked {files} source files)")
        return 1
    print(f"Success: no issues found in {files} source files")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
