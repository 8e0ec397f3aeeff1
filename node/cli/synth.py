"""The ``supramodal synth`` command: :data:`SUMMARY` says what it does."""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from supramodal.node.cli.arguments import output_folder, positive_seconds

#: What ``supramodal synth`` does, in one line: its ``--help`` says it, and the README's command table
#: where a row says what the whole command does.
SUMMARY = "write a texture set as WAV files"
#: Its forms as the README's command table lists them (``python -m supramodal.node.cli.docs`` writes it):
#: (synopsis, what it does), in Markdown.
README_ROWS = (
    ("supramodal synth [--bank B] [--out DIR]", SUMMARY),
)


def add_parser(subparsers: argparse._SubParsersAction[argparse.ArgumentParser],
               common: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the ``synth`` command's parser and its arguments to ``subparsers``.

    ``common`` is the parent parser of every command (``--debug``).
    """
    p = subparsers.add_parser("synth", parents=[common], help=SUMMARY)
    p.add_argument("--force", action="store_true", help="replace existing texture files in --out (default: refuse)")
    p.add_argument("--bank", choices=["whisker", "cochlea"], default="whisker",
                   help="whose reference textures (default whisker)")
    p.add_argument("--textures", metavar="FILE", help="texture-set JSON file (default: the bank's reference set)")
    p.add_argument("--duration", type=positive_seconds, help="seconds per texture (default: the set's)")
    p.add_argument("--out", default="out/textures", type=output_folder, help="directory (default ./out/textures)")
    return p


def run(args: argparse.Namespace) -> int:
    """Write one WAV file per texture of the set into ``--out``.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed command line.

    Returns
    -------
    int
        The exit status (0: done).
    """
    import numpy as np
    from scipy.io import wavfile

    from supramodal.errors import InputError
    from supramodal.node.runtime.outputs import check_new_file
    from supramodal.textures import load_texture_set, reference_texture_set, texture_samples

    ts = load_texture_set(args.textures) if args.textures else reference_texture_set(args.bank)
    out = Path(args.out)
    paths = [out / f"{tex.name}.wav" for tex in ts.textures]
    if out.is_dir():
        for path in paths:
            check_new_file(path, args.force, "the texture file")
    duration = ts.duration if args.duration is None else args.duration
    try:
        texture_samples(duration, ts.fs)
    except InputError as exc:
        raise InputError(f"--duration: {exc}") from None
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    written = []
    try:
        for i, (tex, path) in enumerate(zip(ts.textures, paths)):
            x = ts.synthesize(i, duration=duration).astype(np.float32)
            written.append(path)             # from here on, this file is ours to remove on failure
            wavfile.write(path, int(round(ts.fs)), x)
            print(f"{path}  {len(x) / ts.fs:g} s at {ts.fs:g} Hz, peaks {list(tex.peaks)} Hz")
    except BaseException:
        # A failed (or interrupted) run leaves nothing: no part of a set, no folder it made.
        for path in written:
            path.unlink(missing_ok=True)
        if created:
            shutil.rmtree(out, ignore_errors=True)
        raise
    return 0
