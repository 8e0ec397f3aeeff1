"""Labelled recordings for the manifest tests: reference whisker textures cut into WAV files."""

from __future__ import annotations

from pathlib import Path

from supramodal.replay.wavio import write_wav
from supramodal.textures import reference_texture_set

RATE = 5000
SECONDS = 1.5


def write_texture_recordings(folder: Path, per_texture: int, textures: int = 3) -> Path:
    """``per_texture`` recordings of :data:`SECONDS` s of each of the first ``textures`` reference
    whisker textures (consecutive stretches of one synthesis), and ``all.csv`` listing them with
    their labels; returns the folder."""
    ts = reference_texture_set("whisker")
    n = int(SECONDS * RATE)
    rows = ["path,label"]
    for t in range(textures):
        x = ts.synthesize(t, duration=per_texture * SECONDS)
        for r in range(per_texture):
            name = f"{ts.names[t]}_{r}.wav"
            write_wav(folder / name, x[r * n:(r + 1) * n, None], RATE)
            rows.append(f"{name},{ts.names[t]}")
    (folder / "all.csv").write_text("\n".join(rows) + "\n")
    return folder
