"""Graph scenes of the two-sense world (two `twosense` sources on their own clocks, a stream each
with a model trained on the spot, a fusion), as TOML text for the command-line tests."""

from __future__ import annotations


def two_sense_world_toml(seconds: float, take: int | None = None, blocks: tuple[int, int] = (50, 441),
                         fusion: str = 'weight = "learn"') -> str:
    """The world's scene: ``seconds`` per contact, contact ``take`` (None: the source's default),
    the whiskers' and the microphone's block sizes, and the ``[fusion]`` lines besides its streams."""
    src = ""
    senses = (("whiskers", "whiskers", blocks[0], 0.0), ("mic", "microphone", blocks[1], 0.037))
    for name, sense, block, offset in senses:
        src += (f'[[source]]\nname = "{name}"\ntype = "twosense"\nsense = "{sense}"\n'
                + ("" if take is None else f"take = {take}\n")
                + f'seconds = {seconds}\nblock = {block}\noffset = {offset}\nspeed = "max"\n\n')
    for name, kind in (("whiskers", "whisker"), ("mic", "cochlea")):
        src += (f'[[stream]]\nname = "{name}"\nsource = "{name}"\n[stream.bank]\nkind = "{kind}"\n'
                '[stream.model]\ntrain_on_start = true\n\n')
    return src + f'[fusion]\nstreams = ["whiskers", "mic"]\n{fusion}\n'
