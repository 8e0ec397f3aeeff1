"""Comparing experiment results."""


def strip_timing(x):
    """A result without its timings (the only part that may differ between runs)."""
    if isinstance(x, dict):
        return {k: strip_timing(v) for k, v in x.items() if k not in ("timing", "compute_seconds")}
    if isinstance(x, list):
        return [strip_timing(v) for v in x]
    return x
