"""Checked reads of a JSON-shaped mapping's fields: what each value is, to the type checker and at run time.

A sink's options (validated by the scene's schema before a build sees them) and the frames the ros2 sink sends
its publisher process (JSON it wrote itself) are mappings whose values the code knows the type of, but a type
checker sees only a JSON value. These say which type, in one place, and raise TypeError where a value is not
what its reader expects: a fault of the code that made the mapping (a schema that let another type through, a
frame written otherwise), not of the scene. A missing key raises KeyError, as ``m[key]`` does.
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping

import numpy as np

__all__ = ["bool_of", "float_of", "int_mapping_of", "int_of", "list_of", "mapping_of", "mappings_of",
           "optional_float_of", "optional_int_of", "optional_str_of", "optional_strs_of", "str_mapping_of", "str_of",
           "strs_of"]


def _wrong(key: str, value: object, what: str) -> TypeError:
    return TypeError(f"{key!r}: {value!r} is not {what}")


def str_of(m: Mapping[str, object], key: str) -> str:
    """Return ``m[key]``, text."""
    value = m[key]
    if isinstance(value, str):
        return value
    raise _wrong(key, value, "text")


def optional_str_of(m: Mapping[str, object], key: str) -> str | None:
    """Return ``m[key]``, text or None."""
    return None if m[key] is None else str_of(m, key)


def int_of(m: Mapping[str, object], key: str) -> int:
    """Return ``m[key]``, an integer (not a bool)."""
    value = m[key]
    if isinstance(value, int) and not isinstance(value, bool):
        return value
    raise _wrong(key, value, "an integer")


def optional_int_of(m: Mapping[str, object], key: str) -> int | None:
    """Return ``m[key]``, an integer or None."""
    return None if m[key] is None else int_of(m, key)


def float_of(m: Mapping[str, object], key: str) -> float:
    """Return ``m[key]``, a real number (Python's or NumPy's, not a bool), as a float."""
    value = m[key]
    if isinstance(value, numbers.Real) and not isinstance(value, bool | np.bool_):
        return float(value)
    raise _wrong(key, value, "a number")


def optional_float_of(m: Mapping[str, object], key: str) -> float | None:
    """Return ``m[key]``, a number as a float, or None."""
    return None if m[key] is None else float_of(m, key)


def bool_of(m: Mapping[str, object], key: str) -> bool:
    """Return ``m[key]``, true or false."""
    value = m[key]
    if isinstance(value, bool):
        return value
    raise _wrong(key, value, "true or false")


def strs_of(m: Mapping[str, object], key: str) -> list[str]:
    """Return ``m[key]``, a list of text (a copy)."""
    value = m[key]
    if isinstance(value, list):
        out = [v for v in value if isinstance(v, str)]
        if len(out) == len(value):
            return out
    raise _wrong(key, value, "a list of text")


def optional_strs_of(m: Mapping[str, object], key: str) -> list[str] | None:
    """Return ``m[key]``, a list of text (a copy), or None."""
    return None if m[key] is None else strs_of(m, key)


def list_of(m: Mapping[str, object], key: str) -> list[object]:
    """Return ``m[key]``, a list (a copy)."""
    value = m[key]
    if isinstance(value, list):
        return list(value)
    raise _wrong(key, value, "a list")


def mappings_of(m: Mapping[str, object], key: str) -> list[Mapping[str, object]]:
    """Return ``m[key]``, a list of mappings of text to values (a copy)."""
    value = m[key]
    if isinstance(value, list):
        out = [v for v in value if isinstance(v, Mapping) and all(isinstance(k, str) for k in v)]
        if len(out) == len(value):
            return out
    raise _wrong(key, value, "a list of mappings of text to values")


def str_mapping_of(m: Mapping[str, object], key: str) -> dict[str, str]:
    """Return ``m[key]``, a mapping of text to text (a copy)."""
    value = mapping_of(m, key)
    out = {k: v for k, v in value.items() if isinstance(v, str)}
    if len(out) == len(value):
        return out
    raise _wrong(key, value, "a mapping of text to text")


def int_mapping_of(m: Mapping[str, object], key: str) -> dict[str, int]:
    """Return ``m[key]``, a mapping of text to integers (a copy; counts by name)."""
    value = mapping_of(m, key)
    out = {k: v for k, v in value.items() if isinstance(v, int) and not isinstance(v, bool)}
    if len(out) == len(value):
        return out
    raise _wrong(key, value, "a mapping of text to integers")


def mapping_of(m: Mapping[str, object], key: str) -> Mapping[str, object]:
    """Return ``m[key]``, a mapping of text to values."""
    value = m[key]
    if isinstance(value, Mapping) and all(isinstance(k, str) for k in value):
        return value
    raise _wrong(key, value, "a mapping of text to values")
