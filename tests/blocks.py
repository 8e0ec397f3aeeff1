"""Feeding a signal to a streaming object in given block sizes: shared by the partition tests."""


def feed_blocks(process, x, sizes):
    """Call ``process`` on consecutive blocks of ``x`` (last axis) of the given sizes, then on the rest.

    Sizes past the end give empty blocks. Returns the list of outputs, one per call.
    """
    out, i = [], 0
    for s in sizes:
        out.append(process(x[..., i : i + s]))
        i = min(i + s, x.shape[-1])
    out.append(process(x[..., i:]))
    return out
